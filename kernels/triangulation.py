"""Triangulation, per point: a camera ray meets the surface of its ring, or, where
the sample carries its polar angle too, the point whose projector pixel fits both
coordinates best (docs/design.md §3, §4, §18; docs/reconstruction.md).

- The ring alone: both light models give a quadric (a cylinder for the parallel
  light, the elliptic cone of the ring for a projector); along the ray it is a
  quadratic in t, solved in float64 (``ring_quadric.ray_ring_roots``, Newton steps
  through the projector's distortion); the decoded sector picks the root, and
  without one two roots in the volume are ambiguous, never guessed.
- Both coordinates: Gauss-Newton along the ray from the ray-ray closest point on
  the weighted projector-grid residual (:func:`full_solution`); the calibration
  floor (``kernels.calibration_floor``) discounts the direction across the epipolar line.

Status codes (``status`` array, ``STATUS_NAMES``): 0 point, 1 no real root, 2 no
root in the volume, 3 ambiguous, 4 sector mismatch, 5 grazing (the ray meets the
ring's surface at a glancing angle), 6 isolated (set later by ``point_filter``), 7
not converged (a Newton refinement did not reach its target: the point's place is
unknown), 8 undistort failed (the camera or projector pixel has no undistorted
point in its lens's fold-free region), 9 ill-conditioned (both coordinates graze),
10 inconsistent (the two coordinates disagree beyond ``max_residual_px``), 11
unmatched (two cameras: camera 2 has no sample of the same projector coordinate).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ringscan.kernels.geometry import (
    LIGHT_PARALLEL,
    NEWTON_STEPS,
    CameraModel,
    LightModel,
    Volume,
    camera_ray,
    closest_on_ray,
    light_pixel,
    light_pixel_ray,
    make_volume,
    polar_angle,
)
from ringscan.kernels.launch import check_array, default_threads, launch_spans, scan_counts
from ringscan.kernels.ring_quadric import pattern_offset, ray_ring_roots, root_usable

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

STATUS_OK = wp.constant(0)
STATUS_NO_ROOT = wp.constant(1)
STATUS_OUTSIDE = wp.constant(2)
STATUS_AMBIGUOUS = wp.constant(3)
STATUS_SECTOR_MISMATCH = wp.constant(4)
STATUS_GRAZING = wp.constant(5)
STATUS_ISOLATED = 6  # given by kernels.point_filter
STATUS_NOT_CONVERGED = wp.constant(7)
STATUS_UNDISTORT_FAILED = wp.constant(8)
STATUS_ILL_CONDITIONED = wp.constant(9)
STATUS_INCONSISTENT = wp.constant(10)
STATUS_UNMATCHED = 11  # given by pipeline.reconstruct.stereo: camera 2 has no match for the sample
STATUS_NAMES = ("ok", "no_root", "outside_volume", "ambiguous", "sector_mismatch", "grazing", "isolated",
                "not_converged", "undistort_failed", "ill_conditioned", "inconsistent", "unmatched")
PI = wp.constant(3.14159265358979)


@wp.struct
class TriangulationParams:
    """The scalar settings of :func:`triangulate_kernel`, filled once by :func:`triangulate_rings`."""

    center: wp.vec2
    """The pattern centre, projector px."""
    constraint: wp.int32
    """CONSTRAINT_RINGS (0), CONSTRAINT_ANGLE (1) or CONSTRAINT_BOTH (2)."""
    n_sectors: wp.int32
    """2 ** sector_bits, 0 without sectors."""
    sector_tolerance: wp.float32
    """ReconstructSettings.sector_tolerance."""
    sector_margin: wp.float32
    """ReconstructSettings.sector_margin."""
    min_incidence_cos: wp.float32
    """Below it, a point is grazing."""
    max_residual_px: wp.float32
    """The full coordinate's residual bound, projector px."""
    floor: wp.float32
    """The decode's error floor, projector px (added in quadrature)."""
    fallback_sector_px: wp.float32
    """Where > 0: a sector mismatch is retried with coarser sectors at least this wide (projector px)."""
    widen_angle: wp.int32
    """1: a point placed with the angle (alone or with its ring) grows its sigma by its coordinates'
    disagreement (``triangulate_rings``)."""
CONSTRAINT_RINGS = wp.constant(0)
CONSTRAINT_ANGLE = wp.constant(1)
CONSTRAINT_BOTH = wp.constant(2)
CONSTRAINTS = ("auto", "rings", "angle", "both")
"""``TriangulateSettings.constraint`` values (auto: both where the samples carry an angle, else rings)."""
NOMINAL_SIGMA_PX = 0.05
"""Standard deviation (projector px) assumed for samples whose codec predicts none."""

__all__ = ["TriangulateSettings", "Triangulation", "triangulate_rings", "compact_points", "camera_side_sigmas",
           "STATUS_NAMES", "STATUS_UNMATCHED",
           "CONSTRAINTS", "NOMINAL_SIGMA_PX"]


