"""Column/row Gray-code captures (OpenCV's structured-light layout) -> projector coordinates.

A capture is the frames of a camera (or of two cameras) watching a projector of
W_p x H_p pixels show the binary-reflected Gray code of each column
(``ceil(log2 W_p)`` bits, most significant first) and each row (``ceil(log2 H_p)``
bits), every pattern followed by its inverse, plus a white and a black frame.
Its frames are listed by :mod:`~ringscan.pipeline.calibrate.capture_files` (the ways of naming
them) and read by :mod:`~ringscan.pipeline.calibrate.capture_reader`.


Two orders of white/black are read (``LAYOUTS``):

- ``opencv-graycode``: column pairs, row pairs, then white, black: the files of
  OpenCV's ``GrayCodePattern.generate`` followed by ``getImagesForShadowMasks``, as in
  ../shared/data/procam (``graycode_40`` white, ``graycode_41`` black);
- ``opencv-graycode-wb-first``: white, black, then the column and row pairs
  (the layout of docs/design.md §7).

Decoding (:func:`decode_graycode`): a pixel is decoded where white - black
>= ``min_contrast`` (or, dimmer, >= ``dim_contrast`` with at most two bits weak)
and every pattern differs from its inverse by at least ``min_bit_contrast``;
bit = pattern > inverse; Gray -> binary gives the integer
column c and row r (the plain way: the projector pixel (c, r)).

Sub-pixel (the ringscan way, :func:`subpixel_map`): along the camera axis on which
a code changes fastest, each step c -> c +- 1 between neighbouring camera pixels is
a projector pixel boundary (u_p = c +- 0.5); the one bit that flips there crosses
its inverse, and the zero of (pattern - inverse), interpolated linearly between
the two pixels, places the boundary to sub-pixel precision in the camera. Each
pixel's projector coordinate is then interpolated linearly between the boundaries
on either side of it. Pixels without two consecutive boundaries around them
(code errors, depth edges) keep their integer code and are flagged. Where a camera
pixel spans more than one projector pixel (:func:`resolution_levels`), or the finest
bits barely modulate (:func:`bit_clearance`), the boundaries are those of the blocks
of 2**k projector pixels whose bits the pixel can trust.
"""

from __future__ import annotations

import logging
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.formats.patterns import gray_decode

__all__ = ["LAYOUTS", "GrayCodeSettings", "GrayCodeCapture", "Decoded", "graycode_bits", "decode_graycode",
           "subpixel_map"]

log = logging.getLogger(__name__)

LAYOUTS = ("opencv-graycode", "opencv-graycode-wb-first")
"""Known capture layouts (see the module docstring)."""

DIM_BIT_FRACTION = 0.4
"""A dim pixel's bit is weak below this fraction of its white - black (``GrayCodeSettings.dim_contrast``)."""
DIM_MAX_WEAK = 2
"""Most weak bits of a dim pixel that is decoded: on a projector pixel's corner the column and the row bit that
flip there are weak by nature; more mean the patterns hardly reach the pixel."""

CLEAR_NOISE_SIGMAS = 4.0
"""A bit stands clear of the camera's noise where its modulation |pattern - inverse| reaches this many
standard deviations of a pattern - inverse difference (the noise measured from the capture itself)."""
CLEAR_CONTRAST_FRACTION = 0.1
"""... and this share of the pixel's white - black: a bit that carries less of the pixel's light is at the
mercy of anything else the pixel sees (stray light, a JPEG's ringing, a gamma's harmonics)."""
MAX_COARSE_BITS = 3
"""Finest bits a pixel may leave untrusted and still get a sub-pixel position from the coarser ones (the
boundaries of blocks of up to 2**3 = 8 projector pixels); more and it is dropped as ``low_modulation``."""
RESOLUTION_REACH = 4
"""Camera px on either side of a pixel over which :func:`resolution_levels` reads how many projector px a camera
px spans (the code's change over 2 x 4 px: a misread finest bit moves it by ~2 of ~8 and more)."""
RESOLUTION_WINDOW = 31
"""Side (camera px) of the square whose median gives a pixel its resolution level: the code's slope is a property
of the surface and the rig, smooth but for depth edges and misreads, which the median sets aside (a depth edge's
band of wide steps, 2 x 4 px across, is under half of any such square)."""
RESOLUTION_MAX_LEVEL = 4
"""Most bits a camera may leave unresolved (a camera px spanning up to 16 projector px; a 4K projector on a VGA
camera spans 6): a code that runs faster is read as one that does not resolve more."""
RESOLUTION_GRID = 6
"""The code's slope is read at every 6th pixel along both axes (a 36th of the work; the level is that smooth; the
window then 5 x 5 grid points, OpenCV's fast median)."""
MIN_WIDE_SPACING = 2.0
"""Camera px a projector px spans beyond which a bit's clearance window is its half stripe in camera px (below,
the window of the codes' steps, as it was: the same decode for every camera that resolves the projector)."""
MAX_CLEAR_RADIUS = 64
"""Largest half-side (camera px) of the window in which a bit's modulation is judged."""
SPAN_PROJECTOR_PX = 4.0
"""Projector px apart that two boundaries may lie and still be interpolated between, where that is more camera
px than ``GrayCodeSettings.max_span_px`` (a camera far finer than the projector: 15 camera px a projector px)."""
POINT_SEARCH_COST = 16
"""Line pixels of a walk that a search around one pixel costs, about (a coarser level places its pixels by
searches where fewer than this share of their lines' pixels: 0.58 us a search, 0.04 us a walked pixel at
level 2 of a capture defocused by 3.5 projector px, on one CPU core)."""
LOW_MODULATION_WARN_SHARE = 0.2
"""A view whose finest bit is untrusted at more than this share of its decoded pixels gets a warning."""


