"""Two cameras' support kernels (kernels.stereo_support) against float64 NumPy geometry."""

import cv2
import numpy as np
import warp as wp

from ringscan.kernels.geometry import make_camera
from ringscan.kernels.stereo_support import epipolar_distances
from tests.support.stereo_rig import CAM1, CAM2, project_points, surface_hits


def test_epipolar_distances_match_float64_geometry():
    """The kernel's epipolar distance against the float64 construction (OpenCV's undistortion,
    E = [t]x R): exact matches of a distorting pair lie on their lines (0 up to float32), and
    camera-2 pixels moved by known amounts keep the float64 distance within 1e-3 px (float32
    normalised coordinates: ~1e-7 of a 2600 px focal length, times the lens's stretch)."""

    rng = np.random.default_rng(3)
    uv1 = np.c_[rng.uniform(300, 980, 400), rng.uniform(250, 780, 400)]
    X = surface_hits(CAM1, uv1)
    X = X[np.isfinite(X).all(axis=1)]
    uv1, uv2 = project_points(CAM1, X), project_points(CAM2, X)
    uv2_moved = uv2 + rng.normal(0, 1.5, uv2.shape)
    R = CAM2.R @ CAM1.R.T
    t = CAM2.t - R @ CAM1.t
    t = t / np.linalg.norm(t)
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    cm1 = make_camera(CAM1.K, CAM1.dist, CAM1.R, CAM1.t)
    cm2 = make_camera(CAM2.K, CAM2.dist, CAM2.R, CAM2.t)
    scale = float(np.sqrt(CAM2.K[0, 0] * CAM2.K[1, 1]))

    def kernel(a, b):
        return epipolar_distances(wp.array(a.astype(np.float32), dtype=wp.vec2, device="cpu"),
                                  wp.array(b.astype(np.float32), dtype=wp.vec2, device="cpu"), camera1=cm1,
                                  camera2=cm2, E=E, scale=scale, threads=2).numpy()

    def reference(a, b):
        n1 = cv2.undistortPoints(a.reshape(-1, 1, 2), CAM1.K, CAM1.dist,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))[:, 0]
        n2 = cv2.undistortPoints(b.reshape(-1, 1, 2), CAM2.K, CAM2.dist,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))[:, 0]
        line = np.c_[n1, np.ones(len(n1))] @ E.T
        return np.abs(np.sum(line * np.c_[n2, np.ones(len(n2))], 1)) / np.hypot(line[:, 0], line[:, 1]) * scale

    # the float32 inputs are the reference's too: what is compared is the arithmetic
    uv1, uv2, uv2_moved = (a.astype(np.float32).astype(np.float64) for a in (uv1, uv2, uv2_moved))
    assert len(uv1) > 200
    exact = kernel(uv1, uv2)
    assert np.all(np.isfinite(exact)) and np.max(np.abs(exact - reference(uv1, uv2))) < 1e-3
    assert np.median(exact) < 2e-3
    moved = kernel(uv1, uv2_moved)
    assert np.max(np.abs(moved - reference(uv1, uv2_moved))) < 1e-3
    assert np.median(moved) > 0.3  # the moves are seen: ~N(0, 1.5) across the lines
