"""The sub-pixel positions of a dense column/row Gray-code map's pixels between the code boundaries along a
camera line (what ``ringscan import`` samples a decoded capture with, ``pipeline.calibrate.graycode``):
:func:`subpixel_lines` walks whole lines; :func:`subpixel_points` searches around each of a few pixels (the
coarser levels, where a handful are left to place), with the walk's numbers.

The NumPy construction the walk replaced is kept in tests/kernels/test_graycode_map.py: the kernels give its
numbers to the bit."""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
import warp as wp

from ringscan.kernels.launch import cpu_pool
from ringscan.kernels.runtime import init_warp

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["subpixel_lines", "subpixel_points"]

_first_launch = threading.Lock()
_loaded: set = set()
"""(kernel, device, frame dtype) this module's kernels have run with: a first launch (which builds or loads the
module; Warp's module loading is not thread-safe) is made under the lock, so that an import's cameras may decode
on threads."""


@wp.func
def line_pixel(axis: int, line: int, i: int):
    """(y, x) of pixel i of a line: a row (axis 1: i across) or a column (axis 0: i down)."""
    if axis == 1:
        return line, i
    return i, line


@wp.func
def gray_flip_bit(a: int, b: int, bits: int):
    """Index (0 = MSB) of the one Gray bit that differs between codes a and b (|a - b| = 1)."""
    x = (a ^ (a >> 1)) ^ (b ^ (b >> 1))
    x = wp.max(x, 1)
    high = int(0)
    while x > 1:
        x = x >> 1
        high += 1
    return bits - 1 - high


@wp.func
def pair_level(pairs: wp.array4d(dtype=Any), b: int, f: int, y: int, x: int, scale: wp.float32):
    """Frame f (0 pattern, 1 inverse) of bit b at (y, x) in 8-bit levels: its value as float32 times scale."""
    return wp.float32(pairs[b, f, y, x]) * scale


@wp.func
def code_boundary(code: wp.array2d(dtype=wp.int32), valid: wp.array2d(dtype=wp.uint8),
                  pairs: wp.array4d(dtype=Any), scale: wp.float32, bits: int, axis: int, line: int, k: int):
    """The boundary between pixels k and k + 1 of a line, where both decoded and their codes
    are one apart: (is one, its position in line px: k + the fraction where the flipping
    bit's pattern - inverse crosses 0, the two codes' mean)."""
    y0, x0 = line_pixel(axis, line, k)
    y1, x1 = line_pixel(axis, line, k + 1)
    if valid[y0, x0] == wp.uint8(0) or valid[y1, x1] == wp.uint8(0):
        return False, wp.float64(0.0), wp.float64(0.0)
    c0 = code[y0, x0]
    c1 = code[y1, x1]
    if wp.abs(c1 - c0) != 1:
        return False, wp.float64(0.0), wp.float64(0.0)
    b = gray_flip_bit(c0, c1, bits)
    d0 = pair_level(pairs, b, 0, y0, x0, scale) - pair_level(pairs, b, 1, y0, x0, scale)
    d1 = pair_level(pairs, b, 0, y1, x1, scale) - pair_level(pairs, b, 1, y1, x1, scale)
    den = d0 - d1
    frac = wp.float32(0.5)
    if wp.abs(den) > wp.float32(1.0e-6):
        frac = d0 / den
    frac = wp.clamp(frac, wp.float32(0.0), wp.float32(1.0))
    return True, wp.float64(k) + wp.float64(frac), wp.float64(0.5) * (wp.float64(c0) + wp.float64(c1))


