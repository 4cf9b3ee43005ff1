"""Rings and angle together, end to end on the virtual rig: the angle code's frames
are rendered, decoded and triangulated with the ring; the points fill the bands
where the ring alone is blind, and each has its predicted sigma (the PLY's ``sigma``:
test_reconstruct.py's test_small_scan_truth reads it back)."""

import numpy as np
import pytest

from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.evaluate.metrics import evaluate_view
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.reconstruct.view import reconstruct_view
from ringscan.pipeline.simulate.scan import simulate_scan
from tests.support.reconstruct_rig import PROJ, small_rig
from tests.support.tiny_scan import simulate_tiny_scan


def _settings(constraint):
    return ReconstructSettings(triangulate=TriangulateSettings(constraint=constraint))


def _view(scan, constraint=None):
    """The view's cloud (its ``stats``: reconstruct_scan's view report) and its figures against the truth
    (evaluate_recon's for the view), in memory: the PLY written and read back is not what these tests are about
    (test_reconstruct.py's are)."""
    cloud = reconstruct_view(scan, scan.views[0], settings=_settings(constraint) if constraint else ReconstructSettings())
    return cloud, evaluate_view(scan, scan.views[0].name, cloud.points, sigma=cloud.sigma)


@pytest.fixture(scope="module", params=["gray-rings", "phase-rings"])
def angle_scan(request, tmp_path_factory):
    spec = parse_patterns({"codec": request.param, **PROJ, "rho0": 8.0, "pitch": 16.0, "bits": 5, "sector_bits": 6,
                           "angle_steps": 4, "angle_period": 12.0})
    assert frame_names(spec)[-4:] == ["angle_0", "angle_1", "angle_2", "angle_3"]
    return simulate_scan(tmp_path_factory.mktemp("angle") / "scan", scene="sphere", rig=small_rig(), patterns=spec,
                         progress=False)


def test_both_coordinates_fill_the_blind_bands(angle_scan):
    both, eb = _view(angle_scan)
    rings, er = _view(angle_scan, "rings")
    vb, vr = both.stats, rings.stats
    assert vb["constraint"] == "both" and vr["constraint"] == "rings"
    assert vb["angle_decoded"] > 0.95 * vb["samples"]
    # rings alone drop grazing and ambiguous roots; both coordinates keep them
    assert vr["dropped"]["grazing"] + vr["dropped"]["ambiguous"] > 0.02 * vr["samples"]
    assert vb["dropped"]["grazing"] + vb["dropped"]["ambiguous"] + vb["dropped"]["ill_conditioned"] \
        < 0.2 * (vr["dropped"]["grazing"] + vr["dropped"]["ambiguous"])
    assert vb["points"] > vr["points"]
    assert eb["coverage"] > er["coverage"]
    assert eb["median_mm"] < 1.15 * er["median_mm"]
    assert eb["frac_over_1mm"] < 0.003
    # the virtual rig fits its own images: no calibration floor
    assert not vb["calibration"]["floor_applied"] and vb["calibration"]["residual_px_median"] < 0.2
    assert np.all(both.sigma > 0) and np.median(both.sigma) < 0.1  # mm, camera pixels of 0.65 mm (the PLY's sigma)


def test_angle_alone_places_points_too(angle_scan):
    cloud, e = _view(angle_scan, "angle")
    assert cloud.stats["constraint"] == "angle" and cloud.stats["points"] > 0.5 * cloud.stats["samples"]
    assert e["median_mm"] < 0.2


def test_rings_codec_without_angle_refuses_constraint_both(tmp_path):
    scan = simulate_tiny_scan(tmp_path / "scan")  # gray-rings without angle frames, rendered once per process
    assert scan.patterns.codec == "gray-rings" and not any(n.startswith("angle") for n in frame_names(scan.patterns))
    with pytest.raises(ValueError, match="needs samples with an angle"):
        reconstruct_scan(scan, tmp_path / "rec", settings=_settings("both"), progress=False)


def test_a_view_with_no_sample_under_the_angle_alone_says_why(angle_scan):
    """Frames with no light in them (every pixel below min_contrast): no sample, so no angle
    either; the angle constraint has nothing to place and the view says why instead of
    raising."""
    from ringscan.pipeline.formats.scan import read_view_frames

    frames = read_view_frames(angle_scan, angle_scan.views[0])
    dark = np.zeros_like(frames)
    cloud = reconstruct_view(angle_scan, angle_scan.views[0], settings=_settings("angle"), frames=dark)
    assert cloud.stats["points"] == 0 and cloud.stats["samples"] == 0
    assert cloud.stats["no_points"].startswith("no ring found: no contrast between the white and black frames")
