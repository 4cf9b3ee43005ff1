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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import warp as wp

from ringscan.kernels.launch import default_threads, launch_rows, row_run

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

__all__ = ["DecodeSettings", "RingLabels", "decode_gray_rings"]


@dataclass(frozen=True)
class DecodeSettings:
    """Thresholds of the per-pixel decoder."""

    min_contrast: float = 12.0
    """Least white - black difference, in 8-bit grey levels (scaled by 257 for
    16-bit frames), for a pixel to be decoded at all. Shadowed and unlit pixels
    fall below it."""
    bit_margin: float = 0.12
    """A bit is strong when |frame - inverse| >= bit_margin * (white - black). A weak
    bit is not trusted: the pixel keeps no band label (edge sampling still uses it
    as the one bit that flips between two strong neighbours)."""


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
def lane16(v: wp.uint64, i: int):
    """The i-th 16-bit lane of v."""
    return int((v >> wp.uint64(16 * i)) & wp.uint64(0xFFFF))


@wp.func
def byte_of(v: wp.uint64, i: int):
    return int((v >> wp.uint64(8 * i)) & wp.uint64(0xFF))


@wp.func
def swar_pair(fa: wp.uint64, fb: wp.uint64, tlo: wp.uint64, thi: wp.uint64, odd: int):
    """For four pixels (even or odd bytes) of a frame/inverse word pair:
    (a > b, |a - b| < m), each as four 16-bit lanes holding 0 or 1.

    Each lane holds L = 512 + a - b (257..767, no borrow between lanes); with a
    guard bit at 15, (L | guard) - T keeps the guard iff L >= T.
    """
    sh = wp.uint64(8 * odd)
    la = ((fa >> sh) & LANES_LO) | LANES_512
    l = la - ((fb >> sh) & LANES_LO)
    gt = (((l | LANES_GUARD) - LANES_513) >> wp.uint64(15)) & LANES_ONE
    wk = ((((l | LANES_GUARD) - tlo) & ((thi | LANES_GUARD) - l)) >> wp.uint64(15)) & LANES_ONE
    return gt, wk


@wp.kernel
def decode_gray_rings_swar_kernel(
    words: wp.array3d(dtype=wp.uint64),
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
    """The decode of :func:`decode_gray_rings_kernel` for 8-bit frames, eight
    pixels at a time: each uint64 word of a frame holds eight pixels, and the
    comparisons frame > inverse and |frame - inverse| < margin run on four 16-bit
    lanes at once. Same results, bit for bit. A thread covers ``chunk`` words of
    one row.

    words:    (n_frames, H, W / 8) uint64 (the 8-bit frames viewed as words), read.
    code, weak, band, sector: (H, W) int32, written.
    contrast: (H, W) float32, written.
    """
    tid = wp.tid()
    nw = words.shape[2]
    n_chunks = (nw + chunk - 1) / chunk
    y = row0 + tid / n_chunks
    j0 = (tid - (tid / n_chunks) * n_chunks) * chunk
    for j in range(j0, wp.min(j0 + chunk, nw)):
        wa = words[FRAME_WHITE, y, j]
        wb = words[FRAME_BLACK, y, j]
        # per-pixel margins as lane thresholds: weak <=> 513 - m <= L <= 511 + m,
        # m = ceil(bit_margin * c) (|d| < x <=> |d| < ceil(x) for integer d)
        tlo_e = wp.uint64(0)
        thi_e = wp.uint64(0)
        tlo_o = wp.uint64(0)
        thi_o = wp.uint64(0)
        for i in range(8):
            c = float(byte_of(wa, i) - byte_of(wb, i))
            contrast[y, 8 * j + i] = c
            m = wp.min(int(wp.ceil(wp.max(bit_margin * c, 0.0))), 256)
            sh = wp.uint64(16 * (i / 2))
            if i % 2 == 0:
                tlo_e = tlo_e | (wp.uint64(513 - m) << sh)
                thi_e = thi_e | (wp.uint64(511 + m) << sh)
            else:
                tlo_o = tlo_o | (wp.uint64(513 - m) << sh)
                thi_o = thi_o | (wp.uint64(511 + m) << sh)
        ge = wp.uint64(0)
        go = wp.uint64(0)
        ke = wp.uint64(0)
        ko = wp.uint64(0)
        for b in range(bits):
            fa = words[FRAME_FIRST_BIT + 2 * b, y, j]
            fb = words[FRAME_FIRST_BIT + 2 * b + 1, y, j]
            gte, wke = swar_pair(fa, fb, tlo_e, thi_e, 0)
            gto, wko = swar_pair(fa, fb, tlo_o, thi_o, 1)
            ge = (ge << wp.uint64(1)) | gte
            ke = (ke << wp.uint64(1)) | wke
            go = (go << wp.uint64(1)) | gto
            ko = (ko << wp.uint64(1)) | wko
        se = wp.uint64(0)
        so = wp.uint64(0)
        swe = wp.uint64(0)
        swo = wp.uint64(0)
        base = FRAME_FIRST_BIT + 2 * bits
        for b in range(sector_bits):
            fa = words[base + 2 * b, y, j]
            fb = words[base + 2 * b + 1, y, j]
            gte, wke = swar_pair(fa, fb, tlo_e, thi_e, 0)
            gto, wko = swar_pair(fa, fb, tlo_o, thi_o, 1)
            se = (se << wp.uint64(1)) | gte
            swe = swe | wke
            so = (so << wp.uint64(1)) | gto
            swo = swo | wko
        for i in range(8):
            x = 8 * j + i
            k = i / 2
            g = wp.where(i % 2 == 0, lane16(ge, k), lane16(go, k))
            wk = wp.where(i % 2 == 0, lane16(ke, k), lane16(ko, k))
            code[y, x] = g
            weak[y, x] = wk
            ok = contrast[y, x] >= min_contrast
            band[y, x] = wp.where(ok and wk == 0, gray_to_binary(g, bits), -1)
            sg = wp.where(i % 2 == 0, lane16(se, k), lane16(so, k))
            sw = wp.where(i % 2 == 0, lane16(swe, k), lane16(swo, k))
            sector[y, x] = wp.where(sector_bits > 0 and ok and sw == 0, gray_to_binary(sg, sector_bits), -1)


# Frames are 8- or 16-bit: declare both overloads (so ahead-of-time CUDA builds
# compile them too).
for _t in (wp.uint8, wp.uint16):
    wp.overload(decode_gray_rings_kernel, {"frames": wp.array3d(dtype=_t)})


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
    if words is not None and bits <= 16 and sector_bits <= 16:
        launch_rows(
            decode_gray_rings_swar_kernel, h, w // 8,
            lambda r0, chunk: [words, bits, sector_bits, settings.min_contrast, settings.bit_margin, r0, chunk],
            outputs, dev, threads,
        )
        return out
    launch_rows(
        decode_gray_rings_kernel, h, w,
        lambda r0, chunk: [frames, bits, sector_bits, settings.min_contrast * scale, settings.bit_margin, r0, chunk],
        outputs, dev, threads,
    )
    return out


def as_words(frames: wp.array) -> wp.array | None:
    """The 8-bit frame stack viewed as uint64 words (eight pixels each), or None
    where that view does not exist (16-bit frames, a width not a multiple of 8,
    a strided array)."""
    n, h, w = frames.shape
    if frames.dtype != wp.uint8 or w % 8 or not frames.is_contiguous or h * w == 0:
        return None
    words = wp.array(ptr=frames.ptr, dtype=wp.uint64, shape=(n, h, w // 8), device=frames.device)
    words._ref = frames  # keep the owner alive as long as the view
    return words
