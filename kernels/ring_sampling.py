"""Dense sub-pixel ring sampling (docs/design.md §7).

gray-rings: a band boundary k (radius rho0 + k * pitch) runs between two
neighbouring pixels p, q whose band codes differ in exactly the one bit b that
flips at k, every other bit being strong at both. The boundary point is where
frame b crosses its inverse: with d = frame_b - inverse_b, linear interpolation
between p and q puts it at p + d_p / (d_p - d_q) * (q - p). Each pixel pair is
tried along +x and +y; of the two directions only the one closer to the edge's
normal (the larger component of the gradient of d) is kept, so a boundary gives
about one sample per pixel it crosses and never a grazing one.

Output order is deterministic: per pixel in raster order, the +x sample first.
Counts are computed per run of pixels (a row on the CPU, a pixel on CUDA),
scanned (``wp.utils.array_scan``) and then written; the count pass keeps each
crossing it finds (pair, position, confidence, ring and sector) packed at its
run's slots, so the write pass only copies them to their scanned offsets.
"""

from __future__ import annotations

from typing import Any

import logging

import numpy as np
import warp as wp

from ringscan.kernels.launch import default_threads, launch_rows, row_run, scan_counts
from ringscan.kernels.ring_labels import FRAME_FIRST_BIT, RingLabels, gray_to_binary
from ringscan.kernels.samples import Samples
from ringscan.kernels.settings import SampleSettings

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["sample_gray_rings", "ring_radii", "ring_blur_variance"]

log = logging.getLogger(__name__)

SQRT_2PI = wp.constant(2.5066282746310002)
WALK_STEP = wp.constant(0.5)
"""Step (camera px) of the walk along an edge's normal to the neighbouring band edges."""
WALK_MAX = wp.constant(64.0)
"""Longest walk (camera px): wider bands give the sample no blur estimate."""
MIN_RING_ESTIMATES = 16
"""Rings with fewer blur estimates than this take the median of all rings'."""


# ----------------------------------------------------------------------------- helpers


@wp.func
def bit_diff(frames: wp.array3d(dtype=Any), fidx: int, y: int, x: int):
    """frame - inverse at (y, x) for the frame pair starting at ``fidx``."""
    return float(frames[fidx, y, x]) - float(frames[fidx + 1, y, x])


@wp.func
def across_diff(frames: wp.array3d(dtype=Any), fidx: int, y: int, x: int, dy: int, dx: int, h: int, w: int):
    """Gradient of frame - inverse across the pair p = (y, x), q = (y + dy, x + dx):
    central differences perpendicular to (dy, dx), clamped to the image, averaged
    over p and q."""
    y2 = y + dy
    x2 = x + dx
    ay0 = wp.max(y - dx, 0)
    ay1 = wp.min(y + dx, h - 1)
    ax0 = wp.max(x - dy, 0)
    ax1 = wp.min(x + dy, w - 1)
    by0 = wp.max(y2 - dx, 0)
    by1 = wp.min(y2 + dx, h - 1)
    bx0 = wp.max(x2 - dy, 0)
    bx1 = wp.min(x2 + dy, w - 1)
    return 0.5 * (bit_diff(frames, fidx, ay1, ax1) - bit_diff(frames, fidx, ay0, ax0)) * 0.5 + 0.5 * (
        bit_diff(frames, fidx, by1, bx1) - bit_diff(frames, fidx, by0, bx0)
    ) * 0.5


@wp.func
def single_bit(m: int):
    """Index (from the least significant end) of the only set bit of m, or -1."""
    if m <= 0 or (m & (m - 1)) != 0:
        return -1
    # the bit's index, one binary digit per mask (no loop to mispredict)
    i = wp.where((m & 0x55555555) != 0, 0, 1)
    i = i + wp.where((m & 0x33333333) != 0, 0, 2)
    i = i + wp.where((m & 0x0F0F0F0F) != 0, 0, 4)
    i = i + wp.where((m & 0x00FF00FF) != 0, 0, 8)
    return i + wp.where((m & 0x0000FFFF) != 0, 0, 16)


