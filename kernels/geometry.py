"""Camera and light geometry shared by every kernel (docs/design.md §2, §3).

Warp structs hold a camera (OpenCV pinhole with k1, k2, p1, p2, k3 and, for wide
lenses, OpenCV's rational k4, k5, k6 and thin-prism s1..s4 terms) and a light
(parallel or perspective); ``@wp.func`` helpers project, distort, undistort and cast
rays (meeting a camera ray with a ring's quadric is :mod:`ringscan.kernels.ring_quadric`'s).
Host functions build the structs from plain NumPy values, so this module, like
all of kernels/, knows nothing of the rig file (pipeline/ converts it).
"""

from __future__ import annotations

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

LIGHT_PARALLEL = wp.constant(0)
LIGHT_PERSPECTIVE = wp.constant(1)
UNDISTORT_ITERS = wp.constant(20)
UNDISTORT_TOL_PX = wp.constant(0.01)
LENS_SEGMENT_SAMPLES = wp.constant(32)
LENS_MIN_DET = wp.constant(0.01)
NEWTON_STEPS = wp.constant(12)
R2_UNBOUNDED = 1.0e30

__all__ = [
    "LIGHT_PARALLEL",
    "LIGHT_PERSPECTIVE",
    "UNDISTORT_TOL_PX",
    "LENS_SEGMENT_SAMPLES",
    "LENS_MIN_DET",
    "lens_coefficients",
    "monotonic_radius2",
    "pole_radius2",
    "fold_free_radius2",
    "sqrt_limit32",
    "CameraModel",
    "LightModel",
    "make_camera",
    "make_parallel_light",
    "make_perspective_light",
    "distort",
    "undistort",
    "camera_ray",
    "project_camera",
    "light_pixel",
    "light_point_local",
    "direction_to_light",
    "Volume",
    "make_volume",
    "polar_angle",
    "in_volume",
    "light_pixel_ray",
    "closest_on_ray",
]


@wp.struct
class CameraModel:
    """An OpenCV pinhole camera: X_c = R X_w + t, distortion (k1, k2, p1, p2, k3)
    and OpenCV's rational (k4, k5, k6: the radial factor is
    (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)) and thin-prism
    (s1..s4: x'' += s1 r^2 + s2 r^4, y'' += s3 r^2 + s4 r^4) terms.

    ``rational`` / ``prism`` are 1 where any of k4..k6 / s1..s4 is nonzero (set on
    the host): 0 keeps the 5-coefficient arithmetic exactly as it always was.
    ``lens`` is 1 where any coefficient is nonzero (set on the host: one test where
    every sample would otherwise compare twelve of them).
    ``r2_max`` is the squared normalised radius x^2 + y^2 up to which the radial
    distortion r R(r^2) grows with r (1e30 where it always does): beyond it the
    model folds back, and a point there lands on a pixel that a point inside also
    lands on (:func:`monotonic_radius2`). ``r2_pole`` is the least squared radius
    where the rational denominator vanishes (1e30: none); nothing at or past it
    is in the lens's region.
    ``r2_safe`` is a squared radius inside which every point is provably in the
    fold-free region with a margin (:func:`fold_free_radius2`): the per-sample
    fold checks skip their work there (0: never skip)."""

    fx: float
    fy: float
    cx: float
    cy: float
    skew: float
    k1: float
    k2: float
    p1: float
    p2: float
    k3: float
    k4: float
    k5: float
    k6: float
    s1: float
    s2: float
    s3: float
    s4: float
    rational: int
    prism: int
    lens: int
    R: wp.mat33
    t: wp.vec3
    center: wp.vec3
    r2_max: float
    r2_safe: float
    r2_pole: float


@wp.struct
class LightModel:
    """A parallel light (model 0) or a perspective projector (model 1).

    Parallel: X_L = R X_w + t; pixel (u_p, v_p) lights x_L = s (u_p - a_u),
    y_L = s (v_p - a_v). Perspective: an inverse camera in ``cam``. ``distorted``
    is 1 for a perspective light whose lens distorts (set on the host).
    """

    model: int
    distorted: int
    R: wp.mat33
    t: wp.vec3
    s: float
    a: wp.vec2
    cam: CameraModel


