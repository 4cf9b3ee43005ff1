"""The cone model (a perspective projector) end to end on the virtual rig:
simulate -> reconstruct -> evaluate, next to the parallel light on the same scene.
The full-size figures are benchmarks/cone_accuracy.py's (docs/accuracy.md)."""

import dataclasses
import math

import numpy as np
import pytest

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import default_rig, look_at
from ringscan.pipeline.geometry import projector_polar
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan

PATTERNS = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0,
            "pitch": 16.0, "bits": 5, "sector_bits": 4}


def small(rig):
    """``rig`` with a 320x256 camera (f scaled to keep the field of view): fast."""
    K = np.array([[650.0, 0, 159.5], [0, 650.0, 127.5], [0, 0, 1]])
    return dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, width=320, height=256, K=K))


def tilted_projector_rig():
    """The built-in perspective rig's projector moved to the camera's far side,
    tilted 15 degrees, with lens distortion: oblique cones and Newton refinement."""
    rig = default_rig(light_model="perspective")
    a = math.radians(15.0)
    target = np.array([0.0, 0.0, 25.0])
    R, t = look_at(target + 575.0 * np.array([0.0, math.sin(a), math.cos(a)]), target)
    return dataclasses.replace(rig, light=dataclasses.replace(rig.light, R=R, t=t,
                                                              dist=np.array([-0.08, 0.05, 0.001, 0.0, 0.0])))


RIGS = {"parallel": default_rig(), "perspective": default_rig(light_model="perspective"),
        "perspective-tilted": tilted_projector_rig()}


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    out = {}
    for name, rig in RIGS.items():
        folder = tmp_path_factory.mktemp(name)
        scan = simulate_scan(folder / "scan", scene="sphere", rig=small(rig), patterns=parse_patterns(PATTERNS),
                             progress=False)
        rep = reconstruct_scan(scan, folder / "rec", progress=False)
        out[name] = (scan, rep, evaluate_recon(folder / "rec", scan)["all"], read_ply(folder / "rec" / "view_000.ply"))
    return out


@pytest.mark.parametrize("name", ["perspective", "perspective-tilted"])
def test_cone_path_runs_end_to_end_within_a_loose_bound(results, name):
    scan, rep, ev, _ = results[name]
    assert rep["totals"]["points"] > 2000
    assert ev["median_mm"] < 0.05, ev        # camera pixels of 0.65 mm here
    assert ev["frac_over_1mm"] < 0.005, ev
    assert ev["coverage_mean"] > 0.8, ev
    # As many points as the parallel light gives on the same scene, give or take.
    assert rep["totals"]["points"] > 0.7 * results["parallel"][1]["totals"]["points"]


@pytest.mark.parametrize("name", ["perspective", "perspective-tilted"])
def test_cone_points_lie_on_their_ring_by_opencv(results, name):
    """Each point, projected into the projector by cv2.projectPoints (independent of
    the kernels' cone solve and Newton refinement), lands on its ring's circle."""
    scan, _, _, ply = results[name]
    X = np.stack([ply["x"], ply["y"], ply["z"]], 1).astype(np.float64)
    rho = projector_polar(scan.rig, X, scan.patterns.center)
    err = np.abs(rho - ply["rho"])
    # float32 points: ~1e-4 px; the undistorted cone alone would be ~0.2 px off (tilted rig).
    assert np.median(err) < 0.002 and np.percentile(err, 99) < 0.01, (np.median(err), err.max())
