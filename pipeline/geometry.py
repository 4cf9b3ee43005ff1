"""Host-side rig geometry (NumPy + OpenCV), written once for the whole pipeline.

The kernels have their own ``@wp.func`` twins in :mod:`ringscan.kernels.geometry`;
this module is what host code (the rings codec's labeller, evaluation, the truth
helpers, the NumPy reference) uses, and what turns a parsed
:class:`~ringscan.pipeline.formats.rig.Rig` into the kernels' camera and light
structs. Camera and projector (perspective light) pixels follow OpenCV's model
(docs/design.md §2), so undistortion and projection are OpenCV's own:
OpenCV's iterative ``undistortPoints`` (with a stopping criterion) and
``cv2.projectPoints``.
"""

from __future__ import annotations

import cv2
import numpy as np

from ringscan.kernels.geometry import (
    LENS_MIN_DET,
    LENS_SEGMENT_SAMPLES,
    UNDISTORT_TOL_PX,
    CameraModel,
    LightModel,
    lens_coefficients,
    make_camera,
    make_parallel_light,
    make_perspective_light,
    monotonic_radius2,
    pole_radius2,
)
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.rig import Camera, ParallelLight, Rig, UncalibratedLight

__all__ = ["UNDISTORT_CRITERIA", "in_lens_region", "camera_model_for", "light_model_for", "undistort_normalized", "project_points", "camera_rays", "camera_pixels", "projector_pixels", "projector_offset", "projector_polar", "light_ray", "light_directions", "plane_point",
           "projector_px_span"]

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
"""Stopping rule of the iterative undistortion: 100 iterations or a step below 1e-14
(normalised units), far below float32 pixel precision."""


def camera_model_for(rig: Rig) -> CameraModel:
    """The kernels' camera struct of ``rig.camera``."""
    c = rig.camera
    return make_camera(c.K, c.dist, c.R, c.t)


def light_model_for(rig: Rig) -> LightModel:
    """The kernels' light struct of ``rig.light`` (parallel or perspective).

    Raises:
        FormatError: the rig's projector is not calibrated (a two-camera rig's
            ``uncalibrated`` light): nothing can be triangulated with it.
    """
    li = rig.light
    _check_calibrated(rig)
    if isinstance(li, ParallelLight):
        return make_parallel_light(li.R, li.t, li.pixel_pitch_mm, li.axis_px)
    return make_perspective_light(li.K, li.dist, li.R, li.t)


def _check_calibrated(rig: Rig) -> None:
    if isinstance(rig.light, UncalibratedLight):
        raise FormatError(None, "the rig's projector is not calibrated (light model 'uncalibrated'): triangulate "
                                "camera to camera (--rays camera-camera), or calibrate the projector "
                                "(ringscan calibrate projector-from-scan, docs/calibration.md)")