@wp.func
def edge_pair(
    frames: wp.array3d(dtype=Any),
    code: wp.array2d(dtype=wp.int32),
    weak: wp.array2d(dtype=wp.int32),
    contrast: wp.array2d(dtype=wp.float32),
    bits: int,
    min_contrast: float,
    min_slope: float,
    y: int,
    x: int,
    dy: int,
    dx: int,
):
    """Test the pair p = (y, x), q = (y + dy, x + dx).

    Returns vec4(found, fraction, boundary k, confidence).

    Size: a @wp.func reading the frames and the three label arrays directly (Warp functions take arrays one by
    one), plus the sampler's thresholds and the pair's pixel and direction.
    """
    h = code.shape[0]
    w = code.shape[1]
    none = wp.vec4(0.0, 0.0, 0.0, 0.0)
    y2 = y + dy
    x2 = x + dx
    if y2 >= h or x2 >= w:
        return none
    # cheapest tests first: most pixels are dark or inside a band
    cp = contrast[y, x]
    if cp < min_contrast:
        return none
    gp = code[y, x]
    gq = code[y2, x2]
    if gp == gq:
        return none
    cq = contrast[y2, x2]
    if cq < min_contrast:
        return none
    lsb = single_bit(gp ^ gq)
    if lsb < 0:
        return none
    m = int(1) << lsb
    if ((weak[y, x] | weak[y2, x2]) & (~m)) != 0:
        return none
    kp = gray_to_binary(gp, bits)
    kq = gray_to_binary(gq, bits)
    if wp.abs(kp - kq) != 1:
        return none
    b = bits - 1 - lsb
    fidx = FRAME_FIRST_BIT + 2 * b
    dp = bit_diff(frames, fidx, y, x)
    dq = bit_diff(frames, fidx, y2, x2)
    slope = dp - dq
    cm = 0.5 * (cp + cq)
    if wp.abs(slope) < min_slope * cm:
        return none
    # Keep the direction closer to the edge normal: compare with the gradient
    # component across the pair (central differences, averaged over p and q).
    across = across_diff(frames, fidx, y, x, dy, dx, h, w)
    if dx == 1:
        if wp.abs(across) > wp.abs(slope):
            return none
    else:
        if wp.abs(across) >= wp.abs(slope):
            return none
    f = dp / slope
    conf = wp.min(wp.abs(slope) / cm, 1.0)
    return wp.vec4(1.0, f, float(wp.max(kp, kq)), conf)


@wp.func
def band_at(code: wp.array2d(dtype=wp.int32), contrast: wp.array2d(dtype=wp.float32), bits: int,
            min_contrast: float, fy: float, fx: float):
    """Band index of the raw code (every bit by its sign, weak or not: it flips
    where the edge is) of the pixel nearest (fy, fx); -2 outside the image or dark."""
    yi = int(wp.floor(fy + 0.5))
    xi = int(wp.floor(fx + 0.5))
    if yi < 0 or xi < 0 or yi >= code.shape[0] or xi >= code.shape[1]:
        return -2
    if contrast[yi, xi] < min_contrast:
        return -2
    return gray_to_binary(code[yi, xi], bits)