@wp.struct
class Volume:
    """The rig's working volume (world frame, mm): z_min <= z <= z_max, radius <= r_max.

    ``r2_limit`` is the largest float32 s whose float32 square root is <= r_max
    (:func:`make_volume`): ``x^2 + y^2 <= r2_limit`` is the radius test to the
    bit, without the square root."""

    z_min: float
    z_max: float
    r_max: float
    r2_limit: float


# ----------------------------------------------------------------------------- helpers


@wp.func
def is_full_model(cam: CameraModel):
    """The lens has rational or thin-prism terms (the general branch of the helpers)."""
    return cam.rational != 0 or cam.prism != 0


@wp.func
def full_model_terms(cam: CameraModel, x: float, y: float):
    """Distortion and Jacobian of the rational + thin-prism model at (x, y).

    Returns (vec2(x'', y''), mat22 d(x'', y'') / d(x, y), den): den is the
    rational denominator 1 + k4 r^2 + k5 r^4 + k6 r^6 (the model is defined
    where it is > 0)."""
    r2 = x * x + y * y
    num = 1.0 + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3))
    den = 1.0 + r2 * (cam.k4 + r2 * (cam.k5 + r2 * cam.k6))
    dnum = cam.k1 + r2 * (2.0 * cam.k2 + 3.0 * cam.k3 * r2)
    dden = cam.k4 + r2 * (2.0 * cam.k5 + 3.0 * cam.k6 * r2)
    radial = num / den
    dr = (dnum * den - num * dden) / (den * den)  # d radial / d r^2
    px = r2 * (cam.s1 + cam.s2 * r2)
    py = r2 * (cam.s3 + cam.s4 * r2)
    dpx = 2.0 * (cam.s1 + 2.0 * cam.s2 * r2)  # d px / d r^2, times 2
    dpy = 2.0 * (cam.s3 + 2.0 * cam.s4 * r2)
    xd = x * radial + 2.0 * cam.p1 * x * y + cam.p2 * (r2 + 2.0 * x * x) + px
    yd = y * radial + cam.p1 * (r2 + 2.0 * y * y) + 2.0 * cam.p2 * x * y + py
    a = radial + 2.0 * x * x * dr + 2.0 * cam.p1 * y + 6.0 * cam.p2 * x + x * dpx
    b = 2.0 * x * y * dr + 2.0 * cam.p1 * x + 2.0 * cam.p2 * y
    J = wp.mat22(a, b + y * dpx, b + x * dpy,
                 radial + 2.0 * y * y * dr + 6.0 * cam.p1 * y + 2.0 * cam.p2 * x + y * dpy)
    return wp.vec2(xd, yd), J, den


@wp.func
def distort(cam: CameraModel, x: float, y: float):
    """Normalised undistorted (x, y) -> normalised distorted (x'', y'')."""
    if is_full_model(cam):
        d, _J, _den = full_model_terms(cam, x, y)
        return d
    r2 = x * x + y * y
    radial = 1.0 + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3))
    xd = x * radial + 2.0 * cam.p1 * x * y + cam.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + cam.p1 * (r2 + 2.0 * y * y) + 2.0 * cam.p2 * x * y
    return wp.vec2(xd, yd)


@wp.func
def distortion_jacobian_det(cam: CameraModel, x: float, y: float):
    """Determinant of d(x'', y'') / d(x, y) at the undistorted point (x, y)
    (-1 where a rational lens's denominator is not positive: no model there)."""
    if is_full_model(cam):
        _d, J, den = full_model_terms(cam, x, y)
        if not (den > 0.0):
            return -1.0
        return wp.determinant(J)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3))
    dr = cam.k1 + r2 * (2.0 * cam.k2 + 3.0 * cam.k3 * r2)
    a = radial + 2.0 * x * x * dr + 2.0 * cam.p1 * y + 6.0 * cam.p2 * x
    b = 2.0 * x * y * dr + 2.0 * cam.p1 * x + 2.0 * cam.p2 * y
    d = radial + 2.0 * y * y * dr + 6.0 * cam.p1 * y + 2.0 * cam.p2 * x
    return a * d - b * b