@wp.kernel
def subpixel_lines_kernel(
    code: wp.array2d(dtype=wp.int32),
    valid: wp.array2d(dtype=wp.uint8),
    pairs: wp.array4d(dtype=Any),
    lines: wp.array(dtype=wp.int32),
    scale: wp.float32,
    bits: int,
    axis: int,
    max_span: wp.float64,
    out: wp.array2d(dtype=wp.float64),
    ok: wp.array2d(dtype=wp.uint8),
):
    """One line (lines[tid]) of :func:`subpixel_lines`: each pixel between the last code boundary before it and the
    first after it, in one walk (the boundary after a pixel is found once and becomes the one before the next).

    code (H, W) int32, valid (H, W) uint8, pairs (>= bits, 2, H, W) uint8, uint16 or float32 (levels:
    value * scale), lines (L,) int32 (rows for axis 1, columns for axis 0): read. out (H, W) float64,
    ok (H, W) uint8: written on the line.

    Size: a Warp kernel takes each array as its own argument (five in, two out); the
    scalars are the pattern's bits, the line's axis and span and the levels' scale."""
    line = lines[wp.tid()]
    n = code.shape[1]
    if axis == 0:
        n = code.shape[0]
    has_l = bool(False)
    pl = wp.float64(0.0)
    vl = wp.float64(0.0)
    kr = int(-1)  # the first boundary at or after the pixel; n: none
    pr = wp.float64(0.0)
    vr = wp.float64(0.0)
    for x in range(n):
        if kr < x:
            kr = n
            k = x
            while k < n - 1:
                is_b, pk, vk = code_boundary(code, valid, pairs, scale, bits, axis, line, k)
                if is_b:
                    kr = k
                    pr = pk
                    vr = vk
                    break
                k += 1
        y, xx = line_pixel(axis, line, x)
        c = code[y, xx]
        res = wp.float64(c)
        good = wp.uint8(0)
        if has_l and kr < n - 1 and valid[y, xx] != wp.uint8(0):
            span = pr - pl
            if (wp.abs(vr - vl) == wp.float64(1.0) and span > wp.float64(0.0) and span <= max_span
                    and wp.abs(wp.float64(c) - wp.float64(0.5) * (vl + vr)) < wp.float64(1.0e-9)):
                res = vl + (wp.float64(x) - pl) / span * (vr - vl)
                good = wp.uint8(1)
        out[y, xx] = res
        ok[y, xx] = good
        if kr == x:  # the boundary after this pixel is the one before the next
            has_l = True
            pl = pr
            vl = vr


@wp.kernel
def subpixel_points_kernel(
    code: wp.array2d(dtype=wp.int32),
    valid: wp.array2d(dtype=wp.uint8),
    pairs: wp.array4d(dtype=Any),
    pixels: wp.array(dtype=wp.int32),
    scale: wp.float32,
    bits: int,
    axis: int,
    max_span: wp.float64,
    out: wp.array(dtype=wp.float64),
    ok: wp.array(dtype=wp.uint8),
):
    """One pixel (pixels[tid], y * W + x) of :func:`subpixel_points`: the nearest boundary before it and the
    nearest at or after it on its line, each looked for no farther than a span of ``max_span`` allows (a
    boundary beyond lies more than ``max_span`` from the other: the walk rejects it too).

    code (H, W) int32, valid (H, W) uint8, pairs (>= bits, 2, H, W), pixels (M,) int32: read. out (M,) float64,
    ok (M,) uint8: written.

    Size: a Warp kernel takes each array as its own argument (four in, two out); the scalars as
    :func:`subpixel_lines_kernel`'s."""
    i = wp.tid()
    w = code.shape[1]
    y = pixels[i] / w
    x = pixels[i] - y * w
    line = y
    at = x
    n = w
    if axis == 0:
        line = x
        at = y
        n = code.shape[0]
    c = code[y, x]
    res = wp.float64(c)
    good = wp.uint8(0)
    reach = int(wp.floor(max_span))
    if valid[y, x] != wp.uint8(0):
        kr = int(-1)
        pr = wp.float64(0.0)
        vr = wp.float64(0.0)
        k = at
        while kr < 0 and k <= wp.min(n - 2, at + reach):
            is_b, pk, vk = code_boundary(code, valid, pairs, scale, bits, axis, line, k)
            if is_b:
                kr = k
                pr = pk
                vr = vk
            k += 1
        kl = int(-1)
        pl = wp.float64(0.0)
        vl = wp.float64(0.0)
        k = at - 1
        while kl < 0 and kr >= 0 and k >= wp.max(0, at - 1 - reach):
            is_b, pk, vk = code_boundary(code, valid, pairs, scale, bits, axis, line, k)
            if is_b:
                kl = k
                pl = pk
                vl = vk
            k -= 1
        if kl >= 0:
            span = pr - pl
            if (wp.abs(vr - vl) == wp.float64(1.0) and span > wp.float64(0.0) and span <= max_span
                    and wp.abs(wp.float64(c) - wp.float64(0.5) * (vl + vr)) < wp.float64(1.0e-9)):
                res = vl + (wp.float64(at) - pl) / span * (vr - vl)
                good = wp.uint8(1)
    out[i] = res
    ok[i] = good