@wp.func
def edge_blur(
    frames: wp.array3d(dtype=Any),
    code: wp.array2d(dtype=wp.int32),
    contrast: wp.array2d(dtype=wp.float32),
    bits: int,
    min_contrast: float,
    pitch: float,
    y: int,
    x: int,
    dy: int,
    dx: int,
    frac: float,
):
    """Blur variance sigma^2 (projector px^2, along the radius) of the edge found
    between p = (y, x) and q = (y + dy, x + dx) at ``frac``; -1 where unknown.

    sigma (camera px) from the slope |grad d| = 2 C / (sqrt(2 pi) sigma) of
    d = frame - inverse at the crossing, less the 1/12 px^2 that the one-pixel
    difference itself adds; camera px -> projector px by pitch / (the mean camera
    distance along the normal to the neighbouring band edges on either side).

    Size: a @wp.func reading the frames and labels directly (Warp functions take arrays one by one), plus the
    pattern's pitch and the pair's pixel, direction and crossing.
    """
    h = code.shape[0]
    w = code.shape[1]
    y2 = y + dy
    x2 = x + dx
    kp = gray_to_binary(code[y, x], bits)
    kq = gray_to_binary(code[y2, x2], bits)
    b = bits - 1 - single_bit(code[y, x] ^ code[y2, x2])
    fidx = FRAME_FIRST_BIT + 2 * b
    along = bit_diff(frames, fidx, y2, x2) - bit_diff(frames, fidx, y, x)
    across = across_diff(frames, fidx, y, x, dy, dx, h, w)
    gx = along
    gy = across
    if dy == 1:
        gx = across
        gy = along
    g = wp.sqrt(gx * gx + gy * gy)
    cm = 0.5 * (contrast[y, x] + contrast[y2, x2])
    if g <= 0.0 or cm <= 0.0:
        return -1.0
    sc = 2.0 * cm / (SQRT_2PI * g)
    s2 = wp.max(sc * sc - 1.0 / 12.0, 0.0)
    nx = gx / g
    ny = gy / g
    cy = float(y) + float(dy) * frac
    cx = float(x) + float(dx) * frac
    klo = wp.min(kp, kq)
    khi = wp.max(kp, kq)
    dsum = float(0.0)
    sides = int(0)
    for side in range(2):
        sgn = float(2 * side - 1)
        t = float(WALK_STEP)
        while t <= WALK_MAX:
            k = band_at(code, contrast, bits, min_contrast, cy + sgn * t * ny, cx + sgn * t * nx)
            if k < 0:
                t = WALK_MAX + 1.0
            elif k != kp and k != kq:
                if k == klo - 1 or k == khi + 1:
                    # the first step whose nearest pixel is past the edge: on average
                    # at the edge (measured on synthetic rings, pitch 3-6 px)
                    dsum += t
                    sides = sides + 1
                t = WALK_MAX + 1.0
            t = t + WALK_STEP
    if sides == 0:
        return -1.0
    scale = pitch * float(sides) / dsum
    return s2 * scale * scale