@wp.func
def has_tangential(cam: CameraModel):
    return cam.p1 != 0.0 or cam.p2 != 0.0


@wp.func
def has_lens_distortion(cam: CameraModel):
    return cam.lens != 0


@wp.func
def needs_segment_test(cam: CameraModel):
    """The fold-free region is not a disc: tangential or thin-prism terms."""
    return has_tangential(cam) or cam.prism != 0


@wp.func
def locally_unfolded(cam: CameraModel, x: float, y: float):
    """The distortion is locally invertible at (x, y): a positive Jacobian,
    inside the rational denominator's first zero ``cam.r2_pole`` and, for a lens
    without tangential or thin-prism terms, inside its monotonic radius
    ``cam.r2_max``."""
    r2 = x * x + y * y
    if r2 < cam.r2_safe:
        return True  # the full test's answer, known on the host (fold_free_radius2)
    ok = distortion_jacobian_det(cam, x, y) > 0.0
    if not needs_segment_test(cam):
        ok = ok and r2 < cam.r2_max
    if cam.rational != 0:
        ok = ok and r2 < cam.r2_pole
    return ok


@wp.func
def in_lens_region(cam: CameraModel, x: float, y: float):
    """(x, y) lies in the fold-free region around the optical axis, where the
    distortion maps undistorted points one to one onto pixels. Radial-only
    lens: exactly r^2 < ``cam.r2_max``. With tangential or thin-prism terms the Jacobian
    determinant (1 on the axis) must stay above ``LENS_MIN_DET`` at (x, y) and at
    ``LENS_SEGMENT_SAMPLES`` - 1 evenly spaced points on the way from the axis:
    a sampled test, so it asks for a margin (a lens that squeezes area 100-fold
    is not a model of anything real), which also catches fold bands too thin to
    fall on a sample. Inside ``cam.r2_safe`` the answer is known (True) without
    the samples (:func:`fold_free_radius2`)."""
    if x * x + y * y < cam.r2_safe:
        return True
    ok = locally_unfolded(cam, x, y)
    if ok and needs_segment_test(cam):
        for k in range(1, LENS_SEGMENT_SAMPLES + 1):
            f = float(k) / float(LENS_SEGMENT_SAMPLES)
            if distortion_jacobian_det(cam, f * x, f * y) <= LENS_MIN_DET:
                ok = False
    return ok


