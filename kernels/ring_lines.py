"""Single-shot ``rings`` codec, per pixel: line (ridge) detection with sub-pixel
centres (docs/design.md §10).

Line detection (after Steger's curvilinear-structure detector): the frame is
smoothed with a Gaussian of ``sigma`` camera pixels (separable, two row-run
passes). At every pixel the Hessian H of the smoothed image S gives the direction
n across the line: the eigenvector of its most negative eigenvalue lambda. Along
n the profile S(p + t n) ~ S + t (g . n) + t^2 lambda / 2 peaks at
t = -(g . n) / lambda; the pixel holds a line centre when that peak lies inside
the pixel (|t n_x| <= 0.5 and |t n_y| <= 0.5), the profile bends down strongly
enough (-lambda >= ``min_curvature``), the line is elongated (the other
eigenvalue is small beside lambda), the image is nearly flat along the line
(which rejects the flanks of tightly curved lines) and the peak stands
``min_contrast`` grey levels above the local background on both sides (S read at
the centre +- ``background_px`` along n). The sample is that sub-pixel centre: for a
symmetric line profile it is the line's centre whatever the blur.

Intensities are in 8-bit grey levels (16-bit frames are divided by 257), so the
thresholds mean the same for both depths.

Output order is deterministic (raster order of the pixels): counts per pixel,
``wp.utils.array_scan``, then write.

Ring roots and gap links are in :mod:`ringscan.kernels.ring_links`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from ringscan.kernels.launch import default_threads, launch_rows, row_run, scan_counts
from ringscan.kernels.settings import CONFIDENCE_CONTRAST, LineSettings

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

BORDER = wp.constant(2)
SHADE_PX = wp.constant(2.0)
"""Distance (camera px) along the line at which the light's gradient is read (``RingLines.shading``)."""
RESULT = wp.types.vector(length=10, dtype=wp.float32)
TAYLOR = wp.types.vector(length=6, dtype=wp.float32)
"""A pixel's value, gradient and Hessian (:func:`pixel_taylor`)."""
NOISE_LEVELS = 1.0
"""Camera noise (8-bit grey levels) a line centre's predicted sigma assumes (``centre_sigmas``): the
decode's model of the other codecs (``AngleSettings.noise``); the view's neighbour checks fit the
factor its frames show (docs/reconstruction.md, "Honest sigma")."""

__all__ = ["RingLines", "detect_ring_lines", "smooth_frame", "gaussian_weights", "centre_sigmas"]


@dataclass
class RingLines:
    """Sub-pixel line centres (Warp arrays of length n on the frames' device)."""

    uv: wp.array
    """vec2 (u, v) camera pixel coordinates of the line's centre."""
    normal: wp.array
    """vec2 unit direction across the line (its sign is arbitrary)."""
    pixel: wp.array
    """int32 linear index y * W + x of the pixel that holds the centre."""
    contrast: wp.array
    """float32 peak height above the local background (8-bit grey levels)."""
    curvature: wp.array
    """float32 -lambda: how sharply the profile bends at the centre."""
    confidence: wp.array
    """float32 in (0, 1]: contrast / ``CONFIDENCE_CONTRAST``, at most 1."""
    shading: wp.array
    """float32 camera px: how far the light's gradient may move the centre across the line (its log's
    slope along the line, a proxy for the one across it, times the profile's variance; and the
    background's slope across the line over the curvature), in quadrature."""
    smoothed: wp.array | None = None
    """(H, W) float32 the smoothed frame the centres were found in (8-bit levels)."""

    def __len__(self) -> int:
        return self.uv.shape[0]

    def numpy(self) -> dict[str, np.ndarray]:
        return {"uv": self.uv.numpy(), "normal": self.normal.numpy(), "pixel": self.pixel.numpy(),
                "contrast": self.contrast.numpy(), "curvature": self.curvature.numpy(),
                "confidence": self.confidence.numpy(), "shading": self.shading.numpy()}


# ----------------------------------------------------------------------------- helpers


