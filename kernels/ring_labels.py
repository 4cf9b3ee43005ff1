"""Ring labelling, per pixel: decode gray-rings (and sector) codes (docs/design.md §7).

For every camera pixel the kernel reads the ``white``/``black`` pair and each Gray
code frame/inverse pair, and writes

- ``code``: the raw band Gray code (bit b set where frame b is brighter than its
  inverse; b = 0 is the most significant bit),
- ``weak``: a mask of the band bits whose frame/inverse difference is below the
  margin (a pixel on a band edge has exactly its flipping bit weak),
- ``band``: the band index k (inverse Gray code) where the pixel has contrast and
  no weak bit, else -1,
- ``sector``: the decoded angular sector where every sector bit is strong, else -1,
- ``contrast``: white - black in grey levels of the frames' own scale.

Frame layout in the (n_frames, H, W) stack (the order of
``pipeline.patterns.frame_names``): white, black, gray_0, gray_0_inv, ...,
gray_{bits-1}_inv, then sector_0, sector_0_inv, ...

Two kernels, one result: :func:`decode_gray_rings_swar_kernel` decodes eight 8-bit pixels a
thread in uint64 words and is the one a view of 8-bit frames runs (width a multiple of 8, up to
15 bits); :func:`decode_gray_rings_kernel`, one pixel a thread, serves 16-bit frames and the other
shapes. The word kernel is kept for its speed: 18.0 against 72.0 ms on a default view (1280x1024,
28 frames, one thread: 4.0x) with the same output bytes (``python benchmarks/decode_kernels.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any

import numpy as np
import warp as wp

from ringscan.kernels.launch import default_threads, launch_rows, launch_spans, row_run
from ringscan.kernels.settings import DecodeSettings

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

FRAME_WHITE = wp.constant(0)
FRAME_BLACK = wp.constant(1)
FRAME_FIRST_BIT = wp.constant(2)
SECTOR_WEAK = wp.constant(1 << 30)
BIT_GROUP = wp.constant(4)
# SWAR (SIMD within a register) constants: eight 8-bit pixels per uint64 word,
# split into even and odd bytes held in four 16-bit lanes each.
LANES_LO = wp.constant(wp.uint64(0x00FF00FF00FF00FF))
LANES_GUARD = wp.constant(wp.uint64(0x8000800080008000))
LANES_512 = wp.constant(wp.uint64(0x0200020002000200))
LANES_513 = wp.constant(wp.uint64(0x0201020102010201))
LANES_ONE = wp.constant(wp.uint64(0x0001000100010001))
LANES_1024 = wp.constant(wp.uint64(0x0400040004000400))

__all__ = ["RingLabels", "decode_gray_rings", "count_labels"]


@dataclass
class RingLabels:
    """Per-pixel decode results (Warp arrays of shape (H, W) on the frames' device)."""

    code: wp.array
    """int32 raw band Gray code."""
    weak: wp.array
    """int32 mask of weak band bits."""
    band: wp.array
    """int32 band index, -1 where not decoded."""
    sector: wp.array
    """int32 sector index, -1 where not decoded or no sector code."""
    contrast: wp.array
    """float32 white - black."""


# ----------------------------------------------------------------------------- helpers


@wp.func
def gray_to_binary(g: int, bits: int):
    """Inverse Gray code of a ``bits``-bit code."""
    k = g
    shift = int(1)
    while shift < bits:
        k = k ^ (k >> shift)
        shift = shift * 2
    return k


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def decode_gray_rings_kernel(
    frames: wp.array3d(dtype=Any),
    bits: int,
    sector_bits: int,
    min_contrast: float,
    bit_margin: float,
    row0: int,
    chunk: int,
    code: wp.array2d(dtype=wp.int32),
    weak: wp.array2d(dtype=wp.int32),
    band: wp.array2d(dtype=wp.int32),
    sector: wp.array2d(dtype=wp.int32),
    contrast: wp.array2d(dtype=wp.float32),
):
    """Decode a run of ``chunk`` pixels of one row per thread.

    Thread t covers row row0 + t // n_chunks, columns [c * chunk, (c + 1) * chunk)
    with c = t % n_chunks. Frame planes are streamed one after the other over the
    run (the outer loop is over frames), which keeps a CPU thread's reads
    sequential; on CUDA ``chunk`` is 1 and each thread is one pixel.

    frames:   (n_frames, H, W) uint8/uint16, read.
    code, weak, band, sector: (H, W) int32, written.
    contrast: (H, W) float32, written.

    Size: Warp kernels take each array as its own argument: the frames, five label arrays written, and the
    decode's four scalars plus the run's row0 and chunk.
    """
    w = frames.shape[2]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    x0 = run[1]
    x1 = run[2]
    for x in range(x0, x1):
        contrast[y, x] = float(frames[FRAME_WHITE, y, x]) - float(frames[FRAME_BLACK, y, x])
        code[y, x] = 0
        weak[y, x] = 0
    # Bits in groups of BIT_GROUP frame pairs per pass over the run: few enough
    # streams for the CPU's prefetchers, few read-modify-writes of code/weak.
    for b0 in range(0, bits, BIT_GROUP):
        b1 = wp.min(b0 + BIT_GROUP, bits)
        for x in range(x0, x1):
            g = code[y, x]
            k = weak[y, x]
            margin = bit_margin * contrast[y, x]
            for b in range(b0, b1):
                f = FRAME_FIRST_BIT + 2 * b
                d = float(frames[f, y, x]) - float(frames[f + 1, y, x])
                g = g * 2
                k = k * 2
                if d > 0.0:
                    g = g + 1
                if wp.abs(d) < margin:
                    k = k + 1
            code[y, x] = g
            weak[y, x] = k
    for x in range(x0, x1):
        ok = contrast[y, x] >= min_contrast and weak[y, x] == 0
        band[y, x] = wp.where(ok, gray_to_binary(code[y, x], bits), -1)
        sector[y, x] = 0
    if sector_bits > 0:
        # sector code accumulates in ``sector``; a weak sector bit sets bit 30 of it
        base = FRAME_FIRST_BIT + 2 * bits
        for b0 in range(0, sector_bits, BIT_GROUP):
            b1 = wp.min(b0 + BIT_GROUP, sector_bits)
            for x in range(x0, x1):
                sg = sector[y, x]
                weakbit = sg & SECTOR_WEAK
                sg = sg & (SECTOR_WEAK - 1)
                margin = bit_margin * contrast[y, x]
                for b in range(b0, b1):
                    f = base + 2 * b
                    d = float(frames[f, y, x]) - float(frames[f + 1, y, x])
                    sg = sg * 2
                    if d > 0.0:
                        sg = sg + 1
                    if wp.abs(d) < margin:
                        weakbit = SECTOR_WEAK
                sector[y, x] = sg | weakbit
    for x in range(x0, x1):
        sg = sector[y, x]
        ok = sector_bits > 0 and contrast[y, x] >= min_contrast and (sg & SECTOR_WEAK) == 0
        sector[y, x] = wp.where(ok, gray_to_binary(sg, sector_bits), -1)


@wp.func
def lanes_gray_to_binary(g: wp.uint64):
    """:func:`gray_to_binary` of each 16-bit lane of g (codes of up to 16 bits)."""
    k = g ^ ((g >> wp.uint64(1)) & wp.uint64(0x7FFF7FFF7FFF7FFF))
    k = k ^ ((k >> wp.uint64(2)) & wp.uint64(0x3FFF3FFF3FFF3FFF))
    k = k ^ ((k >> wp.uint64(4)) & wp.uint64(0x0FFF0FFF0FFF0FFF))
    return k ^ ((k >> wp.uint64(8)) & LANES_LO)


@wp.func
def lanes_full(guard: wp.uint64):
    """0xFFFF in each 16-bit lane whose guard bit (15) is set in ``guard``, else 0."""
    return ((guard >> wp.uint64(15)) & LANES_ONE) * wp.uint64(0xFFFF)


@wp.func
def swar_thresholds_of(tlut: wp.array(dtype=wp.uint64), lc: wp.uint64):
    """Lower weak bounds (513 - m) of the four contrast lanes ``lc`` (512 + c)."""
    t = tlut[int(lc & wp.uint64(0x3FF))]
    t = t | (tlut[int((lc >> wp.uint64(16)) & wp.uint64(0x3FF))] << wp.uint64(16))
    t = t | (tlut[int((lc >> wp.uint64(32)) & wp.uint64(0x3FF))] << wp.uint64(32))
    return t | (tlut[int(lc >> wp.uint64(48))] << wp.uint64(48))


@wp.func
def swar_band(g: wp.uint64, k: wp.uint64, ok: wp.uint64, bits: int):
    """(code, weak, band + 1) lanes from the accumulated tests: g, k the band code
    and weak bits in the top bits of each lane, ok's guard bits the contrast test."""
    sh = wp.uint64(16 - bits)
    lm = wp.uint64(0xFFFF) >> sh
    lm = lm | (lm << wp.uint64(16))
    lm = lm | (lm << wp.uint64(32))
    g = (g >> sh) & lm
    k = (k >> sh) & lm
    kz = ~((k | LANES_GUARD) - LANES_ONE)  # guard kept: no weak bit
    return g, k, (lanes_gray_to_binary(g) + LANES_ONE) & lanes_full(ok & kz)


@wp.func
def swar_sector(s: wp.uint64, sw: wp.uint64, ok: wp.uint64, sector_bits: int):
    """Sector + 1 lanes (0 without sector bits) from the sector code s in the top
    bits of each lane, sw's guard bits any weak sector bit, ok's the contrast test."""
    if sector_bits == 0:
        return wp.uint64(0)
    ssh = wp.uint64(16 - sector_bits)
    sm = wp.uint64(0xFFFF) >> ssh
    sm = sm | (sm << wp.uint64(16))
    sm = sm | (sm << wp.uint64(32))
    return (lanes_gray_to_binary((s >> ssh) & sm) + LANES_ONE) & lanes_full(ok & ~sw)


@wp.func
def lane_pair(e: wp.uint64, o: wp.uint64, i: int, bias: wp.uint64):
    """The int32 pixel pair (2i, 2i + 1) as one little-endian word: lane i of the
    even and the odd word, each less ``bias`` (1: lane + 1 stored as 0 reads -1)."""
    sh = wp.uint64(16 * i)
    return (((e >> sh) & wp.uint64(0xFFFF)) - bias) & wp.uint64(0xFFFFFFFF) | (
        (((o >> sh) & wp.uint64(0xFFFF)) - bias) << wp.uint64(32))


@wp.kernel
def decode_gray_rings_swar_kernel(
    words: wp.array3d(dtype=wp.uint64),
    tlut: wp.array(dtype=wp.uint64),
    bits: int,
    sector_bits: int,
    cmin: wp.uint64,
    row0: int,
    chunk: int,
    code: wp.array2d(dtype=wp.uint64),
    weak: wp.array2d(dtype=wp.uint64),
    band: wp.array2d(dtype=wp.uint64),
    sector: wp.array2d(dtype=wp.uint64),
    contrast: wp.array2d(dtype=wp.float32),
):
    """The decode of :func:`decode_gray_rings_kernel` for 8-bit frames, eight
    pixels at a time. Same results, bit for bit. A thread covers ``chunk`` words
    of one row.

    Each uint64 word of a frame holds eight pixels, split into even and odd bytes,
    four 16-bit lanes each. A lane holds L = 512 + a - b (257..767, no borrow
    between lanes); with the guard bit 15 set, (L | guard) - T keeps the guard iff
    L >= T. Per bit the tests' guard bits are shifted in from the top of each
    lane, last bit first, so after all pairs a lane's top bits hold the code, first
    bit most significant. Band, sector and the masks are finished in the lanes
    (:func:`swar_band`, :func:`swar_sector`); only the stores are per pixel.

    words:    (n_frames, H, W / 8) uint64 (the 8-bit frames viewed as words), read.
    tlut:     (1024,) uint64: 513 - ceil(bit_margin * c) at 512 + c, read.
    cmin:     512 + the least integer contrast >= min_contrast, in each lane.
    code, weak, band, sector: (H, W / 2) uint64 (the (H, W) int32 labels viewed as
              pixel pairs, little-endian), written.
    contrast: (H, W) float32, written.

    Size: one thread per run of 64-bit words of a row: the lane arithmetic keeps eight pixels' codes, masks and
    contrasts in registers across all frame pairs, and band, sector and the masks are finished in the lanes
    before the per-pixel stores. Warp kernels take each array as its own argument.
    """
    tid = wp.tid()
    nw = words.shape[2]
    n_chunks = (nw + chunk - 1) / chunk
    y = row0 + tid / n_chunks
    j0 = (tid - (tid / n_chunks) * n_chunks) * chunk
    j1 = wp.min(j0 + chunk, nw)
    # Two passes over the run, the band frames and then the sector frames: a CPU
    # reads 16 and then 12 streams ~1.4x faster than 28 at once. Between them each
    # word's thresholds and contrast tests wait in its own four slots of the
    # sector row, which the second pass then overwrites.
    for j in range(j0, j1):
        wa = words[FRAME_WHITE, y, j]
        wb = words[FRAME_BLACK, y, j]
        ce = ((wa & LANES_LO) | LANES_512) - (wb & LANES_LO)
        co = (((wa >> wp.uint64(8)) & LANES_LO) | LANES_512) - ((wb >> wp.uint64(8)) & LANES_LO)
        # weak <=> |d| < m <=> 513 - m <= L <= 511 + m, m = ceil(bit_margin * c)
        # (|d| < x <=> |d| < ceil(x) for integer d): the lower bound per contrast
        # from a table, the upper one 1024 - lower
        tle = swar_thresholds_of(tlut, ce)
        tlo = swar_thresholds_of(tlut, co)
        the = (LANES_1024 - tle) | LANES_GUARD
        tho = (LANES_1024 - tlo) | LANES_GUARD
        ge = wp.uint64(0)
        go = wp.uint64(0)
        ke = wp.uint64(0)
        ko = wp.uint64(0)
        b = bits - 1
        while b >= 0:
            fa = words[FRAME_FIRST_BIT + 2 * b, y, j]
            fb = words[FRAME_FIRST_BIT + 2 * b + 1, y, j]
            le = ((fa & LANES_LO) | LANES_512) - (fb & LANES_LO)
            lo = (((fa >> wp.uint64(8)) & LANES_LO) | LANES_512) - ((fb >> wp.uint64(8)) & LANES_LO)
            lge = le | LANES_GUARD
            lgo = lo | LANES_GUARD
            ge = (ge >> wp.uint64(1)) | ((lge - LANES_513) & LANES_GUARD)
            go = (go >> wp.uint64(1)) | ((lgo - LANES_513) & LANES_GUARD)
            ke = (ke >> wp.uint64(1)) | ((lge - tle) & (the - le) & LANES_GUARD)
            ko = (ko >> wp.uint64(1)) | ((lgo - tlo) & (tho - lo) & LANES_GUARD)
            b = b - 1
        oke = (ce | LANES_GUARD) - cmin
        oko = (co | LANES_GUARD) - cmin
        ge, ke, be = swar_band(ge, ke, oke, bits)
        go, ko, bo = swar_band(go, ko, oko, bits)
        # pixels 2i, 2i + 1 are lane i of the even and odd words: one 64-bit store
        # writes both int32 labels (-1 where lane + 1 was stored as 0)
        for i in range(4):
            x = 8 * j + 2 * i
            sh = wp.uint64(16 * i)
            contrast[y, x] = float(int((ce >> sh) & wp.uint64(0xFFFF)) - 512)
            contrast[y, x + 1] = float(int((co >> sh) & wp.uint64(0xFFFF)) - 512)
            q = 4 * j + i
            code[y, q] = lane_pair(ge, go, i, wp.uint64(0))
            weak[y, q] = lane_pair(ke, ko, i, wp.uint64(0))
            band[y, q] = lane_pair(be, bo, i, wp.uint64(1))
        sector[y, 4 * j] = tle
        sector[y, 4 * j + 1] = tlo
        sector[y, 4 * j + 2] = oke
        sector[y, 4 * j + 3] = oko
    base = FRAME_FIRST_BIT + 2 * bits
    for j in range(j0, j1):
        tle = sector[y, 4 * j]
        tlo = sector[y, 4 * j + 1]
        oke = sector[y, 4 * j + 2]
        oko = sector[y, 4 * j + 3]
        the = (LANES_1024 - tle) | LANES_GUARD
        tho = (LANES_1024 - tlo) | LANES_GUARD
        se = wp.uint64(0)
        so = wp.uint64(0)
        swe = wp.uint64(0)
        swo = wp.uint64(0)
        b = sector_bits - 1
        while b >= 0:
            fa = words[base + 2 * b, y, j]
            fb = words[base + 2 * b + 1, y, j]
            le = ((fa & LANES_LO) | LANES_512) - (fb & LANES_LO)
            lo = (((fa >> wp.uint64(8)) & LANES_LO) | LANES_512) - ((fb >> wp.uint64(8)) & LANES_LO)
            lge = le | LANES_GUARD
            lgo = lo | LANES_GUARD
            se = (se >> wp.uint64(1)) | ((lge - LANES_513) & LANES_GUARD)
            so = (so >> wp.uint64(1)) | ((lgo - LANES_513) & LANES_GUARD)
            swe = swe | ((lge - tle) & (the - le))
            swo = swo | ((lgo - tlo) & (tho - lo))
            b = b - 1
        se = swar_sector(se, swe, oke, sector_bits)
        so = swar_sector(so, swo, oko, sector_bits)
        for i in range(4):
            sector[y, 4 * j + i] = lane_pair(se, so, i, wp.uint64(1))


# Frames are 8- or 16-bit: declare both overloads (so ahead-of-time CUDA builds
# compile them too).
for _t in (wp.uint8, wp.uint16):
    wp.overload(decode_gray_rings_kernel, {"frames": wp.array3d(dtype=_t)})


@wp.func
def finest_strong(contrast: wp.array2d(dtype=wp.float32), weak: wp.array2d(dtype=wp.int32), min_contrast: float,
                  y: int, x: int):
    """Lit, with the finest band bit strong."""
    return contrast[y, x] >= min_contrast and (weak[y, x] & 1) == 0


@wp.func
def finest_edge(code: wp.array2d(dtype=wp.int32), weak: wp.array2d(dtype=wp.int32),
                contrast: wp.array2d(dtype=wp.float32), min_contrast: float, y: int, x: int, dy: int, dx: int):
    """Pixel (y, x) lies between two opposite neighbours (y -+ dy, x -+ dx) that are lit, hold
    their finest bit strong and disagree on it: on one of that bit's own edges."""
    edge = int(0)
    if finest_strong(contrast, weak, min_contrast, y - dy, x - dx) and finest_strong(contrast, weak, min_contrast,
                                                                                    y + dy, x + dx):
        if (code[y - dy, x - dx] & 1) != (code[y + dy, x + dx] & 1):
            edge = 1
    return edge


@wp.kernel
def count_labels_kernel(
    code: wp.array2d(dtype=wp.int32),
    weak: wp.array2d(dtype=wp.int32),
    band: wp.array2d(dtype=wp.int32),
    contrast: wp.array2d(dtype=wp.float32),
    bits: int,
    min_contrast: float,
    i0: int,
    counts: wp.array2d(dtype=wp.int32),
):
    """Row i0 + tid of a decode's labels, counted: its decoded pixels (band >= 0), its lit ones
    (white - black >= ``min_contrast``, recorded levels) and of those the ones whose finest band bit
    is weak while the coarsest is strong, away from the finest bit's own edges (no two opposite
    neighbours, along a row, a column or a diagonal, lit with that bit strong and different): the
    pixels where the finest pattern barely modulates (``pipeline.codecs.gray_rings.low_modulation_pixels``
    states the same in NumPy).

    code, weak, band (H, W) int32, contrast (H, W) float32: read. counts (H, 3) int32: written at
    the row (decoded, lit, low).

    Size: the four label planes, the bits and the threshold, the span's i0, one array out."""
    y = i0 + wp.tid()
    h = code.shape[0]
    w = code.shape[1]
    coarse = int(1) << (bits - 1)
    decoded = int(0)
    lit = int(0)
    low = int(0)
    for x in range(w):
        if band[y, x] >= 0:
            decoded += 1
        if contrast[y, x] >= min_contrast:
            lit += 1
            wk = weak[y, x]
            if (wk & 1) != 0 and (wk & coarse) == 0:
                edge = int(0)
                if x >= 1 and x < w - 1:
                    edge = edge | finest_edge(code, weak, contrast, min_contrast, y, x, 0, 1)
                if y >= 1 and y < h - 1:
                    edge = edge | finest_edge(code, weak, contrast, min_contrast, y, x, 1, 0)
                    if x >= 1 and x < w - 1:
                        edge = edge | finest_edge(code, weak, contrast, min_contrast, y, x, 1, 1)
                        edge = edge | finest_edge(code, weak, contrast, min_contrast, y, x, 1, -1)
                if edge == 0:
                    low += 1
    counts[y, 0] = decoded
    counts[y, 1] = lit
    counts[y, 2] = low


# ----------------------------------------------------------------------------- host


def decode_gray_rings(
    frames: wp.array,
    *,
    bits: int,
    sector_bits: int = 0,
    settings: DecodeSettings = DecodeSettings(),
    threads: int | None = None,
) -> RingLabels:
    """Decode a gray-rings (+ sectors) frame stack, one pixel per thread.

    Args:
        frames: (n_frames, H, W) uint8 or uint16 Warp array in
            ``frame_names`` order (white, black, gray pairs, sector pairs, ...).
        bits: band Gray-code bits.
        sector_bits: sector Gray-code bits (0: none).
        settings: thresholds.
        threads: CPU threads (row slices); default: all cores.

    Returns:
        :class:`RingLabels` on the frames' device.
    """
    if not isinstance(frames, wp.array) or frames.ndim != 3:
        raise ValueError(f"decode_gray_rings: frames must be a 3D Warp array (n, H, W), got {type(frames).__name__}"
                         f" with ndim {getattr(frames, 'ndim', None)}")
    if frames.dtype not in (wp.uint8, wp.uint16):
        raise ValueError(f"decode_gray_rings: frames must be uint8 or uint16, got {frames.dtype.__name__}")
    if not 1 <= bits <= 16 or not 0 <= sector_bits <= 12:
        raise ValueError(f"decode_gray_rings: bits must be 1..16 and sector_bits 0..12, got {bits}, {sector_bits}")
    need = 2 + 2 * bits + 2 * sector_bits
    if frames.shape[0] < need:
        raise ValueError(f"decode_gray_rings: {bits} bits and {sector_bits} sector bits need {need} frames, got {frames.shape[0]}")
    n, h, w = frames.shape
    dev = frames.device
    scale = 257.0 if frames.dtype == wp.uint16 else 1.0
    out = RingLabels(
        code=wp.empty((h, w), dtype=wp.int32, device=dev),
        weak=wp.empty((h, w), dtype=wp.int32, device=dev),
        band=wp.empty((h, w), dtype=wp.int32, device=dev),
        sector=wp.empty((h, w), dtype=wp.int32, device=dev),
        contrast=wp.empty((h, w), dtype=wp.float32, device=dev),
    )
    if h * w == 0:
        return out
    outputs = [out.code, out.weak, out.band, out.sector, out.contrast]
    threads = default_threads() if threads is None else threads
    words = as_words(frames)
    if words is not None and bits <= 15:
        tlut, cmin = swar_thresholds(settings, dev)
        pairs = [wp.array(ptr=a.ptr, dtype=wp.uint64, shape=(h, w // 2), device=dev) for a in outputs[:4]]
        launch_rows(
            decode_gray_rings_swar_kernel, h, w // 8,
            lambda r0, chunk: [words, tlut, bits, sector_bits, cmin, r0, chunk],
            pairs + [out.contrast], dev, threads,
        )
        return out
    launch_rows(
        decode_gray_rings_kernel, h, w,
        lambda r0, chunk: [frames, bits, sector_bits, settings.min_contrast * scale, settings.bit_margin, r0, chunk],
        outputs, dev, threads,
    )
    return out


def swar_thresholds(settings: DecodeSettings, device) -> tuple[wp.array, int]:
    """The eight-pixel decode's thresholds for 8-bit frames, as integers.

    Returns (tlut, cmin): tlut (1024,) uint64 on ``device`` holds 513 - m at
    512 + c for each contrast c in -255..255, m = ceil(bit_margin * c) clamped to
    0..256, computed in float32 as the per-pixel kernel does; cmin is 512 + the
    least integer contrast >= min_contrast (clamped to 256..768) in each 16-bit lane.
    """
    c = np.arange(-255, 256, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        m = np.minimum(np.ceil(np.maximum(np.float32(settings.bit_margin) * c, np.float32(0.0))), 256.0)
    lut = np.full(1024, 513, dtype=np.uint64)
    lut[512 - 255:512 + 256] = 513 - np.nan_to_num(m, nan=0.0).astype(np.int64)
    t = float(np.float32(settings.min_contrast))
    lo = 256 if math.isnan(t) else int(min(max(math.ceil(t) if math.isfinite(t) else math.copysign(256, t), -256), 256))
    cmin = (512 + lo) * 0x0001000100010001
    return wp.array(lut, dtype=wp.uint64, device=device), cmin


def as_words(frames: wp.array) -> wp.array | None:
    """The 8-bit frame stack viewed as uint64 words (eight pixels each), or None
    where that view does not exist (16-bit frames, a width not a multiple of 8,
    a strided array, a first pixel off an 8-byte boundary: memory that Warp did
    not allocate, where a CUDA kernel's 64-bit loads would fault)."""
    n, h, w = frames.shape
    if frames.dtype != wp.uint8 or w % 8 or not frames.is_contiguous or h * w == 0 or frames.ptr % 8:
        return None
    words = wp.array(ptr=frames.ptr, dtype=wp.uint64, shape=(n, h, w // 8), device=frames.device)
    words._ref = frames  # keep the owner alive as long as the view
    return words


def count_labels(labels: RingLabels, *, bits: int, min_contrast: float, threads: int | None = None) -> tuple[int, int, int]:
    """(decoded, lit, low) pixels of a decode (:func:`count_labels_kernel`): one row of counts a
    thread, summed from an (H, 3) read (the counts, not the planes).

    Args:
        labels: the decode of ``bits`` band bits.
        bits: band Gray-code bits.
        min_contrast: white - black a pixel needs to count as lit (the frames' recorded levels).
        threads: CPU threads; default all cores.
    """
    h, w = labels.code.shape
    if h * w == 0:
        return 0, 0, 0
    dev = labels.code.device
    counts = wp.empty((h, 3), dtype=wp.int32, device=dev)
    launch_spans(count_labels_kernel, h,
                 lambda i0: [labels.code, labels.weak, labels.band, labels.contrast, int(bits), float(min_contrast), i0],
                 [counts], dev, default_threads() if threads is None else threads, min_span=64)
    total = counts.numpy().sum(axis=0, dtype=np.int64)
    return int(total[0]), int(total[1]), int(total[2])
