"""Two cameras, triangulation: a point from two camera rays, or three with the
calibrated projector (docs/reconstruction.md "Two cameras", docs/design.md §19).

Gauss-Newton on the weighted reprojection error of the point in camera 1, camera 2
and (optionally) the calibrated projector, from the midpoint of the two camera rays,
through each lens's distortion (``geometry.project_camera``, ``geometry.light_pixel``).
The rays are the matches of :mod:`ringscan.kernels.stereo_match` (their sigmas
floored as the matcher floors them, ``SIGMA_FLOOR_PX``).

Status codes are those of ``kernels.triangulation`` (``STATUS_NAMES``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import warp as wp

from ringscan.kernels.geometry import (
    NEWTON_STEPS,
    CameraModel,
    LightModel,
    Volume,
    camera_ray,
    closest_on_ray,
    direction_to_light,
    in_volume,
    light_pixel,
    make_volume,
    project_camera,
)
from ringscan.kernels.launch import check_array, default_threads, launch_spans
from ringscan.kernels.stereo_match import SIGMA_FLOOR_PX
from ringscan.kernels.triangulation import (
    STATUS_ILL_CONDITIONED,
    STATUS_INCONSISTENT,
    STATUS_NOT_CONVERGED,
    STATUS_OK,
    STATUS_OUTSIDE,
    STATUS_UNDISTORT_FAILED,
    birge_ratio,
    quad,
)

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

JACOBIAN_STEP_MM = wp.constant(0.5)
"""Central-difference step of the triangulation's Jacobians (mm), at most ``JACOBIAN_STEP_DEPTH`` of the
point's distance from camera 1."""
CHORD_STEP = wp.constant(0.1)
"""A Gauss-Newton step shorter than this share of the difference step keeps the Jacobians for the next step."""
JACOBIAN_STEP_DEPTH = wp.constant(2.0e-3)
"""... so that a scene in other units than mm (metres: a point 1 unit away) is differentiated over a step
its size allows; from 250 mm on (every rig in mm ringscan has met) the step is 0.5 mm as it was."""

PIXEL_RAY_PX = wp.constant(0.01)
"""Camera 1's pixel's own standard deviation (px) in a three-ray triangulation through the matcher's map: its
ray is where the code was read, so the code's error is the projector ray's alone; a hundredth of a pixel keeps
the normal equations well conditioned in float32."""

LINE_MAP_DET = wp.constant(1.0e-4)
"""A matcher's map whose |det| is under this share of its mean squared entry is rank one (neighbours on a
line; float32 leaves ~1e-8 there, a surface's map ~1)."""
EXACT_RADIUS_PX = wp.constant(1.0e-3)
"""A ring edge's radius (projector px): the ring's own, exact to the floor the projector's weights take."""

__all__ = [
    "PIXEL_RAY_PX",
    "RayTriangulation",
    "projector_misses",
    "through_map",
    "widen_along_rays",
    "widen_by_chi",
    "triangulate_rays",
    "place_matches",
    "polar_information",
]


@wp.struct
class RayParams:
    """The scalar settings of :func:`triangulate_rays_kernel`, filled once by :func:`triangulate_rays`."""

    use_light: wp.int32
    """1: the calibrated projector is a third ray; 0: the two cameras alone."""
    use_map: wp.int32
    """1: uv2 was found from the query's projector point (the matcher's ``proj_map``): with the light camera 2's
    residual is taken less the map times the light's, without it camera 2's covariance takes the point's
    error through the map; 0: the rays' errors are independent."""
    projector_floor: wp.float32
    """With the light: what the projector's calibration misses (px, isotropic; 0: nothing), an error of its
    point that uv2 does not share."""
    min_sin: wp.float32
    """Least sine of the widest angle between camera 1's ray and another ray (below: ill-conditioned)."""
    max_residual_px: wp.float32
    """Largest RMS reprojection error, px (above: inconsistent)."""


@dataclass
class RayTriangulation:
    """Per match (Warp arrays of length n)."""

    points: wp.array
    """vec3 world point (mm); zero where the status is not ok, inconsistent or ill-conditioned."""
    status: wp.array
    """int32 status (``kernels.triangulation.STATUS_NAMES``)."""
    residual: wp.array
    """float32 RMS over the rays of each ray's reprojection error (each in its own pixels); -1 where no point."""
    chi2: wp.array
    """float32 weighted chi-square (sum of squared residuals over their predicted sigmas)."""
    sigma: wp.array
    """float32 predicted standard deviation of the point along camera 1's ray (mm)."""


# ----------------------------------------------------------------------------- helpers


@wp.func
def block_terms(r: wp.vec2, jx: wp.vec2, jy: wp.vec2, jz: wp.vec2, W: wp.vec3, H: wp.mat33, g: wp.vec3):
    """Add one 2-D observation (residual r, Jacobian columns j*, information W) to H and g."""
    H = H + wp.mat33(quad(W, jx, jx), quad(W, jx, jy), quad(W, jx, jz),
                     quad(W, jy, jx), quad(W, jy, jy), quad(W, jy, jz),
                     quad(W, jz, jx), quad(W, jz, jy), quad(W, jz, jz))
    g = g + wp.vec3(quad(W, jx, r), quad(W, jy, r), quad(W, jz, r))
    return H, g


