"""ringscan sweep: surface error and coverage against the number of rings."""

import csv
import dataclasses

import cv2
import numpy as np
import pytest

from ringscan.pipeline.evaluate.sweep import (
    SweepSettings,
    interpolate_surface,
    min_rings,
    plot_sweep,
    run_sweep,
    sweep_figure,
)
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.rig import default_rig, save_rig
from ringscan.tools.cli import main


def small_rig(width=320, height=256):
    """The default rig with a ``width`` x ``height`` camera of the same field of view."""
    rig = default_rig()
    f = 650.0 * width / 320
    cam = dataclasses.replace(rig.camera, width=width, height=height,
                              K=np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]))
    return dataclasses.replace(rig, camera=cam)


def _ring_samples(w=200, h=160, step=6.0, drop=None):
    """Samples on concentric image circles (ring j at radius 8 + step j), each on a
    row or column like the edge sampler's, lying on the paraboloid
    z = 0.002 ((u - cx)^2 + (v - cy)^2) over the image plane (x = u, y = v)."""
    cx, cy = w / 2, h / 2
    uv, ring = [], []
    for j in range(1, 12):
        r = 8 + step * j
        for a in np.linspace(0, 2 * np.pi, int(2 * np.pi * r), endpoint=False):
            if drop is not None and drop(j, a):
                continue
            u, v = cx + r * np.cos(a), cy + r * np.sin(a)
            if abs(np.cos(a)) > abs(np.sin(a)):
                v = round(v)
                u = cx + np.sign(np.cos(a)) * np.sqrt(max(r * r - (v - cy) ** 2, 0))
            else:
                u = round(u)
                v = cy + np.sign(np.sin(a)) * np.sqrt(max(r * r - (u - cx) ** 2, 0))
            uv.append((u, v))
            ring.append(j)
    uv = np.array(uv)
    z = 0.002 * ((uv[:, 0] - cx) ** 2 + (uv[:, 1] - cy) ** 2)
    return uv, np.column_stack([uv, z]), np.array(ring), (cx, cy)


def test_interpolation_between_rings_is_close_to_the_surface():
    w, h = 200, 160
    uv, P, ring, (cx, cy) = _ring_samples(w, h)
    v, u = np.mgrid[0:h, 0:w]
    rr = np.hypot(u - cx, v - cy).ravel()
    q = np.arange(w * h)
    X, cov = interpolate_surface(uv, P, ring, q, width=w, height=h, max_gap_mm=20.0)
    between = (rr > 8 + 6 + 1) & (rr < 8 + 6 * 11 - 1)
    assert cov[between].mean() > 0.97
    assert not cov[rr > 8 + 6 * 11 + 4].any() and not cov[rr < 8 + 6 - 4].any()
    z_true = 0.002 * ((X[:, 0] - cx) ** 2 + (X[:, 1] - cy) ** 2)
    # a chord of the paraboloid z = c r^2 of length L lies at most c L^2 / 4 off it;
    # the two bracketing samples are one ring gap (6 px) apart radially, a little
    # more where they are not at the same angle
    err = np.abs(X[cov, 2] - z_true[cov])
    assert np.median(err) <= 0.002 * 6 ** 2 / 4 and err.max() <= 0.002 * 8 ** 2 / 4, (np.median(err), err.max())
    # the interpolated point lies near the pixel it stands for
    assert np.abs(X[cov, :2] - np.column_stack([u.ravel(), v.ravel()])[cov]).max() < 3.0
    # and a few rings give a worse surface than many: the paraboloid from 3x sparser rings
    uv3, P3, ring3, _ = _ring_samples(w, h, step=18.0)
    X3, cov3 = interpolate_surface(uv3, P3, ring3, q, width=w, height=h, max_gap_mm=40.0)
    err3 = np.abs(X3[cov3, 2] - 0.002 * ((X3[cov3, 0] - cx) ** 2 + (X3[cov3, 1] - cy) ** 2))
    assert np.median(err3) > 4 * np.median(err)


def test_interpolation_does_not_bridge_a_missing_ring():
    w, h = 200, 160
    uv, P, ring, (cx, cy) = _ring_samples(w, h, drop=lambda j, a: j == 5 and 0.5 < a < 1.5)
    v, u = np.mgrid[0:h, 0:w]
    rr = np.hypot(u - cx, v - cy).ravel()
    ang = np.arctan2(v - cy, u - cx).ravel()
    q = np.arange(w * h)
    _, cov = interpolate_surface(uv, P, ring, q, width=w, height=h, max_gap_mm=8.0)
    hole = (rr > 8 + 6 * 4 + 2) & (rr < 8 + 6 * 6 - 2) & (ang > 0.8) & (ang < 1.2)
    assert hole.sum() > 50 and not cov[hole].any()
    # Dense samples (ring -1 at pixel centres) give their pixel its own point.
    d_uv = np.array([[10.0, 20.0], [11.0, 20.0]])
    d_P = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    X, cov = interpolate_surface(d_uv, d_P, np.array([-1, -1]), np.array([20 * w + 11, 20 * w + 12]), width=w,
                                 height=h, max_gap_mm=1.0)
    assert cov.tolist() == [True, False] and np.array_equal(X[0], d_P[1])
    X, cov = interpolate_surface(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0), np.arange(5), width=w, height=h,
                                 max_gap_mm=1.0)
    assert not cov.any()


