"""Two cameras, what the match's host side and the rig's check ask for besides the match itself
(docs/reconstruction.md "Two cameras"): a projector point's sigma turned between its polar
(radial, tangential) and its u, v directions, the weighted moments of an integer code's window
(``pipeline.reconstruct.stereo.refine_integer_codes``), and each match's distance from its
epipolar line (the calibration check)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels.geometry import CameraModel, undistort
from ringscan.kernels.compact import count_values
from ringscan.kernels.launch import check_array, default_threads, launch_spans, scan_counts

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

EPIPOLAR_STEP_PX = wp.constant(0.5)
"""Half the central difference of :func:`epipolar_kernel`'s slope (camera-1 px): the line moves smoothly over
a pixel, and float32 distances keep ~1e-3 px (far below a step's change, ~0.5 px)."""

__all__ = ["RefineSettings", "uv_sigmas", "polar_sigmas", "window_sums", "refine_codes", "epipolar_distances",
           "epipolar_slopes"]


@wp.struct
class RefineSettings:
    """How an integer code is read from its window (``pipeline.reconstruct.stereo.refine_integer_codes``)."""

    radius: int
    """The window's half width (camera px)."""
    min_pixels: int
    """Fewest decoded pixels in the window for a plane."""
    max_chi2: wp.float64
    """Largest scatter about the plane, in variances the codes' sigmas predict, a degree of freedom."""
    tolerance: wp.float64
    """A coordinate this close to an integer is an integer code (projector px)."""


@wp.struct
class WindowMoments:
    """The weighted moments of a code's window (``window_sums_kernel``' eleven sums)."""

    S: wp.float64
    Sx: wp.float64
    Sy: wp.float64
    Sxx: wp.float64
    Sxy: wp.float64
    Syy: wp.float64
    wP: wp.float64
    wPx: wp.float64
    wPy: wp.float64
    wPP: wp.float64
    cnt: wp.float64


@wp.func
def window_moments(sample_of: wp.array(dtype=wp.int32), value: wp.array(dtype=wp.float64),
                   weight: wp.array(dtype=wp.float64), width: int, height: int, r: int, xs: int, ys: int):
    """The moments of the (2 r + 1)^2 pixels around (xs, ys), row by row (the order the NumPy statement
    adds them in): sum w, w dx, w dy, w dx^2, w dx dy, w dy^2, w p, w p dx, w p dy, w p^2 and the count
    of pixels with w > 0 (a pixel without a sample, or outside the image: w = 0)."""
    m = WindowMoments()
    m.S = wp.float64(0.0)
    m.Sx = wp.float64(0.0)
    m.Sy = wp.float64(0.0)
    m.Sxx = wp.float64(0.0)
    m.Sxy = wp.float64(0.0)
    m.Syy = wp.float64(0.0)
    m.wP = wp.float64(0.0)
    m.wPx = wp.float64(0.0)
    m.wPy = wp.float64(0.0)
    m.wPP = wp.float64(0.0)
    m.cnt = wp.float64(0.0)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            y = ys + dy
            x = xs + dx
            wk = wp.float64(0.0)
            pk = wp.float64(0.0)
            if y >= 0 and y < height and x >= 0 and x < width:
                j = sample_of[y * width + x]
                if j >= 0:
                    wk = weight[j]
                    pk = value[j]
            fx = wp.float64(dx)
            fy = wp.float64(dy)
            wpk = wk * pk
            m.S = m.S + wk
            m.Sx = m.Sx + wk * fx
            m.Sy = m.Sy + wk * fy
            m.Sxx = m.Sxx + wk * (fx * fx)
            m.Sxy = m.Sxy + wk * (fx * fy)
            m.Syy = m.Syy + wk * (fy * fy)
            m.wP = m.wP + wpk
            m.wPx = m.wPx + wpk * fx
            m.wPy = m.wPy + wpk * fy
            m.wPP = m.wPP + wpk * pk
            m.cnt = m.cnt + wp.where(wk > wp.float64(0.0), wp.float64(1.0), wp.float64(0.0))
    return m


@wp.func
def radial_direction(proj: wp.vec2d, center: wp.vec2d):
    """(cos, sin) of a projector point's direction from ``center`` (the radial unit vector)."""
    off = proj - center
    r = wp.max(wp.length(off), wp.float64(1.0e-12))
    return off[0] / r, off[1] / r


@wp.func
def polar_to_uv(proj: wp.vec2d, sigma_rho: wp.float64, sigma_tan: wp.float64, center: wp.vec2d):
    """Standard deviations along u_p and v_p of a projector point whose errors are radial and tangential
    about ``center``."""
    c, s = radial_direction(proj, center)
    a = sigma_rho * sigma_rho
    b = sigma_tan * sigma_tan
    return wp.vec2d(wp.sqrt(a * (c * c) + b * (s * s)), wp.sqrt(a * (s * s) + b * (c * c)))


@wp.func
def uv_to_polar(proj: wp.vec2d, sigma_uv: wp.vec2d, center: wp.vec2d):
    """The radial and tangential standard deviations of a projector point with independent u_p, v_p errors."""
    c, s = radial_direction(proj, center)
    c2 = c * c
    s2 = s * s
    a = sigma_uv[0] * sigma_uv[0]
    b = sigma_uv[1] * sigma_uv[1]
    return wp.sqrt(a * c2 + b * s2), wp.sqrt(a * s2 + b * c2)


@wp.func
def plane_at_code(m: WindowMoments, p0: wp.float64, settings: RefineSettings):
    """The plane fitted to a code's window (its moments ``m`` about the code's own value ``p0``), read at
    the code's pixel: (whether it holds: ``min_pixels`` codes, well-conditioned normal equations, a scatter
    within ``max_chi2`` a degree of freedom; the refined value; its sigma, scaled by the scatter where
    larger). The 3x3 solve by cofactors, as the NumPy statement ``refine_integer_codes``."""
    S = m.S
    Sx = m.Sx
    Sy = m.Sy
    Sxx = m.Sxx
    Sxy = m.Sxy
    Syy = m.Syy
    Sp = m.wP - p0 * S
    Sxp = m.wPx - p0 * Sx
    Syp = m.wPy - p0 * Sy
    Spp = m.wPP - wp.float64(2.0) * p0 * m.wP + p0 * p0 * S
    c00 = Sxx * Syy - Sxy * Sxy
    c01 = Sxy * Sy - Sx * Syy
    c02 = Sx * Sxy - Sxx * Sy
    c11 = S * Syy - Sy * Sy
    c12 = Sx * Sy - S * Sxy
    c22 = S * Sxx - Sx * Sx
    det = S * c00 + Sx * c01 + Sy * c02
    tiny = wp.float64(1.0e-30)
    good = m.cnt >= wp.float64(float(settings.min_pixels)) and det > wp.float64(1.0e-9) * wp.max(S, tiny) * wp.max(c00, tiny)
    if not good:
        return False, p0, wp.float64(0.0)
    inv_det = wp.float64(1.0) / det
    b0 = (c00 * Sp + c01 * Sxp + c02 * Syp) * inv_det
    b1 = (c01 * Sp + c11 * Sxp + c12 * Syp) * inv_det
    b2 = (c02 * Sp + c12 * Sxp + c22 * Syp) * inv_det
    chi2 = wp.max(Spp - (b0 * Sp + b1 * Sxp + b2 * Syp), wp.float64(0.0))
    dof = wp.max(m.cnt - wp.float64(3.0), wp.float64(1.0))
    if not (chi2 <= settings.max_chi2 * dof):
        return False, p0, wp.float64(0.0)
    return True, p0 + b0, wp.sqrt(c00 * inv_det * wp.max(wp.float64(1.0), chi2 / dof))


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def polar_to_uv_sigma_kernel(
    proj: wp.array(dtype=wp.vec2d),
    sigma_rho: wp.array(dtype=wp.float64),
    sigma_tan: wp.array(dtype=wp.float64),
    center: wp.vec2d,
    i0: int,
    out: wp.array(dtype=wp.vec2d),
):
    """Standard deviations along u_p and v_p of projector point i0 + tid whose errors are radial and
    tangential about ``center`` (:func:`polar_to_uv`). proj (n,) vec2d, sigma_rho, sigma_tan (n,) float64:
    read; out (n,) vec2d: written."""
    i = i0 + wp.tid()
    out[i] = polar_to_uv(proj[i], sigma_rho[i], sigma_tan[i], center)


@wp.kernel
def uv_to_polar_sigma_kernel(
    proj: wp.array(dtype=wp.vec2d),
    sigma_uv: wp.array(dtype=wp.vec2d),
    center: wp.vec2d,
    i0: int,
    sigma_rho: wp.array(dtype=wp.float64),
    sigma_tan: wp.array(dtype=wp.float64),
):
    """The radial and tangential standard deviations of projector point i0 + tid with independent u_p,
    v_p errors (:func:`uv_to_polar`). proj, sigma_uv (n,) vec2d: read; sigma_rho, sigma_tan (n,) float64:
    written."""
    i = i0 + wp.tid()
    sr, st = uv_to_polar(proj[i], sigma_uv[i], center)
    sigma_rho[i] = sr
    sigma_tan[i] = st


@wp.kernel
def window_sums_kernel(
    at: wp.array(dtype=wp.int32),
    sample_of: wp.array(dtype=wp.int32),
    value: wp.array(dtype=wp.float64),
    weight: wp.array(dtype=wp.float64),
    width: int,
    height: int,
    r: int,
    i0: int,
    sums: wp.array2d(dtype=wp.float64),
):
    """The weighted moments of the (2 r + 1)^2 pixels around pixel at[i0 + tid] (row by row, as the NumPy
    statement adds them): sum w, w dx, w dy, w dx^2, w dx dy, w dy^2, w p, w p dx, w p dy, w p^2, and the
    count of pixels with w > 0 (a pixel without a sample, or outside the image: w = 0).

    at (m,) int32 linear pixels; sample_of (H * W,) int32 each pixel's sample (-1: none); value, weight
    (n,) float64 each sample's coordinate p and weight w: read. sums (11, m) float64: written.

    Size: four arrays in, the image's size and the window's half width, the span's i0, one array out."""
    k = i0 + wp.tid()
    a = at[k]
    ys = a / width
    m = window_moments(sample_of, value, weight, width, height, r, a - ys * width, ys)
    sums[0, k] = m.S
    sums[1, k] = m.Sx
    sums[2, k] = m.Sy
    sums[3, k] = m.Sxx
    sums[4, k] = m.Sxy
    sums[5, k] = m.Syy
    sums[6, k] = m.wP
    sums[7, k] = m.wPx
    sums[8, k] = m.wPy
    sums[9, k] = m.wPP
    sums[10, k] = m.cnt


@wp.kernel
def refine_terms_kernel(
    proj: wp.array(dtype=wp.vec2),
    sigma_rho: wp.array(dtype=wp.float32),
    sigma_tan: wp.array(dtype=wp.float32),
    pixel: wp.array(dtype=wp.int32),
    center: wp.vec2d,
    tolerance: wp.float64,
    i0: int,
    value_u: wp.array(dtype=wp.float64),
    value_v: wp.array(dtype=wp.float64),
    weight_u: wp.array(dtype=wp.float64),
    weight_v: wp.array(dtype=wp.float64),
    integer: wp.array(dtype=wp.int32),
    any_integer: wp.array(dtype=wp.int32),
    sample_of: wp.array(dtype=wp.int32),
):
    """Sample i0 + tid's terms of the refinement, in float64: each axis' coordinate and weight 1 / max(sigma,
    1e-3)^2 (its u_p, v_p sigmas from its polar ones, :func:`polar_to_uv`), which axes hold an integer code
    (bit 0: u_p, bit 1: v_p; any_integer 1 where either does: the count to scan), and its pixel's entry of the
    pixel -> sample map.

    proj (n,) vec2, sigma_rho, sigma_tan (n,) float32, pixel (n,) int32: read. value_u, value_v, weight_u,
    weight_v (n,) float64, integer, any_integer (n,) int32: written; sample_of (width * height,) int32: written
    at pixel[i].

    Size: the samples' four arrays, the pattern centre and the integer test's tolerance, the span's i0; the
    six per-sample outputs and the pixel map."""
    i = i0 + wp.tid()
    p = wp.vec2d(wp.float64(proj[i][0]), wp.float64(proj[i][1]))
    suv = polar_to_uv(p, wp.float64(sigma_rho[i]), wp.float64(sigma_tan[i]), center)
    su = wp.max(suv[0], wp.float64(1.0e-3))
    sv = wp.max(suv[1], wp.float64(1.0e-3))
    value_u[i] = p[0]
    value_v[i] = p[1]
    weight_u[i] = wp.float64(1.0) / (su * su)
    weight_v[i] = wp.float64(1.0) / (sv * sv)
    bits = int(0)
    if wp.abs(p[0] - wp.round(p[0])) < tolerance:
        bits = bits | 1
    if wp.abs(p[1] - wp.round(p[1])) < tolerance:
        bits = bits | 2
    integer[i] = bits
    any_integer[i] = wp.where(bits != 0, 1, 0)
    sample_of[pixel[i]] = i


@wp.kernel
def refine_codes_kernel(
    sel: wp.array(dtype=wp.int32),
    pixel: wp.array(dtype=wp.int32),
    sample_of: wp.array(dtype=wp.int32),
    value_u: wp.array(dtype=wp.float64),
    value_v: wp.array(dtype=wp.float64),
    weight_u: wp.array(dtype=wp.float64),
    weight_v: wp.array(dtype=wp.float64),
    integer: wp.array(dtype=wp.int32),
    sigma_rho: wp.array(dtype=wp.float32),
    sigma_tan: wp.array(dtype=wp.float32),
    width: int,
    height: int,
    center: wp.vec2d,
    settings: RefineSettings,
    i0: int,
    proj_out: wp.array(dtype=wp.vec2d),
    sigma_out: wp.array(dtype=wp.vec2d),
    refined: wp.array(dtype=wp.int32),
):
    """Sample sel[i0 + tid] (one with an integer code), each integer axis read from its window: the plane
    fitted (weights 1 / sigma^2) to the codes of the (2 r + 1)^2 pixels around its pixel, read at the pixel
    (:func:`plane_at_code`; the window's moments by :func:`window_moments`, from the codes and sigmas as
    decoded: an axis never reads the other's refinement). proj_out, sigma_out get the sample's point and u_p,
    v_p sigmas with its refined axes in place (slot i0 + tid); refined its bits (1: u_p, 2: v_p).

    sel (m,) int32 the samples with an integer code; pixel (n,) int32; sample_of (width * height,) int32 each
    pixel's sample (-1: none); value_u, value_v, weight_u, weight_v (n,) float64, integer (n,) int32,
    sigma_rho, sigma_tan (n,) float32 (:func:`refine_terms_kernel`): read. proj_out, sigma_out (m,) vec2d:
    written; refined (n,) int32: written at sel[i0 + tid].

    Size: the selection, the samples' pixels and pixel -> sample map, both axes' values and weights, the
    integer bits and polar sigmas, the image's size, the centre and settings, the span's i0, three arrays out."""
    k = i0 + wp.tid()
    i = sel[k]
    a = pixel[i]
    ys = a / width
    xs = a - ys * width
    p = wp.vec2d(value_u[i], value_v[i])
    sg = polar_to_uv(p, wp.float64(sigma_rho[i]), wp.float64(sigma_tan[i]), center)
    bits = integer[i]
    done = int(0)
    for axis in range(2):
        if (bits & (1 << axis)) != 0:
            if axis == 0:
                m = window_moments(sample_of, value_u, weight_u, width, height, settings.radius, xs, ys)
            else:
                m = window_moments(sample_of, value_v, weight_v, width, height, settings.radius, xs, ys)
            ok, v, s = plane_at_code(m, p[axis], settings)
            if ok:
                p[axis] = v
                sg[axis] = s
                done = done | (1 << axis)
    proj_out[k] = p
    sigma_out[k] = sg
    refined[i] = done


@wp.kernel
def join_refined_kernel(
    proj: wp.array(dtype=wp.vec2),
    sigma_rho: wp.array(dtype=wp.float32),
    sigma_tan: wp.array(dtype=wp.float32),
    slot: wp.array(dtype=wp.int32),
    has_slot: wp.array(dtype=wp.int32),
    proj_ref: wp.array(dtype=wp.vec2d),
    sigma_ref: wp.array(dtype=wp.vec2d),
    center: wp.vec2d,
    i0: int,
    proj64: wp.array(dtype=wp.vec2d),
    sigma_rho64: wp.array(dtype=wp.float64),
    sigma_tan64: wp.array(dtype=wp.float64),
    proj_out: wp.array(dtype=wp.vec2),
    sigma_rho_out: wp.array(dtype=wp.float32),
    sigma_tan_out: wp.array(dtype=wp.float32),
    sigma_out: wp.array(dtype=wp.float32),
):
    """Sample i0 + tid's point and polar sigmas after the refinement, in float64 and in float32 for the match
    (and the isotropic sqrt((sr^2 + st^2) / 2)): a sample with an integer code (has_slot) takes its slot of
    proj_ref, sigma_ref; the others their point as decoded and their sigmas through u_p, v_p and back, as
    every sample's are.

    proj (n,) vec2, sigma_rho, sigma_tan (n,) float32, slot, has_slot (n,) int32, proj_ref, sigma_ref (m,)
    vec2d: read. proj64 (n,) vec2d, sigma_rho64, sigma_tan64 (n,) float64, proj_out (n,) vec2, sigma_rho_out,
    sigma_tan_out, sigma_out (n,) float32: written.

    Size: the samples' three arrays, the refined slots (where and which), the centre, the span's i0; the
    float64 and the float32 results (seven arrays)."""
    i = i0 + wp.tid()
    p = wp.vec2d(wp.float64(proj[i][0]), wp.float64(proj[i][1]))
    suv = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    if has_slot[i] != 0:
        p = proj_ref[slot[i]]
        suv = sigma_ref[slot[i]]
    else:
        suv = polar_to_uv(p, wp.float64(sigma_rho[i]), wp.float64(sigma_tan[i]), center)
    sr, st = uv_to_polar(p, suv, center)
    proj64[i] = p
    sigma_rho64[i] = sr
    sigma_tan64[i] = st
    proj_out[i] = wp.vec2(wp.float32(p[0]), wp.float32(p[1]))
    sigma_rho_out[i] = wp.float32(sr)
    sigma_tan_out[i] = wp.float32(st)
    sigma_out[i] = wp.float32(wp.sqrt(wp.float64(0.5) * (sr * sr + st * st)))


@wp.kernel
def write_slots_kernel(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), i0: int,
                       sel: wp.array(dtype=wp.int32)):
    """sel[offsets[i]] = i where flags[i] (count, scan, write). flags, offsets (n,) int32: read; sel (m,)
    int32: written."""
    i = i0 + wp.tid()
    if flags[i] != 0:
        sel[offsets[i]] = i