@dataclass(frozen=True)
class TriangulateSettings:
    """Root choice and consistency settings."""

    sector_tolerance: float = 0.75
    """How far (in sector widths) a root's polar angle may lie outside its decoded
    sector and still count as matching it: it absorbs the half-sector a sample on
    a sector edge may be off. Above it the point is dropped (sector mismatch)."""
    sector_margin: float = 0.5
    """Where both roots lie in the volume, the one nearer the decoded sector wins
    only if the other is farther by at least this many sector widths; otherwise
    the point is dropped as ambiguous."""
    fallback_sector_px: float = 0.0
    """In a scan with an angle code, a sample whose angle did not decode keeps its
    ring alone; where no root matches its decoded sector, with this > 0 it picks the
    root by a coarse sector instead: the sector code's top bits, as many as leave
    sectors at least this wide (projector px) at the sample's ring (where the
    angle's 8-16 px fringes lost their modulation, the finest sector stripes are as
    unreliable; 16 recovers them). 0 (default): a mismatch is dropped. The points it
    recovers are right but noisy (on the demo's sphere, 2.3x the median error), and
    an unweighted Poisson mesh follows them (docs/reconstruction.md). Scans without
    an angle code always use the sector as decoded."""
    min_incidence_cos: float = 0.03
    """Least conditioning of a point, in [0, 1]: |cos| of the angle between the
    camera ray and the normal of the ring's surface (the quadric of constant rho)
    and, with the angle, of the angle's surface (constant phi); with both the
    better of the two counts. A coordinate's depth error is its sampling error
    divided by it: below 0.03 (rays within ~2 degrees of grazing) a 0.05 px error
    costs millimetres. Points below it are dropped as ``grazing`` (rings) or
    ``ill_conditioned`` (angle, both: every coordinate grazes)."""
    constraint: str = "auto"
    """Which projector coordinates place a point: ``rings`` (the paper: the ring's
    cylinder or cone, the sector picks the root), ``angle`` (the polar angle's
    half-plane alone; for comparison), ``both`` (weighted least squares of both),
    or ``auto`` (both where a sample carries an angle, rings elsewhere)."""
    max_residual_px: float = 2.0
    """With the angle: largest distance (projector px) of the observed projector
    pixel from the camera ray's epipolar line; above it the two coordinates
    disagree (a decode error, a reflection, a wrong calibration) and the point
    is dropped as ``inconsistent`` (``reconstruct`` raises it to 5 calibration
    floors on a rig that misses by more)."""

    def __post_init__(self):
        if self.constraint not in CONSTRAINTS:
            raise ValueError(f"triangulate.constraint: must be one of {', '.join(CONSTRAINTS)}, "
                             f"not {self.constraint!r}")
        if not (self.max_residual_px > 0):
            raise ValueError(f"triangulate.max_residual_px: must be > 0, got {self.max_residual_px}")
        if not (0 <= self.fallback_sector_px < float("inf")):
            raise ValueError(f"triangulate.fallback_sector_px: must be >= 0, got {self.fallback_sector_px}")


@dataclass
class Triangulation:
    """Per-sample triangulation results (Warp arrays of length n)."""

    points: wp.array
    """vec3 world point (mm); zero where status != 0."""
    status: wp.array
    """int32 status code (0 = point)."""
    confidence: wp.array
    """float32 sample confidence times |cos| of the ray's incidence on the quadric."""
    residual: wp.array
    """float32 consistency residual: for the ring constraint the angular residual in
    sectors (0 inside the sector; -1 without sectors); with the angle the distance
    (projector px) of the observed projector pixel from the camera ray's epipolar
    line (the projector-side ray-ray distance)."""
    sigma: wp.array
    """float32 predicted standard deviation of the point along the camera ray (mm)."""
    residual_var: wp.array
    """float32 the decode's predicted variance (projector px^2) across the epipolar
    line (with both coordinates; 0 otherwise): residual^2 / residual_var is the
    point's chi-square, which :func:`calibration_floor` reads."""


# ----------------------------------------------------------------------------- helpers


@wp.func
def sector_residual(off: wp.vec2, sector: int, n_sectors: int):
    """Distance (in sector widths) outside decoded ``sector`` of the polar angle of
    a point whose pattern offset (:func:`pattern_offset`) is ``off``."""
    phi = polar_angle(off[1], off[0])
    width = 2.0 * PI / float(n_sectors)
    mid = (float(sector) + 0.5) * width - PI
    dphi = phi - mid
    # into [-pi, pi): dphi - 2 pi floor((dphi + pi) / (2 pi)), bit for bit in float32
    # without the division (dphi lies in (-2 pi, 2 pi), and float32's
    # u / (2 pi) >= 1 exactly where u >= 2 pi)
    u = dphi + PI
    if u >= 2.0 * PI:
        dphi = dphi - 2.0 * PI
    elif u < 0.0:
        dphi = dphi + 2.0 * PI
    return wp.max(wp.abs(dphi) / width - 0.5, 0.0)


# ----------------------------------------------------------------------------- kernels


