"""Reading a Gray-code capture's frames (:mod:`~ringscan.pipeline.calibrate.capture_files` lists them) into a
:class:`~ringscan.pipeline.calibrate.graycode.GrayCodeCapture`: sorted by layout into white, black and
pattern/inverse pairs, decoded on threads, kept as read, checked (sizes, bit depth, white brighter than
black)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ringscan.pipeline.calibrate.capture_files import capture_frames
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import LAYOUTS, GrayCodeCapture, _levels_of, graycode_bits
from ringscan.pipeline.formats.images import FRAME_BITS_RANGE, expand_frame_bits, few_bits_hint, read_image

__all__ = ["read_capture", "read_capture_files", "expand_capture_frame", "check_layout", "cpu_cores"]


def read_capture(folder, *, projector: tuple[int, int], layout: str = "opencv-graycode",
                 frame_bits: int | None = None) -> GrayCodeCapture:
    """Read one capture folder of ``graycode_NN`` frames and sort its frames by ``layout``
    (``frame_bits``: as :func:`read_capture_files`).

    Raises:
        CalibrationError: no frames, a frame count that does not fit the projector
            size, frames of different sizes, or white darker than black (the wrong layout).
    """
    folder = Path(folder)
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    cb, rb = graycode_bits(projector)
    want = 2 + 2 * (cb + rb)
    paths = capture_frames(folder)
    if len(paths) != want:
        raise CalibrationError(folder, f"{len(paths)} graycode_NN frames, but a {projector[0]}x{projector[1]} "
                                       f"projector in layout {layout} has {want} ({cb} column and {rb} row bits, "
                                       "each with its inverse, white and black): wrong --layout or --projector?")
    return read_capture_files(paths, projector=projector, layout=layout, source=folder, frame_bits=frame_bits)


def cpu_cores() -> int:
    """The cores this process may run on (its CPU affinity; the core count where that is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _read_frames(paths: list[Path], threads: int | None):
    """The frames of ``paths`` (uint8/uint16 arrays), in order, decoded on up to ``threads`` threads
    (None: :func:`cpu_cores`), at most ``2 threads + 4`` frames ahead of the caller."""
    from concurrent.futures import ThreadPoolExecutor

    n = max(1, min(len(paths), cpu_cores() if threads is None else int(threads)))
    if n == 1:
        yield from (read_image(p) for p in paths)
        return
    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="ringscan-frames") as ex:
        ahead = 2 * n + 4
        futs = [ex.submit(read_image, p) for p in paths[:ahead]]
        for i in range(len(paths)):
            if i + ahead < len(paths):
                futs.append(ex.submit(read_image, paths[i + ahead]))
            img = futs[i].result()
            futs[i] = None
            yield img


