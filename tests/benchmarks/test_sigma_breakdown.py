"""benchmarks/sigma_breakdown.py's figures on errors drawn with known scales."""

import numpy as np

from tests.support.benchmark_scripts import load_benchmark


def test_a_missing_floor_shows_in_the_octiles_and_a_tiles_shortfall_in_its_factor():
    """Errors with a floor the sigmas lack (sqrt(s^2 + f^2)): the low octiles' error scale stays near the floor
    while their sigma falls; errors twice the sigma in one tile: that tile asks a variance factor of ~4, the
    others ~1, and with those factors the share beyond 3 sigma is a Gaussian's."""
    sb = load_benchmark("sigma_breakdown")
    rng = np.random.default_rng(3)
    n = 200_000
    s = rng.uniform(0.01, 0.05, n)
    e = rng.normal(0, np.sqrt(s ** 2 + 0.02 ** 2))
    rows = sb.octile_rows(s, e)
    for row in rows:  # the scale of the errors drawn there (their sigma's spread within an octile: < 4 %)
        assert abs(row["scale"] / np.sqrt(row["sigma"] ** 2 + 0.02 ** 2) - 1) < 0.05
    assert rows[0]["ratio"] > 1.5 * rows[-1]["ratio"] and rows[0]["beyond_3"] > 0.1

    uv = rng.uniform(0, 128, (n, 2))  # 16 tiles of 32 px
    e = rng.normal(0, s)
    hot = (uv[:, 0] < 32) & (uv[:, 1] < 32)
    e[hot] *= 2.0
    t = sb.tile_factors(s, e, uv, None)
    assert t["need"].size == 16 and (t["have"] == 1).all()
    # the hot tile ~4 (12.5k points: its median known to ~2 %), the others ~1 (never below)
    assert abs(np.max(t["need"]) - 4.0) < 0.3 and np.sort(t["need"])[-2] < 1.1
    r = np.abs(e) / t["sigma_truth"]
    assert abs(np.mean(r > 3) - 0.0027) < 0.001  # a Gaussian's share beyond 3 sigma


def test_a_folder_without_a_run_is_one_line(tmp_path, capsys):
    sb = load_benchmark("sigma_breakdown")
    assert sb.main([str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path) in err[0]


def test_errors_that_grow_with_the_frame_noise_show_by_its_fifths():
    """Errors whose scale is the sigma times the noise over 2 levels (noise 1 to 4 levels; the sigmas blind to
    it): the top fifth's median |e|/sigma ~3x the bottom's (noise ~3.7 against ~1.3 levels), and most of its
    points beyond 3 sigma; noise the sigmas already carry (errors of scale sigma): every fifth a Gaussian's."""
    sb = load_benchmark("sigma_breakdown")
    rng = np.random.default_rng(4)
    n = 100_000
    s = rng.uniform(0.01, 0.05, n)
    noise = rng.uniform(1.0, 4.0, n)
    rows = sb.noise_rows(noise, s, rng.normal(0, s * noise / 2.0))
    assert rows[-1]["ratio"] > 2.5 * rows[0]["ratio"] and rows[-1]["beyond_3"] > 0.1
    assert [abs(r["noise"] - (1.3 + 0.6 * i)) < 0.05 for i, r in enumerate(rows)] == [True] * 5
    for r in sb.noise_rows(noise, s, rng.normal(0, s)):  # 20k points a fifth: the median to ~1 %
        assert abs(r["ratio"] - sb.GAUSS_MEDIAN_RATIO) < 0.03 and r["beyond_3"] < 0.006