@wp.func
def ring_slope(light: LightModel, X: wp.vec3, d: wp.vec3, center: wp.vec2, off: wp.vec2):
    """|d rho / dt| along the unit ray direction d at X (projector px per mm): the
    central difference over +-h along the ray. ``off``: X's pattern offset."""
    h = 0.01
    if light.model == LIGHT_PARALLEL:
        # The pattern offset is affine here (o + s v at X + s d), so the
        # difference of the two lengths is 4 h (o . v) / (|o + h v| + |o - h v|):
        # the same number without the cancellation that cost the float32
        # difference up to ~1e-2 of it (relative; 5e-4 typical) where the ray
        # grazes the ring, and 4 fewer divisions.
        o = off
        Dl = light.R * d
        v = wp.vec2(Dl[0] / light.s, Dl[1] / light.s)
        den = wp.length(o + v * h) + wp.length(o - v * h)
        return wp.where(den > 0.0, 2.0 * wp.abs(wp.dot(o, v)) / den, 0.0)
    a = wp.length(pattern_offset(light, X + d * h, center))
    b = wp.length(pattern_offset(light, X - d * h, center))
    return wp.abs(a - b) / (2.0 * h)


@wp.func
def pixel_offset(light: LightModel, X: wp.vec3, p_obs: wp.vec2):
    """Offset of X's projector pixel from the observed one (projector px)."""
    p = light_pixel(light, X)
    return wp.vec2(p[0] - p_obs[0], p[1] - p_obs[1])


@wp.func
def quad(W: wp.vec3, a: wp.vec2, b: wp.vec2):
    """a^T W b for the symmetric 2x2 W = [[W0, W1], [W1, W2]]."""
    return a[0] * (W[0] * b[0] + W[1] * b[1]) + a[1] * (W[1] * b[0] + W[2] * b[1])


@wp.func
def rings_solution(
    light: LightModel, C: wp.vec3, d: wp.vec3, r: float, s: int, vol: Volume, center: wp.vec2, n_sectors: int,
    sector_tolerance: float, sector_margin: float, min_incidence_cos: float,
):
    """The ring constraint alone: the ray meets the quadric of ring r; the sector
    picks the root. Returns (X, status, |cos| of incidence, sector residual, X's
    pattern offset).

    Size: a @wp.func called twice by triangulate_kernel (the second time with a coarser sector): its arguments
    are the ray, the ring and sector, and the settings the kernel has already unpacked from TriangulationParams.
    """
    zero = wp.vec3(0.0, 0.0, 0.0)
    zero2 = wp.vec2(0.0, 0.0)
    roots, failed = ray_ring_roots(light, C, d, r, center)
    if roots[2] == 0.0:
        return zero, STATUS_NO_ROOT, 0.0, -1.0, zero2
    if failed != 0:
        return zero, STATUS_NOT_CONVERGED, 0.0, -1.0, zero2
    t1 = roots[0]
    t2 = roots[1]
    X1 = C + d * t1
    X2 = C + d * t2
    ok1 = root_usable(light, X1, t1, vol)
    ok2 = root_usable(light, X2, t2, vol)
    if not ok1 and not ok2:
        return zero, STATUS_OUTSIDE, 0.0, -1.0, zero2
    use_sector = n_sectors > 0 and s >= 0
    X = X1
    res = float(-1.0)
    off = wp.vec2(0.0, 0.0)  # the chosen root's pattern offset, where the sector needed it
    if use_sector:
        e1 = float(1.0e9)
        e2 = float(1.0e9)
        off1 = off
        off2 = off
        if ok1:
            off1 = pattern_offset(light, X1, center)
            e1 = sector_residual(off1, s, n_sectors)
        if ok2:
            off2 = pattern_offset(light, X2, center)
            e2 = sector_residual(off2, s, n_sectors)
        if ok1 and ok2 and wp.abs(e1 - e2) < sector_margin:
            return zero, STATUS_AMBIGUOUS, 0.0, -1.0, zero2
        off = off1
        if e2 < e1:
            X = X2
            res = e2
            off = off2
        else:
            res = e1
        if res > sector_tolerance:
            return zero, STATUS_SECTOR_MISMATCH, 0.0, res, zero2
    else:
        if ok1 and ok2:
            return zero, STATUS_AMBIGUOUS, 0.0, -1.0, zero2
        if ok2:
            X = X2
    # Incidence: the angle between the ray and the quadric's normal (the
    # gradient of |p - c|: analytic for the parallel light, numerical otherwise).
    if not use_sector:
        off = pattern_offset(light, X, center)
    g = wp.vec3(0.0, 0.0, 0.0)
    if light.model == LIGHT_PARALLEL:
        g = wp.transpose(light.R) * wp.vec3(off[0], off[1], 0.0)
    else:
        h = 0.01
        f0 = wp.length(off)
        g = wp.vec3(wp.length(pattern_offset(light, X + wp.vec3(h, 0.0, 0.0), center)) - f0,
                    wp.length(pattern_offset(light, X + wp.vec3(0.0, h, 0.0), center)) - f0,
                    wp.length(pattern_offset(light, X + wp.vec3(0.0, 0.0, h), center)) - f0)
    gl = wp.length(g)
    cosi = wp.where(gl > 0.0, wp.abs(wp.dot(g, d)) / gl, 0.0)
    return X, wp.where(cosi >= min_incidence_cos, STATUS_OK, STATUS_GRAZING), cosi, res, off


