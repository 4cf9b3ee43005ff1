"""``evaluate`` on clouds with NaN or infinite points: they are left out and counted,
a cloud of nothing but NaN covers nothing, and the JSON written is strict JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ringscan.pipeline.evaluate.metrics import evaluate_against_mesh, evaluate_recon, evaluate_view, truth_points
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.ply import read_ply, write_ply
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.tools.cli import main
from tests.support.tiny_scan import TINY_PATTERNS, simulate_tiny_scan, tiny_rig


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    scan = simulate_tiny_scan(root / "scan")
    reconstruct_scan(scan, root / "rec", device="cpu", progress=False)
    return scan, root / "rec"


def _with_points(path, ply, pts):
    write_ply(path, {**ply, "x": pts[:, 0].astype(np.float32), "y": pts[:, 1].astype(np.float32),
                     "z": pts[:, 2].astype(np.float32)})
    return path


def _strict(path):
    def no_constants(name):
        raise AssertionError(f"{name} in {path}: not JSON")

    return json.loads(path.read_text(), parse_constant=no_constants)


def test_non_finite_points_are_left_out_and_counted(recon, tmp_path):
    scan, rec = recon
    ply = read_ply(rec / "view_000.ply")
    pts = np.stack([ply["x"], ply["y"], ply["z"]], 1).astype(np.float64)
    good = evaluate_recon(rec / "view_000.ply", scan)["views"]["view_000"]
    assert good["points"] > 50 and good["coverage"] > 0.2 and good["non_finite_points"] == 0
    mixed = np.concatenate([pts, np.full((40, 3), np.nan), np.full((10, 3), np.inf)])
    ply_mixed = {k: np.concatenate([v, v[:50]]) for k, v in ply.items()}
    ev = evaluate_recon(_with_points(tmp_path / "mixed.ply", ply_mixed, mixed), scan)["views"]["view_000"]
    assert ev["non_finite_points"] == 50 and ev["points"] == good["points"]
    for k in ("median_mm", "rms_mm", "p95_mm", "frac_over_1mm", "coverage", "coverage_object"):
        assert ev[k] == pytest.approx(good[k]), k


def test_an_all_nan_cloud_covers_nothing_and_writes_strict_json(recon, tmp_path, capsys):
    scan, rec = recon
    ply = read_ply(rec / "view_000.ply")
    nan = _with_points(tmp_path / "nan.ply", ply, np.full((len(ply["x"]), 3), np.nan))
    res = evaluate_recon(nan, scan)
    v = res["views"]["view_000"]
    assert v["coverage"] == 0.0 and v["median_mm"] is None and v["points"] == 0
    assert v["non_finite_points"] == len(ply["x"]) and res["all"]["coverage_mean"] == 0.0
    out = tmp_path / "ev.json"
    assert main(["evaluate", str(nan), "--truth", str(scan.folder), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"left out {len(ply['x'])} point(s) with a NaN or infinite coordinate" in text
    d = _strict(out)
    assert d["views"]["view_000"]["coverage"] == 0.0 and d["all"]["median_mm"] is None


@pytest.mark.parametrize("r", [-1.0, 0.0, float("nan"), float("inf")])
def test_a_coverage_radius_must_be_a_positive_number(recon, capsys, r):
    scan, rec = recon
    with pytest.raises(ValueError, match="coverage radius: expected a finite number of mm > 0"):
        evaluate_recon(rec, scan, coverage_radius_mm=r)
    assert main(["evaluate", str(rec), "--truth", str(scan.folder), "--coverage-radius", str(r)]) == 2
    assert "--coverage-radius: expected a finite number of mm > 0" in capsys.readouterr().err


def test_clouds_that_do_not_match_the_truth_scan(recon, tmp_path):
    scan, rec = recon
    ply = read_ply(rec / "view_000.ply")
    write_ply(tmp_path / "v5.ply", {**ply, "view": np.full(len(ply["x"]), 5, np.int32)})
    with pytest.raises(FormatError, match=r"v5.ply: its points are of view 5, but .*scan.json has 1 view\(s\)"):
        evaluate_recon(tmp_path / "v5.ply", scan)
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "report.json").write_text(json.dumps({"views": [{"name": "view_000"}]}))
    with pytest.raises(FormatError, match=r"report.json: views\[0\]: expected an object with a name and a ply"):
        evaluate_recon(tmp_path / "rec", scan)


def test_a_simulated_wall_is_not_the_object(tmp_path):
    """A 16 mm cube floating in front of a wall at z = 5 (inside the coded annulus): points on the wall cover the
    view but not the object; points on the cube cover the object."""
    scan = simulate_scan(tmp_path / "scan", scene="cube", size_mm=16.0, rig=tiny_rig(), place=(0.0, 0.0, 30.0),
                         wall_z=5.0, patterns=parse_patterns(TINY_PATTERNS), progress=False)
    X, _ = truth_points(scan, "view_000")
    on_wall = np.abs(X[:, 2] - 5.0) < 0.01
    assert on_wall.sum() > 100 and (~on_wall).sum() > 50
    wall = evaluate_view(scan, "view_000", X[on_wall], coverage_radius_mm=1.0)
    assert wall["median_mm"] < 0.01 and 0 < wall["coverage"] < 1 and wall["coverage_object"] == 0.0
    cube = evaluate_view(scan, "view_000", X[~on_wall], coverage_radius_mm=1.0)
    assert cube["coverage_object"] == 1.0
def test_evaluate_plot_and_a_truth_mesh(recon, tmp_path, capsys):
    scan, rec = recon
    plot = tmp_path / "err.svg"
    assert main(["evaluate", str(rec), "--truth", str(scan.folder), "--report", str(tmp_path / "e.json"),
                 "--plot", str(plot), "--no-progress"]) == 0
    assert f"wrote {plot}" in capsys.readouterr().out
    assert "<svg" in plot.read_text()
    by_scan = json.loads((tmp_path / "e.json").read_text())
    # The same cloud against the bare object mesh (same frame at table angle 0): distances only, no coverage.
    res, dists = evaluate_against_mesh(rec, scan.folder / scan.extra["truth"]["mesh"], return_distances=True)
    assert set(dists) == set(res["views"]) == set(by_scan["views"])
    assert res["all"]["coverage_mean"] is None and res["all"]["points"] == by_scan["all"]["points"]
    # the object mesh has no floor: floor points lie farther from it than from the scan's truth (object + plane)
    assert res["all"]["median_mm"] >= by_scan["all"]["median_mm"]
    assert main(["evaluate", str(rec), "--truth", str(scan.folder / scan.extra["truth"]["mesh"]),
                 "--plot", str(tmp_path / "x.gif")]) == 1
    assert "x.gif" in capsys.readouterr().err


def test_truth_rho_at_pixel_centres_and_depth_edges(recon):
    """The truth's ring radius at sub-pixel camera positions (used to count mislabelled ring samples): at a pixel
    centre it is the radius of that pixel's truth point (projector_polar, independent of the interpolation);
    between two pixels on a smooth surface it lies between theirs; across a depth edge it is NaN."""
    from ringscan.pipeline.evaluate.metrics import truth_rho_at
    from ringscan.pipeline.geometry import projector_polar

    scan, _ = recon
    w, h = scan.rig.camera.width, scan.rig.camera.height
    X, pix = truth_points(scan, "view_000")
    grid = np.full((h * w, 3), np.nan)
    grid[pix] = X
    u, v = pix % w, pix // w
    inner = (u > 0) & (u < w - 2) & (v > 0) & (v < h - 2)
    rho_px = projector_polar(scan.rig, X, scan.patterns.center)
    # the tiny camera's pixels are ~1.3 mm at the object: 4 neighbours within 3 mm of their mean on smooth ground
    got = truth_rho_at(scan, "view_000", np.stack([u, v], 1)[inner].astype(np.float64), max_step_mm=3.0)
    smooth = np.isfinite(got)
    assert smooth.mean() > 0.9
    np.testing.assert_allclose(got[smooth], rho_px[inner][smooth], atol=1e-6)  # float64 through and through
    # half way between two horizontal neighbours: between their radii
    mid = truth_rho_at(scan, "view_000", np.stack([u + 0.5, v], 1)[inner].astype(np.float64), max_step_mm=3.0)
    right = np.full(len(pix), np.nan)
    right[inner] = projector_polar(scan.rig, grid[pix[inner] + 1], scan.patterns.center)
    both = np.isfinite(mid) & np.isfinite(right[inner])
    lo = np.minimum(rho_px[inner], right[inner])[both]
    hi = np.maximum(rho_px[inner], right[inner])[both]
    between = (mid[both] >= lo - 1e-6) & (mid[both] <= hi + 1e-6)
    # the radius is not linear in the point (near the light axis the midpoint's can dip below both): almost all
    assert both.sum() > 100 and between.mean() > 0.98, between.mean()
    # a depth edge (the sphere's rim against the plane: neighbours far apart) is not judged
    step = np.linalg.norm(grid[pix[inner] + 1] - grid[pix[inner]], axis=1)
    edge = step > 10.0
    assert edge.sum() > 10 and np.all(np.isnan(mid[edge]))
