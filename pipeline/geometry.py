"""TODO docstring (ringscan.pipeline.geometry, split from ringscan.pipeline.formats.rig)."""

from __future__ import annotations

import numpy as np

from ringscan.kernels.geometry import make_camera, make_parallel_light, make_perspective_light
from ringscan.pipeline.formats.patterns import PatternSpec
from ringscan.pipeline.formats.rig import Camera, ParallelLight, Rig


def undistort_normalized(camera: Camera, u: np.ndarray, v: np.ndarray, *, iters: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (u, v) -> undistorted normalised coordinates (x', y') in float64,
    by Newton's method on the OpenCV distortion model (as the kernels do)."""
    K = camera.K
    yd = (np.asarray(v, np.float64) - K[1, 2]) / K[1, 1]
    xd = (np.asarray(u, np.float64) - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    k1, k2, p1, p2, k3 = camera.dist
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dr = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
        a = radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x
        b = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
        d = radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x
        det = a * d - b * b
        x, y = x - (d * fx - b * fy) / det, y - (a * fy - b * fx) / det
    return x, y


def camera_model_for(rig: Rig):
    c = rig.camera
    return make_camera(c.K, c.dist, c.R, c.t)


def light_model_for(rig: Rig):
    li = rig.light
    if isinstance(li, ParallelLight):
        return make_parallel_light(li.R, li.t, li.pixel_pitch_mm, li.axis_px)
    return make_perspective_light(li.K, li.dist, li.R, li.t)


def _camera_rays(rig: Rig, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), unit world directions (n, 3)) of the rays through pixels uv."""
    cam = rig.camera
    x, y = undistort_normalized(cam, uv[:, 0], uv[:, 1])
    d = np.stack([x, y, np.ones_like(x)], -1) @ cam.R
    return cam.center, d / np.linalg.norm(d, axis=1, keepdims=True)


def _projector_offset(rig: Rig, spec: PatternSpec, X: np.ndarray) -> np.ndarray:
    """(n, 2) offset p - c on the projector grid of world points X (n, 3)."""
    li = rig.light
    if isinstance(li, ParallelLight):
        XL = X @ li.R.T + li.t
        p = XL[:, :2] / li.pixel_pitch_mm + li.axis_px
    else:
        import cv2

        p = cv2.projectPoints(np.ascontiguousarray(X, np.float64).reshape(-1, 1, 3), cv2.Rodrigues(li.R)[0],
                              li.t.astype(np.float64), li.K, li.dist)[0].reshape(-1, 2)
    return p - np.asarray(spec.center, np.float64)


def _light_ray(rig: Rig, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A point and unit direction (world) of the light's ray through projector pixel p."""
    li = rig.light
    if isinstance(li, ParallelLight):
        XL = np.array([li.pixel_pitch_mm * (p[0] - li.axis_px[0]), li.pixel_pitch_mm * (p[1] - li.axis_px[1]), 0.0])
        return li.R.T @ (XL - li.t), li.R.T @ np.array([0.0, 0.0, -1.0])
    import cv2

    n = cv2.undistortPoints(np.array([[p]], np.float64), li.K, li.dist).ravel()
    d = li.R.T @ np.array([n[0], n[1], 1.0])
    return li.center, d / np.linalg.norm(d)


def _to_camera(rig: Rig, X: np.ndarray) -> np.ndarray:
    import cv2

    cam = rig.camera
    return cv2.projectPoints(np.ascontiguousarray(X, np.float64).reshape(-1, 1, 3), cv2.Rodrigues(cam.R)[0],
                             cam.t.astype(np.float64), cam.K, cam.dist)[0].reshape(-1, 2)


def _light_dirs(rig: Rig, X: np.ndarray) -> np.ndarray:
    """Unit directions from points X toward the light."""
    li = rig.light
    if isinstance(li, ParallelLight):
        return np.broadcast_to(li.R.T @ np.array([0.0, 0.0, 1.0]), X.shape)
    d = li.center - X
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _plane_point(rig: Rig, spec: PatternSpec, p) -> np.ndarray:
    o, d = _light_ray(rig, np.asarray(p, np.float64))
    return o + (-o[2] / d[2]) * d


def _projector_polar(rig: Rig, X: np.ndarray, center) -> np.ndarray:
    import cv2

    li = rig.light
    if isinstance(li, ParallelLight):
        XL = X @ li.R.T + li.t
        p = XL[:, :2] / li.pixel_pitch_mm + li.axis_px
    else:
        p = cv2.projectPoints(X.reshape(-1, 1, 3), cv2.Rodrigues(li.R)[0], li.t, li.K, li.dist)[0].reshape(-1, 2)
    return np.hypot(p[:, 0] - center[0], p[:, 1] - center[1])


def _light_direction(rig: Rig, X: np.ndarray) -> np.ndarray:
    li = rig.light
    if isinstance(li, ParallelLight):
        return np.broadcast_to(li.R.T @ np.array([0.0, 0.0, 1.0]), X.shape)
    d = li.center - X
    return d / np.linalg.norm(d, axis=1, keepdims=True)
