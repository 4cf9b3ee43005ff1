"""The ring's quadric: where a camera ray meets the light's ring ``rho`` (docs/design.md §3, §4).

A ring is a quadric of the light: the cylinder of a parallel light, or the cone of a
perspective projector's rays whose undistorted pixel lies on ``|p - c| = rho``
(:func:`ring_terms`). :func:`ray_ring_roots` meets a camera ray with it (the one
solve that triangulation and the single-shot labeller both call), refining each root
through the projector's lens distortion (:func:`refine_root`); :func:`root_usable`
keeps a root only where it can be lit and seen. ``@wp.func`` helpers only: the
structs and the lens model are :mod:`ringscan.kernels.geometry`'s.
"""

from __future__ import annotations

import warp as wp

from ringscan.kernels.geometry import (
    LIGHT_PARALLEL,
    NEWTON_STEPS,
    LightModel,
    Volume,
    in_lens_region,
    in_volume,
    light_pixel,
    light_point_local,
)

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

ROOT_TOL_PX = wp.constant(0.01)
ROOT_FAILED_1 = wp.constant(1)
ROOT_FAILED_2 = wp.constant(2)

__all__ = [
    "ROOT_TOL_PX",
    "ROOT_FAILED_1",
    "ROOT_FAILED_2",
    "light_dir_local",
    "ring_terms",
    "pattern_offset",
    "refine_root",
    "ray_ring_roots",
    "root_usable",
]


@wp.func
def light_dir_local(light: LightModel, d: wp.vec3):
    """World direction -> light frame (parallel) or projector frame (perspective)."""
    if light.model == LIGHT_PARALLEL:
        return light.R * d
    return light.cam.R * d


@wp.func
def ring_terms(light: LightModel, P: wp.vec3d, center: wp.vec2d):
    """(a, b, z) at a point P of the light's own frame, with a^2 + b^2 = rho^2 z^2
    on the ring's quadric (z = 1 for the parallel light, in projector pixels)."""
    if light.model == LIGHT_PARALLEL:
        s = wp.float64(light.s)
        a = P[0] / s + wp.float64(light.a[0]) - center[0]
        b = P[1] / s + wp.float64(light.a[1]) - center[1]
        return wp.vec3d(a, b, wp.float64(1.0))
    c = light.cam
    a = wp.float64(c.fx) * P[0] + wp.float64(c.skew) * P[1] + (wp.float64(c.cx) - center[0]) * P[2]
    b = wp.float64(c.fy) * P[1] + (wp.float64(c.cy) - center[1]) * P[2]
    return wp.vec3d(a, b, P[2])


@wp.func
def has_distortion(light: LightModel):
    return light.distorted != 0


@wp.func
def pattern_offset(light: LightModel, X: wp.vec3, center: wp.vec2):
    """Pixel offset p - c of world point X on the projector grid (with distortion)."""
    p = light_pixel(light, X)
    return wp.vec2(p[0] - center[0], p[1] - center[1])


@wp.func
def ring_residual(light: LightModel, C: wp.vec3, d: wp.vec3, t: float, rho: float, center: wp.vec2):
    """|pixel(X(t)) - c| - rho on the projector grid (with its lens distortion)."""
    return wp.length(pattern_offset(light, C + d * t, center)) - rho


@wp.func
def refine_root(light: LightModel, C: wp.vec3, d: wp.vec3, t0: float, rho: float, center: wp.vec2):
    """Newton steps on g(t) = |pixel(X(t)) - c| - rho (projector lens distortion),
    from the undistorted cone's root t0. Returns (t, converged).

    The derivative is a central difference over h = 0.05 mm (the pattern offset
    is smooth on that scale, and float32 resolves it); the iteration stops at
    float32's resolution (|g| < 1e-4 px or a step below 1e-7 of t; 2-4 steps for
    a usual lens) or after ``NEWTON_STEPS`` steps. converged is True
    only where |g(t)| <= ``ROOT_TOL_PX`` at the end, the point lies in front of
    the projector and inside the fold-free region of its lens
    (:func:`in_lens_region`): anywhere else the root is unknown (or lit by no
    pixel the model can name) and must be dropped, never kept."""
    t = t0
    h = wp.max(0.05, 1.0e-4 * wp.abs(t0))
    g = float(0.0)
    g_at_t = bool(False)  # g is the residual at the final t (no step taken since)
    for _i in range(NEWTON_STEPS):
        g0 = ring_residual(light, C, d, t, rho, center)
        g = g0
        g_at_t = True
        if wp.abs(g0) < 1.0e-4:
            break
        dg = (ring_residual(light, C, d, t + h, rho, center) - ring_residual(light, C, d, t - h, rho, center)) / (2.0 * h)
        if not (wp.abs(dg) > 1.0e-9):
            break
        step = g0 / dg
        t = t - step
        g_at_t = False
        if wp.abs(step) < 1.0e-7 * wp.max(1.0, wp.abs(t)):
            break
    Xp = light.cam.R * (C + d * t) + light.cam.t
    ok = False
    if Xp[2] > 0.0:
        xn = Xp[0] / Xp[2]
        yn = Xp[1] / Xp[2]
        if not g_at_t:
            g = ring_residual(light, C, d, t, rho, center)
        ok = wp.abs(g) <= ROOT_TOL_PX and in_lens_region(light.cam, xn, yn)
    return t, ok


