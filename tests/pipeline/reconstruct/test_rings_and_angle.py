"""Rings and angle together, end to end on the virtual rig: the angle code's frames
are rendered, decoded and triangulated with the ring; the points fill the bands
where the ring alone is blind, and their predicted sigma is in the PLY."""

import numpy as np
import pytest

from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.simulate.scan import simulate_scan
from tests.pipeline.reconstruct.test_reconstruct import PROJ, small_rig
from tests.pipeline.reconstruct.tiny_scan import simulate_tiny_scan


def _settings(constraint):
    return ReconstructSettings(triangulate=TriangulateSettings(constraint=constraint))


@pytest.fixture(scope="module", params=["gray-rings", "phase-rings"])
def angle_scan(request, tmp_path_factory):
    spec = parse_patterns({"codec": request.param, **PROJ, "rho0": 8.0, "pitch": 16.0, "bits": 5, "sector_bits": 6,
                           "angle_steps": 4, "angle_period": 12.0})
    assert frame_names(spec)[-4:] == ["angle_0", "angle_1", "angle_2", "angle_3"]
    return simulate_scan(tmp_path_factory.mktemp("angle") / "scan", scene="sphere", rig=small_rig(), patterns=spec,
                         progress=False)


def test_both_coordinates_fill_the_blind_bands(angle_scan, tmp_path):
    both = reconstruct_scan(angle_scan, tmp_path / "both", progress=False)
    rings = reconstruct_scan(angle_scan, tmp_path / "rings", settings=_settings("rings"), progress=False)
    vb, vr = both["views"][0], rings["views"][0]
    assert vb["constraint"] == "both" and vr["constraint"] == "rings"
    assert vb["angle_decoded"] > 0.95 * vb["samples"]
    # rings alone drop grazing and ambiguous roots; both coordinates keep them
    assert vr["dropped"]["grazing"] + vr["dropped"]["ambiguous"] > 0.02 * vr["samples"]
    assert vb["dropped"]["grazing"] + vb["dropped"]["ambiguous"] + vb["dropped"]["ill_conditioned"] \
        < 0.2 * (vr["dropped"]["grazing"] + vr["dropped"]["ambiguous"])
    assert vb["points"] > vr["points"]
    rb = evaluate_recon(tmp_path / "both", angle_scan)
    rr = evaluate_recon(tmp_path / "rings", angle_scan)
    eb, er = rb["all"], rr["all"]
    assert rb["views"]["view_000"]["coverage"] > rr["views"]["view_000"]["coverage"]
    assert eb["median_mm"] < 1.15 * er["median_mm"]
    assert eb["frac_over_1mm"] < 0.003
    # the virtual rig fits its own images: no calibration floor
    assert not vb["calibration"]["floor_applied"] and vb["calibration"]["residual_px_median"] < 0.2
    ply = read_ply(tmp_path / "both" / "view_000.ply")
    assert np.all(ply["sigma"] > 0) and np.median(ply["sigma"]) < 0.1  # mm, camera pixels of 0.65 mm


def test_angle_alone_places_points_too(angle_scan, tmp_path):
    rep = reconstruct_scan(angle_scan, tmp_path / "angle", settings=_settings("angle"), progress=False)
    e = evaluate_recon(tmp_path / "angle", angle_scan)["all"]
    assert rep["views"][0]["points"] > 0.5 * rep["views"][0]["samples"]
    assert e["median_mm"] < 0.2


def test_rings_codec_without_angle_refuses_constraint_both(tmp_path):
    scan = simulate_tiny_scan(tmp_path / "scan")  # gray-rings without angle frames, rendered once per process
    assert scan.patterns.codec == "gray-rings" and not any(n.startswith("angle") for n in frame_names(scan.patterns))
    with pytest.raises(ValueError, match="needs samples with an angle"):
        reconstruct_scan(scan, tmp_path / "rec", settings=_settings("both"), progress=False)