@dataclass(frozen=True)
class GrayCodeSettings:
    """Decoding settings."""

    min_contrast: float = 20.0
    """Least white - black (8-bit levels) of a pixel decoded on contrast alone."""
    dim_contrast: float = 10.0
    """Least white - black (8-bit levels) of a dim pixel (below ``min_contrast``),
    decoded only where the patterns visibly modulate it: at most ``DIM_MAX_WEAK``
    of its bits differ from their inverse by less than ``DIM_BIT_FRACTION`` of its
    contrast (the flipping column and row bits of a pixel on a projector pixel's
    corner). On the virtual rig (camera noise 1.5) the dim parts of an object
    (grazing light) pass and read right; on real captures the pixels between 10
    and 20 levels whose white - black comes from stray light (the procam board's
    black squares beside white ones) have most bits weak and stay out (docs/calibration.md).
    Set it to ``min_contrast`` or above to decode on contrast alone."""
    min_bit_contrast: float = 0.0
    """Least |pattern - inverse| (8-bit levels) of every bit of a decoded pixel. 0 by
    default: on a projector pixel boundary the bit that flips there has no contrast
    by nature, and the sub-pixel stage checks codes against their neighbours."""
    max_span_px: float = 12.0
    """Boundaries farther apart than this (camera px) are not interpolated between."""


@dataclass
class GrayCodeCapture:
    """The frames of one capture, sorted into white, black and pattern/inverse pairs."""

    folder: Path
    """The capture folder."""
    white: np.ndarray
    """(H, W) float32 white frame (8-bit levels)."""
    black: np.ndarray
    """(H, W) float32 black frame."""
    col_pairs: np.ndarray
    """(col_bits, 2, H, W) column patterns and inverses, MSB first, as read (uint8 or uint16) or float32:
    their levels are ``float32(value) * scale`` (:func:`pair_diff`)."""
    row_pairs: np.ndarray
    """(row_bits, 2, H, W) row patterns and inverses, MSB first, as ``col_pairs``."""
    projector: tuple[int, int]
    """Projector (width, height)."""
    scale: float = 1.0
    """8-bit levels of one unit of the pairs' values: 1 (8-bit or float frames), 1 / 257 (16-bit frames).
    The frames are kept as read, a quarter of float32's memory and of the decode's reads."""


def pair_diff(pairs: np.ndarray, b: int, scale: float = 1.0, out: np.ndarray | None = None) -> np.ndarray:
    """(H, W) float32 pattern - inverse of bit ``b`` of ``pairs`` in 8-bit levels: each frame's value as
    float32 times ``scale`` (rounded to float32), then the difference: the figures a float32 copy of the
    frames scaled as they were read gives, to the bit."""
    p, inv = pairs[b, 0], pairs[b, 1]
    if scale == 1.0:
        return np.subtract(p, inv, out=out, dtype=np.float32)
    s = np.float32(scale)
    a = np.multiply(p, s, dtype=np.float32)
    return np.subtract(a, np.multiply(inv, s, dtype=np.float32), out=out if out is not None else a)