FRAME_TYPES = (wp.uint8, wp.uint16, wp.float32)
"""The dtypes a capture's frames are kept in (as read: 8- or 16-bit; float32 levels where mixed)."""
for _t in FRAME_TYPES:  # each kernel's overloads made up front (and compiled ahead for CUDA by the tests)
    wp.overload(subpixel_lines_kernel, {"pairs": wp.array4d(dtype=_t)})
    wp.overload(subpixel_points_kernel, {"pairs": wp.array4d(dtype=_t)})


def _launch(kernel, dim, inputs, outputs, frames_dtype) -> None:
    """One CPU launch; the first of a kernel and frame dtype under the module's lock (see ``_loaded``)."""
    key = (kernel.key, frames_dtype.str)
    if key in _loaded:
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device="cpu")
    else:
        with _first_launch:
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device="cpu")
            _loaded.add(key)
    wp.synchronize_device("cpu")


def _frames(pairs: np.ndarray) -> np.ndarray:
    """A pattern/inverse stack as a kernel reads it: uint8, uint16 or float32, C-contiguous."""
    if pairs.dtype not in (np.uint8, np.uint16, np.float32):
        pairs = pairs.astype(np.float32)
    return np.ascontiguousarray(pairs)


def _cpu(a: np.ndarray, dtype) -> wp.array:
    return wp.array(a, dtype=dtype, device="cpu", copy=False)