@wp.func
def undistort(cam: CameraModel, xd: float, yd: float):
    """Normalised distorted -> undistorted, by Newton's method on the 2x2 system
    (float32). Returns vec3(x, y, ok).

    Newton converges quadratically, so once a step is below 1e-6 (~0.003 px at
    f = 2600 px) the error left is far below float32's resolution; that stops it
    after 2-3 steps. The iteration starts at (xd, yd), or nearer the axis where
    that point is folded, and a step that would land where the distortion folds
    (:func:`locally_unfolded`) is halved until it does not, so the iteration
    cannot converge on the polynomial's far branch. ok = 1 only where the result
    is a true inverse: in the fold-free region (:func:`in_lens_region`) and
    distorting back onto the pixel within ``UNDISTORT_TOL_PX``. ok = 0 where the
    pixel has no such inverse (beyond the image of that region, or the
    iteration did not converge): such a pixel's ray is unknown and must be
    dropped, never used."""
    if not has_lens_distortion(cam):
        # the iteration's first step is exactly 0, the point distorts back onto
        # itself, and the region test is r^2 < r2_max: the same answer at once
        ok0 = wp.where(xd * xd + yd * yd < cam.r2_max, 1.0, 0.0)
        return wp.vec3(xd, yd, ok0)
    x = xd
    y = yd
    for _h in range(60):
        if in_lens_region(cam, x, y):
            break
        x = 0.5 * x
        y = 0.5 * y
    full = is_full_model(cam)
    for _i in range(UNDISTORT_ITERS):
        sx = float(0.0)
        sy = float(0.0)
        if full:
            # rational / thin-prism lens: the same Newton step with the general Jacobian
            dd, J, _den = full_model_terms(cam, x, y)
            gx = dd[0] - xd
            gy = dd[1] - yd
            detJ = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
            if wp.abs(detJ) < 1.0e-12:
                break
            sx = (J[1, 1] * gx - J[0, 1] * gy) / detJ
            sy = (J[0, 0] * gy - J[1, 0] * gx) / detJ
        else:
            # the 5-coefficient lens: these expressions are kept exactly as they were
            r2 = x * x + y * y
            radial = 1.0 + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3))
            dr = cam.k1 + r2 * (2.0 * cam.k2 + 3.0 * cam.k3 * r2)
            fx = x * radial + 2.0 * cam.p1 * x * y + cam.p2 * (r2 + 2.0 * x * x) - xd
            fy = y * radial + cam.p1 * (r2 + 2.0 * y * y) + 2.0 * cam.p2 * x * y - yd
            a = radial + 2.0 * x * x * dr + 2.0 * cam.p1 * y + 6.0 * cam.p2 * x
            b = 2.0 * x * y * dr + 2.0 * cam.p1 * x + 2.0 * cam.p2 * y
            d = radial + 2.0 * y * y * dr + 6.0 * cam.p1 * y + 2.0 * cam.p2 * x
            det = a * d - b * b
            if wp.abs(det) < 1.0e-12:
                break
            sx = (d * fx - b * fy) / det
            sy = (a * fy - b * fx) / det
        for _h in range(30):
            if locally_unfolded(cam, x - sx, y - sy):
                break
            sx = 0.5 * sx
            sy = 0.5 * sy
        x = x - sx
        y = y - sy
        if wp.abs(sx) + wp.abs(sy) < 1.0e-6:
            break
    back = distort(cam, x, y)
    ex = cam.fx * (back[0] - xd) + cam.skew * (back[1] - yd)
    ey = cam.fy * (back[1] - yd)
    ok = float(0.0)
    if ex * ex + ey * ey <= UNDISTORT_TOL_PX * UNDISTORT_TOL_PX and in_lens_region(cam, x, y):
        ok = 1.0
    return wp.vec3(x, y, ok)


@wp.func
def camera_ray(cam: CameraModel, u: float, v: float):
    """The ray through pixel (u, v): (unit world direction (origin: cam.center),
    ok). ok is False where the pixel has no undistorted point (:func:`undistort`):
    the direction is then meaningless and the pixel must be dropped."""
    yd = (v - cam.cy) / cam.fy
    xd = (u - cam.cx - cam.skew * yd) / cam.fx
    n = undistort(cam, xd, yd)
    dc = wp.vec3(n[0], n[1], 1.0)
    return wp.normalize(wp.transpose(cam.R) * dc), n[2] > 0.0


@wp.func
def project_camera(cam: CameraModel, X: wp.vec3):
    """World point -> (u, v, Z_c): pixel with distortion and the camera-frame depth."""
    Xc = cam.R * X + cam.t
    z = Xc[2]
    zs = wp.where(wp.abs(z) > 1.0e-12, z, 1.0e-12)
    d = distort(cam, Xc[0] / zs, Xc[1] / zs)
    return wp.vec3(cam.fx * d[0] + cam.skew * d[1] + cam.cx, cam.fy * d[1] + cam.cy, z)


@wp.func
def light_point_local(light: LightModel, X: wp.vec3):
    """World point -> light frame (parallel) or projector frame (perspective)."""
    if light.model == LIGHT_PARALLEL:
        return light.R * X + light.t
    return light.cam.R * X + light.cam.t


@wp.func
def light_pixel(light: LightModel, X: wp.vec3):
    """World point -> (u_p, v_p, valid) on the projector pixel grid.

    valid is 0 when the point is behind a perspective projector.
    """
    if light.model == LIGHT_PARALLEL:
        XL = light.R * X + light.t
        return wp.vec3(XL[0] / light.s + light.a[0], XL[1] / light.s + light.a[1], 1.0)
    p = project_camera(light.cam, X)
    return wp.vec3(p[0], p[1], wp.where(p[2] > 1.0e-6, 1.0, 0.0))