@dataclass
class Decoded:
    """A decoded capture."""

    col: np.ndarray
    """(H, W) int32 integer projector column (-1 where not decoded)."""
    row: np.ndarray
    """(H, W) int32 integer projector row (-1 where not decoded)."""
    valid: np.ndarray
    """(H, W) bool: decoded (enough contrast, every bit clear, code inside the projector)."""
    contrast: np.ndarray
    """(H, W) float32 white - black."""
    u: np.ndarray | None = None
    """(H, W) float64 sub-pixel projector u (NaN where not decoded)."""
    v: np.ndarray | None = None
    """(H, W) float64 sub-pixel projector v."""
    subpixel: np.ndarray | None = None
    """(H, W) bool: both u and v were interpolated between boundaries (else integer codes)."""
    coarse: np.ndarray | None = None
    """(H, W, 2) int8: finest column and row bits left untrusted at each pixel (0: every bit stands clear of
    the noise; ``MAX_COARSE_BITS`` at most, see :func:`bit_clearance`)."""
    low_modulation: np.ndarray | None = None
    """(H, W) bool: dropped (not ``valid``) because a bit coarser than ``MAX_COARSE_BITS`` from the finest
    barely modulates: the pixel's code would be a guess along the epipolar line."""
    unresolved: np.ndarray | None = None
    """(H, W, 2) int8: finest column and row bits the camera cannot resolve at each pixel (it spans more than
    one projector px there: :func:`resolution_levels`); 0 where it spans at most one. Positions come from the
    coarser bits, as for ``coarse``; ``coarse`` counts only the bits that barely modulate beyond these."""
    axes: tuple[int, int] | None = None
    """The camera axes (1: across, 0: down) along which the column and the row code change fastest: their
    sub-pixel walks' (:func:`fast_axis`; None: found again)."""
    spacing: tuple[float, float] | None = None
    """Camera px a projector px spans along each walk's axis, at least 1 (:func:`axis_and_spacing`; None: 1)."""
    noise: float = 0.0
    """Standard deviation (8-bit levels) of one frame's camera noise, measured from the capture."""


def graycode_bits(projector: tuple[int, int]) -> tuple[int, int]:
    """Column and row bits of a W_p x H_p projector: ceil(log2 W_p), ceil(log2 H_p)."""
    w, h = projector
    if w < 2 or h < 2:
        raise ValueError(f"projector size must be at least 2x2, got {w}x{h}")
    return int(math.ceil(math.log2(w))), int(math.ceil(math.log2(h)))


def _levels_of(a: np.ndarray) -> np.ndarray:
    """float32 8-bit levels of frames as read: uint16 values / 257 (as float32(value) * float32(1 / 257)),
    others as they are (a new array)."""
    out = a.astype(np.float32)
    if a.dtype == np.uint16:
        out *= np.float32(1.0 / 257.0)
    return out


def _integer_levels(pairs: np.ndarray, scale: float) -> bool:
    """Whether ``pairs`` are 8-bit frames read as they are: their |pattern - inverse| is then an integer
    level, compared in 8 bits (the float32 figures' outcomes, a quarter of the memory traffic)."""
    return pairs.dtype == np.uint8 and scale == 1.0


def _level_threshold(t: np.ndarray, ints: bool) -> np.ndarray:
    """Float32 thresholds ``t`` as a modulation (:func:`_modulation`) is compared with them (``a < t``): for
    integer levels the least integer not below ``t`` (for an integer ``a``, ``a < t`` exactly where
    ``a < ceil(t)``), as uint16 (0..256: a threshold above 255 keeps every 8-bit ``a`` below it)."""
    if not ints:
        return t
    return np.clip(np.ceil(t), 0, 256).astype(np.uint16)


def _modulation(pairs: np.ndarray, b: int, scale: float, ints: bool, bit: np.ndarray, d: np.ndarray) -> np.ndarray:
    """|pattern - inverse| of bit ``b`` (8-bit levels: uint8 for 8-bit frames, else float32 in ``d``), with
    ``bit`` set to pattern > inverse (the sign of :func:`pair_diff`: levels of integer frames keep their order)."""
    if ints:
        p, inv = pairs[b, 0], pairs[b, 1]
        np.greater(p, inv, out=bit)
        return cv2.absdiff(p, inv)
    pair_diff(pairs, b, scale, out=d)
    np.greater(d, 0, out=bit)
    return np.abs(d, out=d)