@wp.func
def bilinear(img: wp.array2d(dtype=wp.float32), u: float, v: float):
    """Bilinear read of img at (u, v) (x = u, y = v), clamped to the image."""
    h = img.shape[0]
    w = img.shape[1]
    uc = wp.clamp(u, 0.0, float(w - 1))
    vc = wp.clamp(v, 0.0, float(h - 1))
    x0 = wp.min(int(wp.floor(uc)), w - 2)
    y0 = wp.min(int(wp.floor(vc)), h - 2)
    x0 = wp.max(x0, 0)
    y0 = wp.max(y0, 0)
    fx = uc - float(x0)
    fy = vc - float(y0)
    a = img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx
    b = img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx
    return a * (1.0 - fy) + b * fy


@wp.func
def pixel_taylor(img: wp.array2d(dtype=wp.float32), y: int, x: int):
    """img's value, gradient and Hessian at pixel (y, x) by central differences: TAYLOR(c, gx, gy,
    hxx, hyy, hxy)."""
    c = img[y, x]
    return TAYLOR(c, 0.5 * (img[y, x + 1] - img[y, x - 1]), 0.5 * (img[y + 1, x] - img[y - 1, x]),
                  img[y, x + 1] - 2.0 * c + img[y, x - 1], img[y + 1, x] - 2.0 * c + img[y - 1, x],
                  0.25 * (img[y + 1, x + 1] - img[y + 1, x - 1] - img[y - 1, x + 1] + img[y - 1, x - 1]))


@wp.func
def quadratic_at(img: wp.array2d(dtype=wp.float32), u: float, v: float):
    """img at (u, v) from its second-order Taylor expansion about the nearest pixel (central
    differences), clamped to the image. On a line's crest a bilinear read errs by up to an
    eighth of the profile's curvature (~3 % of its height for a 2 px profile), varying with the
    crest's sub-pixel place: two reads along a line then differ by that much though the light
    does not; this one errs by the fourth derivative's share (well under 0.1 %)."""
    h = img.shape[0]
    w = img.shape[1]
    x = wp.clamp(int(wp.round(u)), 1, w - 2)
    y = wp.clamp(int(wp.round(v)), 1, h - 2)
    dx = wp.clamp(u, 0.0, float(w - 1)) - float(x)
    dy = wp.clamp(v, 0.0, float(h - 1)) - float(y)
    q = pixel_taylor(img, y, x)
    return q[0] + q[1] * dx + q[2] * dy + 0.5 * (q[3] * dx * dx + 2.0 * q[5] * dx * dy + q[4] * dy * dy)


