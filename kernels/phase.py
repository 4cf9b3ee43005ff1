"""Phase-rings, per pixel: linearise, wrapped phase and modulation by weighted least
squares, unwrapping by the band code anchored at band edges, optional smoothing; then
count, scan and write one sample per valid pixel (docs/design.md §7, §9).

The phase frames are I_n = 0.5 + 0.5 cos(2 pi t - 2 pi n / N), n = 0..N-1, with
t = (rho - rho0) / pitch the continuous band coordinate; band k = floor(t) is what the
gray-rings frames of the same scan code. Why each step is as it is: docs/design.md §9.

Status codes per pixel: 0 point, 1 dark (contrast below ``min_contrast``), 2 code
(band code unreliable), 3 modulation (below ``min_modulation``), 4 slip (phase
and code disagree), 5 lonely (no agreeing neighbour pair).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from ringscan.kernels.geometry import polar_angle
from ringscan.kernels.launch import default_threads, launch_rows, row_run, scan_counts
from ringscan.kernels.ring_labels import FRAME_BLACK, FRAME_FIRST_BIT, FRAME_WHITE, RingLabels, gray_to_binary
from ringscan.kernels.samples import Samples
from ringscan.kernels.settings import PhaseSettings

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

PHASE_OK = wp.constant(0)
PHASE_DARK = wp.constant(1)
PHASE_CODE = wp.constant(2)
PHASE_MODULATION = wp.constant(3)
PHASE_SLIP = wp.constant(4)
PHASE_LONELY = wp.constant(5)
PHASE_STATUS_NAMES = ("ok", "dark", "code", "modulation", "slip", "lonely")
TWO_PI = wp.constant(6.283185307179586)
SECTOR_FILL_RADIUS = wp.constant(2)
MODULATION_FLOOR = wp.constant(0.05)
"""The ring-curvature correction reads a blur variance off the fringe modulation
q as -2 ln(q) (pitch / 2 pi)^2; below this q it reads it as at this q."""

__all__ = [
    "PhaseMap",
    "PHASE_STATUS_NAMES",
    "decode_phase",
    "smooth_phase",
    "drop_lone_fringes",
    "compact_phase_points",
]


@wp.struct
class PhaseParams:
    """The scalar settings of :func:`phase_unwrap_kernel`, filled once by :func:`decode_phase`
    (the pattern's layout, the light's response and :class:`PhaseSettings`)."""

    bits: wp.int32
    """The pattern's band bits."""
    phase0: wp.int32
    """Frame index of ``phase_0``."""
    steps: wp.int32
    """The number of phase frames N."""
    inv_light_gamma: wp.float32
    """1 / the light's response exponent (1: the frames are not normalised)."""
    min_contrast: wp.float32
    """``PhaseSettings.min_contrast`` in recorded levels (x257 for 16-bit)."""
    min_modulation: wp.float32
    """``PhaseSettings.min_modulation``."""
    edge_ratio: wp.float32
    """``PhaseSettings.edge_ratio``."""
    slip_tolerance: wp.float32
    """``PhaseSettings.slip_tolerance`` (bands)."""


@dataclass
class PhaseMap:
    """Per-pixel phase results (Warp arrays of shape (H, W) on the frames' device)."""

    t: wp.array
    """float32 continuous band coordinate (rho - rho0) / pitch (0 where status != 0)."""
    modulation: wp.array
    """float32 fringe modulation q (0 where not computed)."""
    status: wp.array
    """int32 status code (0 = valid; see ``PHASE_STATUS_NAMES``)."""
    sector: wp.array | None = None
    """int32 sector per pixel with gaps at sector edges filled from neighbours
    (set by :func:`smooth_phase`), -1 unknown."""
    flags: wp.array | None = None
    """int32 (H*W,) 1 where status is 0 (set by :func:`smooth_phase`)."""


# ----------------------------------------------------------------------------- helpers


@wp.func
def trailing_zeros(k: int):
    """Number of trailing zero bits of k > 0."""
    n = int(0)
    while (k & 1) == 0:
        k = k >> 1
        n = n + 1
    return n


