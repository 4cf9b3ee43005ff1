"""OpenCV's lens model as the reference for the kernels' distortion (tests/kernels/test_geometry.py,
test_ring_quadric.py): its projection of normalised points, the least Jacobian determinant that marks
the fold-free region, and strongly distorted projector lenses (five-coefficient and rational)."""

import cv2
import numpy as np

STRONG_PROJECTOR = {
    # no fold, but far from the undistorted cone: 4 fixed Newton steps kept
    # points tens of px off their ring
    "steep": np.array([-5.0, 20.0, 0.01, 0.01, 0.0]),
    # folds at r = 0.167, inside the projector's field
    "folding": np.array([-12.0, 0.0, 0.0, 0.0, 0.0]),
}
RATIONAL_PROJECTOR = {
    # OpenCV's rational model, steep inside the projector's field (r < 0.17)
    "rational-steep": np.array([-5.0, 20.0, 0.01, 0.01, 0.0, 2.0, -10.0, 0.0]),
    # rational + thin prism, folding inside the field
    "prism-folding": np.array([-12.0, 0.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.05, 0.0, -0.05, 0.0]),
}


def cv_pixels(xy, K, dist):
    """OpenCV's projection of normalised undistorted points (x, y, 1)."""
    P = np.c_[xy, np.ones(len(xy))].astype(np.float64)
    return cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)[0][:, 0]


def cv_min_det(xy, K, dist, samples=64, h=1e-6):
    """Least Jacobian determinant (normalised units, 1 on the axis) of OpenCV's
    projection at ``samples`` points on the segment from the axis to each point:
    > 0 where the point lies in the fold-free region around the axis."""
    out = np.full(len(xy), np.inf)
    for f in np.linspace(1.0 / samples, 1.0, samples):
        q = xy * f
        jx = (cv_pixels(q + [h, 0], K, dist) - cv_pixels(q - [h, 0], K, dist)) / (2 * h)
        jy = (cv_pixels(q + [0, h], K, dist) - cv_pixels(q - [0, h], K, dist)) / (2 * h)
        det = (jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0]) / (K[0, 0] * K[1, 1])
        out = np.minimum(out, det)
    return out