@wp.func
def sym_vec(M: wp.mat22):
    """A symmetric 2x2 (float32 rounding's asymmetry averaged out) as (M00, M01, M11), the form
    :func:`block_terms` weighs by."""
    return wp.vec3(M[0, 0], 0.5 * (M[0, 1] + M[1, 0]), M[1, 1])


@wp.func
def ray_residual(cam: CameraModel, X: wp.vec3, uv: wp.vec2):
    """A camera ray's reprojection residual (px); the overload below is the light's (each model's own
    projection only: no switch between them inlined at every call)."""
    p = project_camera(cam, X)
    return wp.vec2(p[0] - uv[0], p[1] - uv[1])


@wp.func
def ray_residual(light: LightModel, X: wp.vec3, p_obs: wp.vec2):  # noqa: F811  (Warp overload)
    p = light_pixel(light, X)
    return wp.vec2(p[0] - p_obs[0], p[1] - p_obs[1])


@wp.func
def ray_jacobian(model: Any, X: wp.vec3, obs: wp.vec2, h: float):
    """The columns d r / d x, y, z of a ray's residual (a camera's or the light's: one instance a model) by
    central differences over h mm (the lens's exact derivative was tried and not taken: it converges samples
    of a rig that does not fit that these leave ``not_converged``, a change of behaviour; docs/batch.md gives
    the figures)."""
    ex = wp.vec3(h, 0.0, 0.0)
    ey = wp.vec3(0.0, h, 0.0)
    ez = wp.vec3(0.0, 0.0, h)
    jx = (ray_residual(model, X + ex, obs) - ray_residual(model, X - ex, obs)) / (2.0 * h)
    jy = (ray_residual(model, X + ey, obs) - ray_residual(model, X - ey, obs)) / (2.0 * h)
    jz = (ray_residual(model, X + ez, obs) - ray_residual(model, X - ez, obs)) / (2.0 * h)
    return jx, jy, jz


# ----------------------------------------------------------------------------- kernels


@wp.func
def all_residuals(cam1: CameraModel, cam2: CameraModel, light: LightModel, use_light: int, use_map: int,
                  A: wp.mat22, X: wp.vec3, obs1: wp.vec2, obs2: wp.vec2, obs_light: wp.vec2, W1: wp.vec3,
                  W2: wp.vec3, WL: wp.vec3):
    """Every ray's reprojection residual at X (the two cameras, and the light where ``use_light``; one
    projection a ray): (chi2, sum of squared residuals px^2). With ``use_map`` camera 2's residual enters
    chi2 less A times the light's (the part of it that the projector point's error makes, counted once,
    in the light's own); the sum of squares is of the plain residuals.

    Size: each ray's model, observation and weights as separate values (two cameras and the light), the
    map, as triangulate_rays_kernel holds them in registers."""
    r1 = ray_residual(cam1, X, obs1)
    r2 = ray_residual(cam2, X, obs2)
    ss = wp.dot(r1, r1) + wp.dot(r2, r2)
    chi = quad(W1, r1, r1)
    if use_light != 0:
        r3 = ray_residual(light, X, obs_light)
        chi += quad(WL, r3, r3)
        ss += wp.dot(r3, r3)
        if use_map != 0:
            r2 = r2 - A * r3
    chi += quad(W2, r2, r2)
    return chi, ss