@wp.func
def edge_bit_ratio(frames: wp.array3d(dtype=Any), y: int, x: int, edge: int, bits: int, contrast: float):
    """|frame - inverse| / contrast of the bit that flips at band edge ``edge``
    (between bands edge - 1 and edge), or 2 where the edge does not exist."""
    if edge < 1 or edge >= (1 << bits):
        return 2.0
    b = bits - 1 - trailing_zeros(edge)
    f = FRAME_FIRST_BIT + 2 * b
    d = float(frames[f, y, x]) - float(frames[f + 1, y, x])
    return wp.abs(d) / contrast


@wp.func
def edge_mask(edge: int, bits: int):
    """Code mask (LSB numbering) of the bit that flips at band edge ``edge``, 0 if none."""
    if edge < 1 or edge >= (1 << bits):
        return 0
    return 1 << trailing_zeros(edge)


@wp.func
def ring_curvature_bias(t: float, q: float, cnt: float, sxx: float, sxy: float, syy: float, bx: float, by: float,
                        rho0: float, pitch: float):
    """Outward bias (bands) of a smoothed t: (s_light^2 + s_window^2) / (2 rho pitch).

    s_light^2 = -2 ln(q) (pitch / 2 pi)^2 (projector px^2) is the variance of every
    blur the pixel's fringe went through (projector pixel and defocus, camera
    pixel), read off its modulation q as for a Gaussian, taken as isotropic.
    s_window^2 is the smoothing window's tangential second moment: each agreeing
    pair (offsets +-h, camera px) adds 2 |A h|^2 - 2 (a . h)^2, with a = pitch grad t
    (least squares from the pairs' half differences: S g = b, S = sum h h^T,
    b = sum h (t_a - t_b) / 2) and |A h|^2 = |a|^2 |h|^2 (a conformal camera-to-
    projector map: tangential stretch = radial).

    Size: a @wp.func called with smooth_phase_kernel's registers: the smoothed t, the modulation q, the pair
    moments (cnt, sxx, sxy, syy, bx, by) the kernel accumulated and the pattern's rho0 and pitch, each a scalar.
    """
    rho = rho0 + pitch * t
    if rho < 0.5 * pitch:
        return 0.0
    k = pitch / TWO_PI
    s2 = -2.0 * wp.log(wp.clamp(q, MODULATION_FLOOR, 1.0)) * k * k
    sh = sxx + syy
    if sh > 0.0:
        det = sxx * syy - sxy * sxy
        tan2 = float(0.0)
        if det > 1.0e-6 * sh * sh:
            gx = (syy * bx - sxy * by) / det
            gy = (sxx * by - sxy * bx) / det
            tan2 = (gx * gx + gy * gy) * sh - (gx * bx + gy * by)
        else:
            # pairs along one line: the gradient across it is unknown; conformal
            tan2 = (bx * bx + by * by) / sh
        s2 += 2.0 * pitch * pitch * wp.max(tan2, 0.0) / cnt
    return s2 / (2.0 * rho * pitch)


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def phase_unwrap_kernel(
    frames: wp.array3d(dtype=Any),
    lut: wp.array(dtype=wp.float32),
    wlut: wp.array(dtype=wp.float32),
    trig: wp.array(dtype=wp.vec2),
    code: wp.array2d(dtype=wp.int32),
    weak: wp.array2d(dtype=wp.int32),
    contrast: wp.array2d(dtype=wp.float32),
    params: PhaseParams,
    row0: int,
    chunk: int,
    t_out: wp.array2d(dtype=wp.float32),
    modulation: wp.array2d(dtype=wp.float32),
    status: wp.array2d(dtype=wp.int32),
):
    """Wrapped phase, modulation and unwrapped band coordinate of a run of
    ``chunk`` pixels of one row per thread (see ``kernels.launch.launch_rows``).

    frames: (n_frames, H, W) uint8/uint16, read (white, black, gray pairs, ...,
        phase_0 at index ``phase0``).
    lut, wlut: (full_scale + 1,) float32, read: linear value and weight of each
        recorded value.
    trig: (steps,) vec2, read: (cos, sin) of each step's shift 2 pi n / steps.
    code, weak: (H, W) int32, contrast: (H, W) float32, read (the band decode).
    params: the frame layout and thresholds (:class:`PhaseParams`).
    t_out, modulation: (H, W) float32, status: (H, W) int32, written.

    Size: one thread per run of a row's pixels, and each pixel's steps share their locals: the weighted normal
    equations of the phase fit, their solution and the band code's edges are read by the unwrapping that
    follows. Warp kernels take each array as its own argument; the scalar settings already travel in
    PhaseParams.
    """
    bits = params.bits
    phase0 = params.phase0
    steps = params.steps
    inv_light_gamma = params.inv_light_gamma
    min_contrast = params.min_contrast
    min_modulation = params.min_modulation
    edge_ratio = params.edge_ratio
    slip_tolerance = params.slip_tolerance
    w = frames.shape[2]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    for x in range(x0, x1):
        t_out[y, x] = 0.0
        modulation[y, x] = 0.0
        c = contrast[y, x]
        if c < min_contrast:
            status[y, x] = PHASE_DARK
            continue
        lw = lut[int(frames[FRAME_WHITE, y, x])]
        lb = lut[int(frames[FRAME_BLACK, y, x])]
        span = lw - lb
        if span <= 0.0:
            status[y, x] = PHASE_DARK
            continue
        normalise = inv_light_gamma != 1.0
        # Weighted normal equations of L_n = A + Bc cos(d_n) + Bs sin(d_n).
        s0 = float(0.0)
        sc = float(0.0)
        ss = float(0.0)
        scc = float(0.0)
        scs = float(0.0)
        sss = float(0.0)
        r0 = float(0.0)
        rc = float(0.0)
        rs = float(0.0)
        for n in range(steps):
            r = int(frames[phase0 + n, y, x])
            val = lut[r]
            wt = wlut[r]
            if normalise:
                u = wp.clamp((val - lb) / span, 1.0e-6, 1.0)
                val = wp.pow(u, inv_light_gamma)
                # chain rule: d val / dL = inv_gamma * u^(inv_gamma - 1) / span
                g = inv_light_gamma * wp.pow(u, inv_light_gamma - 1.0) / span
                wt = wt / (g * g)
            cn = trig[n][0]
            sn = trig[n][1]
            s0 += wt
            sc += wt * cn
            ss += wt * sn
            scc += wt * cn * cn
            scs += wt * cn * sn
            sss += wt * sn * sn
            r0 += wt * val
            rc += wt * cn * val
            rs += wt * sn * val
        # Solve the symmetric system by its cofactors (Cramer's rule).
        c12 = ss * scs - sc * sss
        c13 = sc * scs - ss * scc
        c22 = s0 * sss - ss * ss
        c23 = sc * ss - s0 * scs
        c33 = s0 * scc - sc * sc
        det = s0 * (scc * sss - scs * scs) + sc * c12 + ss * c13
        if not (det > 1.0e-9 * s0 * s0 * s0):
            status[y, x] = PHASE_MODULATION
            continue
        bc = (c12 * r0 + c22 * rc + c23 * rs) / det
        bs = (c13 * r0 + c23 * rc + c33 * rs) / det
        amp = wp.sqrt(bc * bc + bs * bs)
        q = 2.0 * amp
        if not normalise:
            q = q / span
        modulation[y, x] = q
        if q < min_modulation:
            status[y, x] = PHASE_MODULATION
            continue
        f = polar_angle(bs, bc) / TWO_PI
        f = f - wp.floor(f)
        # Band code and its two edges.
        k = gray_to_binary(code[y, x], bits)
        wk = weak[y, x]
        m_lo = edge_mask(k, bits)
        m_hi = edge_mask(k + 1, bits)
        if wk != 0 and wk != m_lo and wk != m_hi:
            status[y, x] = PHASE_CODE
            continue
        e_lo = edge_bit_ratio(frames, y, x, k, bits, c)
        e_hi = edge_bit_ratio(frames, y, x, k + 1, bits, c)
        tb = float(k) + 0.5
        edge = int(-1)
        if wp.min(e_lo, e_hi) < edge_ratio:
            if e_lo <= e_hi:
                edge = k
            else:
                edge = k + 1
            tb = float(edge)
        t = wp.round(tb - f) + f
        if edge >= 0:
            strong = (wk & edge_mask(edge, bits)) == 0
            # a strong edge bit says which side of the edge the pixel is on
            if strong and edge == k and t < float(edge) - slip_tolerance:
                status[y, x] = PHASE_SLIP
                continue
            if strong and edge == k + 1 and t > float(edge) + slip_tolerance:
                status[y, x] = PHASE_SLIP
                continue
        t_out[y, x] = t
        status[y, x] = PHASE_OK