def subpixel_lines(code: np.ndarray, valid: np.ndarray, pairs: np.ndarray, *, bits: int, axis: int,
                   max_span: float, scale: float = 1.0, lines: np.ndarray | None = None,
                   threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel projector coordinate of a dense Gray-code map along camera ``axis`` (1: across, 0: down).

    A boundary lies between neighbours that both decoded and whose codes are one apart, at the
    fraction where the one Gray bit that flips there (of ``bits``, MSB first) crosses its
    inverse; a decoded pixel between two boundaries whose codes step by one, at most
    ``max_span`` line px apart, with its own code between them, takes the linear
    interpolation of the two boundaries' codes at its position.

    Args:
        code: (H, W) int32 codes (any value where not valid).
        valid: (H, W) bool.
        pairs: (>= bits, 2, H, W) patterns and inverses, MSB first (the first ``bits`` are read): uint8,
            uint16 or float32 values, their levels ``float32(value) * scale`` (a frame stack as read).
        bits, axis, max_span: as above.
        lines: the rows (axis 1) or columns (axis 0) to walk (None: all); the others' ``out`` and ``ok``
            are left as they were allocated (``ok`` False, ``out`` NaN).
        threads: CPU threads the lines are shared out among (each line's numbers are its own).

    Size: the map's three arrays and the walk's own settings (bits, axis, span, the levels' scale), the lines
    to walk and the threads, each keyword-only.

    Returns:
        (out (H, W) float64: the interpolated coordinate, the code itself where none;
        ok (H, W) bool: interpolated).
    """
    init_warp()
    code = np.ascontiguousarray(code, np.int32)
    valid = np.ascontiguousarray(valid, bool).view(np.uint8)
    pairs = _frames(pairs)
    H, W = code.shape
    if valid.shape != (H, W) or pairs.ndim != 4 or pairs.shape[1:] != (2, H, W) or not (0 < bits <= pairs.shape[0]):
        raise ValueError(f"subpixel_lines: code {code.shape}, valid {valid.shape}, pairs {pairs.shape}, "
                         f"bits {bits} do not agree")
    n_lines = H if axis == 1 else W
    if lines is None:
        out, ok = np.empty((H, W), np.float64), np.empty((H, W), np.uint8)
        lines = np.arange(n_lines, dtype=np.int32)
    else:
        out, ok = np.full((H, W), np.nan), np.zeros((H, W), np.uint8)
        lines = np.ascontiguousarray(lines, np.int32)
        if lines.ndim != 1 or (lines.size and (lines.min() < 0 or lines.max() >= n_lines)):
            raise ValueError(f"subpixel_lines: lines must be 1-D indices below {n_lines}")
    if H and W and lines.size:
        arrays = [_cpu(code, wp.int32), _cpu(valid, wp.uint8), _cpu(pairs, wp.dtype_from_numpy(pairs.dtype))]
        outputs = [_cpu(out, wp.float64), _cpu(ok, wp.uint8)]

        def walk(part: np.ndarray) -> None:
            _launch(subpixel_lines_kernel, part.size,
                    arrays + [_cpu(part, wp.int32), wp.float32(scale), int(bits), int(axis), wp.float64(max_span)],
                    outputs, pairs.dtype)

        parts = [p for p in np.array_split(lines, max(1, min(int(threads), lines.size // 64))) if p.size]
        walk(parts[0])  # (the first on this thread: it loads the module under the lock)
        if len(parts) > 1:
            list(cpu_pool(len(parts) - 1).map(walk, parts[1:]))
    return out, ok.view(bool)


def subpixel_points(code: np.ndarray, valid: np.ndarray, pairs: np.ndarray, pixels: np.ndarray, *, bits: int,
                    axis: int, max_span: float, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`subpixel_lines`' numbers at a few pixels: (out (M,) float64, ok (M,) bool) of ``pixels`` (M,)
    linear indices y * W + x, to the bit, each from a search no wider than ``max_span`` on either side
    (the coarser levels of ``graycode._levels``, where a whole line's walk would place a handful)."""
    init_warp()
    code = np.ascontiguousarray(code, np.int32)
    valid = np.ascontiguousarray(valid, bool).view(np.uint8)
    pairs = _frames(pairs)
    pixels = np.ascontiguousarray(pixels, np.int32)
    H, W = code.shape
    if valid.shape != (H, W) or pairs.ndim != 4 or pairs.shape[1:] != (2, H, W) or not (0 < bits <= pairs.shape[0]):
        raise ValueError(f"subpixel_points: code {code.shape}, valid {valid.shape}, pairs {pairs.shape}, "
                         f"bits {bits} do not agree")
    if pixels.ndim != 1 or (pixels.size and (pixels.min() < 0 or pixels.max() >= H * W)):
        raise ValueError(f"subpixel_points: pixels must be 1-D indices below {H * W}")
    if math.isnan(max_span):  # no span passes (as in the walk)
        return code.reshape(-1)[pixels].astype(np.float64), np.zeros(pixels.size, bool)
    max_span = min(float(max_span), float(max(H, W)))  # (no span is longer than a line: the search's bound)
    out, ok = np.empty(pixels.size, np.float64), np.empty(pixels.size, np.uint8)
    if pixels.size:
        _launch(subpixel_points_kernel, pixels.size,
                [_cpu(code, wp.int32), _cpu(valid, wp.uint8), _cpu(pairs, wp.dtype_from_numpy(pairs.dtype)),
                 _cpu(pixels, wp.int32), wp.float32(scale), int(bits), int(axis), wp.float64(max_span)],
                [_cpu(out, wp.float64), _cpu(ok, wp.uint8)], pairs.dtype)
    return out, ok.view(bool)