@wp.func
def ray_ring_roots(light: LightModel, C: wp.vec3, d: wp.vec3, rho: float, center: wp.vec2):
    """Both meetings of the ray X(t) = C + t d with the quadric of ring ``rho``.

    The ring's quadric is a^2 + b^2 = rho^2 z^2 in :func:`ring_terms`; along the
    ray the terms are affine in t, so this is a (t^2) + b t + c = 0, solved in
    float64 with the stable form. With projector distortion each root in front
    of the projector is then refined by :func:`refine_root` (a root behind it is
    on the cone's other nappe, lit by nothing: it is left as it is, and
    :func:`root_usable` drops it).

    Returns (vec3(t1, t2, real), failed): t1 <= t2 and real = 1 where the ray
    meets the quadric (0: no real root; t1 = t2 = 0); ``failed`` has bit
    ``ROOT_FAILED_1`` / ``ROOT_FAILED_2`` set where the refinement of t1 / t2 did
    not converge: that root's place is unknown.
    """
    P0 = light_point_local(light, C)
    D0 = light_dir_local(light, d)
    o = wp.vec3d(wp.float64(P0[0]), wp.float64(P0[1]), wp.float64(P0[2]))
    e = wp.vec3d(wp.float64(D0[0]), wp.float64(D0[1]), wp.float64(D0[2]))
    c2 = wp.vec2d(wp.float64(center[0]), wp.float64(center[1]))
    q0 = ring_terms(light, o, c2)
    dq = ring_terms(light, o + e, c2) - q0
    if light.model == LIGHT_PARALLEL:
        dq = wp.vec3d(dq[0], dq[1], wp.float64(0.0))
    r2 = wp.float64(rho) * wp.float64(rho)
    A = dq[0] * dq[0] + dq[1] * dq[1] - r2 * dq[2] * dq[2]
    B = wp.float64(2.0) * (q0[0] * dq[0] + q0[1] * dq[1] - r2 * q0[2] * dq[2])
    Cc = q0[0] * q0[0] + q0[1] * q0[1] - r2 * q0[2] * q0[2]
    disc = B * B - wp.float64(4.0) * A * Cc
    failed = int(0)
    if disc < wp.float64(0.0) or wp.abs(A) < wp.float64(1.0e-18):
        return wp.vec3(0.0, 0.0, 0.0), failed
    sq = wp.sqrt(disc)
    qq = wp.float64(-0.5) * (B + wp.where(B >= wp.float64(0.0), sq, -sq))
    ta = float(qq / A)
    tb = float(Cc / qq) if qq != wp.float64(0.0) else ta
    t1 = wp.min(ta, tb)
    t2 = wp.max(ta, tb)
    if has_distortion(light):
        if (light.cam.R * (C + d * t1) + light.cam.t)[2] > 0.0:
            t1, ok1 = refine_root(light, C, d, t1, rho, center)
            if not ok1:
                failed = failed | ROOT_FAILED_1
        if (light.cam.R * (C + d * t2) + light.cam.t)[2] > 0.0:
            t2, ok2 = refine_root(light, C, d, t2, rho, center)
            if not ok2:
                failed = failed | ROOT_FAILED_2
        if t2 < t1:
            tt = t1
            t1 = t2
            t2 = tt
            failed = ((failed & ROOT_FAILED_1) << 1) | ((failed & ROOT_FAILED_2) >> 1)
    return wp.vec3(t1, t2, 1.0), failed


@wp.func
def root_usable(light: LightModel, X: wp.vec3, t: float, vol: Volume):
    """A root is kept only in front of the camera (t > 0), inside the working
    volume and, for a perspective light, in front of the projector (docs/design.md §4)."""
    ok = t > 0.0 and in_volume(X, vol)
    if light.model != LIGHT_PARALLEL:
        ok = ok and (light.cam.R * X + light.cam.t)[2] > 0.0
    return ok