@wp.func
def pair_sector(sector: wp.array2d(dtype=wp.int32), y: int, x: int, y2: int, x2: int):
    s = sector[y, x]
    if s < 0:
        s = sector[y2, x2]
    return s


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def count_edges_kernel(
    frames: wp.array3d(dtype=Any),
    code: wp.array2d(dtype=wp.int32),
    weak: wp.array2d(dtype=wp.int32),
    contrast: wp.array2d(dtype=wp.float32),
    sector: wp.array2d(dtype=wp.int32),
    bits: int,
    min_contrast: float,
    min_slope: float,
    curvature: int,
    pitch: float,
    row0: int,
    chunk: int,
    counts: wp.array(dtype=wp.int32),
    pair: wp.array(dtype=wp.int32),
    ring: wp.array(dtype=wp.int32),
    pair_sectors: wp.array(dtype=wp.int32),
    fraction: wp.array(dtype=wp.float32),
    slope: wp.array(dtype=wp.float32),
    blur: wp.array(dtype=wp.float32),
):
    """Test both pairs of every pixel of a run (``chunk`` pixels of one row, see
    ``kernels.launch.launch_rows``); count the run's samples and keep, packed in
    raster order (+x first) from slot 2 * (its first pixel) on, what the write
    pass needs, so that no pair is evaluated twice. On the CPU a run is a row, so
    the scan and the write pass see one count a row, not one a pixel.

    frames: (n, H, W) read; code, weak, sector: (H, W) int32 read; contrast (H, W)
    read; ``curvature`` 1: estimate each crossing's blur (``pitch``: projector px).
    counts: (runs,) int32 written: run r = row * n_chunks + chunk index
        (n_chunks = ceil(W / chunk)).
    pair: (2*H*W,) int32 written at the run's slots: 2 * pixel + direction (0: +x,
        1: +y) of each sample.
    ring, pair_sectors: (2*H*W,) int32 written likewise: the boundary index and
        the pair's sector (:func:`pair_sector`).
    fraction, slope: (2*H*W,) float32 written likewise: the crossing's position
        along the pair and its confidence.
    blur: (2*H*W,) float32 written likewise with ``curvature`` 1: the edge's blur
        variance (projector px^2, -1 unknown; :func:`edge_blur`).

    Size: Warp kernels take each array as its own argument: five read (frames and the decode's labels) and seven
    written for the write pass (counts and six per-pair arrays), plus the sampler's scalars and the run's row0
    and chunk.
    """
    w = code.shape[1]
    tid = wp.tid()
    run = row_run(tid, w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    o = 2 * (y * w + x0)
    n = int(0)
    for x in range(x0, x1):
        if contrast[y, x] >= min_contrast:
            i = y * w + x
            ex = edge_pair(frames, code, weak, contrast, bits, min_contrast, min_slope, y, x, 0, 1)
            ey = edge_pair(frames, code, weak, contrast, bits, min_contrast, min_slope, y, x, 1, 0)
            if ex[0] > 0.0:
                pair[o + n] = 2 * i
                ring[o + n] = int(ex[2])
                pair_sectors[o + n] = pair_sector(sector, y, x, y, x + 1)
                fraction[o + n] = ex[1]
                slope[o + n] = ex[3]
                if curvature != 0:
                    blur[o + n] = edge_blur(frames, code, contrast, bits, min_contrast, pitch, y, x, 0, 1, ex[1])
                n = n + 1
            if ey[0] > 0.0:
                pair[o + n] = 2 * i + 1
                ring[o + n] = int(ey[2])
                pair_sectors[o + n] = pair_sector(sector, y, x, y + 1, x)
                fraction[o + n] = ey[1]
                slope[o + n] = ey[3]
                if curvature != 0:
                    blur[o + n] = edge_blur(frames, code, contrast, bits, min_contrast, pitch, y, x, 1, 0, ey[1])
                n = n + 1
    counts[row0 * ((w + chunk - 1) / chunk) + tid] = n


@wp.kernel
def write_edges_kernel(
    w: int,
    counts: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    pair: wp.array(dtype=wp.int32),
    pair_ring: wp.array(dtype=wp.int32),
    pair_sectors: wp.array(dtype=wp.int32),
    fraction: wp.array(dtype=wp.float32),
    slope: wp.array(dtype=wp.float32),
    blur: wp.array(dtype=wp.float32),
    curvature: int,
    row0: int,
    chunk: int,
    uv: wp.array(dtype=wp.vec2),
    ring: wp.array(dtype=wp.int32),
    sample_sector: wp.array(dtype=wp.int32),
    confidence: wp.array(dtype=wp.float32),
    pixel: wp.array(dtype=wp.int32),
    sample_blur: wp.array(dtype=wp.float32),
):
    """Copy each run's samples to its scanned offset (runs as in the count pass).

    w: the image width. counts and offsets (runs,) int32 (offsets: their exclusive
    scan), pair/pair_ring/pair_sectors/fraction/slope/blur (2*H*W,) from the count
    pass: read (blur only with ``curvature`` 1).
    uv (n_samples,) vec2, ring/sample_sector/pixel (n_samples,) int32,
    confidence (n_samples,) float32, sample_blur (n_samples,) float32 (with
    ``curvature`` 1): written.

    Size: Warp kernels take each array as its own argument: the count pass's eight arrays read and six
    per-sample arrays written.
    """
    tid = wp.tid()
    r = row0 * ((w + chunk - 1) / chunk) + tid
    n = counts[r]
    if n == 0:
        return
    run = row_run(tid, w, row0, chunk)
    src = 2 * (run[0] * w + run[1])
    o = offsets[r]
    for k in range(n):
        pd = pair[src + k]
        i = pd / 2
        y = i / w
        x = i - y * w
        f = fraction[src + k]
        if pd == 2 * i:
            uv[o + k] = wp.vec2(float(x) + f, float(y))
        else:
            uv[o + k] = wp.vec2(float(x), float(y) + f)
        ring[o + k] = pair_ring[src + k]
        sample_sector[o + k] = pair_sectors[src + k]
        confidence[o + k] = slope[src + k]
        pixel[o + k] = i
        if curvature != 0:
            sample_blur[o + k] = blur[src + k]


for _t in (wp.uint8, wp.uint16):
    wp.overload(count_edges_kernel, {"frames": wp.array3d(dtype=_t)})


# ----------------------------------------------------------------------------- host


def sample_gray_rings(
    frames: wp.array,
    labels: RingLabels,
    *,
    bits: int,
    settings: SampleSettings = SampleSettings(),
    threads: int | None = None,
    rho0: float | None = None,
    pitch: float | None = None,
) -> Samples:
    """Sub-pixel samples of every band boundary seen in a gray-rings frame stack.

    Args:
        frames: (n_frames, H, W) uint8/uint16 Warp array (``frame_names`` order).
        labels: the decode of the same frames (:func:`decode_gray_rings`).
        bits: band Gray-code bits.
        settings: sampler thresholds.
        threads: CPU threads (row slices); default: all cores.
        rho0, pitch: the pattern's inner radius and pitch (projector px); given
            both, ``rho`` is filled: the ring's radius (:func:`ring_radii`), less
            the blurred edge's inward shift with ``settings.ring_curvature``
            (:func:`ring_blur_variance`); else it is None.

    Returns:
        :class:`~ringscan.kernels.samples.Samples` on the frames' device, in
        raster order (``ring`` set, ``phi``/``sigma_*`` None).

    Size: a public entry point running two kernel passes (count, then write) that share the arrays it allocates
    and, with the pattern's radii, the ring-blur correction; over a third of its length is its signature,
    documentation and input checks.
    """
    if not isinstance(frames, wp.array) or frames.ndim != 3 or frames.dtype not in (wp.uint8, wp.uint16):
        raise ValueError("sample_gray_rings: frames must be a (n, H, W) uint8/uint16 Warp array")
    n, h, w = frames.shape
    if tuple(labels.code.shape) != (h, w):
        raise ValueError(f"sample_gray_rings: labels are {tuple(labels.code.shape)}, frames are {(h, w)}")
    if frames.shape[0] < 2 + 2 * bits:
        raise ValueError(f"sample_gray_rings: {bits} bits need {2 + 2 * bits} frames, got {frames.shape[0]}")
    if (rho0 is None) != (pitch is None):
        raise ValueError("sample_gray_rings: give both rho0 and pitch, or neither")
    if pitch is not None and not (np.isfinite(pitch) and pitch > 0 and np.isfinite(rho0)):
        raise ValueError(f"sample_gray_rings: pitch must be > 0 and rho0 finite, got {pitch}, {rho0}")
    curvature = int(settings.ring_curvature and pitch is not None)
    dev = frames.device
    threads = default_threads() if threads is None else threads
    scale = 257.0 if frames.dtype == wp.uint16 else 1.0
    mc = settings.min_contrast * scale
    # count pass: each run's count (scanned below) and its samples' pairs, crossings,
    # confidences and blurs packed at the run's slots (read back by the write pass)
    counts = wp.empty(h * w, dtype=wp.int32, device=dev)  # runs <= pixels
    pair = wp.empty(2 * h * w, dtype=wp.int32, device=dev)
    ring = wp.empty(2 * h * w, dtype=wp.int32, device=dev)
    sectors = wp.empty(2 * h * w, dtype=wp.int32, device=dev)
    fraction = wp.empty(2 * h * w, dtype=wp.float32, device=dev)
    slope = wp.empty(2 * h * w, dtype=wp.float32, device=dev)
    blur = wp.empty(2 * h * w if curvature else 0, dtype=wp.float32, device=dev)
    runs = [0]

    def count_inputs(r0, chunk):
        runs[0] = h * ((w + chunk - 1) // chunk)  # the launcher's run length decides the runs
        return [frames, labels.code, labels.weak, labels.contrast, labels.sector, bits, mc, settings.min_slope,
                curvature, float(pitch or 1.0), r0, chunk]

    if h * w:
        launch_rows(count_edges_kernel, h, w, count_inputs, [counts, pair, ring, sectors, fraction, slope, blur], dev,
                    threads)
    counts = counts[:runs[0]]
    offsets, total = scan_counts(counts)
    out = Samples(
        uv=wp.empty(total, dtype=wp.vec2, device=dev),
        rho=None,
        ring=wp.empty(total, dtype=wp.int32, device=dev),
        sector=wp.empty(total, dtype=wp.int32, device=dev),
        confidence=wp.empty(total, dtype=wp.float32, device=dev),
        pixel=wp.empty(total, dtype=wp.int32, device=dev),
    )
    sample_blur = wp.empty(total if curvature else 0, dtype=wp.float32, device=dev)
    if total:
        launch_rows(write_edges_kernel, h, w,
                    lambda r0, chunk: [w, counts, offsets, pair, ring, sectors, fraction, slope, blur, curvature,
                                       r0, chunk],
                    [out.uv, out.ring, out.sector, out.confidence, out.pixel, sample_blur], dev, threads)
    if pitch is not None:
        out.rho = ring_radii(out.ring, rho0=rho0, pitch=pitch)
        if curvature and total:
            shift = ring_blur_variance(out.ring.numpy(), sample_blur.numpy(), rings=2 ** bits)
            log.debug("ring-edge blur variance (projector px^2) per ring: %s", np.round(shift, 2).tolist())
            wp.launch(ring_curvature_kernel, dim=total,
                      inputs=[out.ring, wp.array(shift.astype(np.float32), device=dev)], outputs=[out.rho], device=dev)
    return out


def ring_blur_variance(ring: np.ndarray, blur: np.ndarray, *, rings: int) -> np.ndarray:
    """Per-ring median of the samples' blur variances (projector px^2).

    ring: (n,) int band boundary index, blur: (n,) float per-sample estimates (< 0:
    none). Returns (rings,) float64: the median over each ring's estimates, or over
    all estimates for rings with fewer than ``MIN_RING_ESTIMATES`` (0 with none).
    """
    out = np.zeros(rings, dtype=np.float64)
    ok = (blur >= 0) & (ring >= 0) & (ring < rings)
    if not ok.any():
        return out
    r, b = ring[ok], blur[ok].astype(np.float64)
    out[:] = np.median(b)
    order = np.argsort(r, kind="stable")
    r, b = r[order], b[order]
    ks, starts, n = np.unique(r, return_index=True, return_counts=True)
    for k, s0, c in zip(ks, starts, n):
        if c >= MIN_RING_ESTIMATES:
            out[k] = np.median(b[s0:s0 + c])
    return out


@wp.kernel
def ring_curvature_kernel(ring: wp.array(dtype=wp.int32), blur: wp.array(dtype=wp.float32),
                          rho: wp.array(dtype=wp.float32)):
    """rho[i] -= blur[ring[i]] / (2 rho[i]): the blurred edge's inward shift.

    ring (n,) int32 and blur (rings,) float32 (projector px^2) read; rho (n,) float32
    read and written (nominal radii in, where the edge was seen out)."""
    i = wp.tid()
    r = rho[i]
    if r > 0.0:
        rho[i] = r - blur[ring[i]] / (2.0 * r)


@wp.kernel
def ring_radius_kernel(ring: wp.array(dtype=wp.int32), rho0: float, pitch: float, rho: wp.array(dtype=wp.float32)):
    """rho[i] = rho0 + ring[i] * pitch. ring (n,) read; rho (n,) written."""
    i = wp.tid()
    rho[i] = rho0 + float(ring[i]) * pitch


def ring_radii(ring: wp.array, *, rho0: float, pitch: float) -> wp.array:
    """Radius (projector px) of each sample's ring: rho0 + k * pitch, on ring's device."""
    if not isinstance(ring, wp.array) or ring.dtype != wp.int32 or ring.ndim != 1:
        raise ValueError("ring_radii: ring must be a 1D int32 Warp array")
    rho = wp.empty(ring.shape[0], dtype=wp.float32, device=ring.device)
    if ring.shape[0]:
        wp.launch(ring_radius_kernel, dim=ring.shape[0], inputs=[ring, float(rho0), float(pitch)], outputs=[rho],
                  device=ring.device)
    return rho