@wp.func
def ridge_at(
    S: wp.array2d(dtype=wp.float32),
    y: int,
    x: int,
    min_contrast: float,
    min_curvature: float,
    max_eigen_ratio: float,
    max_tangent_slope: float,
    background_px: float,
):
    """Test pixel (y, x) of the smoothed image for a line centre.

    Returns RESULT(found, u, v, n_x, n_y, contrast, curvature, the log's slope along the line (per px),
    the profile's variance (px^2: its height over its curvature), the background's tilt (px)).

    Size: one pixel's whole test, each step feeding the next (the Hessian, its eigenvector, the
    flank test, the sub-pixel centre, the contrast, the shading read around it), in one function
    that both passes (count, write) call.
    """
    none = RESULT(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    h = S.shape[0]
    w = S.shape[1]
    if x < BORDER or y < BORDER or x >= w - BORDER or y >= h - BORDER:
        return none
    q = pixel_taylor(S, y, x)
    c = q[0]
    gx = q[1]
    gy = q[2]
    hxx = q[3]
    hyy = q[4]
    hxy = q[5]
    half = 0.5 * (hxx + hyy)
    disc = wp.sqrt(0.25 * (hxx - hyy) * (hxx - hyy) + hxy * hxy)
    lam = half - disc  # most negative eigenvalue
    other = half + disc
    if -lam < min_curvature or wp.abs(other) > max_eigen_ratio * (-lam):
        return none
    # eigenvector of lam: the better conditioned of the two row forms
    ax = lam - hyy
    ay = hxy
    bx = hxy
    by = lam - hxx
    la = ax * ax + ay * ay
    lb = bx * bx + by * by
    nx = float(0.0)
    ny = float(0.0)
    if la >= lb and la > 1.0e-20:
        s = 1.0 / wp.sqrt(la)
        nx = ax * s
        ny = ay * s
    elif lb > 1.0e-20:
        s = 1.0 / wp.sqrt(lb)
        nx = bx * s
        ny = by * s
    elif hxx <= hyy:
        nx = 1.0
    else:
        ny = 1.0
    # Along the line the image must be nearly flat: on the flank of a tightly
    # curved line the profile along the line's tangent also bends down, but the
    # image still climbs steeply toward the line there.
    if wp.abs(-gx * ny + gy * nx) > max_tangent_slope * (-lam):
        return none
    t = -(gx * nx + gy * ny) / lam
    px = t * nx
    py = t * ny
    if wp.abs(px) > 0.5 or wp.abs(py) > 0.5:
        return none
    u = float(x) + px
    v = float(y) + py
    peak = c + t * (gx * nx + gy * ny) + 0.5 * t * t * lam
    b1 = bilinear(S, u + background_px * nx, v + background_px * ny)
    b2 = bilinear(S, u - background_px * nx, v - background_px * ny)
    contrast = peak - wp.max(b1, b2)
    if contrast < min_contrast:
        return none
    # A gradient of the light across the line moves a symmetric profile's peak by the gradient of
    # its log times the profile's variance and leaves its shape as is: nothing at the centre shows
    # it. Along the line the same shading shows (on average as steep: a proxy), read 2 px to
    # either side, over the height above the background.
    bg = 0.5 * (b1 + b2)
    fa = quadratic_at(S, u - SHADE_PX * ny, v + SHADE_PX * nx) - bg
    fb = quadratic_at(S, u + SHADE_PX * ny, v - SHADE_PX * nx) - bg
    slope = float(0.0)
    if fa > 0.0 and fb > 0.0:
        slope = wp.abs(wp.log(fa / fb)) / (2.0 * SHADE_PX)
    # a background that differs across the line (light bounced in from one side, a shadow's edge)
    # tilts the profile: its slope over the curvature is how far it moves the peak
    # (read as the crest is: a bilinear read on the profile's flank errs by as much as the tilt it would show)
    q1 = quadratic_at(S, u + background_px * nx, v + background_px * ny)
    q2 = quadratic_at(S, u - background_px * nx, v - background_px * ny)
    tilt = wp.abs(q1 - q2) / (2.0 * background_px) / (-lam)
    return RESULT(1.0, u, v, nx, ny, contrast, -lam, slope, (peak - bg) / (-lam), tilt)


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def smooth_rows_kernel(
    frames: wp.array3d(dtype=Any),
    frame: int,
    weights: wp.array(dtype=wp.float32),
    radius: int,
    scale: float,
    row0: int,
    chunk: int,
    out: wp.array2d(dtype=wp.float32),
):
    """Horizontal Gaussian pass over a run of ``chunk`` pixels of one row
    (``kernels.launch.launch_rows``), edges replicated.

    frames: (n_frames, H, W) uint8/uint16, read (plane ``frame`` only).
    weights: (2 * radius + 1,) float32, read.
    out: (H, W) float32 in 8-bit grey levels (``scale`` = 1 or 1/257), written.
    """
    w = frames.shape[2]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    for x in range(x0, x1):
        acc = float(0.0)
        for k in range(-radius, radius + 1):
            xx = wp.clamp(x + k, 0, w - 1)
            acc = acc + weights[k + radius] * float(frames[frame, y, xx])
        out[y, x] = acc * scale


@wp.kernel
def smooth_cols_kernel(
    src: wp.array2d(dtype=wp.float32),
    weights: wp.array(dtype=wp.float32),
    radius: int,
    row0: int,
    chunk: int,
    out: wp.array2d(dtype=wp.float32),
):
    """Vertical Gaussian pass over a run of ``chunk`` pixels of one row, edges replicated.

    src: (H, W) float32, read. weights: (2 * radius + 1,) float32, read.
    out: (H, W) float32, written.
    """
    h = src.shape[0]
    w = src.shape[1]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    for x in range(x0, x1):
        out[y, x] = 0.0
    for k in range(-radius, radius + 1):
        yy = wp.clamp(y + k, 0, h - 1)
        wk = weights[k + radius]
        for x in range(x0, x1):
            out[y, x] = out[y, x] + wk * src[yy, x]


@wp.kernel
def count_ridges_kernel(
    S: wp.array2d(dtype=wp.float32),
    min_contrast: float,
    min_curvature: float,
    max_eigen_ratio: float,
    max_tangent_slope: float,
    background_px: float,
    row0: int,
    chunk: int,
    counts: wp.array(dtype=wp.int32),
):
    """counts[y * W + x] = 1 where pixel (y, x) holds a line centre, else 0; a
    thread covers ``chunk`` pixels of one row.

    S: (H, W) float32 smoothed frame, read. counts: (H * W,) int32, written.

    Size: Warp kernels take each array as its own argument; the five ridge thresholds are the ones
    write_ridges_kernel tests again, passed the same way, plus the run's row0 and chunk.
    """
    w = S.shape[1]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    for x in range(x0, x1):
        r = ridge_at(S, y, x, min_contrast, min_curvature, max_eigen_ratio, max_tangent_slope, background_px)
        counts[y * w + x] = wp.where(r[0] > 0.0, 1, 0)


@wp.kernel
def write_ridges_kernel(
    S: wp.array2d(dtype=wp.float32),
    counts: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    min_contrast: float,
    min_curvature: float,
    max_eigen_ratio: float,
    max_tangent_slope: float,
    background_px: float,
    confidence_contrast: float,
    row0: int,
    chunk: int,
    uv: wp.array(dtype=wp.vec2),
    normal: wp.array(dtype=wp.vec2),
    pixel: wp.array(dtype=wp.int32),
    contrast: wp.array(dtype=wp.float32),
    curvature: wp.array(dtype=wp.float32),
    confidence: wp.array(dtype=wp.float32),
    shading: wp.array(dtype=wp.float32),
):
    """Write each line centre at its pixel's scanned offset.

    S (H, W) float32, counts and offsets (H * W,) int32 (their exclusive scan): read.
    uv, normal (n,) vec2; pixel (n,) int32; contrast, curvature, confidence, shading (n,)
    float32: written.

    Size: Warp kernels take each array as its own argument: three read, seven written, and the ridge thresholds of
    count_ridges_kernel plus the confidence's contrast.
    """
    w = S.shape[1]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    for x in range(x0, x1):
        i = y * w + x
        if counts[i] > 0:
            r = ridge_at(S, y, x, min_contrast, min_curvature, max_eigen_ratio, max_tangent_slope, background_px)
            o = offsets[i]
            uv[o] = wp.vec2(r[1], r[2])
            normal[o] = wp.vec2(r[3], r[4])
            pixel[o] = i
            contrast[o] = r[5]
            curvature[o] = r[6]
            confidence[o] = wp.min(r[5] / confidence_contrast, 1.0)
            # the light's gradient moves the centre by its slope times the variance of the line as it
            # lies on the surface; taken as the profile's whole (the bound where all blur comes before
            # the surface): the gradient across is read along the line, a proxy whose scatter the
            # bound covers (the profile's less the smoothing's left 5.3 % beyond 3 sigma on Spot)
            shade = r[7] * r[8]
            shading[o] = wp.sqrt(shade * shade + r[9] * r[9])


for _t in (wp.uint8, wp.uint16):
    wp.overload(smooth_rows_kernel, {"frames": wp.array3d(dtype=_t)})


# ----------------------------------------------------------------------------- host


def gaussian_weights(sigma: float) -> np.ndarray:
    """Normalised 1D Gaussian taps, radius ceil(3 sigma): (2 r + 1,) float32."""
    r = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).astype(np.float32)