for _t in (wp.uint8, wp.uint16):
    wp.overload(phase_unwrap_kernel, {"frames": wp.array3d(dtype=_t)})


@wp.kernel
def smooth_phase_kernel(
    t: wp.array2d(dtype=wp.float32),
    status: wp.array2d(dtype=wp.int32),
    sector: wp.array2d(dtype=wp.int32),
    modulation: wp.array2d(dtype=wp.float32),
    radius: int,
    tolerance: float,
    min_pairs: int,
    curvature: int,
    rho0: float,
    pitch: float,
    row0: int,
    chunk: int,
    t_out: wp.array2d(dtype=wp.float32),
    status_out: wp.array2d(dtype=wp.int32),
    sector_out: wp.array2d(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """Pair-wise smoothing of t, the ring-curvature correction (``curvature`` 1)
    and sector gap filling, ``chunk`` pixels of one row per thread.

    t: (H, W) float32, status: (H, W) int32, sector: (H, W) int32, modulation:
    (H, W) float32, read; rho0, pitch: the pattern's (t = (rho - rho0) / pitch).
    t_out: (H, W) float32, status_out, sector_out: (H, W) int32, flags: (H*W,)
    int32 (1 where the pixel stays a point, the count for the compaction), written.

    Size: one thread per run of a row's pixels; a pixel's pair smoothing, the moments its curvature correction
    needs and the sector gap fill share the window walk's locals. Warp kernels take each array as its own
    argument; its six scalars (radius, tolerance, min_pairs, curvature, rho0, pitch) are loose arguments:
    PhaseParams holds the settings of phase_unwrap_kernel, a launch of its own.
    """
    h = t.shape[0]
    w = t.shape[1]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    for x in range(x0, x1):
        st = status[y, x]
        t_out[y, x] = t[y, x]
        status_out[y, x] = st
        s = int(sector[y, x])
        flags[y * w + x] = 0
        if st != PHASE_OK:
            sector_out[y, x] = s
            continue
        tc = t[y, x]
        acc = float(tc)
        cnt = float(1.0)
        pairs = int(0)
        seen = int(0)
        # moments of the agreeing pairs, for the gradient of t (least squares)
        sxx = float(0.0)
        sxy = float(0.0)
        syy = float(0.0)
        bx = float(0.0)
        by = float(0.0)
        for dy in range(0, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy > 0 or dx > 0:
                    ya = y + dy
                    xa = x + dx
                    yb = y - dy
                    xb = x - dx
                    oka = ya < h and xa >= 0 and xa < w
                    okb = yb >= 0 and xb >= 0 and xb < w
                    if oka:
                        oka = status[ya, xa] == PHASE_OK
                    if okb:
                        okb = status[yb, xb] == PHASE_OK
                    if oka or okb:
                        seen = seen + 1
                    if oka and okb:
                        ta = t[ya, xa]
                        tb = t[yb, xb]
                        if wp.abs(0.5 * (ta + tb) - tc) <= tolerance:
                            acc += ta + tb
                            cnt += 2.0
                            pairs = pairs + 1
                            half = 0.5 * (ta - tb)
                            fx = float(dx)
                            fy = float(dy)
                            sxx += fx * fx
                            sxy += fx * fy
                            syy += fy * fy
                            bx += half * fx
                            by += half * fy
        if radius > 0 and seen > 0 and pairs < min_pairs:
            status_out[y, x] = PHASE_LONELY
        else:
            flags[y * w + x] = 1
        ts = acc / cnt
        if curvature != 0:
            ts = ts - ring_curvature_bias(ts, modulation[y, x], cnt, sxx, sxy, syy, bx, by, rho0, pitch)
        t_out[y, x] = ts
        # A pixel on a sector edge has a weak sector bit: either neighbouring
        # sector is right to within the triangulation's tolerance.
        if s < 0:
            best = int(1 << 30)
            for dy in range(-SECTOR_FILL_RADIUS, SECTOR_FILL_RADIUS + 1):
                for dx in range(-SECTOR_FILL_RADIUS, SECTOR_FILL_RADIUS + 1):
                    yy = y + dy
                    xx = x + dx
                    d2 = dx * dx + dy * dy
                    if yy >= 0 and yy < h and xx >= 0 and xx < w and d2 < best:
                        if sector[yy, xx] >= 0:
                            best = d2
                            s = sector[yy, xx]
        sector_out[y, x] = s


@wp.kernel
def lone_fringe_kernel(
    status: wp.array2d(dtype=wp.int32),
    half: int,
    share: float,
    row0: int,
    chunk: int,
    status_out: wp.array2d(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """A valid pixel whose fringe washed out around it: more than ``share`` of the lit pixels (status not
    dark) of the (2 half + 1)^2 square about it (clipped at the image's edges) dropped for modulation; it
    becomes ``modulation`` too. ``chunk`` pixels of one row per thread.

    status (H, W) int32: read. status_out (H, W) int32, flags (H*W,) int32 (1 where status_out is ok): written.
    """
    h = status.shape[0]
    w = status.shape[1]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    for x in range(run[1], run[2]):
        s = status[y, x]
        if s == PHASE_OK:
            washed = int(0)
            lit = int(0)
            for yy in range(wp.max(y - half, 0), wp.min(y + half + 1, h)):
                for xx in range(wp.max(x - half, 0), wp.min(x + half + 1, w)):
                    t = status[yy, xx]
                    if t == PHASE_MODULATION:
                        washed += 1
                    if t != PHASE_DARK:
                        lit += 1
            if float(washed) > share * float(lit):
                s = PHASE_MODULATION
        status_out[y, x] = s
        flags[y * w + x] = wp.where(s == PHASE_OK, 1, 0)


@wp.kernel
def write_points_kernel(
    t: wp.array2d(dtype=wp.float32),
    modulation: wp.array2d(dtype=wp.float32),
    status: wp.array2d(dtype=wp.int32),
    sector: wp.array2d(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    rho0: float,
    pitch: float,
    row0: int,
    chunk: int,
    uv: wp.array(dtype=wp.vec2),
    rho: wp.array(dtype=wp.float32),
    sector_out: wp.array(dtype=wp.int32),
    confidence: wp.array(dtype=wp.float32),
    pixel: wp.array(dtype=wp.int32),
):
    """Write each valid pixel's point at its scanned offset, ``chunk`` pixels of
    one row per thread.

    t, modulation (H, W) float32, status, sector (H, W) int32, offsets (H*W,)
    int32 (exclusive scan of the flags): read.
    uv (n,) vec2, rho/confidence (n,) float32, sector_out/pixel (n,) int32: written.

    Size: Warp kernels take each array as its own argument: five read, five written, plus the pattern's rho0 and
    pitch and the run's row0 and chunk.
    """
    w = t.shape[1]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    for x in range(x0, x1):
        if status[y, x] == PHASE_OK:
            i = y * w + x
            o = offsets[i]
            uv[o] = wp.vec2(float(x), float(y))
            rho[o] = rho0 + pitch * t[y, x]
            sector_out[o] = sector[y, x]
            confidence[o] = wp.clamp(modulation[y, x], 0.0, 1.0)
            pixel[o] = i


# ----------------------------------------------------------------------------- host


def decode_phase(
    frames: wp.array,
    labels: RingLabels,
    *,
    bits: int,
    sector_bits: int,
    steps: int,
    lut: wp.array,
    wlut: wp.array,
    light_gamma: float = 1.0,
    settings: PhaseSettings = PhaseSettings(),
    threads: int | None = None,
) -> PhaseMap:
    """Wrapped phase, modulation and unwrapped band coordinate of every pixel.

    Args:
        frames: (n_frames, H, W) uint8/uint16 Warp array of a phase-rings view
            (``frame_names`` order: white, black, gray pairs, sector pairs, phase).
        labels: the band (and sector) decode of the same frames
            (:func:`ringscan.kernels.ring_labels.decode_gray_rings`).
        bits, sector_bits, steps: the pattern's band bits, sector bits and phase steps.
        lut, wlut: (full_scale + 1,) float32 Warp arrays from :func:`~ringscan.kernels.response.response_tables`.
        light_gamma: the light's response exponent (1: linear).
        settings: thresholds.
        threads: CPU threads (row slices); default: all cores.

    Returns:
        :class:`PhaseMap` on the frames' device (``sector`` unset).

    Size: a public function: the frames, their band decode and its documented keyword-only options, one per
    pattern figure, table or setting the caller chooses.
    """
    if not isinstance(frames, wp.array) or frames.ndim != 3 or frames.dtype not in (wp.uint8, wp.uint16):
        raise ValueError("decode_phase: frames must be a (n, H, W) uint8/uint16 Warp array")
    if not 1 <= bits <= 16 or not 0 <= sector_bits <= 12 or not 3 <= steps <= 64:
        raise ValueError(f"decode_phase: bits 1..16, sector_bits 0..12 and steps 3..64 expected, got {bits}, "
                         f"{sector_bits}, {steps}")
    n, h, w = frames.shape
    phase0 = 2 + 2 * bits + 2 * sector_bits
    if n < phase0 + steps:
        raise ValueError(f"decode_phase: {bits} bits, {sector_bits} sector bits and {steps} steps need "
                         f"{phase0 + steps} frames, got {n}")
    if tuple(labels.code.shape) != (h, w):
        raise ValueError(f"decode_phase: labels are {tuple(labels.code.shape)}, frames are {(h, w)}")
    full = 255 if frames.dtype == wp.uint8 else 65535
    for name, a in (("lut", lut), ("wlut", wlut)):
        if not isinstance(a, wp.array) or a.dtype != wp.float32 or a.shape != (full + 1,):
            raise ValueError(f"decode_phase: {name} must be a ({full + 1},) float32 Warp array for "
                             f"{frames.dtype.__name__} frames")
    if not (np.isfinite(light_gamma) and light_gamma > 0):
        raise ValueError(f"decode_phase: light_gamma must be > 0, got {light_gamma}")
    dev = frames.device
    scale = 257.0 if frames.dtype == wp.uint16 else 1.0
    out = PhaseMap(t=wp.empty((h, w), dtype=wp.float32, device=dev),
                   modulation=wp.empty((h, w), dtype=wp.float32, device=dev),
                   status=wp.empty((h, w), dtype=wp.int32, device=dev))
    if h * w == 0:
        return out
    s = settings
    shifts = 2.0 * np.pi * np.arange(steps) / steps
    trig = wp.array(np.stack([np.cos(shifts), np.sin(shifts)], -1).astype(np.float32), dtype=wp.vec2, device=dev)
    params = PhaseParams()
    params.bits = bits
    params.phase0 = phase0
    params.steps = steps
    params.inv_light_gamma = 1.0 / float(light_gamma)
    params.min_contrast = s.min_contrast * scale
    params.min_modulation = s.min_modulation
    params.edge_ratio = s.edge_ratio
    params.slip_tolerance = s.slip_tolerance
    launch_rows(
        phase_unwrap_kernel, h, w,
        lambda r0, chunk: [frames, lut, wlut, trig, labels.code, labels.weak, labels.contrast, params, r0, chunk],
        [out.t, out.modulation, out.status], dev, default_threads() if threads is None else threads,
    )
    return out


def smooth_phase(
    phase: PhaseMap,
    sector: wp.array,
    *,
    settings: PhaseSettings = PhaseSettings(),
    rho0: float | None = None,
    pitch: float | None = None,
    threads: int | None = None,
) -> PhaseMap:
    """Pair-wise smoothing of the band coordinate, the ring-curvature correction,
    lonely-pixel rejection and sector gap filling.

    Args:
        phase: the output of :func:`decode_phase`.
        sector: (H, W) int32 decoded sector per pixel (-1 unknown).
        settings: ``smooth_radius``, ``smooth_tolerance``, ``min_pairs``,
            ``ring_curvature``.
        rho0, pitch: the pattern's inner radius and pitch (projector px); the
            ring-curvature correction needs them (without them t is as averaged).
        threads: CPU threads (row slices); default: all cores.

    Returns:
        A new :class:`PhaseMap` with ``sector`` set.
    """
    h, w = phase.t.shape
    if not isinstance(sector, wp.array) or sector.dtype != wp.int32 or tuple(sector.shape) != (h, w):
        raise ValueError(f"smooth_phase: sector must be a ({h}, {w}) int32 Warp array")
    if (rho0 is None) != (pitch is None):
        raise ValueError("smooth_phase: give both rho0 and pitch, or neither")
    if pitch is not None and not (np.isfinite(pitch) and pitch > 0 and np.isfinite(rho0)):
        raise ValueError(f"smooth_phase: pitch must be > 0 and rho0 finite, got {pitch}, {rho0}")
    curvature = int(settings.ring_curvature and pitch is not None)
    dev = phase.t.device
    out = PhaseMap(t=wp.empty_like(phase.t), modulation=phase.modulation, status=wp.empty_like(phase.status),
                   sector=wp.empty_like(sector), flags=wp.empty(h * w, dtype=wp.int32, device=dev))
    if h * w == 0:
        return out
    s = settings
    launch_rows(
        smooth_phase_kernel, h, w,
        lambda r0, chunk: [phase.t, phase.status, sector, phase.modulation, int(s.smooth_radius),
                           float(s.smooth_tolerance), int(s.min_pairs), curvature, float(rho0 or 0.0),
                           float(pitch or 1.0), r0, chunk],
        [out.t, out.status, out.sector, out.flags], dev, default_threads() if threads is None else threads,
    )
    return out


def drop_lone_fringes(phase: PhaseMap, *, size: int, share: float, threads: int | None = None) -> PhaseMap:
    """The phase map with each valid pixel whose fringe washed out around it dropped as ``modulation``
    (:func:`lone_fringe_kernel`: more than ``share`` of the lit pixels of the ``size`` x ``size`` square
    about it dropped for modulation, ``size`` odd): a new status and new flags, the other fields shared."""
    if phase.flags is None:
        raise ValueError("drop_lone_fringes: the phase map has no flags (run smooth_phase first)")
    if size < 1 or size % 2 == 0 or not 0.0 <= share <= 1.0:
        raise ValueError(f"drop_lone_fringes: size must be odd and >= 1, share within 0..1; got {size}, {share}")
    h, w = phase.status.shape
    out = dataclasses.replace(phase, status=wp.empty_like(phase.status), flags=wp.empty_like(phase.flags))
    if h * w:
        launch_rows(lone_fringe_kernel, h, w, lambda r0, chunk: [phase.status, size // 2, float(share), r0, chunk],
                    [out.status, out.flags], phase.status.device, default_threads() if threads is None else threads)
    return out


def compact_phase_points(phase: PhaseMap, *, rho0: float, pitch: float, threads: int | None = None) -> Samples:
    """One point per valid pixel, in raster order (count: the flags that
    :func:`smooth_phase` wrote; scan; write).

    Args:
        phase: a :class:`PhaseMap` with ``sector`` set (:func:`smooth_phase`).
        rho0, pitch: the pattern's inner radius and pitch (projector px).
        threads: CPU threads (row slices); default: all cores.

    Returns:
        :class:`~ringscan.kernels.samples.Samples`: ``uv`` the pixel centre,
        ``rho`` = rho0 + pitch * t, ``confidence`` the modulation clamped to
        [0, 1], ``ring`` None (dense), ``phi``/``sigma_*`` None.
    """
    if phase.sector is None or phase.flags is None:
        raise ValueError("compact_phase_points: the phase map has no sector (run smooth_phase first)")
    h, w = phase.t.shape
    dev = phase.t.device
    n = h * w
    total = 0
    if n:
        flags = phase.flags
        offsets, total = scan_counts(flags)
    out = Samples(uv=wp.empty(total, dtype=wp.vec2, device=dev), rho=wp.empty(total, dtype=wp.float32, device=dev), ring=None,
                      sector=wp.empty(total, dtype=wp.int32, device=dev),
                      confidence=wp.empty(total, dtype=wp.float32, device=dev),
                      pixel=wp.empty(total, dtype=wp.int32, device=dev))
    if total:
        launch_rows(write_points_kernel, h, w,
                    lambda r0, chunk: [phase.t, phase.modulation, phase.status, phase.sector, offsets, float(rho0),
                                       float(pitch), r0, chunk],
                    [out.uv, out.rho, out.sector, out.confidence, out.pixel], dev,
                    default_threads() if threads is None else threads)
    return out