def read_capture_files(paths, *, projector: tuple[int, int], layout: str = "opencv-graycode",
                       source=None, frame_bits: int | None = None, threads: int | None = None) -> GrayCodeCapture:
    """Read one camera's frames of a capture (in capture order) and sort them by ``layout``.

    ``frame_bits`` (9..16): the bits its 16-bit frames hold (a 12-bit camera's values
    0..4095), scaled to the full 16-bit range by bit replication as they are read, as
    a scan's ``frame_bits`` does (docs/formats.md); 8: 8-bit frames; None: the frames' own.
    ``threads``: frames decoded at once (None: :func:`cpu_cores`).

    Raises:
        CalibrationError: a frame count that does not fit the projector size, frames of
            different sizes, or white darker than black (the wrong layout), naming ``source``;
            a frame of another depth than ``frame_bits`` says, or a value above its range,
            naming the frame.
    """
    lo, hi = FRAME_BITS_RANGE
    if frame_bits is not None and (isinstance(frame_bits, bool) or not isinstance(frame_bits, int)
                                   or not (frame_bits == 8 or lo <= frame_bits <= hi)):
        raise ValueError(f"frame_bits must be 8 or {lo}..{hi}, got {frame_bits!r}")
    paths = [Path(p) for p in paths]
    source = Path(source) if source is not None else (paths[0].parent if paths else None)
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    cb, rb = graycode_bits(projector)
    want = 2 + 2 * (cb + rb)
    if len(paths) != want:
        raise CalibrationError(source, f"{len(paths)} frames, but a {projector[0]}x{projector[1]} projector in "
                                       f"layout {layout} has {want}")
    brightest = -1  # of 16-bit frames read as they are (the hint for a 10- or 12-bit camera's)
    fr = None
    # the frames are decoded on threads (the image decoders release the GIL), checked and
    # stored in capture order: the first bad frame in that order is the one named. They are
    # kept as read (their levels: value * scale); a capture of 8- and 16-bit frames mixed
    # becomes float32 levels
    for i, (p, img) in enumerate(zip(paths, _read_frames(paths, threads))):
        if fr is None:
            fr = np.empty((len(paths), *img.shape), img.dtype)  # filled frame by frame: no stacked copy
        elif img.shape != fr.shape[1:]:
            raise CalibrationError(p, f"frame is {img.shape[1]}x{img.shape[0]}, {paths[0].name} is "
                                      f"{fr.shape[2]}x{fr.shape[1]}")
        if frame_bits is not None:
            expand_capture_frame(p, img, frame_bits)
        elif img.dtype == np.uint16:
            brightest = max(brightest, int(img.max()))
        if img.dtype != fr.dtype:
            if fr.dtype != np.float32:
                fr = np.concatenate([_levels_of(fr[:i]), np.empty((len(paths) - i, *img.shape), np.float32)])
            fr[i] = _levels_of(img)
        else:
            fr[i] = img
    scale = 1.0 / 257.0 if fr.dtype == np.uint16 else 1.0
    if layout == "opencv-graycode":
        pairs, white, black = fr[:-2], fr[-2], fr[-1]
    else:
        white, black, pairs = fr[0], fr[1], fr[2:]
    pairs = pairs.reshape(cb + rb, 2, *fr.shape[1:])
    cap = GrayCodeCapture(folder=source, white=_levels_of(white), black=_levels_of(black), col_pairs=pairs[:cb],
                          row_pairs=pairs[cb:], projector=(int(projector[0]), int(projector[1])), scale=scale)
    try:
        check_layout(cap, layout)
    except CalibrationError as e:
        hint = few_bits_hint(brightest, "give their bits (ringscan import --frame-bits, docs/calibration.md)")
        if hint and "no projector light" in e.message:
            raise CalibrationError(e.path, e.message + hint) from None
        raise
    return cap


def expand_capture_frame(p: Path, img: np.ndarray, bits: int) -> None:
    """``img`` (read from ``p``) scaled in place from ``bits`` (a command's ``--frame-bits``: 8, or 9..16 for
    16-bit frames) to 16 bits, after checking that it holds them.

    Raises:
        CalibrationError: naming ``p``: a frame of the other depth, or a value above the range.
    """
    if (img.dtype == np.uint8) != (bits == 8):
        raise CalibrationError(p, f"frame is {8 if img.dtype == np.uint8 else 16}-bit, but --frame-bits says {bits}")
    if img.dtype == np.uint16 and bits < 16:
        top = (1 << bits) - 1
        m = int(img.max())
        if m > top:
            raise CalibrationError(p, f"frame holds {m}, above the {bits}-bit range --frame-bits says ({top})")
        expand_frame_bits(img, bits)


def check_layout(cap: GrayCodeCapture, layout: str) -> None:
    """White must be brighter than black, and brighter than each pattern/inverse pair's dimmer frame.

    A capture read in the wrong layout takes a pattern and its inverse for white and
    black: then 'white' is darker than 'black' on about half of the lit pixels.
    """
    diff = cap.white - cap.black
    lit = np.abs(diff) >= 20.0
    n = int(np.count_nonzero(lit))
    if n < 100:
        raise CalibrationError(cap.folder, f"white and black differ by 20 levels at only {n} pixels: "
                                           "no projector light in the capture, or the wrong layout")
    dark = float(np.count_nonzero(diff[lit] < 0)) / n
    if dark > 0.05:
        raise CalibrationError(cap.folder, f"the frame read as white is darker than the one read as black at "
                                           f"{100 * dark:.0f} % of the lit pixels: not layout {layout!r}?")