def centre_sigmas(curvature: np.ndarray, *, sigma: float, noise: float = NOISE_LEVELS) -> np.ndarray:
    """(n,) float32 standard deviation (camera px, across the line) of line centres found at
    ``curvature`` (-lambda, 8-bit levels per px^2) in a frame smoothed by a Gaussian of ``sigma``
    px with white camera noise of ``noise`` levels: the centre t = -(g . n) / lambda moves by
    the noise of the smoothed gradient over the curvature (the gradient's central difference
    through the separable Gaussian: noise^2 sum(c_m^2) sum(G_j^2), c_m = (G_{m-1} - G_{m+1}) / 2;
    the curvature's own noise moves t by t times less, |t| <= 0.7 px)."""
    g = gaussian_weights(sigma).astype(np.float64)
    padded = np.concatenate([[0.0, 0.0], g, [0.0, 0.0]])
    c = 0.5 * (padded[:-2] - padded[2:])
    gain = noise * math.sqrt(float(np.sum(c * c)) * float(np.sum(g * g)))
    return (gain / np.maximum(np.asarray(curvature, np.float64), 1e-6)).astype(np.float32)


def smooth_frame(frames: wp.array, *, frame: int = 0, sigma: float = 1.2, threads: int | None = None) -> wp.array:
    """Gaussian-smoothed copy of one frame of a stack, in 8-bit grey levels.

    Args:
        frames: (n_frames, H, W) uint8/uint16 Warp array.
        frame: the plane to smooth.
        sigma: Gaussian sigma in pixels.
        threads: CPU threads (row slices); default all cores.

    Returns:
        (H, W) float32 Warp array on the frames' device.
    """
    _check_frames(frames, frame, "smooth_frame")
    n, h, w = frames.shape
    dev = frames.device
    threads = default_threads() if threads is None else threads
    wts = gaussian_weights(sigma)
    radius = (wts.size - 1) // 2
    weights = wp.array(wts, dtype=wp.float32, device=dev)
    scale = 1.0 / 257.0 if frames.dtype == wp.uint16 else 1.0
    tmp = wp.empty((h, w), dtype=wp.float32, device=dev)
    out = wp.empty((h, w), dtype=wp.float32, device=dev)
    if h * w == 0:
        return out
    launch_rows(smooth_rows_kernel, h, w, lambda r0, c: [frames, int(frame), weights, radius, scale, r0, c], [tmp],
                dev, threads)
    launch_rows(smooth_cols_kernel, h, w, lambda r0, c: [tmp, weights, radius, r0, c], [out], dev, threads)
    return out