@wp.func
def full_solution(
    light: LightModel, C: wp.vec3, d: wp.vec3, p_obs: wp.vec2, e_r: wp.vec2, info_r: float, info_t: float,
    var_r: float, floor2: float, vol: Volume, min_incidence_cos: float, max_residual_px: float,
):
    """Both projector coordinates: the point on the ray whose projector pixel is
    nearest the observed one in the decode's own metric (Gauss-Newton in t from
    the ray-ray closest point, through the projector's lens distortion).

    The information matrix is info_r e_r e_r^T + info_t e_t e_t^T (radial and
    tangential: 1 / sigma^2 each; info_r = 0 for the angle alone), with the
    calibration floor ``floor2`` (px^2) added as a covariance across the
    epipolar line (the only direction a calibration error can be seen in).
    Returns (X, status, conditioning in [0, 1], residual px across the epipolar
    line, sigma mm along the ray, the decode's variance (px^2) across the line, and
    that variance with the ring's ``var_r`` (px^2) counted where the angle alone
    places the point: what the residual is set against to widen its sigma).

    Size: a @wp.func of one sample's registers: the Gauss-Newton iteration, the conditioning of each coordinate
    and the residual across the epipolar line share the point and its derivatives. Its arguments are the light,
    the ray, the observation with its information, and the settings triangulate_kernel has already unpacked from
    TriangulationParams.
    """
    zero = wp.vec3(0.0, 0.0, 0.0)
    O, e, lok = light_pixel_ray(light, p_obs[0], p_obs[1])
    if not lok:
        return zero, STATUS_UNDISTORT_FAILED, 0.0, -1.0, 0.0, 0.0, 0.0
    t = closest_on_ray(C, d, O, e)
    h = wp.max(0.05, 1.0e-4 * wp.abs(t))
    e_t = wp.vec2(-e_r[1], e_r[0])
    W = wp.vec3(info_r * e_r[0] * e_r[0] + info_t * e_t[0] * e_t[0],
                info_r * e_r[0] * e_r[1] + info_t * e_t[0] * e_t[1],
                info_r * e_r[1] * e_r[1] + info_t * e_t[1] * e_t[1])
    if floor2 > 0.0:
        # Woodbury: (W^-1 + c^2 n n^T)^-1, n across the epipolar line at t
        J0 = pixel_offset(light, C + d * (t + h), p_obs) - pixel_offset(light, C + d * (t - h), p_obs)
        jl0 = wp.length(J0)
        if jl0 > 0.0:
            n = wp.vec2(-J0[1] / jl0, J0[0] / jl0)
            Wn = wp.vec2(W[0] * n[0] + W[1] * n[1], W[1] * n[0] + W[2] * n[1])
            k = floor2 / (1.0 + floor2 * wp.dot(n, Wn))
            W = wp.vec3(W[0] - k * Wn[0] * Wn[0], W[1] - k * Wn[0] * Wn[1], W[2] - k * Wn[1] * Wn[1])
    converged = bool(False)
    jj = float(0.0)
    for _i in range(NEWTON_STEPS):
        r0 = pixel_offset(light, C + d * t, p_obs)
        J = (pixel_offset(light, C + d * (t + h), p_obs) - pixel_offset(light, C + d * (t - h), p_obs)) / (2.0 * h)
        jj = quad(W, J, J)
        if not (jj > 1.0e-24):
            break
        step = quad(W, J, r0) / jj
        t = t - step
        # 2 % of the point's own standard deviation is as far as refining helps;
        # float32 coordinates put a floor of ~1e-6 |t| under the steps
        if wp.abs(step) < wp.max(wp.max(2.0e-4, 1.0e-6 * wp.abs(t)), 0.02 / wp.sqrt(jj)):
            converged = True
            break
    X = C + d * t
    if not converged:
        # a far-off observation (the coordinates disagree) leaves float32 noise
        # in the steps: name it for what it is
        res_nc = wp.length(pixel_offset(light, X, p_obs))
        if res_nc > max_residual_px:
            return zero, STATUS_INCONSISTENT, 0.0, res_nc, 0.0, 0.0, 0.0
        return zero, STATUS_NOT_CONVERGED, 0.0, -1.0, 0.0, 0.0, 0.0
    if not root_usable(light, X, t, vol):
        return zero, STATUS_OUTSIDE, 0.0, -1.0, 0.0, 0.0, 0.0
    # Conditioning, of each coordinate on its own: |cos| between the ray and the
    # normal of the surface of constant rho (the ring's cone) and of constant phi
    # (the angle's half-plane); the point is ill-conditioned only where both graze.
    hx = 0.05
    ax = (pixel_offset(light, X + wp.vec3(hx, 0.0, 0.0), p_obs) - pixel_offset(light, X - wp.vec3(hx, 0.0, 0.0), p_obs)) / (2.0 * hx)
    ay = (pixel_offset(light, X + wp.vec3(0.0, hx, 0.0), p_obs) - pixel_offset(light, X - wp.vec3(0.0, hx, 0.0), p_obs)) / (2.0 * hx)
    az = (pixel_offset(light, X + wp.vec3(0.0, 0.0, hx), p_obs) - pixel_offset(light, X - wp.vec3(0.0, 0.0, hx), p_obs)) / (2.0 * hx)
    g_r = wp.vec3(wp.dot(ax, e_r), wp.dot(ay, e_r), wp.dot(az, e_r))
    g_t = wp.vec3(wp.dot(ax, e_t), wp.dot(ay, e_t), wp.dot(az, e_t))
    cos_r = wp.where(wp.length(g_r) > 0.0, wp.abs(wp.dot(g_r, d)) / wp.length(g_r), 0.0)
    cos_t = wp.where(wp.length(g_t) > 0.0, wp.abs(wp.dot(g_t, d)) / wp.length(g_t), 0.0)
    cond = wp.where(info_r > 0.0, wp.max(cos_r, cos_t), cos_t)
    Jd = ax * d[0] + ay * d[1] + az * d[2]
    info = wp.max(quad(W, Jd, Jd), 0.0)
    sigma = wp.where(info > 0.0, 1.0 / wp.sqrt(info), 1.0e9)
    # The residual across the epipolar line (its direction e at the point): the
    # one thing the ray and the observation can disagree on; its variance under
    # the decode's own model, for the chi-square of :func:`calibration_floor`.
    rv = pixel_offset(light, X, p_obs)
    el = wp.length(Jd)
    res = wp.length(rv)
    var = float(0.0)
    var_both = float(0.0)
    if el > 0.0:
        n = wp.vec2(-Jd[1] / el, Jd[0] / el)
        res = wp.abs(wp.dot(n, rv))
        cr = wp.dot(n, e_r)
        ct = wp.dot(n, e_t)
        if info_r > 0.0:
            var = cr * cr / info_r + ct * ct / info_t
        var_both = cr * cr * var_r + ct * ct / info_t
    status = int(STATUS_OK)
    if cond < min_incidence_cos:
        status = STATUS_ILL_CONDITIONED
    elif res > max_residual_px:
        status = STATUS_INCONSISTENT
    return X, status, cond, res, sigma, var, var_both


