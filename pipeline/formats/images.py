"""Frame images: 8- or 16-bit PNG/TIFF, grey or colour (converted to grey), written atomically."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.limits import check_image_header

log = logging.getLogger(__name__)

__all__ = ["read_image", "write_image", "png_params", "tiff_params", "expand_frame_bits", "FRAME_BITS_RANGE",
           "FEW_BITS_MAX", "few_bits_hint"]

FRAME_BITS_RANGE = (9, 16)
"""Significant bits a 16-bit frame may hold (``frame_bits`` of scan.json; an 8-bit frame holds 8)."""
FEW_BITS_MAX = 1 << 14
"""16-bit frames whose brightest value is below this (a quarter of the range) may be a 10- to
14-bit camera's, LSB-aligned: a message about frames without contrast says so."""


def few_bits_hint(brightest: int, advice: str) -> str:
    """``"; <hint>"`` for a no-contrast message about 16-bit frames whose brightest value
    (``brightest``) is below :data:`FEW_BITS_MAX`, ending with ``advice`` (what to give:
    scan.json's frame_bits, a command's --frame-bits); ``""`` for brighter frames."""
    if not 0 <= brightest < FEW_BITS_MAX:
        return ""
    return f"; 16-bit frames whose brightest value is {brightest}: a 10- or 12-bit camera's frames? {advice}"


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an 8- or 16-bit PNG/TIFF as a 2D grey array (uint8 or uint16).

    Colour images are converted to grey (ITU-R 601 luma, as OpenCV does). The file's
    header is checked before it is decoded (:func:`~.limits.check_image_header`: a
    regular file of at most 200 megapixels).
    """
    import cv2

    path = Path(path)
    check_image_header(path)
    # (OpenCV >= 4.10 can decode into a given array, but a file it cannot decode
    # then leaves the array as it was with no sign of failure: not used.)
    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error:  # a header this reads as small, a decoder that disagrees
        img = None
    if img is None:
        raise FormatError(path, "not a readable image (corrupt file or unsupported format)")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            raise FormatError(path, f"unsupported channel count {img.shape[2]}")
    if img.dtype not in (np.uint8, np.uint16):
        raise FormatError(path, f"unsupported pixel type {img.dtype} (need 8- or 16-bit)")
    return img


def expand_frame_bits(frames: np.ndarray, bits: int) -> np.ndarray:
    """Scale ``bits``-bit values held LSB-aligned in uint16 (0..2^bits - 1: a 10- or
    12-bit camera's frames, V4L2's Y10/Y12, Mono12 saves) to the full 16-bit range, in
    place, by bit replication: shifted left by 16 - bits, with the value's own top bits
    repeated in the freed low bits (the PNG specification's way to scale sBIT data;
    12 bits: ``v << 4 | v >> 8``). Exact and monotonic: 0 -> 0, 2^bits - 1 -> 65535, so
    every threshold in 8-bit grey levels (x257) and the saturation level hold as for
    16-bit frames.

    Args:
        frames: uint16 array of any shape (a frame or a stack), values at most
            2^bits - 1 (the caller checks: a larger value would lose its top bits).
        bits: 9..16 (16: nothing to do).

    Returns:
        ``frames``, scaled.
    """
    if frames.dtype != np.uint16:
        raise ValueError(f"expand_frame_bits: frames must be uint16, got {frames.dtype}")
    lo, hi = FRAME_BITS_RANGE
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or not lo <= bits <= hi:
        raise ValueError(f"expand_frame_bits: bits must be a whole number in {lo}..{hi}, got {bits!r}")
    if bits == 16:
        return frames
    # 16 - bits <= bits, so the value's top 16 - bits bits fill the freed ones in one step
    for f in (frames if frames.ndim == 3 else (frames,)):  # a stack a frame at a time: one frame's temporary
        top = f >> (2 * bits - 16)
        np.left_shift(f, 16 - bits, out=f)
        np.bitwise_or(f, top, out=f)
    return frames


def png_params(*, smooth: bool = False) -> list[int]:
    """OpenCV's PNG writer settings for frames: run-length zlib strategy with the
    "up" row filter; for a ``smooth`` image (an imported capture's decoded maps: projector
    coordinates, contrast) zlib's default strategy at level 1, "up" filter.

    Camera frames carry sensor noise, so zlib finds few long matches whatever it
    tries; what differs is how fast a frame decodes. Against OpenCV's default
    (run-length strategy, "sub" filter) these frames decode ~30 % faster (libpng
    undoes "sub" one byte after another, "up" a whole row at once) and come out the
    same size or smaller: on 1280x1024 frames, simulated 563 vs 565 KB, 5.2 vs
    7.1 ms; real captures (shared/data/procam) 551 vs 575 KB, 4.9 vs 7.1 ms
    (docs/batch.md). Reading PNG frames is the largest cost of a batch.

    A smooth 16-bit map is another matter: zlib finds matches in it, and its default
    strategy at level 1 writes the maps of a 1920x1280 camera as fast (24-46 ms each)
    20-28 % smaller, and they decode 25-30 % faster (12-22 ms against 17-29), than the
    run-length strategy does (docs/batch.md, "Real captures"); on noisy frames it is
    the other way round (1234 against 1010 KB, 16 against 14 ms).
    """
    import cv2

    if smooth:  # (a compression level given, OpenCV uses zlib's default strategy)
        params = [cv2.IMWRITE_PNG_COMPRESSION, 1]
        if hasattr(cv2, "IMWRITE_PNG_FILTER"):
            params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]
        return params
    params = [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # OpenCV >= 4.11
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]
    return params


def tiff_params() -> list[int]:
    """OpenCV's TIFF writer settings: no compression. A TIFF frame is the fast
    choice (1280x1024: 1.1 ms to read against 4.8 ms for the PNG, at 2.3x the
    space); OpenCV's default LZW would make it as slow as the PNG and larger."""
    import cv2

    return [cv2.IMWRITE_TIFF_COMPRESSION, 1]


def write_image(path: str | os.PathLike, img: np.ndarray, *, smooth: bool = False) -> None:
    """Write a grey or BGR uint8/uint16 image atomically (format from the
    extension; PNG with :func:`png_params` (``smooth``: a map, not a camera frame), TIFF
    uncompressed: :func:`tiff_params`)."""
    import cv2

    path = Path(path)
    suffix = path.suffix.lower()
    params = png_params(smooth=smooth) if suffix == ".png" else tiff_params() if suffix in (".tif", ".tiff") else []
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img, params):
            raise FormatError(path, "OpenCV could not write the image")