@wp.kernel
def triangulate_rays_kernel(
    uv1: wp.array(dtype=wp.vec2),
    uv2: wp.array(dtype=wp.vec2),
    sigma1: wp.array(dtype=wp.float32),
    sigma2: wp.array(dtype=wp.float32),
    proj: wp.array(dtype=wp.vec2),
    proj_info: wp.array(dtype=wp.vec3),
    proj_map: wp.array(dtype=wp.vec4),
    cam1: CameraModel,
    cam2: CameraModel,
    light: LightModel,
    vol: Volume,
    params: RayParams,
    i0: int,
    points: wp.array(dtype=wp.vec3),
    status: wp.array(dtype=wp.int32),
    residual: wp.array(dtype=wp.float32),
    chi2: wp.array(dtype=wp.float32),
    sigma: wp.array(dtype=wp.float32),
):
    """Triangulate match i0 + tid from camera 1, camera 2 and, with ``params.use_light``,
    the projector.

    uv1, uv2 (n,) vec2 camera pixels (distorted), sigma1, sigma2 (n,) float32
    px, proj (n,) vec2 projector px, proj_info (n,) vec3 its information matrix
    (W00, W01, W11; 1/px^2) (proj unread without ``use_light``, proj_info without it and ``use_map``), proj_map
    (n,) vec4 the matcher's map
    (:class:`~ringscan.kernels.stereo_match.Matches` ``proj_map``; unread without ``use_map``): read. params:
    the third ray's and the map's switches and the bounds (:class:`RayParams`). points (n,)
    vec3, status (n,) int32, residual, chi2, sigma (n,) float32: written.

    Size: one thread per match: the Gauss-Newton iteration (each ray's residual and, where they moved, its
    Jacobian per step), the check at the solution and
    the point's sigma share the point's registers. Warp kernels take each array, each camera and the light as
    its own argument; the scalar settings already travel in RayParams.
    """
    i = i0 + wp.tid()
    use_light = params.use_light
    use_map = params.use_map
    min_sin = params.min_sin
    max_residual_px = params.max_residual_px
    points[i] = wp.vec3(0.0, 0.0, 0.0)
    residual[i] = -1.0
    chi2[i] = 0.0
    sigma[i] = 0.0
    d1, ok1 = camera_ray(cam1, uv1[i][0], uv1[i][1])
    d2, ok2 = camera_ray(cam2, uv2[i][0], uv2[i][1])
    if not ok1 or not ok2:
        status[i] = STATUS_UNDISTORT_FAILED
        return
    C1 = cam1.center
    C2 = cam2.center
    t1 = closest_on_ray(C1, d1, C2, d2)
    t2 = closest_on_ray(C2, d2, C1, d1)
    X = 0.5 * (C1 + d1 * t1 + C2 + d2 * t2)
    s1 = wp.max(sigma1[i], SIGMA_FLOOR_PX)
    s2 = wp.max(sigma2[i], SIGMA_FLOOR_PX)
    W1 = wp.vec3(1.0 / (s1 * s1), 0.0, 1.0 / (s1 * s1))
    W2 = wp.vec3(1.0 / (s2 * s2), 0.0, 1.0 / (s2 * s2))
    WL = wp.vec3(0.0, 0.0, 0.0)
    pL = wp.vec2(0.0, 0.0)
    A = wp.mat22(0.0, 0.0, 0.0, 0.0)
    if use_light != 0:
        WL = proj_info[i]
        pL = proj[i]
        if use_map != 0:
            m = proj_map[i]
            A = wp.mat22(m[0], m[1], m[2], m[3])
        f2 = params.projector_floor * params.projector_floor
        if f2 > 0.0:
            # the projector's calibration misses by f px (isotropic), which moves its point but not uv2 (camera
            # 2 reads the code): the projector's covariance S + f^2 I, camera 2's residual less B = A G times
            # the projector's (G = (I + f^2 W)^-1 = S (S + f^2 I)^-1), the rest of the code's error,
            # f^2 A G A^T, left on camera 2 (exact Gaussian conditioning; information form: W may be singular)
            Wm = wp.mat22(WL[0], WL[1], WL[1], WL[2])
            G = wp.inverse(wp.mat22(1.0, 0.0, 0.0, 1.0) + f2 * Wm)
            WG = Wm * G
            WL = sym_vec(WG)
            B = A * G
            Cov2 = f2 * (B * wp.transpose(A)) + wp.mat22(s2 * s2, 0.0, 0.0, s2 * s2)
            W2 = sym_vec(wp.inverse(Cov2))
            A = B
    elif use_map != 0:
        # two rays through the map: uv2 carries the query's code error through it, camera 2's covariance
        # s2^2 I + A S A^T (S: the query's, from its information; the three rays' floor f -> infinity)
        m = proj_map[i]
        Am = wp.mat22(m[0], m[1], m[2], m[3])
        Wq = proj_info[i]
        S = wp.inverse(wp.mat22(Wq[0], Wq[1], Wq[1], Wq[2]))
        Cov2 = Am * S * wp.transpose(Am) + wp.mat22(s2 * s2, 0.0, 0.0, s2 * s2)
        W2 = sym_vec(wp.inverse(Cov2))
    converged = bool(False)
    H = wp.mat33(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    chi = float(0.0)
    ss = float(0.0)
    # Jacobians by central differences over 0.5 mm: the projections are smooth on
    # that scale, and a smaller step lets float32 noise into the Jacobian, which
    # a point with a large residual (rays that miss) multiplies into its steps
    h = wp.min(float(JACOBIAN_STEP_MM), JACOBIAN_STEP_DEPTH * wp.length(X - C1))
    o1 = uv1[i]
    o2 = uv2[i]
    j1x = wp.vec2(0.0, 0.0)
    j1y = wp.vec2(0.0, 0.0)
    j1z = wp.vec2(0.0, 0.0)
    j2x = wp.vec2(0.0, 0.0)
    j2y = wp.vec2(0.0, 0.0)
    j2z = wp.vec2(0.0, 0.0)
    jlx = wp.vec2(0.0, 0.0)
    jly = wp.vec2(0.0, 0.0)
    jlz = wp.vec2(0.0, 0.0)
    fresh = bool(True)
    for _it in range(NEWTON_STEPS):
        r1 = ray_residual(cam1, X, o1)
        r2 = ray_residual(cam2, X, o2)
        if fresh:
            j1x, j1y, j1z = ray_jacobian(cam1, X, o1, h)
            j2x, j2y, j2z = ray_jacobian(cam2, X, o2, h)
        H = wp.mat33(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        g = wp.vec3(0.0, 0.0, 0.0)
        H, g = block_terms(r1, j1x, j1y, j1z, W1, H, g)
        if use_light != 0:
            rl = ray_residual(light, X, pL)
            if fresh:
                jlx, jly, jlz = ray_jacobian(light, X, pL, h)
                if use_map != 0:
                    # camera 2's residual less what the projector point's error made of it (uv2 = where
                    # camera 2 reads that point): its Jacobian alike, kept with the others
                    j2x = j2x - A * jlx
                    j2y = j2y - A * jly
                    j2z = j2z - A * jlz
            if use_map != 0:
                r2 = r2 - A * rl
            H, g = block_terms(rl, jlx, jly, jlz, WL, H, g)
        H, g = block_terms(r2, j2x, j2y, j2z, W2, H, g)
        if not (wp.abs(wp.determinant(H)) > 0.0):
            break
        step = wp.inverse(H) * g
        X = X - step
        # 2 % of the point's own standard deviation along the step is as far as refining helps
        sd = wp.sqrt(wp.max(wp.dot(step, wp.inverse(H) * step), 0.0)) / wp.max(wp.length(step), 1.0e-30)
        if wp.length(step) < wp.max(1.0e-4, 0.02 * sd):
            converged = True
            break
        # within a tenth of the difference step of where they were taken, the Jacobians stand (the next
        # steps are the same Newton steps to float32, at one projection a ray instead of seven)
        fresh = wp.length(step) > CHORD_STEP * h
    # the residual at the solution; its covariance from the last step's normal equations (the
    # step that converged moved the point by under 2 % of its sigma: H is the same to float32)
    chi, ss = all_residuals(cam1, cam2, light, use_light, use_map, A, X, uv1[i], uv2[i], pL, W1, W2, WL)
    nr = wp.where(use_light != 0, 3.0, 2.0)
    rms = wp.sqrt(ss / nr)
    if not converged:
        # rays that miss each other by far leave float32 noise in the steps: name it for what it is
        status[i] = wp.where(rms > max_residual_px, STATUS_INCONSISTENT, STATUS_NOT_CONVERGED)
        residual[i] = wp.where(rms > max_residual_px, rms, -1.0)
        return
    # in front of both cameras (and the projector), inside the volume
    z1 = (cam1.R * X + cam1.t)[2]
    z2 = (cam2.R * X + cam2.t)[2]
    front = z1 > 0.0 and z2 > 0.0
    if use_light != 0:
        front = front and light_pixel(light, X)[2] > 0.0
    if not front or not in_volume(X, vol):
        status[i] = STATUS_OUTSIDE
        return
    # conditioning: the widest angle between camera 1's ray and another ray
    sn = wp.length(wp.cross(d1, d2))
    if use_light != 0:
        sn = wp.max(sn, wp.length(wp.cross(d1, direction_to_light(light, X))))
    cov = wp.inverse(H)
    var = wp.dot(d1, cov * d1)
    points[i] = X
    residual[i] = rms
    chi2[i] = chi
    sigma[i] = wp.where(var > 0.0, wp.sqrt(var), 1.0e9)
    st = int(STATUS_OK)
    if sn < min_sin:
        st = STATUS_ILL_CONDITIONED
    elif rms > max_residual_px:
        st = STATUS_INCONSISTENT
    status[i] = st


@wp.kernel
def place_matches_kernel(
    index: wp.array(dtype=wp.int32),
    points_m: wp.array(dtype=wp.vec3),
    status_m: wp.array(dtype=wp.int32),
    sigma_m: wp.array(dtype=wp.float32),
    residual_m: wp.array(dtype=wp.float32),
    confidence_s: wp.array(dtype=wp.float32),
    i0: int,
    points: wp.array(dtype=wp.vec3),
    status: wp.array(dtype=wp.int32),
    confidence: wp.array(dtype=wp.float32),
    sigma: wp.array(dtype=wp.float32),
    residual: wp.array(dtype=wp.float32),
):
    """Match i0 + tid's triangulation written at its sample: index (m,) int32 the sample of each match;
    points_m (m,) vec3, status_m (m,) int32, sigma_m, residual_m (m,) float32 the matches'; confidence_s (n,)
    float32 the samples': read. points (n,) vec3, status (n,) int32, confidence, sigma, residual (n,)
    float32: written at the matched samples (the others keep what they hold).

    Size: the matches' four results and the samples' confidence in, the five per-sample arrays out."""
    k = i0 + wp.tid()
    i = index[k]
    st = status_m[k]
    points[i] = points_m[k]
    status[i] = st
    confidence[i] = wp.where(st == STATUS_OK, confidence_s[i], 0.0)
    sigma[i] = sigma_m[k]
    residual[i] = residual_m[k]


@wp.kernel
def polar_information_kernel(
    proj: wp.array(dtype=wp.vec2),
    sigma_rho: wp.array(dtype=wp.float32),
    sigma_tan: wp.array(dtype=wp.float32),
    extra: wp.array(dtype=wp.float32),
    gain: wp.array(dtype=wp.float32),
    use_extra: int,
    center: wp.vec2d,
    i0: int,
    info: wp.array(dtype=wp.vec3),
):
    """The information matrix (W00, W01, W11; 1/px^2) of projector pixel proj[i] whose errors are radial
    (sigma_rho, at least 1e-3 px) and tangential (sigma_tan) about ``center``: R diag(1/sr^2, 1/st^2) R^T
    with R the radial direction's rotation (the u axis at the centre itself).

    With ``use_extra`` an isotropic error ``extra`` (camera px, over ``gain``: camera px per projector px) is
    added to both in quadrature.

    proj (n,) vec2, sigma_rho, sigma_tan, extra, gain (n,) float32 (the last two unread without use_extra):
    read; info (n,) vec3: written.

    Size: five per-sample arrays and extra's switch, the centre, the span's i0, one array out."""
    i = i0 + wp.tid()
    ox = wp.float64(proj[i][0]) - center[0]
    oy = wp.float64(proj[i][1]) - center[1]
    r = wp.sqrt(ox * ox + oy * oy)
    c = wp.float64(1.0)
    s = wp.float64(0.0)
    if r > wp.float64(0.0):
        c = ox / r
        s = oy / r
    sr = wp.float64(sigma_rho[i])
    st = wp.float64(sigma_tan[i])
    if use_extra != 0:
        e = wp.float64(extra[i]) / wp.max(wp.float64(gain[i]), wp.float64(1.0e-6))
        sr = wp.sqrt(sr * sr + e * e)
        st = wp.sqrt(st * st + e * e)
    sr = wp.max(sr, wp.float64(1e-3))
    st = wp.max(st, wp.float64(1e-3))
    ir = wp.float64(1.0) / (sr * sr)
    it = wp.float64(1.0) / (st * st)
    info[i] = wp.vec3(wp.float32(ir * c * c + it * s * s), wp.float32((ir - it) * c * s),
                      wp.float32(ir * s * s + it * c * c))


@wp.kernel
def through_map_kernel(
    sigma1: wp.array(dtype=wp.float32),
    query_model: wp.array(dtype=wp.float32),
    proj_map: wp.array(dtype=wp.vec4),
    sigma_rho: wp.array(dtype=wp.float32),
    gain: wp.array(dtype=wp.float32),
    ring_edges: int,
    i0: int,
    sigma1_out: wp.array(dtype=wp.float32),
    extra: wp.array(dtype=wp.float32),
    sigma_rho_out: wp.array(dtype=wp.float32),
):
    """Match i0 + tid's camera-1 sigma, projector extra and radial sigma for three rays.

    A full map (both columns known: a dense code): camera 1's pixel is its ray (``PIXEL_RAY_PX``), the query's
    share of the scatter goes to the projector's point (``extra``, camera px), its radial sigma as it is.
    A map along a line where the samples are ring edges (``ring_edges``: camera 2's neighbours on the query's
    ring, the map across it unknown): the ring's radius is the code's own, exact (``EXACT_RADIUS_PX``), and
    the edge's error is where it was measured, camera 1's place (sigma_rho through the gain, and the query's
    share, camera px); uv2 carries the angle's error alone, which the rank-one map takes. No map (0), or a
    line of another code's samples (whose radius errs too): the rays independent, as given.

    sigma1, query_model, sigma_rho, gain (n,) float32, proj_map (n,) vec4: read; sigma1_out, extra,
    sigma_rho_out (n,) float32: written.

    Size: the five match arrays in, three out."""
    i = i0 + wp.tid()
    m = proj_map[i]
    n2 = 0.5 * (m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3])
    det = m[0] * m[3] - m[1] * m[2]
    sigma1_out[i] = sigma1[i]
    extra[i] = 0.0
    sigma_rho_out[i] = sigma_rho[i]
    if n2 > 0.0:
        if wp.abs(det) > LINE_MAP_DET * n2:
            sigma1_out[i] = PIXEL_RAY_PX
            extra[i] = query_model[i]
        elif ring_edges != 0:
            g = gain[i] * sigma_rho[i]
            sigma1_out[i] = wp.sqrt(g * g + query_model[i] * query_model[i])
            sigma_rho_out[i] = EXACT_RADIUS_PX


@wp.kernel
def projector_miss_kernel(
    points: wp.array(dtype=wp.vec3),
    status: wp.array(dtype=wp.int32),
    sigma: wp.array(dtype=wp.float32),
    proj: wp.array(dtype=wp.vec2),
    proj_info: wp.array(dtype=wp.vec3),
    cam1: CameraModel,
    light: LightModel,
    i0: int,
    residual: wp.array(dtype=wp.float32),
    residual_var: wp.array(dtype=wp.float32),
):
    """Match i0 + tid's projector point against the two cameras' point: the projector pixel's residual
    along the direction in which camera 1's ray runs through the projector (where a miss moves the point),
    and its predicted variance (the projector point's, from its information matrix, and the cameras' point's
    along camera 1's ray through that direction); residual -1 and variance 0 where the cameras placed no
    point or the information is singular there.

    points (n,) vec3, status (n,) int32, sigma (n,) float32 (the two-ray triangulation's), proj (n,) vec2,
    proj_info (n,) vec3: read; residual, residual_var (n,) float32: written.

    Size: the two rays' three results and the projector point's two arrays, both models."""
    i = i0 + wp.tid()
    residual[i] = -1.0
    residual_var[i] = 0.0
    if status[i] != STATUS_OK:
        return
    X = points[i]
    pL = proj[i]
    g = px_per_mm_along(light, cam1.center, X)
    gl = wp.length(g)
    W = proj_info[i]
    det = W[0] * W[2] - W[1] * W[1]
    if not (gl > 0.0 and det > 0.0):
        return
    u = g / gl
    # u^T W^-1 u
    var_p = (W[2] * u[0] * u[0] - 2.0 * W[1] * u[0] * u[1] + W[0] * u[1] * u[1]) / det
    s = gl * sigma[i]
    residual[i] = wp.abs(wp.dot(u, ray_residual(light, X, pL)))
    residual_var[i] = var_p + s * s


@wp.func
def px_per_mm_along(light: LightModel, C: wp.vec3, X: wp.vec3):
    """How far (projector px per mm) the projector pixel of X moves as X moves along the ray from C through
    it (central differences over the rays' Jacobian step)."""
    d = wp.normalize(X - C)
    h = wp.min(float(JACOBIAN_STEP_MM), JACOBIAN_STEP_DEPTH * wp.length(X - C))
    pa = light_pixel(light, X + d * h)
    pb = light_pixel(light, X - d * h)
    return wp.vec2(pa[0] - pb[0], pa[1] - pb[1]) / (2.0 * h)


@wp.kernel
def along_ray_floor_kernel(
    points: wp.array(dtype=wp.vec3),
    status: wp.array(dtype=wp.int32),
    sigma: wp.array(dtype=wp.float32),
    floor: float,
    cam1: CameraModel,
    light: LightModel,
    i0: int,
    out: wp.array(dtype=wp.float32),
):
    """Point i0 + tid's sigma along camera 1's ray with a projector miss of ``floor`` px along that ray's
    course through the projector added in quadrature (floor over the px a mm there); unplaced points (status
    not ok) as they were.

    points (n,) vec3, status (n,) int32, sigma (n,) float32: read; out (n,) float32: written.

    Size: a triangulation's three arrays, the miss, both models."""
    i = i0 + wp.tid()
    out[i] = sigma[i]
    if status[i] != STATUS_OK:
        return
    gl = wp.length(px_per_mm_along(light, cam1.center, points[i]))
    if gl > 0.0:
        e = floor / gl
        out[i] = wp.sqrt(sigma[i] * sigma[i] + e * e)


@wp.kernel
def chi_widen_kernel(
    status: wp.array(dtype=wp.int32),
    chi2: wp.array(dtype=wp.float32),
    sigma: wp.array(dtype=wp.float32),
    dof: float,
    i0: int,
    out: wp.array(dtype=wp.float32),
):
    """Point i0 + tid's sigma times its chi (sqrt(chi2 / dof): the Birge ratio of its fit's ``dof`` degrees of
    freedom) where that is above 1; as it was elsewhere and where the point is not placed.

    status (n,) int32, chi2, sigma (n,) float32: read; out (n,) float32: written."""
    i = i0 + wp.tid()
    out[i] = sigma[i]
    if status[i] == STATUS_OK:
        out[i] = sigma[i] * birge_ratio(chi2[i] / dof)


# ----------------------------------------------------------------------------- host


def through_map(sigma1: wp.array, query_model: wp.array, proj_map: wp.array, sigma_rho: wp.array, gain: wp.array, *,
                ring_edges: bool, threads: int | None = None) -> tuple[wp.array, wp.array, wp.array]:
    """Three rays through the matcher's map (:func:`through_map_kernel`): (sigma1 for
    :func:`triangulate_rays`, ``extra`` and sigma_rho for :func:`polar_information`), (n,) float32 each on
    sigma1's device.

    sigma1, query_model, sigma_rho, gain (n,) float32, proj_map (n,) vec4 (``kernels.stereo_match.Matches``,
    widened); ``ring_edges``: camera 1's samples are ring edges (their radius the ring's)."""
    fn = "through_map"
    n = check_array("sigma1", sigma1, None, wp.float32, fn)
    check_array("query_model", query_model, n, wp.float32, fn)
    check_array("proj_map", proj_map, n, wp.vec4, fn)
    check_array("sigma_rho", sigma_rho, n, wp.float32, fn)
    check_array("gain", gain, n, wp.float32, fn)
    dev = sigma1.device
    out = [wp.empty(n, dtype=wp.float32, device=dev) for _ in range(3)]
    args = [sigma1, query_model, proj_map, sigma_rho, gain, 1 if ring_edges else 0]
    launch_spans(through_map_kernel, n, lambda i0: args + [i0], out, dev,
                 default_threads() if threads is None else threads)
    return out[0], out[1], out[2]


def projector_misses(tri: RayTriangulation, proj: wp.array, proj_info: wp.array, *, camera1: CameraModel,
                     light: LightModel, threads: int | None = None) -> tuple[wp.array, wp.array]:
    """Each match's projector point against the two cameras' point (:func:`projector_miss_kernel`):
    (residual, residual_var), (n,) float32 each on proj's device, for
    ``kernels.calibration_floor.residual_floor``: what the projector's calibration misses where the cameras
    agree.

    tri: a two-ray :func:`triangulate_rays` of the matches; proj (n,) vec2, proj_info (n,) vec3 as the third
    ray takes them."""
    fn = "projector_misses"
    n = check_array("proj", proj, None, wp.vec2, fn)
    check_array("proj_info", proj_info, n, wp.vec3, fn)
    check_array("tri.points", tri.points, n, wp.vec3, fn)
    dev = proj.device
    res, var = wp.empty(n, dtype=wp.float32, device=dev), wp.empty(n, dtype=wp.float32, device=dev)
    launch_spans(projector_miss_kernel, n, lambda i0: [tri.points, tri.status, tri.sigma, proj, proj_info, camera1,
                                                          light, i0], [res, var], dev,
                 default_threads() if threads is None else threads)
    return res, var


def widen_along_rays(tri, floor_px: float, *, camera1: CameraModel, light: LightModel,
                     threads: int | None = None) -> wp.array:
    """(n,) float32 the points' sigmas (``tri``: a triangulation's ``points``, ``status``, ``sigma``, camera 1's
    samples) with a projector miss of ``floor_px`` along camera 1's rays added (:func:`along_ray_floor_kernel`):
    camera-projector points of a view whose two cameras found the projector missing them (the miss runs where
    no camera-projector check sees it)."""
    fn = "widen_along_rays"
    n = check_array("tri.points", tri.points, None, wp.vec3, fn)
    check_array("tri.status", tri.status, n, wp.int32, fn)
    check_array("tri.sigma", tri.sigma, n, wp.float32, fn)
    dev = tri.points.device
    out = wp.empty(n, dtype=wp.float32, device=dev)
    launch_spans(along_ray_floor_kernel, n, lambda i0: [tri.points, tri.status, tri.sigma, float(floor_px), camera1,
                                                           light, i0], [out], dev,
                 default_threads() if threads is None else threads)
    return out


def widen_by_chi(tri: RayTriangulation, *, dof: int, threads: int | None = None) -> RayTriangulation:
    """``tri`` with each placed point's sigma grown by its chi where its rays disagree more than their sigmas
    allow (:func:`chi_widen_kernel`; ``dof``: the fit's degrees of freedom, 1 for two rays, 3 for three), as a
    one-camera point of both coordinates grows by its own (``kernels.triangulation.disagreement_factor``):
    what no model of the view predicts (a mixed pixel at camera 1's silhouette, a misread edge) shows in the
    point's own residual."""
    fn = "widen_by_chi"
    n = check_array("tri.status", tri.status, None, wp.int32, fn)
    check_array("tri.chi2", tri.chi2, n, wp.float32, fn)
    check_array("tri.sigma", tri.sigma, n, wp.float32, fn)
    if dof < 1:
        raise ValueError(f"{fn}: dof must be at least 1, got {dof}")
    dev = tri.sigma.device
    out = wp.empty(n, dtype=wp.float32, device=dev)
    launch_spans(chi_widen_kernel, n, lambda i0: [tri.status, tri.chi2, tri.sigma, float(dof), i0], [out], dev,
                 default_threads() if threads is None else threads)
    return replace(tri, sigma=out)


def place_matches(index: wp.array, tri: RayTriangulation, confidence: wp.array, *, points: wp.array,
                  status: wp.array, sigma: wp.array, residual: wp.array, placed_confidence: wp.array,
                  threads: int | None = None) -> None:
    """Write each match's triangulation (``tri``, (m,)) at its sample (``index``, (m,) int32) into the
    per-sample arrays ((n,): ``points`` vec3, ``status`` int32, ``sigma``, ``residual``, ``placed_confidence``
    float32, the samples' ``confidence`` where the point is ok, else 0), on their device; the samples without
    a match keep what the arrays hold.

    Size: the matches' index and results and the samples' confidence in, the five per-sample arrays (each a
    keyword: where the caller's fallback already stands) out, and the CPU threads."""
    fn = "place_matches"
    m = check_array("index", index, None, wp.int32, fn)
    n = check_array("confidence", confidence, None, wp.float32, fn)
    for name, a, dt in (("points", points, wp.vec3), ("status", status, wp.int32), ("sigma", sigma, wp.float32),
                        ("residual", residual, wp.float32), ("placed_confidence", placed_confidence, wp.float32)):
        check_array(name, a, n, dt, fn)
    check_array("tri.points", tri.points, m, wp.vec3, fn)
    dev = index.device
    args = [index, tri.points, tri.status, tri.sigma, tri.residual, confidence]
    launch_spans(place_matches_kernel, m, lambda i0: args + [i0], [points, status, placed_confidence, sigma, residual],
                 dev, default_threads() if threads is None else threads)


def polar_information(proj: wp.array, sigma_rho: wp.array, sigma_tan: wp.array, *,
                      center: tuple[float, float], extra: wp.array | None = None, gain: wp.array | None = None,
                      threads: int | None = None) -> wp.array:
    """Information matrices (W00, W01, W11; 1/px^2) of projector pixels whose
    errors are radial (sigma_rho) and tangential (sigma_tan) about ``center``
    (:func:`polar_information_kernel`, float64 as NumPy computed them before), and isotropic
    (``extra`` camera px over ``gain`` camera px per projector px, where given: added to both in quadrature).

    proj (n,) vec2, sigma_rho, sigma_tan, extra, gain (n,) float32 -> (n,) vec3 on proj's device."""
    fn = "polar_information"
    n = check_array("proj", proj, None, wp.vec2, fn)
    check_array("sigma_rho", sigma_rho, n, wp.float32, fn)
    check_array("sigma_tan", sigma_tan, n, wp.float32, fn)
    if (extra is None) != (gain is None):
        raise ValueError(f"{fn}: extra and gain go together")
    if extra is not None:
        check_array("extra", extra, n, wp.float32, fn)
        check_array("gain", gain, n, wp.float32, fn)
    out = wp.empty(n, dtype=wp.vec3, device=proj.device)
    use_extra = 0 if extra is None else 1
    if extra is None:
        extra = gain = wp.zeros(1, dtype=wp.float32, device=proj.device)
    args = [proj, sigma_rho, sigma_tan, extra, gain, use_extra, wp.vec2d(float(center[0]), float(center[1]))]
    launch_spans(polar_information_kernel, n, lambda i0: args + [i0], [out], proj.device,
                 default_threads() if threads is None else threads)
    return out


def triangulate_rays(    uv1: wp.array,
    uv2: wp.array,
    sigma1: wp.array,
    sigma2: wp.array,
    *,
    camera1: CameraModel,
    camera2: CameraModel,
    volume: tuple[float, float, float],
    light: LightModel | None = None,
    proj: wp.array | None = None,
    proj_info: wp.array | None = None,
    proj_map: wp.array | None = None,
    projector_floor_px: float = 0.0,
    min_sin: float = 0.03,
    max_residual_px: float = 2.0,
    threads: int | None = None,
) -> RayTriangulation:
    """Points from two camera rays, or three rays with the calibrated projector.

    Args:
        uv1, uv2: (n,) vec2 camera-1 and camera-2 pixels (distorted images).
        sigma1, sigma2: (n,) float32 their standard deviations (px).
        camera1, camera2: :class:`~ringscan.kernels.geometry.CameraModel` each.
        volume: (z_min, z_max, r_max) of the working volume, world mm.
        light: the calibrated projector (or parallel light) for a third ray; None: two rays.
        proj: (n,) vec2 projector pixels (with ``light``).
        proj_info: (n,) vec3 their information matrices (with ``light``, or with ``proj_map``: the query's
            projector point's; :func:`polar_information`).
        proj_map: (n,) vec4 (optional) how uv2 moves with the query's projector point (row-major 2x2,
            camera-2 px per projector px: the matcher's ``proj_map``) where uv2 was found as the place camera 2
            reads it: its error then carries the point's through the map. With ``light`` camera 2's residual is
            taken less the map times the light's (counted once); without, camera 2's covariance is s2^2 I +
            A S A^T (S: the point's, from ``proj_info``). ``sigma1`` is then camera 1's pixel's own error (the
            code read there carries the rest, in ``proj_info``). None: the rays' errors are independent.
        projector_floor_px: (with ``light``) the projector calibration's miss (px, isotropic: added to proj's
            covariance; uv2 does not share it, so the map's share of proj's error is conditioned on it).
        min_sin: least sine of the widest angle between camera 1's ray and another
            ray: below it the point is ``ill_conditioned``.
        max_residual_px: largest RMS reprojection error (px): above it ``inconsistent``.
        threads: CPU threads; default all cores.

    Size: a public function: the four sample arrays and its documented keyword-only options (cameras, volume,
    the optional third ray and its inputs, the two bounds, threads).
    """
    fn = "triangulate_rays"
    n = check_array("uv1", uv1, None, wp.vec2, fn)
    check_array("uv2", uv2, n, wp.vec2, fn)
    check_array("sigma1", sigma1, n, wp.float32, fn)
    check_array("sigma2", sigma2, n, wp.float32, fn)
    if (light is None) != (proj is None) or (light is not None and proj_info is None):
        raise ValueError(f"{fn}: light, proj and proj_info go together")
    if light is not None:
        check_array("proj", proj, n, wp.vec2, fn)
    if proj_map is not None:
        if proj_info is None:
            raise ValueError(f"{fn}: proj_map needs proj_info (the query's information)")
        check_array("proj_map", proj_map, n, wp.vec4, fn)
    elif light is None and proj_info is not None:
        raise ValueError(f"{fn}: proj_info without the light needs proj_map (two rays through the map)")
    if proj_info is not None:
        check_array("proj_info", proj_info, n, wp.vec3, fn)
    if not (projector_floor_px >= 0) or (projector_floor_px > 0 and light is None):
        raise ValueError(f"{fn}: projector_floor_px must be >= 0, and needs the light")
    z_min, z_max, r_max = (float(x) for x in volume)
    if not (z_max > z_min and r_max > 0):
        raise ValueError(f"{fn}: bad volume {volume}")
    if not (0 <= min_sin < 1) or not (max_residual_px > 0):
        raise ValueError(f"{fn}: need 0 <= min_sin < 1 and max_residual_px > 0")
    dev = uv1.device
    out = RayTriangulation(points=wp.empty(n, dtype=wp.vec3, device=dev),
                           status=wp.empty(n, dtype=wp.int32, device=dev),
                           residual=wp.empty(n, dtype=wp.float32, device=dev),
                           chi2=wp.empty(n, dtype=wp.float32, device=dev),
                           sigma=wp.empty(n, dtype=wp.float32, device=dev))
    if n == 0:
        return out
    use_light = 1 if light is not None else 0
    use_map = 1 if proj_map is not None else 0
    if proj_map is None:
        proj_map = wp.zeros(1, dtype=wp.vec4, device=dev)
    if light is None:
        # an unused struct: the kernel reads no field of it
        from_cam = LightModel()
        from_cam.model = 1
        from_cam.distorted = 0
        from_cam.cam = camera1
        from_cam.R = wp.mat33(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        light = from_cam
        proj = wp.zeros(1, dtype=wp.vec2, device=dev)
        if proj_info is None:
            proj_info = wp.zeros(1, dtype=wp.vec3, device=dev)
    params = RayParams()
    params.use_light = use_light
    params.use_map = use_map
    params.projector_floor = float(projector_floor_px)
    params.min_sin = float(min_sin)
    params.max_residual_px = float(max_residual_px)
    args = [uv1, uv2, sigma1, sigma2, proj, proj_info, proj_map, camera1, camera2, light,
            make_volume(z_min, z_max, r_max), params]
    outputs = [out.points, out.status, out.residual, out.chi2, out.sigma]
    threads = default_threads() if threads is None else threads
    launch_spans(triangulate_rays_kernel, n, lambda i0: args + [i0], outputs, dev, threads)
    return out