@wp.func
def birge_ratio(chi2_per_dof: float):
    """A fit's chi-square over its degrees of freedom, square-rooted where above 1, else 1: the factor a
    sigma grows by where the fit's own numbers disagree beyond their sigmas (the Birge ratio)."""
    return wp.sqrt(wp.max(chi2_per_dof, 1.0))


@wp.func
def disagreement_factor(res: float, vboth: float, floor: float):
    """The factor a point's sigma grows by where its two projector coordinates disagree across the epipolar
    line (``res`` px, from :func:`full_solution`) beyond what both sigmas and the calibration floor allow
    (``vboth`` + floor^2 px^2: a mixed pixel at a silhouette, a fringe a highlight or a blur bent, bounced
    light): its chi (the Birge ratio of one degree of freedom) where above 1, else 1 (1 without a residual)."""
    factor = float(1.0)
    if vboth > 0.0 and res >= 0.0:
        factor = birge_ratio(res * res / (vboth + floor * floor))
    return factor


@wp.kernel
def camera_rays_kernel(uv: wp.array(dtype=wp.vec2), cam: CameraModel, i0: int, rays: wp.array(dtype=wp.vec4)):
    """The camera ray of sample i = i0 + tid (:func:`camera_ray`).

    uv (n,) vec2: read. rays (n,) vec4: written, (unit world direction, 1), or w = 0
    where the pixel has no ray.
    """
    i = i0 + wp.tid()
    d, ok = camera_ray(cam, uv[i][0], uv[i][1])
    rays[i] = wp.vec4(d[0], d[1], d[2], wp.where(ok, 1.0, 0.0))