@wp.func
def direction_to_light(light: LightModel, X: wp.vec3):
    """Unit world direction from X toward the light source."""
    if light.model == LIGHT_PARALLEL:
        return wp.transpose(light.R) * wp.vec3(0.0, 0.0, 1.0)
    return wp.normalize(light.cam.center - X)


@wp.func
def polar_angle(y: float, x: float):
    """atan2(y, x) in (-pi, pi] to within 1e-5 rad (Abramowitz & Stegun 4.4.49 on
    [0, 1] with octant reduction), at a fraction of the cost of the library atan2:
    the polar angle of a point around the pattern centre (sectors, phase)."""
    ax = wp.abs(x)
    ay = wp.abs(y)
    mx = wp.max(ax, ay)
    if mx == 0.0:
        return 0.0
    a = wp.min(ax, ay) / mx
    s = a * a
    r = a * (0.9998660 + s * (-0.3302995 + s * (0.1801410 + s * (-0.0851330 + s * 0.0208351))))
    if ay > ax:
        r = 1.5707963267948966 - r
    if x < 0.0:
        r = 3.141592653589793 - r
    if y < 0.0:
        r = -r
    return r


@wp.func
def in_volume(X: wp.vec3, vol: Volume):
    # sqrt(r2) <= r_max, decided exactly without the square root (Volume.r2_limit)
    r2 = X[0] * X[0] + X[1] * X[1]
    return X[2] >= vol.z_min and X[2] <= vol.z_max and r2 <= vol.r2_limit


@wp.func
def light_pixel_ray(light: LightModel, u: float, v: float):
    """The light's ray through projector pixel (u, v) (lens distortion undone).

    Returns (origin, unit direction, ok) in the world frame; ok is False where the
    projector pixel has no undistorted point (:func:`undistort`)."""
    if light.model == LIGHT_PARALLEL:
        XL = wp.vec3(light.s * (u - light.a[0]), light.s * (v - light.a[1]), 0.0)
        RT = wp.transpose(light.R)
        return RT * (XL - light.t), RT * wp.vec3(0.0, 0.0, -1.0), True
    c = light.cam
    yd = (v - c.cy) / c.fy
    xd = (u - c.cx - c.skew * yd) / c.fx
    n = undistort(c, xd, yd)
    return c.center, wp.normalize(wp.transpose(c.R) * wp.vec3(n[0], n[1], 1.0)), n[2] > 0.0


@wp.func
def closest_on_ray(C: wp.vec3, d: wp.vec3, O: wp.vec3, e: wp.vec3):
    """Parameter t of the point of the ray C + t d (d unit) nearest the line O + s e
    (e unit); 0 where the two are parallel."""
    w = C - O
    b = wp.dot(d, e)
    den = 1.0 - b * b
    if den < 1.0e-12:
        return 0.0
    return (b * wp.dot(e, w) - wp.dot(d, w)) / den


# ----------------------------------------------------------------------------- host builders


def lens_coefficients(dist) -> np.ndarray:
    """OpenCV's distortion vector (up to 12 coefficients: k1, k2, p1, p2, k3, k4,
    k5, k6, s1, s2, s3, s4; a 14-vector's tilt taux, tauy only when both are 0)
    padded with zeros to 12.

    Raises:
        ValueError: more than 14 coefficients, or a nonzero tilt."""
    dd = np.asarray(dist if dist is not None else [], float).ravel()
    if dd.size > 14 or (dd.size > 12 and np.any(dd[12:] != 0)):
        raise ValueError(f"distortion: {dd.size} coefficients {dd.tolist()}: the tilted-sensor model (taux, tauy) "
                         "is not supported")
    d = np.zeros(12)
    d[: min(dd.size, 12)] = dd[:12]
    return d


def _least_positive_root(coef_low_first) -> float:
    coef = np.trim_zeros(np.asarray(coef_low_first, float)[::-1], "f")
    if coef.size < 2:
        return R2_UNBOUNDED
    roots = np.roots(coef)
    s = roots.real[(np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots.real))) & (roots.real > 0)]
    return float(min(s.min(), R2_UNBOUNDED)) if s.size else R2_UNBOUNDED