@wp.func
def signed_epipolar(cam1: CameraModel, cam2: CameraModel, E: wp.mat33, scale: float, p1: wp.vec2, n2: wp.vec3):
    """Signed distance (camera-2 px) of camera 2's undistorted normalised point n2 (n2[2] > 0: it has one) from
    the epipolar line of camera 1's distorted pixel p1; NaN where p1 has no undistorted point."""
    y1 = (p1[1] - cam1.cy) / cam1.fy
    n1 = undistort(cam1, (p1[0] - cam1.cx - cam1.skew * y1) / cam1.fx, y1)
    if not (n1[2] > 0.0):
        return wp.nan
    line = E * wp.vec3(n1[0], n1[1], 1.0)
    den = wp.sqrt(line[0] * line[0] + line[1] * line[1])
    return wp.where(den > 0.0, (line[0] * n2[0] + line[1] * n2[1] + line[2]) / den * scale, wp.nan)


@wp.func
def undistorted_camera2(cam2: CameraModel, p2: wp.vec2):
    """Camera 2's distorted pixel p2 as an undistorted normalised point (its [2] <= 0: none)."""
    y2 = (p2[1] - cam2.cy) / cam2.fy
    return undistort(cam2, (p2[0] - cam2.cx - cam2.skew * y2) / cam2.fx, y2)