@wp.kernel
def triangulate_kernel(
    rays: wp.array(dtype=wp.vec4),
    rho: wp.array(dtype=wp.float32),
    phi: wp.array(dtype=wp.float32),
    sigma_rho: wp.array(dtype=wp.float32),
    sigma_tan: wp.array(dtype=wp.float32),
    sector: wp.array(dtype=wp.int32),
    sample_conf: wp.array(dtype=wp.float32),
    cam: CameraModel,
    light: LightModel,
    vol: Volume,
    params: TriangulationParams,
    i0: int,
    points: wp.array(dtype=wp.vec3),
    status: wp.array(dtype=wp.int32),
    confidence: wp.array(dtype=wp.float32),
    residual: wp.array(dtype=wp.float32),
    sigma: wp.array(dtype=wp.float32),
    residual_var: wp.array(dtype=wp.float32),
):
    """Triangulate sample i0 + tid.

    rays (n,) vec4 (:func:`camera_rays_kernel`), rho (n,) float32 projector px, phi (n,) float32 rad (NaN: no
    angle), sigma_rho (n,), sigma_tan (n,) float32 projector px, sector (n,)
    int32 (-1 unknown), sample_conf (n,) float32: read. With ``constraint``
    CONSTRAINT_RINGS, or where a sample has no angle, the ring constraint alone;
    otherwise both coordinates (CONSTRAINT_BOTH) or the angle alone
    (CONSTRAINT_ANGLE).
    points (n,) vec3, status (n,) int32, confidence (n,) float32, residual (n,)
    float32 (sector widths for the ring constraint, projector px otherwise),
    sigma (n,) float32 mm, residual_var (n,) float32 (projector px^2: the decode's
    predicted variance in the residual's direction; 0 for the ring constraint):
    written.

    Size: one thread per sample; nearly half of its length is its signature, its docstring and
    TriangulationParams unpacked into locals; the rest picks between rings_solution and full_solution (already
    @wp.func) and writes six outputs. Warp kernels take each array, the camera, the light and the volume as its
    own argument; the scalar settings already travel in TriangulationParams.
    """
    i = i0 + wp.tid()
    center = params.center
    constraint = params.constraint
    n_sectors = params.n_sectors
    sector_tolerance = params.sector_tolerance
    sector_margin = params.sector_margin
    min_incidence_cos = params.min_incidence_cos
    max_residual_px = params.max_residual_px
    floor = params.floor
    fallback_sector_px = params.fallback_sector_px
    ray = rays[i]
    d = wp.vec3(ray[0], ray[1], ray[2])
    C = cam.center
    r = rho[i]
    f = phi[i]
    points[i] = wp.vec3(0.0, 0.0, 0.0)
    confidence[i] = 0.0
    residual[i] = -1.0
    sigma[i] = 0.0
    residual_var[i] = 0.0
    if not (ray[3] > 0.0):
        status[i] = STATUS_UNDISTORT_FAILED
        return
    st = int(0)
    X = wp.vec3(0.0, 0.0, 0.0)
    q = float(0.0)
    res = float(-1.0)
    sg = float(0.0)
    rvar = float(0.0)
    st_t = sigma_tan[i]
    if constraint != CONSTRAINT_RINGS and f == f and st_t > 0.0:
        e_r = wp.vec2(wp.cos(f), wp.sin(f))
        p_obs = wp.vec2(center[0] + r * e_r[0], center[1] + r * e_r[1])
        sr = wp.max(sigma_rho[i], 1.0e-6)
        st_t = wp.max(st_t, 1.0e-6)
        info_r = wp.where(constraint == CONSTRAINT_ANGLE, 0.0, 1.0 / (sr * sr))
        X, st, q, res, sg, rvar, vboth = full_solution(light, C, d, p_obs, e_r, info_r, 1.0 / (st_t * st_t), sr * sr,
                                                       floor * floor, vol, min_incidence_cos, max_residual_px)
        if params.widen_angle != 0:
            sg = sg * disagreement_factor(res, vboth, floor)
    else:
        X, st, q, res, off = rings_solution(light, C, d, r, sector[i], vol, center, n_sectors, sector_tolerance,
                                       sector_margin, min_incidence_cos)
        if st == STATUS_SECTOR_MISMATCH and fallback_sector_px > 0.0:
            # A sample whose angle failed (low modulation: fine fringes lost) may
            # read the finest sector bits wrong too; the root choice needs only a
            # coarse sector (the top bits of a reflected Gray code are the coarse
            # sector's own Gray code).
            s = sector[i]
            ns = n_sectors
            while ns > 2 and 2.0 * PI * r < fallback_sector_px * float(ns):
                ns = ns // 2
                s = s // 2
            if ns < n_sectors:
                X, st, q, res, off = rings_solution(light, C, d, r, s, vol, center, ns, sector_tolerance, sector_margin,
                                               min_incidence_cos)
        if st == STATUS_OK or st == STATUS_GRAZING:
            slope = ring_slope(light, X, d, center, off)
            sg = wp.where(slope > 0.0, sigma_rho[i] / slope, 1.0e9)
            if params.widen_angle != 0 and f == f and st_t > 0.0:
                # the angle was read but the ring alone places the point (``constraint`` rings): the pair's
                # solve only for its disagreement (bounced light bending both, a mixed pixel), which widens
                # the ring's sigma as it does the angle's and both's
                e_r = wp.vec2(wp.cos(f), wp.sin(f))
                p_obs = wp.vec2(center[0] + r * e_r[0], center[1] + r * e_r[1])
                sr = wp.max(sigma_rho[i], 1.0e-6)
                stt = wp.max(st_t, 1.0e-6)
                X2, st2, q2, res2, sg2, rvar2, vboth2 = full_solution(
                    light, C, d, p_obs, e_r, 1.0 / (sr * sr), 1.0 / (stt * stt), sr * sr, floor * floor, vol,
                    min_incidence_cos, max_residual_px)
                sg = sg * disagreement_factor(res2, vboth2, floor)
    status[i] = st
    residual[i] = res
    residual_var[i] = rvar
    if st == STATUS_OK or st == STATUS_GRAZING or st == STATUS_ILL_CONDITIONED or st == STATUS_INCONSISTENT:
        points[i] = X
        confidence[i] = sample_conf[i] * q
        sigma[i] = sg


