"""A view's PLY holds each residual in one unit: ``residual`` in px (the angle's or a second
camera's), ``sector_residual`` in sector widths (the rings alone), NaN where a point has
none; no -1 (docs/formats.md, "Outputs")."""

from __future__ import annotations

import numpy as np
import pytest

from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.simulate.scan import simulate_scan
from tests.support.tiny_scan import TINY_PATTERNS, tiny_rig


@pytest.fixture(scope="module")
def angle_scan(tmp_path_factory):
    """The tiny scan (one view) with the angle code: both projector coordinates."""
    spec = parse_patterns({**TINY_PATTERNS, "angle_steps": 4, "angle_period": 12.0})
    return simulate_scan(tmp_path_factory.mktemp("units") / "scan", scene="sphere", size_mm=40.0, rig=tiny_rig(),
                         patterns=spec, progress=False)


def _ply(scan, out, constraint):
    rep = reconstruct_scan(scan, out, settings=ReconstructSettings(triangulate=TriangulateSettings(
        constraint=constraint)), progress=False)
    return read_ply(out / "view_000.ply"), rep["views"][0]


def test_the_angles_points_have_px_the_rings_points_sector_widths(angle_scan, tmp_path):
    both, vb = _ply(angle_scan, tmp_path / "both", "both")
    rings, vr = _ply(angle_scan, tmp_path / "rings", "rings")
    for ply in (both, rings):
        assert ply["residual"].dtype == np.float32 and ply["sector_residual"].dtype == np.float32
        # one of the two per point at most, never the old -1
        assert not np.any(np.isfinite(ply["residual"]) & np.isfinite(ply["sector_residual"]))
        assert np.all(ply["residual"][np.isfinite(ply["residual"])] >= 0)
        assert np.all(ply["sector_residual"][np.isfinite(ply["sector_residual"])] >= 0)
    # both coordinates: nearly every point (99.6 % measured) placed by the angle, its epipolar
    # distance in projector px (the virtual rig fits its images: 0.08 px median; at most
    # max_residual_px, 2 px, or the point is dropped as inconsistent)
    px = np.isfinite(both["residual"])
    assert px.mean() > 0.95 and np.median(both["residual"][px]) < 0.3 and both["residual"][px].max() <= 2.0
    assert vb["median_residual"] == pytest.approx(float(np.median(both["residual"][px])), rel=1e-6)
    # the rings alone: no px residual; how far outside its sector, within the sector tolerance
    assert np.all(np.isnan(rings["residual"])) and vr["median_residual"] is None
    sr = rings["sector_residual"]
    tol = TriangulateSettings().sector_tolerance
    # 93 % inside their sector measured, the rest at most 0.22 sector widths out
    assert np.all(np.isfinite(sr)) and np.all(sr <= tol) and np.mean(sr == 0) > 0.85