@wp.kernel
def epipolar_kernel(
    uv1: wp.array(dtype=wp.vec2),
    uv2: wp.array(dtype=wp.vec2),
    cam1: CameraModel,
    cam2: CameraModel,
    E: wp.mat33,
    scale: float,
    keep_sign: int,
    i0: int,
    dist: wp.array(dtype=wp.float32),
    slope2: wp.array(dtype=wp.float32),
):
    """Distance (camera-2 px) of uv2[i] from the epipolar line of uv1[i], i = i0 + tid: its size, or with
    ``keep_sign`` its sign too; and where ``slope2`` has n places, the squared norm of its derivative by uv1[i]
    ((camera-2 px per camera-1 px)^2: how far camera 1's error moves the line; central differences over
    ``EPIPOLAR_STEP_PX``).

    uv1, uv2 (n,) vec2 distorted pixels: read. E: the essential matrix (unit
    baseline) taking camera 1's undistorted normalised point to its line in
    camera 2's normalised plane; scale: camera 2's sqrt(fx fy). dist (n,), slope2 (n,) or (0,)
    float32: written, NaN where a pixel has no undistorted point
    (:func:`~ringscan.kernels.geometry.undistort`)."""
    i = i0 + wp.tid()
    n2 = undistorted_camera2(cam2, uv2[i])
    p1 = uv1[i]
    d = wp.nan
    g2 = wp.nan
    if n2[2] > 0.0:
        d = signed_epipolar(cam1, cam2, E, scale, p1, n2)
        if slope2.shape[0] > 0:
            h = EPIPOLAR_STEP_PX
            gx = (signed_epipolar(cam1, cam2, E, scale, p1 + wp.vec2(h, 0.0), n2)
                  - signed_epipolar(cam1, cam2, E, scale, p1 - wp.vec2(h, 0.0), n2)) / (2.0 * h)
            gy = (signed_epipolar(cam1, cam2, E, scale, p1 + wp.vec2(0.0, h), n2)
                  - signed_epipolar(cam1, cam2, E, scale, p1 - wp.vec2(0.0, h), n2)) / (2.0 * h)
            g2 = gx * gx + gy * gy
    dist[i] = wp.where(keep_sign != 0, d, wp.abs(d))
    if slope2.shape[0] > 0:
        slope2[i] = g2