def test_min_rings_and_settings():
    runs = [{"rings": 7, "surface_p95_mm": 0.9, "coverage": 0.95}, {"rings": 15, "surface_p95_mm": 0.3, "coverage": 0.8},
            {"rings": 31, "surface_p95_mm": 0.15, "coverage": 0.93}, {"rings": None, "surface_p95_mm": 0.01,
                                                                         "coverage": 0.99}]
    assert min_rings(runs, (1.0, 0.5, 0.2, 0.1), 0.9) == {"1": 7, "0.5": 31, "0.2": 31, "0.1": None}
    with pytest.raises(ValueError, match="bits"):
        SweepSettings(bits=(11,))
    with pytest.raises(ValueError, match="below one projector pixel"):
        SweepSettings(bits=(10,), radius=520.0)
    with pytest.raises(ValueError, match="radius"):
        SweepSettings(rho0=10.0, radius=5.0)
    img = plot_sweep(runs, title="t")
    assert img.shape == (600, 960, 3) and img.dtype == np.uint8 and (img < 128).any()
    # the error targets and the least coverage are drawn as horizontal lines at their values
    fig = sweep_figure(runs, targets_mm=(0.5, 0.1), min_coverage=0.9)
    err_ax, cov_ax = fig.axes
    flat = {float(ln.get_ydata()[0]) for ln in err_ax.get_lines() if len(set(ln.get_ydata())) == 1
            and len(ln.get_ydata()) == 2}
    assert flat == {0.5, 0.1}
    assert [float(ln.get_ydata()[0]) for ln in cov_ax.get_lines() if len(ln.get_ydata()) == 2] == [0.9]


@pytest.fixture(scope="module")
def sweep_result(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    # a 240x192 camera (same field of view as 320x256, ~half the work): the sphere covers ~5100
    # pixels (~9000 at 320x256); measured medians 2.95, 0.034, 0.0074 mm, coverage 0.77-0.82. Two gray-rings
    # runs (3 and 63 rings) and the dense one: the error falls over the three (a 15-ring run between the two,
    # measured 0.17 mm, added a render and little else)
    res = run_sweep(out, scene="sphere", rig=small_rig(240, 192), settings=SweepSettings(bits=(2, 6)), progress=False)
    return out, res


def test_sweep_error_falls_as_rings_rise(sweep_result):
    out, res = sweep_result
    runs = res["runs"]
    assert [r["codec"] for r in runs] == ["gray-rings"] * 2 + ["phase-rings"]
    assert [r["rings"] for r in runs[:2]] == [3, 63]
    assert [r["pitch"] for r in runs[:2]] == [128.0, 8.0]  # (520 - 8) / 2**bits
    med = [r["surface_median_mm"] for r in runs]
    p95 = [r["surface_p95_mm"] for r in runs]
    assert med[0] > med[1] > med[2], med
    assert p95[0] > p95[1] > p95[2], p95
    assert med[0] > 1.0 and med[1] < 0.05  # 3 rings cannot hold a sphere, 63 can
    assert all(r["coverage"] > 0.6 for r in runs)
    assert runs[1]["rings_on_object"] > 30
    # the same pixels each run, and the sphere in view (~5100 pixels on this camera)
    assert all(r["object_pixels"] == runs[0]["object_pixels"] > 4000 for r in runs)


def test_sweep_files(sweep_result):
    out, res = sweep_result
    assert read_json(out / "sweep.json") == res | {"time_s": res["time_s"]}
    rows = list(csv.DictReader((out / "sweep.csv").open()))
    assert len(rows) == 3 and rows[0]["rings"] == "3" and rows[-1]["rings"] == ""
    assert float(rows[1]["surface_median_mm"]) == pytest.approx(res["runs"][1]["surface_median_mm"])
    img = cv2.imread(str(out / "sweep.png"))
    assert img is not None and img.shape == (600, 960, 3)
    assert (out / "sweep.svg").read_text().lstrip().startswith("<?xml") and "<svg" in (out / "sweep.svg").read_text()
    assert set(res["min_rings"]) == {"0.5", "0.2", "0.1", "0.05"}
    assert not (out / "scans").exists()


def test_cli_sweep(tmp_path, capsys):
    rig_file = tmp_path / "rig.json"
    save_rig(rig_file, small_rig(160, 128))  # 7 rings against 5 mm and 0.01 mm: far either side at any camera size
    assert main(["sweep", "--scene", "sphere", "--out", str(tmp_path / "s"), "--bits", "3", "--no-dense",
                 "--rig", str(rig_file), "--targets", "5,0.01", "--min-coverage", "0.5", "--keep-scans",
                 "--no-progress", "--device", "cpu"]) == 0
    text = capsys.readouterr().out
    assert "surface p95 <= 5 mm" in text and "7 rings" in text and "not reached" in text
    res = read_json(tmp_path / "s" / "sweep.json")
    assert res["min_rings"] == {"5": 7, "0.01": None}
    assert (tmp_path / "s" / "scans").is_dir()
    assert main(["sweep", "--scene", "sphere", "--out", str(tmp_path / "t"), "--bits", "x"]) == 2
    assert "--bits" in capsys.readouterr().err
