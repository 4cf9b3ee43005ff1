"""Two cameras, what the match's host side and the rig's check ask for besides the match itself
(docs/reconstruction.md "Two cameras"): a projector point's sigma turned between its polar
(radial, tangential) and its u, v directions, the weighted moments of an integer code's window
(``pipeline.reconstruct.stereo.refine_integer_codes``), and each match's distance from its
epipolar line (the calibration check)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels.geometry import CameraModel, undistort
from ringscan.kernels.launch import check_array, default_threads, launch_spans

__all__ = ["uv_sigmas", "polar_sigmas", "window_sums", "epipolar_distances"]


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
    tangential about ``center``. proj (n,) vec2d, sigma_rho, sigma_tan (n,) float64: read; out (n,) vec2d:
    written."""
    i = i0 + wp.tid()
    off = proj[i] - center
    r = wp.max(wp.length(off), wp.float64(1.0e-12))
    c = off[0] / r
    s = off[1] / r
    a = sigma_rho[i] * sigma_rho[i]
    b = sigma_tan[i] * sigma_tan[i]
    out[i] = wp.vec2d(wp.sqrt(a * (c * c) + b * (s * s)), wp.sqrt(a * (s * s) + b * (c * c)))


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
    v_p errors. proj, sigma_uv (n,) vec2d: read; sigma_rho, sigma_tan (n,) float64: written."""
    i = i0 + wp.tid()
    off = proj[i] - center
    r = wp.max(wp.length(off), wp.float64(1.0e-12))
    c = off[0] / r
    s = off[1] / r
    c2 = c * c
    s2 = s * s
    a = sigma_uv[i][0] * sigma_uv[i][0]
    b = sigma_uv[i][1] * sigma_uv[i][1]
    sigma_rho[i] = wp.sqrt(a * c2 + b * s2)
    sigma_tan[i] = wp.sqrt(a * s2 + b * c2)


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
    xs = a - ys * width
    s0 = wp.float64(0.0)
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    s3 = wp.float64(0.0)
    s4 = wp.float64(0.0)
    s5 = wp.float64(0.0)
    s6 = wp.float64(0.0)
    s7 = wp.float64(0.0)
    s8 = wp.float64(0.0)
    s9 = wp.float64(0.0)
    s10 = wp.float64(0.0)
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
            s0 += wk
            s1 += wk * fx
            s2 += wk * fy
            s3 += wk * (fx * fx)
            s4 += wk * (fx * fy)
            s5 += wk * (fy * fy)
            s6 += wpk
            s7 += wpk * fx
            s8 += wpk * fy
            s9 += wpk * pk
            s10 += wp.where(wk > wp.float64(0.0), wp.float64(1.0), wp.float64(0.0))
    sums[0, k] = s0
    sums[1, k] = s1
    sums[2, k] = s2
    sums[3, k] = s3
    sums[4, k] = s4
    sums[5, k] = s5
    sums[6, k] = s6
    sums[7, k] = s7
    sums[8, k] = s8
    sums[9, k] = s9
    sums[10, k] = s10


@wp.kernel
def epipolar_kernel(
    uv1: wp.array(dtype=wp.vec2),
    uv2: wp.array(dtype=wp.vec2),
    cam1: CameraModel,
    cam2: CameraModel,
    E: wp.mat33,
    scale: float,
    i0: int,
    dist: wp.array(dtype=wp.float32),
):
    """Distance (camera-2 px) of uv2[i] from the epipolar line of uv1[i], i = i0 + tid.

    uv1, uv2 (n,) vec2 distorted pixels: read. E: the essential matrix (unit
    baseline) taking camera 1's undistorted normalised point to its line in
    camera 2's normalised plane; scale: camera 2's sqrt(fx fy). dist (n,)
    float32: written, NaN where a pixel has no undistorted point
    (:func:`~ringscan.kernels.geometry.undistort`)."""
    i = i0 + wp.tid()
    p1 = uv1[i]
    p2 = uv2[i]
    y1 = (p1[1] - cam1.cy) / cam1.fy
    n1 = undistort(cam1, (p1[0] - cam1.cx - cam1.skew * y1) / cam1.fx, y1)
    y2 = (p2[1] - cam2.cy) / cam2.fy
    n2 = undistort(cam2, (p2[0] - cam2.cx - cam2.skew * y2) / cam2.fx, y2)
    if not (n1[2] > 0.0 and n2[2] > 0.0):
        dist[i] = wp.nan
        return
    line = E * wp.vec3(n1[0], n1[1], 1.0)
    den = wp.sqrt(line[0] * line[0] + line[1] * line[1])
    dist[i] = wp.where(den > 0.0, wp.abs(line[0] * n2[0] + line[1] * n2[1] + line[2]) / den * scale, wp.nan)


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
    if n:
        Em = wp.mat33(*np.asarray(E, np.float64).astype(np.float32).ravel().tolist())
        args = [uv1, uv2, camera1, camera2, Em, float(scale)]
        launch_spans(epipolar_kernel, n, lambda i0: args + [i0], [out], dev,
                     default_threads() if threads is None else threads)
    return out