def pole_radius2(dist) -> float:
    """Least squared normalised radius s > 0 where the rational denominator
    1 + k4 s + k5 s^2 + k6 s^3 of ``dist`` vanishes; ``R2_UNBOUNDED`` where none."""
    d = lens_coefficients(dist)
    return _least_positive_root([1.0, d[5], d[6], d[7]])


def monotonic_radius2(dist) -> float:
    """Squared normalised radius up to which the radial distortion of ``dist``
    (OpenCV order k1, k2, p1, p2, k3[, k4, k5, k6, ...]) is monotonic: the least
    s = r^2 > 0 with d/dr [r (1 + k1 s + k2 s^2 + k3 s^3)] = 1 + 3 k1 s + 5 k2 s^2
    + 7 k3 s^3 = 0, and for a rational lens (radial factor N(s) / D(s)) the least
    s > 0 where D vanishes or d/dr [r N / D] = (N D + 2 s (N' D - N D')) / D^2 does;
    ``R2_UNBOUNDED`` (1e30) where there is none."""
    d = lens_coefficients(dist)
    k1, k2, _p1, _p2, k3, k4, k5, k6 = d[:8]
    if k4 == k5 == k6 == 0.0:
        return _least_positive_root([1.0, 3.0 * k1, 5.0 * k2, 7.0 * k3])
    N = np.polynomial.Polynomial([1.0, k1, k2, k3])
    D = np.polynomial.Polynomial([1.0, k4, k5, k6])
    s = np.polynomial.Polynomial([0.0, 1.0])
    growth = N * D + 2.0 * s * (N.deriv() * D - N * D.deriv())
    return min(_least_positive_root(growth.coef), pole_radius2(d))


def fold_free_radius2(dist) -> float:
    """A squared normalised radius s inside which the lens of ``dist`` (OpenCV order
    k1, k2, p1, p2, k3) is provably fold-free with a margin: the Jacobian
    determinant of the distortion is >= 2 ``LENS_MIN_DET`` everywhere in the disc
    x^2 + y^2 <= s, so :func:`locally_unfolded` and :func:`in_lens_region` answer
    True there whatever their float32 rounding, and may skip their work.

    With R = 1 + k1 s + k2 s^2 + k3 s^3, D = dR/ds, M = R + 2 s D and P = |(p1, p2)|,
    the determinant at radius r = sqrt(s) is R M plus tangential terms bounded by
    12 P r (|R| + 2 s |D|) + 4 P r s |D| + 40 P^2 s; each factor is bounded by its
    coefficients' absolute values, which makes the bound decrease with s, so
    where it holds at s it holds on the whole disc (bisection finds the largest
    such s). ``R2_UNBOUNDED`` for a lens without distortion; 0 where even the
    axis has no margin. A lens with rational (k4..k6) or thin-prism (s1..s4) terms:
    :func:`_fold_free_radius2_full`."""
    full = lens_coefficients(dist)
    if np.any(full[5:] != 0):
        return _fold_free_radius2_full(full)
    k1, k2, p1, p2, k3 = (abs(float(v)) for v in full[:5])
    if not np.all(np.isfinite([k1, k2, p1, p2, k3])):
        return 0.0
    if k1 == k2 == p1 == p2 == k3 == 0.0:
        return R2_UNBOUNDED
    P = float(np.hypot(p1, p2))
    need = 2.0 * float(LENS_MIN_DET)

    def bound(s):
        r = np.sqrt(s)
        r_lo = 1.0 - s * (k1 + s * (k2 + s * k3))
        m_lo = 1.0 - s * (3.0 * k1 + s * (5.0 * k2 + s * 7.0 * k3))
        r_hi = 1.0 + s * (k1 + s * (k2 + s * k3))
        d_hi = k1 + s * (2.0 * k2 + s * 3.0 * k3)
        if r_lo <= 0.0 or m_lo <= 0.0:
            return -1.0
        return r_lo * m_lo - 12.0 * P * r * (r_hi + 2.0 * s * d_hi) - 4.0 * P * r * s * d_hi - 40.0 * P * P * s

    if not bound(0.0) >= need:
        return 0.0
    lo, hi = 0.0, 1.0
    while bound(hi) >= need and hi < 1.0e6:
        lo, hi = hi, 2.0 * hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if bound(mid) >= need else (lo, mid)
    # The radial-only test also compares with r2_max: stay clear of it in float32 too.
    return float(min(lo, 0.99 * monotonic_radius2(dist)))


