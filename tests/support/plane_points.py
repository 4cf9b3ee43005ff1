"""Points of a plane facing a pinhole camera, one a pixel, for the neighbour filter's tests
(tests/kernels/test_point_filter.py, test_launch.py)."""

import numpy as np

from ringscan.kernels.geometry import make_camera

def plane_points(w=40, h=30, f=500.0, z=400.0):
    """A camera facing a plane at depth ``z``, the plane's point at every pixel and the pixels' indices."""
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    cam = make_camera(K, None, np.eye(3), np.zeros(3))
    v, u = np.mgrid[0:h, 0:w]
    X = np.stack([(u - w / 2) / f * z, (v - h / 2) / f * z, np.full(u.shape, z)], -1).reshape(-1, 3)
    return cam, X.astype(np.float32), (v * w + u).ravel().astype(np.int32)