def decode_graycode(cap: GrayCodeCapture, *, settings: GrayCodeSettings = GrayCodeSettings(),
                    threads: int = 1) -> Decoded:
    """Integer projector column and row of every camera pixel (the plain decode; ``threads``: row bands
    decoded at once, each pixel's numbers its own)."""
    contrast = cap.white - cap.black
    weak = np.zeros(contrast.shape, np.uint8)  # (at most 2 x 30 bits)
    dim_levels = DIM_BIT_FRACTION * contrast
    dims = {ints: _level_threshold(dim_levels, ints)  # each kind of pairs' thresholds (a capture's share one)
            for ints in {_integer_levels(p, cap.scale) for p in (cap.col_pairs, cap.row_pairs)}}
    wide = len(cap.col_pairs) > 30 or len(cap.row_pairs) > 30
    col, row = (np.empty(contrast.shape, np.int64 if wide else np.int32) for _ in range(2))
    okc, okr = np.empty(contrast.shape, bool), np.empty(contrast.shape, bool)

    def code(pairs, rows, out, ok, bit, d):
        g = np.zeros(bit.shape, out.dtype)
        ok[rows] = True
        ints = _integer_levels(pairs, cap.scale)
        dim = dims[ints]
        for b in range(len(pairs)):
            a = _modulation(pairs[:, :, rows], b, cap.scale, ints, bit, d)
            g <<= 1
            g |= bit
            if settings.min_bit_contrast > 0:  # (at 0, the default, every bit passes: two passes saved)
                np.greater_equal(a, np.float32(settings.min_bit_contrast), out=bit)
                ok[rows] &= bit
            np.less(a, dim[rows], out=bit)
            weak[rows] += bit
        out[rows] = gray_decode(g, len(pairs))

    def band(rows):
        shape = (rows.stop - rows.start, contrast.shape[1])
        bit, d = np.empty(shape, bool), np.empty(shape, np.float32)
        code(cap.col_pairs, rows, col, okc, bit, d)
        code(cap.row_pairs, rows, row, okr, bit, d)

    edges = np.linspace(0, contrast.shape[0], max(1, min(int(threads), contrast.shape[0] // 64)) + 1).astype(int)
    bands = [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    if len(bands) > 1:  # (NumPy's loops release the GIL; a pool of its own: no Warp, see load_subpixel_kernels)
        with ThreadPoolExecutor(max_workers=len(bands), thread_name_prefix="ringscan-decode") as ex:
            list(ex.map(band, bands))
    else:
        for rows in bands:
            band(rows)
    valid = (contrast >= settings.min_contrast) | ((contrast >= settings.dim_contrast) & (weak <= DIM_MAX_WEAK))
    valid &= okc & okr & (col < cap.projector[0]) & (row < cap.projector[1])
    noise = frame_noise(cap, valid)
    coarse = np.zeros(contrast.shape + (2,), np.int8)
    unresolved = np.zeros(contrast.shape + (2,), np.int8)
    low = np.zeros(contrast.shape, bool)
    axes, spacing = [], []
    for a, (pairs, c) in enumerate(((cap.col_pairs, col), (cap.row_pairs, row))):
        ax, sp, steps = axis_and_spacing(c, valid)
        axes.append(ax)
        spacing.append(sp)
        res, rate = resolution_levels(c, valid, ax, bits=len(pairs))
        k = bit_clearance(pairs, contrast, valid, c, noise, scale=cap.scale, unresolved=res, rate=rate, spacing=sp,
                          steps=steps)
        if res is not None:  # the camera spans more than a projector px somewhere
            low |= k > res.astype(np.int16) + MAX_COARSE_BITS
            coarse[..., a] = np.where(k > res, np.minimum(k, res + MAX_COARSE_BITS), 0)
            unresolved[..., a] = res
        else:
            low |= k > MAX_COARSE_BITS
            coarse[..., a] = np.minimum(k, MAX_COARSE_BITS)
    low &= valid
    valid &= ~low
    col = np.where(valid, col, -1).astype(np.int32)
    row = np.where(valid, row, -1).astype(np.int32)
    log.info("%s: %d of %d pixels decoded (%d dropped: low_modulation)", cap.folder, int(valid.sum()), valid.size,
             int(low.sum()))
    if unresolved.any() and log.isEnabledFor(logging.INFO):
        log.info("%s: the camera spans more than one projector px at %d decoded pixels: their finest bits "
                 "(up to %d) are below its resolution; their positions come from the coarser bits", cap.folder,
                 int(np.count_nonzero(valid & (unresolved.max(axis=2) > 0))), int(unresolved.max()))
    return Decoded(col=col, row=row, valid=valid, contrast=contrast, coarse=coarse, low_modulation=low, noise=noise,
                   unresolved=unresolved, axes=(axes[0], axes[1]), spacing=(spacing[0], spacing[1]))


def frame_noise(cap: GrayCodeCapture, valid: np.ndarray) -> float:
    """Standard deviation (8-bit levels) of one frame's camera noise, from the capture itself.

    Where the coarsest column pattern's stripe lies wholly on a pixel, the pattern and its inverse
    are the white and the black frames again (whatever the camera's and the projector's response):
    pattern + inverse - white - black is then four frames' noise. Its standard deviation over the decoded
    pixels, the few on a stripe's edge left out (beyond 4 of a robust first guess; the guess is widened by
    half a level, as a median of integer levels is coarse), gives the noise of one frame.
    """
    p, inv = (_levels_of(a) if cap.scale != 1.0 else a.astype(np.float32, copy=False) for a in cap.col_pairs[0])
    r = (p + inv - cap.white - cap.black)[valid].astype(np.float64)
    if r.size < 100:
        return 1.0
    # 8-bit frames: r is in whole levels, |r - its median| in half levels: both medians counted, not sorted
    # (np.median's values exactly, in a third of its time on a 2.4-megapixel capture)
    whole = _integer_levels(cap.col_pairs, cap.scale)
    r -= _whole_median(r, 1) if whole else np.median(r)
    guess = 1.4826 * float(_whole_median(np.abs(r), 2) if whole else np.median(np.abs(r))) + 0.5
    return max(float(np.std(r[np.abs(r) < 4.0 * guess])) / 2.0, 0.25)


def _whole_median(x: np.ndarray, per: int) -> float:
    """``np.median`` of ``x`` ((n,) float64, n >= 1), whose values are whole multiples of 1 / ``per`` within
    +-1024 (8-bit levels: sums and differences of four frames): counted by value (the middle one, or the mean
    of the two middle ones as np.median takes it)."""
    lo = -1024 * per
    k = (x * per if per != 1 else x).astype(np.int64)  # (exact: whole numbers)
    k -= lo
    counts = np.cumsum(np.bincount(k))
    n = x.size
    at = lambda i: (int(np.searchsorted(counts, i, side="right")) + lo) / per  # noqa: E731 (the i-th, from 0)
    return float(at(n // 2)) if n % 2 else (at(n // 2 - 1) + at(n // 2)) / 2.0


def _code_steps(code: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How many decoded neighbours' codes step by 0, 1 and 2 across (camera x) and down (camera y):
    two (3,) counts (steps over 2, depth edges and misreads, left out). Counts, not the steps
    themselves: their median and mean are all that is asked, and counting in the codes' own integers
    is ~5x faster than a float64 copy of the steps (the same medians and means to the bit)."""
    out = []
    for axis in (1, 0):
        a, b = (code[:, 1:], code[:, :-1]) if axis == 1 else (code[1:, :], code[:-1, :])
        both = (valid[:, 1:] & valid[:, :-1]) if axis == 1 else (valid[1:, :] & valid[:-1, :])
        step = np.abs(np.subtract(a, b, dtype=np.int32))
        out.append(np.array([np.count_nonzero(both & (step == k)) for k in (0, 1, 2)], np.int64))
    return out[0], out[1]


def _median_step(counts: np.ndarray) -> float:
    """The median of the steps of 1 and 2 that ``counts`` (of 0, 1, 2) holds (1.0 with none), as
    ``np.median`` of those steps gives it."""
    n1, n2 = int(counts[1]), int(counts[2])
    n = n1 + n2
    if n == 0:
        return 1.0
    at = lambda i: 1.0 if i < n1 else 2.0  # noqa: E731  (the i-th of the sorted steps)
    return at(n // 2) if n % 2 else (at(n // 2 - 1) + at(n // 2)) / 2.0


def _mean_step(counts: np.ndarray) -> float:
    """The mean of the steps of 0, 1 and 2 that ``counts`` holds (0 with none)."""
    n = int(counts.sum())
    return float(counts[1] + 2 * counts[2]) / n if n else 0.0


def bit_clearance(pairs: np.ndarray, contrast: np.ndarray, valid: np.ndarray, code: np.ndarray,
                  noise: float, *, scale: float = 1.0, unresolved: np.ndarray | None = None,
                  rate: float = 0.0, spacing: float = 1.0,
                  steps: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(H, W) int8: how many of a code's finest bits, counted from the finest, do not stand clear at each pixel.

    A bit stands clear where its modulation |pattern - inverse| near the pixel (the largest within half a
    stripe's width, so that a pixel on a stripe's edge, where the bit flips and has no contrast by nature,
    is judged by the stripe's middle) reaches ``CLEAR_NOISE_SIGMAS`` standard deviations of the
    difference's noise and ``CLEAR_CONTRAST_FRACTION`` of the pixel's white - black. A far, dark, grazing
    or defocused surface blurs the finest stripes into grey: their bits are then read by the noise, a
    zigzag of whole projector pixels along the epipolar line that no calibration check can see. The
    ``MAX_COARSE_BITS + 1`` finest bits are judged (the coarser ones are as wide as the contrast tests), and as
    many more as the camera resolves fewer somewhere (``unresolved``: :func:`resolution_levels`, whose ``rate``
    the projector px a camera px spans, where above the codes' own steps, sets how near a stripe's middle is;
    ``steps``: the codes' step counts where already counted, :func:`axis_and_spacing`).
    """
    bits = pairs.shape[0]
    extra = int(unresolved.max(initial=0)) if unresolved is not None else 0
    out = np.zeros(contrast.shape, np.int8)  # at most MAX_COARSE_BITS + 2 + extra
    # projector px per camera px along the code's fast axis: the finest stripe's period in camera px
    rate = max(_median_step(np.add(*(steps if steps is not None else _code_steps(code, valid)))), rate)
    ints = _integer_levels(pairs, scale)
    thresh = _level_threshold(np.maximum(CLEAR_NOISE_SIGMAS * math.sqrt(2.0) * noise,
                                         CLEAR_CONTRAST_FRACTION * contrast), ints)
    bit, work = np.empty(contrast.shape, bool), np.empty(contrast.shape, np.float32)
    for j in range(min(bits, MAX_COARSE_BITS + 2 + extra)):  # j = 0: the finest bit
        d = _modulation(pairs, bits - 1 - j, scale, ints, bit, work)
        # bit j's stripes are 2**(j + 1) projector px wide: a pixel lies within half that of a stripe's middle
        # (``spacing`` camera px a projector px where a projector px spans more than two: a camera far finer)
        r = int(min(max(math.ceil(2 ** j / max(rate, 1e-3)), 1,
                        math.ceil(2 ** j * spacing) if spacing > MIN_WIDE_SPACING else 1), MAX_CLEAR_RADIUS))
        near = cv2.dilate(d, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1)))
        out[near < thresh] = j + 1
    return out


FAST_AXIS_CAP = 64
"""A step between neighbouring pixels' codes counts at most this much towards the fast axis (a depth edge's
jump is not the code's slope)."""


def fast_axis(code: np.ndarray, valid: np.ndarray) -> int:
    """The camera axis along which a code changes fastest (1: across, x; 0: down, y): its sub-pixel walk's.

    Where most codes step by 0, 1 or 2 between neighbours (a camera that resolves the projector's pixels), the
    axis of the larger mean of those steps; else (a camera pixel spanning more than two projector px along
    some axis) the axis of the larger mean step, each counted up to ``FAST_AXIS_CAP``."""
    return axis_and_spacing(code, valid)[0]


def axis_and_spacing(code: np.ndarray, valid: np.ndarray) -> tuple[int, float, tuple[np.ndarray, np.ndarray]]:
    """(:func:`fast_axis`, the camera px a projector px spans along it: 1 / the mean step of neighbouring codes
    there, at least 1 (e.g. 15 for a 20-megapixel camera on a small projector's pixels), and the steps' counts
    across and down: :func:`_code_steps`'s, counted once for all three)."""
    counts, wide = [], []
    for axis in (1, 0):
        a, b = (code[:, 1:], code[:, :-1]) if axis == 1 else (code[1:, :], code[:-1, :])
        both = (valid[:, 1:] & valid[:, :-1]) if axis == 1 else (valid[1:, :] & valid[:-1, :])
        step = np.abs(np.subtract(a, b, dtype=np.int32))
        c = np.array([np.count_nonzero(both & (step == k)) for k in (0, 1, 2)], np.int64)
        over = both & (step > 2)
        counts.append(c)
        wide.append((np.count_nonzero(over), int(np.minimum(step[over], FAST_AXIS_CAP).sum())))
    mean = [(c[1] + 2 * c[2] + w[1]) / max(1, c.sum() + w[0]) for c, w in zip(counts, wide)]
    if all(w[0] < c[1] + c[2] for c, w in zip(counts, wide)):
        axis = 1 if _mean_step(counts[0]) >= _mean_step(counts[1]) else 0
    else:
        axis = 1 if mean[0] >= mean[1] else 0
    m = mean[0 if axis == 1 else 1]
    return axis, (1.0 / m if 0 < m < 1 else 1.0), (counts[0], counts[1])


def resolution_levels(code: np.ndarray, valid: np.ndarray, axis: int, *,
                      bits: int) -> tuple[np.ndarray | None, float]:
    """((H, W) int8 or None, float): how many of a code's finest bits the camera cannot resolve at each pixel
    (None: none anywhere), and the median of the projector px a camera px spans along ``axis`` over the decoded
    pixels (0 where that is at most one).

    Where a camera px spans r > 1 projector px, the stripes of the finer bits are narrower than a camera pixel:
    it averages a pattern and its inverse, the bit is read by what is left (a moire, or the noise), the integer
    code zigzags by whole projector px, and neighbouring pixels' codes step by r, so that no boundary between
    them places one to sub-pixel precision. The smallest k with 2**k >= r is the level whose blocks of 2**k
    projector px the camera resolves: the pixel takes its position from their boundaries (as a pixel whose
    finest bits barely modulate does). r is read as |code(x + 4) - code(x - 4)| / 8 along ``axis``
    (``RESOLUTION_REACH``) on a grid of every ``RESOLUTION_GRID``-th pixel, its level's median over a
    ``RESOLUTION_WINDOW`` square; 0 (no change) wherever a camera px spans at most one projector px, as on most
    rigs."""
    h, w = code.shape
    reach, g = RESOLUTION_REACH, RESOLUTION_GRID
    n = w if axis == 1 else h
    if n <= 2 * reach + 1 or min(h, w) < g:
        return None, 0.0
    at = np.arange(reach, n - reach, g)  # grid points along the axis, each with its reach inside the image
    other = np.arange(g // 2, h if axis == 1 else w, g)
    ix = (lambda d: np.ix_(other, at + d)) if axis == 1 else (lambda d: np.ix_(at + d, other))  # noqa: E731
    a, m, b = (code[ix(d)].astype(np.int32) for d in (reach, 0, -reach))
    both = valid[ix(reach)] & valid[ix(0)] & valid[ix(-reach)]
    hi, lo = a - m, m - b
    step = np.abs(a - b)
    # a surface's code runs one way and evenly (a misread finest bit moves each half by ~1-2 of >= 4): halves
    # of one sign within 2:1 of each other; codes that jump about (a depth edge, the noise of an unlit wall
    # read as a code) are left at 0
    even = (hi * lo > 0) & (np.abs(hi - lo) * 3 <= step)
    step[~(both & even)] = 0
    level = (step > 2 * reach).astype(np.uint8)
    k = RESOLUTION_WINDOW // g | 1  # the window in grid points (odd)
    if np.count_nonzero(level) * 2 < k * k:  # (no window's median can be above 0)
        return None, 0.0
    t = 4 * reach
    while level.max() < min(bits - 1, RESOLUTION_MAX_LEVEL) and np.count_nonzero(step > t):
        level += step > t
        t *= 2
    level = cv2.medianBlur(level, k)
    if not level.any():
        return None, 0.0
    out = np.zeros((h, w), np.int8)
    # back to every pixel: grid point i stands for the g x g pixels around it (the few at the image's edges
    # beyond the grid keep 0)
    big = cv2.resize(level, (level.shape[1] * g, level.shape[0] * g), interpolation=cv2.INTER_NEAREST)
    y0, x0 = ((other[0], at[0]) if axis == 1 else (at[0], other[0]))
    y0, x0 = y0 - g // 2, x0 - g // 2
    hh, ww = min(h - y0, big.shape[0]), min(w - x0, big.shape[1])
    np.copyto(out[y0:y0 + hh, x0:x0 + ww], big[:hh, :ww], casting="unsafe", where=valid[y0:y0 + hh, x0:x0 + ww])
    rate = float(np.median(step[both & even])) / (2.0 * reach) if (both & even).any() else 0.0
    return out, rate if rate > 1.0 else 0.0


def _along_axis(code: np.ndarray, valid: np.ndarray, pairs: np.ndarray, axis: int, max_span: float,
                scale: float = 1.0, lines: np.ndarray | None = None, threads: int = 1):
    """Sub-pixel coordinate along ``axis`` (0: camera rows, i.e. down; 1: across): each decoded pixel
    interpolated between the code boundaries around it (one Warp kernel walk a line,
    ``kernels.graycode_map.subpixel_lines``; its figures are the NumPy construction's to the bit), on
    ``lines`` (None: all)."""
    from ringscan.kernels.graycode_map import subpixel_lines  # (see load_subpixel_kernels)

    return subpixel_lines(code, valid, pairs, bits=pairs.shape[0], axis=axis, max_span=max_span, scale=scale,
                          lines=lines, threads=threads)


def _levels(code: np.ndarray, valid: np.ndarray, coarse: np.ndarray, pairs: np.ndarray, axis: int,
            max_span: float, scale: float = 1.0, threads: int = 1,
            weak: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel coordinate of every pixel from the bits it trusts: a pixel that leaves its ``k`` finest bits
    untrusted is interpolated between the boundaries of blocks of 2**k projector pixels (the code without
    those bits: ``code >> k``, whose Gray bits are the first ``bits - k``), found between the pixels that
    trust at least those bits. A pixel that finds no two boundaries around it at its own level (beside a
    region of coarser pixels, say) takes the next coarser level that has them; where none has, a pixel
    whose bits all stand clear of the noise (``weak`` 0: (H, W) the bits that barely modulate, of ``coarse``'s;
    None: ``coarse`` itself) keeps its integer code (and is not sub-pixel)."""
    from ringscan.kernels.graycode_map import subpixel_points  # (see load_subpixel_kernels)

    out, ok = None, np.zeros(code.shape, bool)
    bits = pairs.shape[0]
    coarse = np.ascontiguousarray(coarse)
    top = int(coarse.max(where=valid, initial=0))
    for k in range(0, min(top, bits - 1) + 1):
        # (the walk reads a pixel's code only where it is valid at this level: the codes go in unmasked)
        lvl_valid = valid if top == 0 else valid & (coarse <= k)
        todo = lvl_valid if k == 0 else lvl_valid & ~ok
        n = np.count_nonzero(todo)
        if not n:
            if k == 0:  # (k = 0 comes first: out is set there)
                out = np.full(code.shape, np.nan)
            continue
        ck, pk, span = (code >> k if k else code), pairs[:bits - k], max_span * 2 ** k
        # the finest level walks every line; a coarser one only the lines with a pixel still to place, or,
        # where those are few (a sharp capture's handful beside a silhouette), searches around each of them
        lines = None if k == 0 else np.flatnonzero(todo.any(axis=axis))
        if k and n * POINT_SEARCH_COST < lines.size * code.shape[axis]:
            at = np.flatnonzero(todo)
            res, good = subpixel_points(ck, lvl_valid, pk, at, bits=bits - k, axis=axis, max_span=span, scale=scale)
            # block c of 2**k projector pixels has its centre at 2**k * c + (2**k - 1) / 2
            out.reshape(-1)[at[good]] = res[good] * 2 ** k + (2 ** k - 1) / 2.0
            ok.reshape(-1)[at[good]] = True
            continue
        res, good = _along_axis(ck, lvl_valid, pk, axis, span, scale, lines, threads)
        take = todo & good
        if k == 0:  # (the walk's array itself: a fresh one, kept)
            np.copyto(res, np.nan, where=~take)
            out, ok = res, take
        else:
            out[take] = res[take] * 2 ** k + (2 ** k - 1) / 2.0
            ok |= take
    keep = valid & ~ok & ((coarse if weak is None else weak) == 0)
    out[keep] = code[keep]
    return out, ok


def load_subpixel_kernels() -> None:
    """Import the sub-pixel kernels' module (``kernels.graycode_map``: Warp's import, ~0.2 s of one core).

    This module imports it where it is first used, so that ``ringscan import`` can start reading frames at
    once and load it on a thread of its own meanwhile (``importer``): a plain decode needs no Warp."""
    import importlib

    importlib.import_module("ringscan.kernels.graycode_map")


def subpixel_map(cap: GrayCodeCapture, dec: Decoded, *, settings: GrayCodeSettings = GrayCodeSettings(),
                 threads: int = 1) -> Decoded:
    """Fill ``dec.u``, ``dec.v`` and ``dec.subpixel`` (see the module docstring); returns ``dec``
    (``threads``: the lines walked at once, each line's numbers its own)."""

    ax_u, ax_v = dec.axes if dec.axes is not None else (fast_axis(dec.col, dec.valid), fast_axis(dec.row, dec.valid))
    # boundaries farther apart than max_span_px are not interpolated between, unless a projector px itself spans
    # more (a camera far finer than the projector): then as far as SPAN_PROJECTOR_PX projector px
    sp_u, sp_v = dec.spacing if dec.spacing is not None else (1.0, 1.0)
    span_u, span_v = (max(settings.max_span_px, SPAN_PROJECTOR_PX * sp) for sp in (sp_u, sp_v))
    coarse = dec.coarse if dec.coarse is not None else np.zeros(dec.valid.shape + (2,), np.int8)
    levels = coarse
    if dec.unresolved is not None and dec.unresolved.any():  # the bits the camera cannot resolve, then those
        levels = np.maximum(coarse, dec.unresolved)           # that barely modulate beyond them
    u, oku = _levels(dec.col, dec.valid, levels[..., 0], cap.col_pairs, ax_u, span_u, cap.scale, threads,
                     weak=coarse[..., 0])
    v, okv = _levels(dec.row, dec.valid, levels[..., 1], cap.row_pairs, ax_v, span_v, cap.scale, threads,
                     weak=coarse[..., 1])
    # a pixel whose finest bits are untrusted has no integer code to fall back on: it is dropped
    lost = dec.valid & (((coarse[..., 0] > 0) & ~oku) | ((coarse[..., 1] > 0) & ~okv))
    if dec.low_modulation is not None:
        dec.low_modulation |= lost
    dec.valid = dec.valid & ~lost
    for a in (u, v):  # (arrays of _levels' own: NaN'd in place)
        np.copyto(a, np.nan, where=~dec.valid)
    dec.u, dec.v = u, v
    dec.subpixel = oku & okv & dec.valid
    if log.isEnabledFor(logging.INFO):
        log.info("%s: sub-pixel u along camera %s, v along camera %s; %d of %d decoded pixels interpolated "
                 "(%d from coarser bits)", cap.folder, "x" if ax_u else "y", "x" if ax_v else "y",
                 int(dec.subpixel.sum()), int(dec.valid.sum()),
                 int((dec.subpixel & ((coarse[..., 0] | coarse[..., 1]) != 0)).sum()))
    return dec