def _extremes(num, den, s: float) -> tuple[float, float]:
    """(min, max) of the rational function num / den (numpy Polynomials, den > 0
    on [0, s]) over t in [0, s]: at the ends or where its derivative vanishes."""
    crit = (num.deriv() * den - num * den.deriv()).trim()
    ts = [0.0, s]
    if crit.degree() >= 1 and np.any(crit.coef != 0):
        roots = crit.roots()
        ts += [float(t.real) for t in roots if abs(t.imag) <= 1e-9 * max(1.0, abs(t.real)) and 0.0 < t.real < s]
    vals = [float(num(t) / den(t)) for t in ts]
    return min(vals), max(vals)


def _fold_free_radius2_full(full) -> float:
    """:func:`fold_free_radius2` for a lens with rational (k4..k6) or thin-prism
    (s1..s4) terms (``full``: the 12 coefficients).

    The radial map x R(t), t = r^2, R = N / D, has Jacobian determinant R M with
    M = R + 2 t R'. Over the disc t <= s its least value is at least
    min R * min M (both > 0), the extremes of these rational functions of t taken
    exactly on [0, s] (at the ends or at roots of their derivatives' numerators:
    cancelling terms, as in a fitted wide-angle lens, are accounted for). The
    tangential and thin-prism terms add E with |E_ij| <= e = (6 P + Q) r, P =
    |(p1, p2)|, Q = 2 max(|s1| + 2 |s2| t, |s3| + 2 |s4| t); with A_max = max |R| +
    2 s max |R'| and C = s max |R'|, the determinant is at least
    min R min M - 2 e A_max - 2 e C - 2 e^2. Every term is monotonic in s, so
    bisection finds the largest s where it is >= 2 ``LENS_MIN_DET``, searched
    inside 0.99 of the monotonic radius and of the pole.
    """
    full = np.asarray(full, float)
    if not np.all(np.isfinite(full)):
        return 0.0
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = full[:12]
    P = float(np.hypot(p1, p2))
    Poly = np.polynomial.Polynomial
    N, D, t = Poly([1.0, k1, k2, k3]), Poly([1.0, k4, k5, k6]), Poly([0.0, 1.0])
    dR_num, dR_den = N.deriv() * D - N * D.deriv(), D * D  # R' = dR_num / dR_den
    M_num = N * D + 2.0 * t * dR_num  # M = M_num / D^2
    limit = 0.99 * min(monotonic_radius2(full), pole_radius2(full))  # clear of the fold and the pole
    need = 2.0 * float(LENS_MIN_DET)

    def bound(s):
        if s > limit:
            return -1.0
        r_lo, r_hi = _extremes(N, D, s)
        m_lo, _ = _extremes(M_num, dR_den, s)
        dr_lo, dr_hi = _extremes(dR_num, dR_den, s)
        if r_lo <= 0.0 or m_lo <= 0.0:
            return -1.0
        d_abs = max(abs(dr_lo), abs(dr_hi))
        r = np.sqrt(s)
        Q = 2.0 * max(abs(s1) + 2.0 * abs(s2) * s, abs(s3) + 2.0 * abs(s4) * s)
        e = (6.0 * P + Q) * r
        a_max = max(abs(r_lo), abs(r_hi)) + 2.0 * s * d_abs
        return r_lo * m_lo - 2.0 * e * a_max - 2.0 * e * s * d_abs - 2.0 * e * e

    if not bound(0.0) >= need:
        return 0.0
    cap = min(1.0e6, limit)
    if bound(cap) >= need:
        return float(cap)
    lo, hi = 0.0, cap
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if bound(mid) >= need else (lo, mid)
    return float(lo)