def undistort_normalized(camera: Camera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (u, v) -> undistorted normalised coordinates (x', y') in float64.

    ``camera`` is anything with ``K`` (3x3, skew allowed) and ``dist`` (4, 5, 8
    or 12 coefficients, OpenCV's order): a
    camera or a perspective light. The pixels are first normalised with K's
    inverse (so a skewed K is exact), then undistorted by OpenCV's iterative
    solver with :data:`UNDISTORT_CRITERIA`. A pixel without a true inverse (the
    result does not distort back onto it within 0.01 px, or lies past the
    lens's fold, :func:`in_lens_region`) gives NaN: its ray is unknown, as the
    kernels' ``undistort`` says for the same pixel.
    """
    u = np.asarray(u, np.float64)
    v = np.asarray(v, np.float64)
    shape = np.broadcast_shapes(u.shape, v.shape)
    u, v = (a.reshape(-1) for a in np.broadcast_arrays(u, v))
    if u.size == 0:
        return np.zeros(shape), np.zeros(shape)
    K = np.asarray(camera.K, np.float64)
    yd = (v - K[1, 2]) / K[1, 1]
    xd = (u - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    dist = np.asarray(camera.dist, np.float64)
    if not np.any(dist):
        return xd.reshape(shape), yd.reshape(shape)
    pts = np.stack([xd, yd], -1).reshape(-1, 1, 2)
    n = _undistort_iter(pts, np.eye(3), dist).reshape(-1, 2)
    # OpenCV's iteration reports no failure: keep only true inverses (the rule of
    # kernels.geometry.undistort: back onto the pixel, inside the fold-free region)
    back = _cv_distort(n, dist)
    err = np.hypot(K[0, 0] * (back[:, 0] - xd) + K[0, 1] * (back[:, 1] - yd), K[1, 1] * (back[:, 1] - yd))
    bad = ~((err <= UNDISTORT_TOL_PX) & in_lens_region(dist, n[:, 0], n[:, 1]))
    if bad.any():
        n[bad] = np.nan
    return n[:, 0].reshape(shape), n[:, 1].reshape(shape)


def _cv_distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    P = np.c_[xy, np.ones(len(xy))].reshape(-1, 1, 3)
    return cv2.projectPoints(P, np.zeros(3), np.zeros(3), np.eye(3), dist)[0].reshape(-1, 2)


def _distortion_det(dist: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Jacobian determinant of OpenCV's distortion (12 coefficients) at (x, y); -1
    where a rational lens's denominator is not positive (no model there)."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = dist
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    dr = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * den - num * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / (den * den)
    dpx = 2 * (s1 + 2 * s2 * r2)
    dpy = 2 * (s3 + 2 * s4 * r2)
    a = radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x + x * dpx
    b = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
    d = radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x + y * dpy
    return np.where(den > 0, a * d - (b + y * dpx) * (b + x * dpy), -1.0)


def in_lens_region(dist, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Where undistorted normalised points (x, y) lie in the lens's fold-free
    region: the host twin of ``kernels.geometry.in_lens_region`` (lens without
    tangential or thin-prism terms: r^2 below
    :func:`~ringscan.kernels.geometry.monotonic_radius2`; with them, a Jacobian
    determinant above 0.01 at 32 points on the way from the axis; a rational
    lens also inside its denominator's first zero,
    :func:`~ringscan.kernels.geometry.pole_radius2`). NaN points are outside."""
    d = lens_coefficients(dist)
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        ok = _distortion_det(d, x, y) > 0
        if np.any(d[5:8]):
            ok &= x * x + y * y < pole_radius2(d)
        if d[2] == 0 and d[3] == 0 and not np.any(d[8:]):
            return ok & (x * x + y * y < monotonic_radius2(d))
        for k in range(1, LENS_SEGMENT_SAMPLES + 1):
            f = k / LENS_SEGMENT_SAMPLES
            ok &= _distortion_det(d, f * x, f * y) > LENS_MIN_DET
    return ok


def _undistort_iter(pts: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    # OpenCV 4.x names the criteria overload undistortPointsIter; 5.x adds the
    # criteria to undistortPoints itself.
    fn = getattr(cv2, "undistortPointsIter", None)
    if fn is not None:
        return fn(pts, K, dist, None, None, UNDISTORT_CRITERIA)
    return cv2.undistortPoints(pts, K, dist, None, None, None, UNDISTORT_CRITERIA)


def project_points(X: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(n, 2) pixels of world points X (n, 3) through a pinhole (OpenCV model)."""
    X = np.ascontiguousarray(X, np.float64).reshape(-1, 1, 3)
    if X.shape[0] == 0:
        return np.zeros((0, 2))
    rvec = cv2.Rodrigues(np.asarray(R, np.float64))[0]
    return cv2.projectPoints(X, rvec, np.asarray(t, np.float64), np.asarray(K, np.float64),
                             np.asarray(dist, np.float64))[0].reshape(-1, 2)


def camera_rays(rig: Rig, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), unit world directions (n, 3)) of the camera rays through pixels uv (n, 2)."""
    cam = rig.camera
    x, y = undistort_normalized(cam, uv[:, 0], uv[:, 1])
    d = np.stack([x, y, np.ones_like(x)], -1) @ cam.R
    return cam.center, d / np.linalg.norm(d, axis=1, keepdims=True)


def camera_pixels(rig: Rig, X: np.ndarray) -> np.ndarray:
    """(n, 2) camera pixels of world points X (n, 3)."""
    cam = rig.camera
    return project_points(X, cam.R, cam.t, cam.K, cam.dist)


def projector_pixels(rig: Rig, X: np.ndarray) -> np.ndarray:
    """(n, 2) projector pixels (u_p, v_p) that light world points X (n, 3)."""
    li = rig.light
    _check_calibrated(rig)
    X = np.asarray(X, np.float64).reshape(-1, 3)
    if isinstance(li, ParallelLight):
        XL = X @ li.R.T + li.t
        return XL[:, :2] / li.pixel_pitch_mm + li.axis_px
    return project_points(X, li.R, li.t, li.K, li.dist)


def projector_offset(rig: Rig, X: np.ndarray, center) -> np.ndarray:
    """(n, 2) offset p - c on the projector grid of world points X (n, 3)."""
    return projector_pixels(rig, X) - np.asarray(center, np.float64)


def projector_polar(rig: Rig, X: np.ndarray, center) -> np.ndarray:
    """(n,) ring radius rho = |p - c| (projector px) of world points X (n, 3)."""
    off = projector_offset(rig, X, center)
    return np.hypot(off[:, 0], off[:, 1])


def light_ray(rig: Rig, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A point and unit direction (world) of the light's ray through projector pixel p (2,)."""
    li = rig.light
    _check_calibrated(rig)
    if isinstance(li, ParallelLight):
        XL = np.array([li.pixel_pitch_mm * (p[0] - li.axis_px[0]), li.pixel_pitch_mm * (p[1] - li.axis_px[1]), 0.0])
        return li.R.T @ (XL - li.t), li.R.T @ np.array([0.0, 0.0, -1.0])
    x, y = undistort_normalized(li, np.array([p[0]]), np.array([p[1]]))
    d = li.R.T @ np.array([x[0], y[0], 1.0])
    return li.center, d / np.linalg.norm(d)


def light_directions(rig: Rig, X: np.ndarray) -> np.ndarray:
    """(n, 3) unit directions from points X (n, 3) toward the light."""
    li = rig.light
    _check_calibrated(rig)
    if isinstance(li, ParallelLight):
        return np.broadcast_to(li.R.T @ np.array([0.0, 0.0, 1.0]), X.shape)
    d = li.center - X
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def plane_point(rig: Rig, p) -> np.ndarray:
    """Where the light's ray through projector pixel p meets the reference plane z = 0."""
    o, d = light_ray(rig, np.asarray(p, np.float64))
    return o + (-o[2] / d[2]) * d


def projector_px_span(rig) -> float:
    """Camera px that one projector px spans in the middle of the rig's working volume (on the world z axis, the
    light's, halfway between z_min and z_max; the mean of a step along x and along y), 1 where the rig cannot say
    (an uncalibrated light)."""
    vol = rig.volume
    X0 = np.array([0.0, 0.0, 0.5 * (vol.z_min + vol.z_max)])
    X = np.stack([X0, X0 + [0.1, 0.0, 0.0], X0 + [0.0, 0.1, 0.0]])
    cam = rig.camera
    if not (np.asarray(cam.R, np.float64) @ X0 + np.asarray(cam.t, np.float64))[2] > 0:
        return 1.0  # (the volume's middle is not before the camera: a rig whose world says nothing of it)
    try:
        p, c = projector_pixels(rig, X), camera_pixels(rig, X)
    except (ValueError, TypeError):  # (no calibrated light: nothing to say)
        return 1.0
    dp = np.linalg.norm(p[1:] - p[0], axis=1)
    dc = np.linalg.norm(c[1:] - c[0], axis=1)
    ok = (dp > 0) & np.isfinite(dp) & np.isfinite(dc)
    return float(np.mean(dc[ok] / dp[ok])) if ok.any() else 1.0