def _check_frames(frames, frame, who):
    if not isinstance(frames, wp.array) or frames.ndim != 3:
        raise ValueError(f"{who}: frames must be a 3D Warp array (n, H, W), got {type(frames).__name__}"
                         f" with ndim {getattr(frames, 'ndim', None)}")
    if frames.dtype not in (wp.uint8, wp.uint16):
        raise ValueError(f"{who}: frames must be uint8 or uint16, got {frames.dtype.__name__}")
    if not 0 <= int(frame) < frames.shape[0]:
        raise ValueError(f"{who}: frame {frame} is not in the stack of {frames.shape[0]} frame(s)")


def detect_ring_lines(
    frames: wp.array,
    *,
    frame: int = 0,
    settings: LineSettings = LineSettings(),
    threads: int | None = None,
) -> RingLines:
    """Sub-pixel centres of the bright lines of one frame (the ``rings`` frame).

    Args:
        frames: (n_frames, H, W) uint8 or uint16 Warp array.
        frame: which plane holds the ring lines (0 for a ``rings`` scan).
        settings: detector thresholds.
        threads: CPU threads (row slices); default all cores.

    Returns:
        :class:`RingLines` on the frames' device, one sample per pixel that holds
        a line centre, in raster order.
    """
    _check_frames(frames, frame, "detect_ring_lines")
    if not isinstance(settings, LineSettings):
        raise ValueError(f"detect_ring_lines: settings must be LineSettings, got {type(settings).__name__}")
    n, h, w = frames.shape
    dev = frames.device
    threads = default_threads() if threads is None else threads
    S = smooth_frame(frames, frame=frame, sigma=settings.sigma, threads=threads)
    params = [float(settings.min_contrast), float(settings.min_curvature), float(settings.max_eigen_ratio),
              float(settings.max_tangent_slope), float(settings.background_px)]
    counts = wp.zeros(h * w, dtype=wp.int32, device=dev)
    if h * w:
        launch_rows(count_ridges_kernel, h, w, lambda r0, c: [S, *params, r0, c], [counts], dev, threads)
    offsets, total = scan_counts(counts)
    out = RingLines(
        uv=wp.empty(total, dtype=wp.vec2, device=dev),
        normal=wp.empty(total, dtype=wp.vec2, device=dev),
        pixel=wp.empty(total, dtype=wp.int32, device=dev),
        contrast=wp.empty(total, dtype=wp.float32, device=dev),
        curvature=wp.empty(total, dtype=wp.float32, device=dev),
        confidence=wp.empty(total, dtype=wp.float32, device=dev),
        shading=wp.empty(total, dtype=wp.float32, device=dev),
        smoothed=S,
    )
    if total:
        launch_rows(write_ridges_kernel, h, w,
                    lambda r0, c: [S, counts, offsets, *params, float(CONFIDENCE_CONTRAST), r0, c],
                    [out.uv, out.normal, out.pixel, out.contrast, out.curvature, out.confidence, out.shading], dev, threads)
    return out