def make_camera(K, dist, R, t) -> CameraModel:
    """Build a :class:`CameraModel` from OpenCV K (3x3), dist (4, 5, 8 or 12
    coefficients, :func:`lens_coefficients`), R (3x3), t (3)."""
    K = np.asarray(K, float)
    R = np.asarray(R, float)
    t = np.asarray(t, float).ravel()
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"make_camera: expected K 3x3, R 3x3, t 3; got {K.shape}, {R.shape}, {t.shape}")
    d = lens_coefficients(dist)
    c = CameraModel()
    c.fx, c.fy, c.cx, c.cy, c.skew = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(K[0, 1])
    c.k1, c.k2, c.p1, c.p2, c.k3 = (float(x) for x in d[:5])
    c.k4, c.k5, c.k6 = (float(x) for x in d[5:8])
    c.s1, c.s2, c.s3, c.s4 = (float(x) for x in d[8:12])
    # flags from the float32 values the kernels see: 0 keeps the 5-coefficient arithmetic
    c.rational = int(np.any(d[5:8].astype(np.float32) != 0))
    c.prism = int(np.any(d[8:12].astype(np.float32) != 0))
    c.lens = int(np.any(d.astype(np.float32) != 0))
    c.R = wp.mat33(*R.ravel().tolist())
    c.t = wp.vec3(*t.tolist())
    c.center = wp.vec3(*(-R.T @ t).tolist())
    c.r2_max = monotonic_radius2(d)
    c.r2_safe = fold_free_radius2(d)
    c.r2_pole = pole_radius2(d)
    return c


def make_parallel_light(R, t, pixel_pitch_mm: float, axis_px) -> LightModel:
    """Build a parallel :class:`LightModel` (docs/design.md §3)."""
    li = LightModel()
    li.model = 0
    li.R = wp.mat33(*np.asarray(R, float).ravel().tolist())
    li.t = wp.vec3(*np.asarray(t, float).ravel().tolist())
    li.s = float(pixel_pitch_mm)
    li.a = wp.vec2(*np.asarray(axis_px, float).ravel().tolist())
    li.cam = make_camera(np.eye(3), None, np.eye(3), np.zeros(3))
    li.distorted = 0
    return li


def make_perspective_light(K, dist, R, t) -> LightModel:
    """Build a perspective (projector) :class:`LightModel` (docs/design.md §3)."""
    li = LightModel()
    li.model = 1
    li.R = wp.mat33(*np.eye(3).ravel().tolist())
    li.t = wp.vec3(0.0, 0.0, 0.0)
    li.s = 1.0
    li.a = wp.vec2(0.0, 0.0)
    li.cam = make_camera(K, dist, R, t)
    li.distorted = li.cam.lens
    return li


def make_volume(z_min: float, z_max: float, r_max: float) -> Volume:
    """Build a :class:`Volume` (mm)."""
    v = Volume()
    v.z_min, v.z_max, v.r_max = float(z_min), float(z_max), float(r_max)
    v.r2_limit = float(sqrt_limit32(r_max))
    return v


def sqrt_limit32(r: float) -> np.float32:
    """The largest float32 s with float32 sqrt(s) <= float32(r) (IEEE square roots are
    correctly rounded, so the test sqrt(s) <= r is exactly s <= this); -1 where r < 0
    or is NaN (no s passes), +inf where r is +inf."""
    r32 = np.float32(r)
    if not r32 >= 0:
        return np.float32(-1.0)
    if np.isinf(r32):
        return np.float32(np.inf)
    up, down = np.float32(np.inf), np.float32(-np.inf)
    with np.errstate(over="ignore"):
        s = np.float32(r32 * r32)  # within an ulp or two of the answer
        while s > 0 and np.sqrt(s) > r32:
            s = np.nextafter(s, down)
        while np.isfinite(s) and np.sqrt(np.nextafter(s, up)) <= r32:
            s = np.nextafter(s, up)
    return s