@wp.kernel
def count_valid_kernel(status: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """flags[i] = 1 where status[i] == 0. status (n,) read; flags (n,) written."""
    i = wp.tid()
    flags[i] = wp.where(status[i] == STATUS_OK, 1, 0)


@wp.kernel
def compact_kernel(
    status: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    index: wp.array(dtype=wp.int32),
):
    """index[offsets[i]] = i for every valid sample. status, offsets (n,) read;
    index (n_valid,) written."""
    i = wp.tid()
    if status[i] == STATUS_OK:
        index[offsets[i]] = i


@wp.func
def rho_at(camera: CameraModel, light: LightModel, center: wp.vec2, u: float, v: float, dist: float):
    """Radius (projector px) about ``center`` of the point ``dist`` mm along the camera ray of
    pixel (u, v); -1 where that ray or its light pixel does not exist."""
    r = camera_ray(camera, u, v)
    if not r[1]:
        return -1.0
    p = light_pixel(light, camera.center + dist * r[0])
    if p[2] <= 0.0:
        return -1.0
    return wp.length(wp.vec2(p[0] - center[0], p[1] - center[1]))


@wp.kernel
def camera_side_kernel(
    uv: wp.array(dtype=wp.vec2),
    sigma_uv: wp.array(dtype=wp.vec2),
    points: wp.array(dtype=wp.vec3),
    status: wp.array(dtype=wp.int32),
    camera: CameraModel,
    light: LightModel,
    center: wp.vec2,
    i0: int,
    out: wp.array(dtype=wp.float32),
):
    """out[i] = the standard deviation of rho (projector px) that moves a placed point along its
    camera ray as much as the sample's camera-side error does: |sigma_uv[i]| times the change of
    rho per camera px along sigma_uv[i]'s direction at the point's distance from the camera
    (the implicit function: the ray's depth error is that over the ring's slope along the ray,
    what triangulation divides sigma_rho by). |sigma_uv[i]| itself where the point is not placed.

    uv, sigma_uv (n,) vec2 camera px; points (n,) vec3; status (n,) int32 (``kernels.triangulation``):
    read. out (n,) float32: written.

    Size: the four per-sample arrays, the two models and the pattern centre, the span's i0, one out."""
    i = i0 + wp.tid()
    s = wp.length(sigma_uv[i])
    out[i] = s
    st = status[i]
    if s > 0.0 and (st == STATUS_OK or st == STATUS_GRAZING):
        n = sigma_uv[i] / s
        dist = wp.length(points[i] - camera.center)
        a = rho_at(camera, light, center, uv[i][0] + 0.5 * n[0], uv[i][1] + 0.5 * n[1], dist)
        b = rho_at(camera, light, center, uv[i][0] - 0.5 * n[0], uv[i][1] - 0.5 * n[1], dist)
        if a >= 0.0 and b >= 0.0:
            out[i] = s * wp.abs(a - b)


# ----------------------------------------------------------------------------- host


def triangulate_rings(
    uv: wp.array,
    rho: wp.array,
    sector: wp.array,
    sample_confidence: wp.array,
    *,
    camera: CameraModel,
    light: LightModel,
    volume: tuple[float, float, float],
    center: tuple[float, float],
    sector_bits: int = 0,
    phi: wp.array | None = None,
    sigma_rho: wp.array | None = None,
    sigma_tan: wp.array | None = None,
    settings: TriangulateSettings = TriangulateSettings(),
    floor: float = 0.0,
    widen_angle: bool = True,
    threads: int | None = None,
) -> Triangulation:
    """Triangulate samples: each camera ray meets its ring's quadric, or, where a
    sample carries its polar angle too, the point that fits both projector
    coordinates best (``settings.constraint``).

    Args:
        uv: (n,) vec2 camera pixel coordinates (distorted image).
        rho: (n,) float32 ring radius in projector pixels.
        sector: (n,) int32 decoded sector, -1 where unknown.
        sample_confidence: (n,) float32.
        camera, light: from :mod:`ringscan.kernels.geometry`.
        volume: (z_min, z_max, r_max) of the working volume, world mm.
        center: pattern centre (c_u, c_v) in projector pixels.
        sector_bits: sector Gray-code bits of the scan (0: none).
        phi: (n,) float32 polar angle (rad) around the centre, NaN where unknown;
            None: no sample has one.
        sigma_rho: (n,) float32 standard deviation of rho (projector px);
            None: ``NOMINAL_SIGMA_PX``.
        sigma_tan: (n,) float32 standard deviation of the tangential position
            rho * phi (projector px); required with ``phi``.
        settings: root-choice and constraint settings.
        floor: calibration floor (projector px, :func:`calibration_floor`): a
            standard deviation added across the epipolar line to samples with an angle.
        widen_angle: a point of a sample with an angle grows its sigma by the chi of its two coordinates'
            disagreement across the epipolar line where it is above 1 (a mixed pixel, a fringe bent by a
            highlight, a blur or bounced light: the point is no better known than that), whichever
            ``settings.constraint`` places it.
            False: the decode's sigma as it is (the error model's fit, which measures what the decode misses).
        threads: CPU threads; default all cores.

    Size: a public entry point: most of its length is its parameters (the sample arrays and documented
    keyword-only options, one per user-facing setting), their documentation and the checks of each input (one
    message each); the rest packs TriangulationParams and launches the two passes.
    """
    n = uv.shape[0] if isinstance(uv, wp.array) else None
    if n is None or uv.dtype != wp.vec2:
        raise ValueError("triangulate_rings: uv must be a Warp array of vec2")
    if settings.constraint not in CONSTRAINTS:
        raise ValueError(f"triangulate_rings: constraint must be one of {', '.join(CONSTRAINTS)}, "
                         f"not {settings.constraint!r}")
    if phi is not None and sigma_tan is None:
        raise ValueError("triangulate_rings: phi needs sigma_tan")
    if phi is None and settings.constraint in ("angle", "both"):
        raise ValueError(f"triangulate_rings: constraint {settings.constraint!r} needs samples with an angle "
                         "(this codec decodes none)")
    checks = [("rho", rho, wp.float32), ("sector", sector, wp.int32), ("sample_confidence", sample_confidence, wp.float32)]
    checks += [(k, a, wp.float32) for k, a in (("phi", phi), ("sigma_rho", sigma_rho), ("sigma_tan", sigma_tan))
               if a is not None]
    for name, a, dt in checks:
        if not isinstance(a, wp.array) or a.dtype != dt or a.shape != (n,):
            raise ValueError(f"triangulate_rings: {name} must be a ({n},) {dt.__name__} Warp array")
    z_min, z_max, r_max = (float(x) for x in volume)
    if not (z_max > z_min and r_max > 0):
        raise ValueError(f"triangulate_rings: bad volume {volume}")
    if not (np.isfinite(floor) and floor >= 0):
        raise ValueError(f"triangulate_rings: floor must be a finite number >= 0, got {floor}")
    dev = uv.device
    out = Triangulation(
        points=wp.empty(n, dtype=wp.vec3, device=dev),
        status=wp.empty(n, dtype=wp.int32, device=dev),
        confidence=wp.empty(n, dtype=wp.float32, device=dev),
        residual=wp.empty(n, dtype=wp.float32, device=dev),
        sigma=wp.empty(n, dtype=wp.float32, device=dev),
        residual_var=wp.empty(n, dtype=wp.float32, device=dev),
    )
    if n == 0:
        return out
    if sigma_rho is None:
        sigma_rho = wp.full(n, NOMINAL_SIGMA_PX, dtype=wp.float32, device=dev)
    has_angle = phi is not None
    if phi is None:
        phi = wp.full(n, float("nan"), dtype=wp.float32, device=dev)
        sigma_tan = wp.zeros(n, dtype=wp.float32, device=dev)
    constraint = {"auto": 2, "both": 2, "angle": 1, "rings": 0}[settings.constraint]
    vol = make_volume(z_min, z_max, r_max)
    n_sectors = 2 ** sector_bits if sector_bits > 0 else 0
    # Two passes over the samples, the camera rays and then the rest: each sample's
    # work is a chain of dependent divisions and square roots, and in a shorter
    # pass the CPU runs the chains of consecutive samples side by side (the one
    # kernel that did both took ~12 % longer on one thread; the same numbers).
    threads = default_threads() if threads is None else threads
    rays = wp.empty(n, dtype=wp.vec4, device=dev)
    launch_spans(camera_rays_kernel, n, lambda i0: [uv, camera, i0], [rays], dev, threads)
    params = TriangulationParams()
    params.center = wp.vec2(*center)
    params.constraint = constraint
    params.n_sectors = n_sectors
    params.sector_tolerance = settings.sector_tolerance
    params.sector_margin = settings.sector_margin
    params.min_incidence_cos = settings.min_incidence_cos
    params.max_residual_px = settings.max_residual_px
    params.floor = float(floor)
    params.widen_angle = int(bool(widen_angle))
    params.fallback_sector_px = float(settings.fallback_sector_px) if has_angle and constraint != 0 else 0.0
    args = [rays, rho, phi, sigma_rho, sigma_tan, sector, sample_confidence, camera, light, vol, params]
    outputs = [out.points, out.status, out.confidence, out.residual, out.sigma, out.residual_var]
    launch_spans(triangulate_kernel, n, lambda i0: args + [i0], outputs, dev, threads)
    return out


def compact_points(status: wp.array) -> wp.array:
    """Indices (int32, ascending) of the samples that became points (status 0)."""
    n = status.shape[0]
    dev = status.device
    if n == 0:
        return wp.empty(0, dtype=wp.int32, device=dev)
    flags = wp.empty(n, dtype=wp.int32, device=dev)
    wp.launch(count_valid_kernel, dim=n, inputs=[status], outputs=[flags], device=dev)
    offsets, total = scan_counts(flags)
    index = wp.empty(total, dtype=wp.int32, device=dev)
    if total:
        wp.launch(compact_kernel, dim=n, inputs=[status, offsets], outputs=[index], device=dev)
    return index


def camera_side_sigmas(uv: wp.array, sigma_uv: wp.array, points: wp.array, status: wp.array, *,
                       camera: CameraModel, light: LightModel, center: tuple[float, float],
                       threads: int | None = None) -> wp.array:
    """(n,) float32 sigma_rho (projector px) for samples whose error is on the camera's side
    (:func:`camera_side_kernel`: a line centre placed across its line), from the points one
    triangulation placed them at; on uv's device.

    Size: the four per-sample arrays, the two models, the pattern centre, the thread count."""
    fn = "camera_side_sigmas"
    n = check_array("uv", uv, None, wp.vec2, fn)
    check_array("sigma_uv", sigma_uv, n, wp.vec2, fn)
    check_array("points", points, n, wp.vec3, fn)
    check_array("status", status, n, wp.int32, fn)
    dev = uv.device
    out = wp.empty(n, dtype=wp.float32, device=dev)
    args = [uv, sigma_uv, points, status, camera, light, wp.vec2(float(center[0]), float(center[1]))]
    launch_spans(camera_side_kernel, n, lambda i0: args + [i0], [out], dev,
                 default_threads() if threads is None else threads)
    return out