# ----------------------------------------------------------------------------- host


def uv_sigmas(proj: wp.array, sigma_rho: wp.array, sigma_tan: wp.array, *, center: tuple[float, float],
              threads: int | None = None) -> wp.array:
    """(n,) vec2d standard deviations along u_p and v_p of projector points ``proj`` ((n,) vec2d) whose
    errors ``sigma_rho``, ``sigma_tan`` ((n,) float64) are radial and tangential about ``center``
    (:func:`polar_to_uv_sigma_kernel`), on proj's device."""
    fn = "uv_sigmas"
    n = check_array("proj", proj, None, wp.vec2d, fn)
    check_array("sigma_rho", sigma_rho, n, wp.float64, fn)
    check_array("sigma_tan", sigma_tan, n, wp.float64, fn)
    dev = proj.device
    out = wp.empty(n, dtype=wp.vec2d, device=dev)
    args = [proj, sigma_rho, sigma_tan, wp.vec2d(*center)]
    launch_spans(polar_to_uv_sigma_kernel, n, lambda i0: args + [i0], [out], dev,
                 default_threads() if threads is None else threads)
    return out


def polar_sigmas(proj: wp.array, sigma_uv: wp.array, *, center: tuple[float, float],
                 threads: int | None = None) -> tuple[wp.array, wp.array]:
    """((n,) float64 radial, (n,) float64 tangential) standard deviations of projector points ``proj``
    ((n,) vec2d) with independent u_p, v_p errors ``sigma_uv`` ((n,) vec2d) (:func:`uv_to_polar_sigma_kernel`)."""
    fn = "polar_sigmas"
    n = check_array("proj", proj, None, wp.vec2d, fn)
    check_array("sigma_uv", sigma_uv, n, wp.vec2d, fn)
    dev = proj.device
    sr, st = wp.empty(n, dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.float64, device=dev)
    args = [proj, sigma_uv, wp.vec2d(*center)]
    launch_spans(uv_to_polar_sigma_kernel, n, lambda i0: args + [i0], [sr, st], dev,
                 default_threads() if threads is None else threads)
    return sr, st


def window_sums(at: wp.array, sample_of: wp.array, value: wp.array, weight: wp.array, *, width: int, height: int,
                radius: int, threads: int | None = None) -> wp.array:
    """(11, m) float64 weighted moments of each window around the pixels ``at`` ((m,) int32 linear
    indices): :func:`window_sums_kernel`, whose docstring lists them. ``sample_of`` ((width * height,)
    int32) names each pixel's sample (-1: none), ``value`` and ``weight`` ((n,) float64) the samples'."""
    fn = "window_sums"
    m = check_array("at", at, None, wp.int32, fn)
    check_array("sample_of", sample_of, int(width) * int(height), wp.int32, fn)
    n = check_array("value", value, None, wp.float64, fn)
    check_array("weight", weight, n, wp.float64, fn)
    dev = at.device
    out = wp.empty((11, m), dtype=wp.float64, device=dev)
    args = [at, sample_of, value, weight, int(width), int(height), int(radius)]
    launch_spans(window_sums_kernel, m, lambda i0: args + [i0], [out], dev,
                 default_threads() if threads is None else threads)
    return out


def refine_codes(proj: wp.array, sigma_rho: wp.array, sigma_tan: wp.array, pixel: wp.array, *,
                 center: tuple[float, float], width: int, height: int, settings: RefineSettings,
                 threads: int | None = None) -> dict | None:
    """Integer projector codes of a dense per-pixel map read to a fraction of a projector pixel from
    their camera neighbourhood, on the samples' device (:func:`refine_codes_kernel`; the NumPy
    statement is ``pipeline.reconstruct.stereo.refine_integer_codes``, which sums a window the same way
    where it has few codes to refine and by the image's filters where it has many).

    Args:
        proj: (n,) vec2 projector points (one sample a camera pixel).
        sigma_rho, sigma_tan: (n,) float32 their polar standard deviations (projector px).
        pixel: (n,) int32 each sample's camera pixel (y * width + x).
        center: the pattern centre (projector px).
        width, height: the camera's size.
        settings: the window and its tests.
        threads: CPU threads; default all cores.

    Returns:
        None where no code was refined, else {"proj", "sigma_rho", "sigma_tan", "sigma"} in float32 for the
        match (sigma: the isotropic sqrt((sr^2 + st^2) / 2)), the same in float64 ("proj64", "sigma_rho64",
        "sigma_tan64": every sample's polar sigmas through u, v and back), and "refined" (n,) int32 bits
        (1: u_p, 2: v_p) and its count of samples, all but the count on the device.

    Size: four per-sample arrays, the pattern centre and the camera's size the windows need, the
    window's settings, the thread count.
    """
    fn = "refine_codes"
    n = check_array("proj", proj, None, wp.vec2, fn)
    for name, a in (("sigma_rho", sigma_rho), ("sigma_tan", sigma_tan)):
        check_array(name, a, n, wp.float32, fn)
    check_array("pixel", pixel, n, wp.int32, fn)
    if n == 0:
        return None
    dev = proj.device
    threads = default_threads() if threads is None else threads
    c = wp.vec2d(float(center[0]), float(center[1]))
    # one pass for the terms of every sample, the windows only around the integer codes, one pass for the
    # results: no float64 copy of every sample but the terms the windows read (~40 B a sample fewer)
    f64 = lambda: wp.empty(n, dtype=wp.float64, device=dev)  # noqa: E731
    value_u, value_v, weight_u, weight_v = f64(), f64(), f64(), f64()
    integer = wp.empty(n, dtype=wp.int32, device=dev)
    flags = wp.empty(n, dtype=wp.int32, device=dev)
    sample_of = wp.full(int(width) * int(height), -1, dtype=wp.int32, device=dev)
    launch_spans(refine_terms_kernel, n, lambda i0: [proj, sigma_rho, sigma_tan, pixel, c,
                                                     wp.float64(settings.tolerance), i0],
                 [value_u, value_v, weight_u, weight_v, integer, flags, sample_of], dev, threads)
    slot, m = scan_counts(flags)
    if m == 0:
        return None
    sel = wp.empty(m, dtype=wp.int32, device=dev)
    launch_spans(write_slots_kernel, n, lambda i0: [flags, slot, i0], [sel], dev, threads)
    proj_ref = wp.empty(m, dtype=wp.vec2d, device=dev)
    sigma_ref = wp.empty(m, dtype=wp.vec2d, device=dev)
    refined = wp.zeros(n, dtype=wp.int32, device=dev)
    launch_spans(refine_codes_kernel, m,
                 lambda i0: [sel, pixel, sample_of, value_u, value_v, weight_u, weight_v, integer, sigma_rho,
                             sigma_tan, int(width), int(height), c, settings, i0],
                 [proj_ref, sigma_ref, refined], dev, threads)
    counts = count_values(refined, 4, threads=threads)
    done = int(counts[1:].sum())
    if done == 0:
        return None
    out = {"proj64": wp.empty(n, dtype=wp.vec2d, device=dev), "sigma_rho64": f64(), "sigma_tan64": f64(),
           "proj": wp.empty(n, dtype=wp.vec2, device=dev), "sigma_rho": wp.empty(n, dtype=wp.float32, device=dev),
           "sigma_tan": wp.empty(n, dtype=wp.float32, device=dev), "sigma": wp.empty(n, dtype=wp.float32, device=dev)}
    launch_spans(join_refined_kernel, n,
                 lambda i0: [proj, sigma_rho, sigma_tan, slot, flags, proj_ref, sigma_ref, c, i0],
                 [out["proj64"], out["sigma_rho64"], out["sigma_tan64"], out["proj"], out["sigma_rho"],
                  out["sigma_tan"], out["sigma"]], dev, threads)
    out.update(refined=refined, count=done)
    return out


def epipolar_distances(uv1: wp.array, uv2: wp.array, *, camera1: CameraModel, camera2: CameraModel,
                       E: np.ndarray, scale: float, threads: int | None = None) -> wp.array:
    """(n,) float32 distance (camera-2 px) of each uv2 from the epipolar line of its uv1
    (:func:`epipolar_kernel`; NaN where a pixel has no undistorted point).

    Args:
        uv1, uv2: (n,) vec2 distorted pixels of camera 1 and camera 2.
        camera1, camera2: their models.
        E: (3, 3) essential matrix [t]x R with a unit t (X2 = R X1 + t).
        scale: camera 2's sqrt(fx fy) (normalised -> px).
        threads: CPU threads; default all cores.
    """
    fn = "epipolar_distances"
    n = check_array("uv1", uv1, None, wp.vec2, fn)
    check_array("uv2", uv2, n, wp.vec2, fn)
    dev = uv1.device
    out = wp.empty(n, dtype=wp.float32, device=dev)
    _epipolar_launch(uv1, uv2, camera1, camera2, E, scale, 0, [out, wp.empty(0, dtype=wp.float32, device=dev)],
                     threads)
    return out


def _epipolar_launch(uv1, uv2, camera1, camera2, E, scale, keep_sign: int, outputs: list, threads) -> None:
    n = uv1.shape[0]
    if n:
        Em = wp.mat33(*np.asarray(E, np.float64).astype(np.float32).ravel().tolist())
        args = [uv1, uv2, camera1, camera2, Em, float(scale), int(keep_sign)]
        launch_spans(epipolar_kernel, n, lambda i0: args + [i0], outputs, uv1.device,
                     default_threads() if threads is None else threads)


def epipolar_slopes(uv1: wp.array, uv2: wp.array, *, camera1: CameraModel, camera2: CameraModel, E: np.ndarray,
                    scale: float, threads: int | None = None) -> tuple[wp.array, wp.array]:
    """Each match's signed distance from its epipolar line and how fast camera 1 moves it
    (:func:`epipolar_kernel`): ((n,) float32 camera-2 px, (n,) float32 its squared derivative by uv1,
    (camera-2 px per camera-1 px)^2), NaN where a pixel has no undistorted point; arguments as
    :func:`epipolar_distances`'."""
    fn = "epipolar_slopes"
    n = check_array("uv1", uv1, None, wp.vec2, fn)
    check_array("uv2", uv2, n, wp.vec2, fn)
    dev = uv1.device
    dist = wp.empty(n, dtype=wp.float32, device=dev)
    slope2 = wp.empty(n, dtype=wp.float32, device=dev)
    _epipolar_launch(uv1, uv2, camera1, camera2, E, scale, 1, [dist, slope2], threads)
    return dist, slope2
