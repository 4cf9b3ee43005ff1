"""Column/row Gray-code captures (OpenCV's structured-light layout) -> projector coordinates.

A capture is the frames of a camera (or of two cameras) watching a projector of
W_p x H_p pixels show the binary-reflected Gray code of each column
(``ceil(log2 W_p)`` bits, most significant first) and each row (``ceil(log2 H_p)``
bits), every pattern followed by its inverse, plus a white and a black frame.
These ways of naming the frames are read (:func:`list_capture`, ``CAPTURE_INPUTS``):

- a folder of ``graycode_00.png`` ... (numbered from 0; one camera);
- a folder of ``pattern_cam1_im1.png`` ... ``pattern_cam2_im44.png`` (OpenCV's
  structured-light sample, ``cap_pattern``: numbered from 1, one or two cameras; the
  sample glues its output path and the name together without a separator, so the
  names may carry one common prefix, ``scanpattern_cam1_im1.png``);
- a folder of frames named by the camera (``DSC04052.JPG`` ...; one camera) whose count
  is the layout's exactly: taken in natural name order (``DSC2`` before ``DSC10``);
- an image list as ``cv::FileStorage`` writes it (YAML, XML or JSON:
  ``cam1: [paths...]`` and optionally ``cam2: [...]``, in capture order), as OpenCV's
  sample reads it: its first top-level list is camera 1's whatever its name, ``cam2``
  camera 2's; a relative path is looked up beside the list, then in the current
  folder (where OpenCV's sample looks);
- a plain-text image list (``.txt``, ``.lst``, ``.list``: one path a line, in capture
  order, blank lines and ``#`` comments ignored; one camera), its paths looked up as
  a FileStorage list's.

PNG, TIFF, JPEG and BMP frames are read. Two orders of white/black are read (``LAYOUTS``):

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
(code errors, depth edges, a camera that sees more than one projector pixel per
camera pixel) keep their integer code and are flagged.
"""

from __future__ import annotations

import logging
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ringscan.kernels.samples import subpixel_lines
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.formats.images import FRAME_BITS_RANGE, expand_frame_bits, few_bits_hint, read_image
from ringscan.pipeline.formats.patterns import gray_decode

__all__ = ["LAYOUTS", "CAPTURE_INPUTS", "TEXT_LIST_SUFFIXES", "natural_key", "expand_capture_frame", "GrayCodeSettings", "GrayCodeCapture", "Decoded", "CaptureFiles",
           "graycode_bits", "list_capture", "check_capture_sizes", "read_capture", "read_capture_files",
           "decode_graycode", "subpixel_map", "open_filestorage", "cpu_cores"]

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
LOW_MODULATION_WARN_SHARE = 0.2
"""A view whose finest bit is untrusted at more than this share of its decoded pixels gets a warning."""

CAPTURE_INPUTS = (
    "a folder of graycode_NN.<ext> (from 00, one camera)",
    "a folder of pattern_camN_imK.<ext> (OpenCV's sample: K from 1, cameras 1 and 2; one common prefix allowed)",
    "a folder of frames of other names (DSC04052.JPG ...: one camera) holding exactly the layout's count, taken "
    "in natural name order (DSC2 before DSC10)",
    "an image list (OpenCV FileStorage YAML/XML/JSON: cam1: [paths] (or the first list), cam2: [paths]; relative "
    "paths beside the list, else in the current folder)",
    "a plain-text image list (.txt, .lst, .list: one path a line in capture order, # comments; one camera)",
)
"""What ``ringscan import`` takes as a capture (one view each); <ext> is png, tif(f), jpg/jpeg or bmp."""

IMAGE_EXT = r"(png|tif|tiff|bmp|jpg|jpeg)"
FRAME_RE = re.compile(rf"^graycode_(\d+)\.{IMAGE_EXT}$", re.IGNORECASE)
SAMPLE_RE = re.compile(rf"^(.*?)pattern_cam(\d+)_im(\d+)\.{IMAGE_EXT}$", re.IGNORECASE)
"""OpenCV's sample's names (group 1: a prefix, the sample's output path glued on without a separator)."""
LIST_SUFFIXES = (".yml", ".yaml", ".xml", ".json")
"""A FileStorage image-list capture is a file with one of these suffixes."""
TEXT_LIST_SUFFIXES = (".txt", ".lst", ".list")
"""A plain-text image-list capture (one path a line) is a file with one of these suffixes."""
MAX_LIST_BYTES = 16 * 1024 * 1024
"""Largest image-list file read."""
MAX_FRAMES = 4096
"""Most frames per camera in one capture (2 x 2 x 16 bits + 2 is 66)."""


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
    noise: float = 0.0
    """Standard deviation (8-bit levels) of one frame's camera noise, measured from the capture."""


def graycode_bits(projector: tuple[int, int]) -> tuple[int, int]:
    """Column and row bits of a W_p x H_p projector: ceil(log2 W_p), ceil(log2 H_p)."""
    w, h = projector
    if w < 2 or h < 2:
        raise ValueError(f"projector size must be at least 2x2, got {w}x{h}")
    return int(math.ceil(math.log2(w))), int(math.ceil(math.log2(h)))


@dataclass(frozen=True)
class CaptureFiles:
    """The frame files of one capture, per camera, in capture order (:func:`list_capture`)."""

    source: Path
    """The capture folder or the image-list file."""
    kind: str
    """``graycode`` (graycode_NN names), ``pattern`` (pattern_camN_imK names), ``named`` (other names, in
    natural name order), ``list`` (a FileStorage image list) or ``text`` (a plain-text image list)."""
    cameras: tuple[tuple[Path, ...], ...]
    """Camera 1's frames, then camera 2's (when the capture has two cameras)."""

    def frames_of(self, camera: int) -> tuple[Path, ...]:
        """The frames of camera 1 or 2."""
        return self.cameras[camera - 1]


def capture_frames(folder: Path) -> list[Path]:
    """The ``graycode_NN`` frames of a capture folder, in numeric order."""
    if not folder.is_dir():
        raise CalibrationError(folder, "capture folder not found")
    found = []
    for p in folder.iterdir():
        m = FRAME_RE.match(p.name)
        if m:
            found.append((int(m.group(1)), p))
    found.sort()
    idx = [i for i, _ in found]
    if idx != list(range(len(idx))):
        raise CalibrationError(folder, f"graycode_NN frames are not numbered 0..{len(idx) - 1} without gaps")
    return [p for _, p in found]


def _want(projector, layout) -> tuple[int, str]:
    cb, rb = graycode_bits(projector)
    return 2 + 2 * (cb + rb), (f"a {projector[0]}x{projector[1]} projector in layout {layout} has {2 + 2 * (cb + rb)} "
                               f"({cb} column and {rb} row bits, each with its inverse, white and black)")


def _fit_hint(n: int) -> str:
    """What projector a frame count fits: n = 2 (column + row bits) + 2."""
    if n < 6 or n % 2:
        return ""
    bits = (n - 2) // 2
    return f" ({n} frames fit {bits} column + row bits; a 1024x768 projector has 10 + 10, 1280x800 11 + 10)"


def _sample_frames(folder: Path, entries: list[str], *, projector, layout) -> tuple[tuple[Path, ...], ...]:
    """pattern_camN_imK frames of a folder, per camera, numbered from 1."""
    cams: dict[int, list[tuple[int, Path]]] = {}
    prefixes = set()
    for name in entries:
        m = SAMPLE_RE.match(name)
        if m:
            prefixes.add(m.group(1))
            cams.setdefault(int(m.group(2)), []).append((int(m.group(3)), folder / name))
    if len(prefixes) > 1:
        shown = ", ".join(f"{p or '(none)'}pattern_cam1_im1" for p in sorted(prefixes)[:3])
        raise CalibrationError(folder, f"pattern_camN_imK frames with {len(prefixes)} different prefixes ({shown}): "
                                       "one capture per folder")
    others = sorted(c for c in cams if c not in (1, 2))
    if others:
        raise CalibrationError(folder, f"frames of camera {others[0]} (pattern_cam{others[0]}_imK): ringscan reads "
                                       "cameras 1 and 2")
    if 1 not in cams:
        raise CalibrationError(folder, "camera 1's frames are missing: only pattern_cam2_imK frames (a capture needs "
                                       "camera 1's frames, and camera 2's for a two-camera scan)")
    want, what = _want(projector, layout)
    out = []
    for c in sorted(cams):
        found = sorted(cams[c])
        idx = [i for i, _ in found]
        if len(set(idx)) != len(idx):
            dup = next(i for i in idx if idx.count(i) > 1)
            raise CalibrationError(folder, f"two files for frame pattern_cam{c}_im{dup} (one extension each, please)")
        if len(found) != want:
            raise CalibrationError(folder, f"{len(found)} pattern_cam{c}_imK frames, but {what}: wrong --projector?"
                                           f"{_fit_hint(len(found))}")
        if idx != list(range(1, want + 1)):
            gap = next(k for k in range(1, want + 1) if k not in idx)
            raise CalibrationError(folder, f"pattern_cam{c}_imK frames are not numbered 1..{want}: "
                                           f"pattern_cam{c}_im{gap} is missing")
        out.append(tuple(p for _, p in found))
    return tuple(out)


def open_filestorage(path, *, what: str, max_bytes: int = MAX_LIST_BYTES):
    """Open an OpenCV FileStorage file (YAML, XML or JSON) for reading: a regular file of at most
    ``max_bytes``, parsed by OpenCV.

    Raises:
        CalibrationError: naming the file: not found, not a regular file, too large, or not
            FileStorage (with OpenCV's line and reason).
    """
    import cv2

    from ringscan.pipeline.formats.limits import check_regular_file

    path = Path(path)
    check_regular_file(path, what=what, max_bytes=max_bytes)  # a FIFO would block OpenCV
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as e:  # cv2.error, or SystemError wrapping it (OpenCV 5)
        msg = str(e.__cause__ or e)
        m = re.search(r"\((\d+)\): ([^'\n]*)", msg)
        why = f": line {m.group(1)}: {m.group(2).strip()}" if m else ""
        raise CalibrationError(path, f"not an OpenCV FileStorage file (YAML, XML or JSON as cv::FileStorage "
                                     f"writes it){why}") from None
    if not fs.isOpened():
        raise CalibrationError(path, "not an OpenCV FileStorage file (YAML, XML or JSON as cv::FileStorage writes it)")
    return fs


def _list_frames(path: Path, *, projector, layout) -> tuple[tuple[Path, ...], ...]:
    """The frames of an image list: ``cam1: [...]``, optionally ``cam2: [...]``."""
    fs = open_filestorage(path, what="image list")
    try:
        keys = list(fs.root().keys())
        lists = {}
        for c in (1, 2):
            node = fs.getNode(f"cam{c}")
            if c == 1 and (node.empty() or node.isNone()) and keys and keys[0] != "cam2":
                # OpenCV's sample takes the first top-level node as camera 1's list, whatever its name
                node = fs.getNode(keys[0])
                if not node.isSeq():
                    continue
                log.info("%s: camera 1's frames from the first list, %r (no cam1 list)", path, keys[0])
            if node.empty() or node.isNone():
                continue
            if not node.isSeq():
                raise CalibrationError(path, f"cam{c}: expected a list of image paths")
            if node.size() > MAX_FRAMES:
                raise CalibrationError(path, f"cam{c}: {node.size()} entries (at most {MAX_FRAMES} are read)")
            items = []
            for i in range(node.size()):
                it = node.at(i)
                if not it.isString() or not it.string():
                    raise CalibrationError(path, f"cam{c}[{i}]: expected an image path (a string)")
                items.append(it.string())
            lists[c] = items
    finally:
        fs.release()
    if 1 not in lists:
        got = ", ".join(keys[:5]) or "nothing"
        raise CalibrationError(path, f"no cam1 list (an image list has cam1: [paths...] and optionally cam2: "
                                     f"[paths...]; this file has {got})" if 2 not in lists else
                                     "camera 1's frames are missing: a cam2 list but no cam1 list")
    want, what = _want(projector, layout)
    out = []
    for c, items in sorted(lists.items()):
        if len(items) != want:
            raise CalibrationError(path, f"cam{c} lists {len(items)} frames, but {what}: wrong --projector?"
                                         f"{_fit_hint(len(items))}")
        out.append(tuple(_resolve_listed(path, rel, f"cam{c}[{i}]") for i, rel in enumerate(items)))
    return tuple(out)


def _resolve_listed(path: Path, rel: str, where: str) -> Path:
    """A listed image's path: absolute as it is; relative beside the list, else in the current folder.

    Raises:
        CalibrationError: naming the list and ``where`` (the entry): not found, not a regular file, not an
            image name.
    """
    if "\0" in rel:
        raise CalibrationError(path, f"{where}: the path contains a NUL character")
    p = Path(rel)
    if not p.is_absolute():
        # beside the list, else where OpenCV's sample looks: the current folder
        p = path.parent / p if (path.parent / p).exists() or not p.exists() else p.absolute()
    if not p.is_file():
        why = "not found" if not p.exists() else "not a regular file"
        at = p if Path(rel).is_absolute() else f"{p} or {Path(rel).absolute()}"
        raise CalibrationError(path, f"{where}: {rel} {why} ({at}; a relative path is looked up beside the list, "
                                     "then in the current folder)")
    if not re.search(rf"\.{IMAGE_EXT}$", p.name, re.IGNORECASE):
        raise CalibrationError(path, f"{where}: {rel} is not a PNG, TIFF, JPEG or BMP file name")
    return p


def _text_list_frames(path: Path, *, projector, layout) -> tuple[tuple[Path, ...]]:
    """The frames of a plain-text image list: one path a line, blank lines and ``#`` comments left out."""
    from ringscan.pipeline.formats.limits import check_regular_file

    check_regular_file(path, what="image list", max_bytes=MAX_LIST_BYTES)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise CalibrationError(path, f"not a text image list (one path a line): not UTF-8 text at byte "
                                     f"{e.start}") from None
    entries = []
    for k, line in enumerate(text.splitlines(), start=1):
        item = line.strip()
        if not item or item.startswith("#"):
            continue
        if len(entries) >= MAX_FRAMES:
            raise CalibrationError(path, f"more than {MAX_FRAMES} paths (at most {MAX_FRAMES} are read)")
        entries.append((k, item))
    want, what = _want(projector, layout)
    if len(entries) != want:
        raise CalibrationError(path, f"lists {len(entries)} frames, but {what}: wrong --projector?"
                                     f"{_fit_hint(len(entries))}")
    return (tuple(_resolve_listed(path, item, f"line {k}") for k, item in entries),)


def natural_key(name: str) -> tuple:
    """Sort key of a file name in natural order: runs of digits compare as numbers (DSC2 before DSC10),
    the rest without regard to case."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(t)) if t.isdigit() else (1, t.casefold()) for t in parts if t != ""), name


def list_capture(path, *, projector: tuple[int, int], layout: str = "opencv-graycode") -> CaptureFiles:
    """The frame files of one capture: a folder of ``graycode_NN`` or ``pattern_camN_imK`` frames, or an
    image list (see the module docstring), checked: names, frame counts against the projector size,
    every listed file there. Nothing is decoded.

    Raises:
        CalibrationError: naming the folder or file: not found, no frames of a known name (the
            names found), both kinds of names, a count that does not fit the projector, a gap in the
            numbering, camera 1's frames missing, a listed file that does not exist, an image list
            that is not FileStorage.
    """
    path = Path(path)
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    suffix = path.suffix.lower()
    if path.is_file() or (suffix in LIST_SUFFIXES + TEXT_LIST_SUFFIXES and not path.is_dir()):
        if suffix in TEXT_LIST_SUFFIXES:
            return CaptureFiles(source=path, kind="text",
                                cameras=_text_list_frames(path, projector=projector, layout=layout))
        if suffix not in LIST_SUFFIXES:
            raise CalibrationError(path, "a capture is a folder of frames or an image list (.yml, .yaml, .xml, "
                                         ".json; or a plain-text list, one path a line: .txt, .lst, .list), not "
                                         "this file")
        return CaptureFiles(source=path, kind="list", cameras=_list_frames(path, projector=projector, layout=layout))
    if not path.is_dir():
        raise CalibrationError(path, "capture folder not found")
    entries = sorted(p.name for p in path.iterdir())
    n_gc = sum(1 for e in entries if FRAME_RE.match(e))
    n_sample = sum(1 for e in entries if SAMPLE_RE.match(e))
    if n_gc and n_sample:
        raise CalibrationError(path, f"both graycode_NN ({n_gc}) and pattern_camN_imK ({n_sample}) frames: one "
                                     "capture per folder")
    if n_sample:
        return CaptureFiles(source=path, kind="pattern",
                            cameras=_sample_frames(path, entries, projector=projector, layout=layout))
    if not n_gc:
        imgs = sorted((e for e in entries if re.search(rf"\.{IMAGE_EXT}$", e, re.IGNORECASE)
                       and (path / e).is_file()), key=natural_key)
        want, what = _want(projector, layout)
        if imgs and len(imgs) == want:
            # frames named by the camera (DSC04052.JPG ...), as many as the layout has: capture order is
            # name order (the import prints the first and last names)
            log.info("%s: no graycode_NN or pattern_camN_imK names; %d frames taken in name order, %s .. %s",
                     path, len(imgs), imgs[0], imgs[-1])
            return CaptureFiles(source=path, kind="named", cameras=(tuple(path / e for e in imgs),))
        lists = [e for e in entries if Path(e).suffix.lower() in LIST_SUFFIXES + TEXT_LIST_SUFFIXES]
        seen = (f"; found {len(imgs)} image(s) of other names ({imgs[0]} .. {imgs[-1]}), but {what}: in name order "
                f"they would be its frames if there were {want}{_fit_hint(len(imgs))}" if imgs else
                "; it holds no PNG, TIFF, JPEG or BMP image")
        hint = f" (to import an image list, give the list: {path / lists[0]})" if lists else ""
        raise CalibrationError(path, "no frames named graycode_NN.<ext> (from 00) or pattern_camN_imK.<ext> "
                                     f"(OpenCV's sample, from 1){seen}{hint}")
    paths = capture_frames(path)
    want, what = _want(projector, layout)
    if len(paths) != want:
        raise CalibrationError(path, f"{len(paths)} graycode_NN frames, but {what}: wrong --layout or "
                                     f"--projector?{_fit_hint(len(paths))}")
    return CaptureFiles(source=path, kind="graycode", cameras=(tuple(paths),))


def check_capture_sizes(files: CaptureFiles) -> list[tuple[int, int]]:
    """Each camera's frame size (width, height), from the files' headers (nothing decoded).

    Raises:
        FormatError / CalibrationError: naming the file: unreadable header, too large, or a frame of
            another size than the camera's first frame.
    """
    from ringscan.pipeline.formats.limits import check_image_header

    sizes = []
    for c, frames in enumerate(files.cameras, start=1):
        first = check_image_header(frames[0])
        for p in frames[1:]:
            wh = check_image_header(p)
            if wh != first:
                cam = f" (camera {c})" if len(files.cameras) > 1 and files.kind != "pattern" else ""
                raise CalibrationError(p, f"frame is {wh[0]}x{wh[1]}, {frames[0].name}{cam} is {first[0]}x{first[1]}: "
                                          "every frame of a camera must have one size")
        sizes.append(first)
    return sizes


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


def _levels_of(a: np.ndarray) -> np.ndarray:
    """float32 8-bit levels of frames as read: uint16 values / 257 (as float32(value) * float32(1 / 257)),
    others as they are (a new array)."""
    out = a.astype(np.float32)
    if a.dtype == np.uint16:
        out *= np.float32(1.0 / 257.0)
    return out


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


def decode_graycode(cap: GrayCodeCapture, *, settings: GrayCodeSettings = GrayCodeSettings()) -> Decoded:
    """Integer projector column and row of every camera pixel (the plain decode)."""
    contrast = cap.white - cap.black
    weak = np.zeros(contrast.shape, np.int32)
    dim = DIM_BIT_FRACTION * contrast
    d = np.empty_like(contrast)
    bit = np.empty(contrast.shape, bool)

    def code(pairs):
        g = np.zeros(contrast.shape, np.int64 if len(pairs) > 30 else np.int32)
        ok = np.ones(contrast.shape, bool)
        for b in range(len(pairs)):
            pair_diff(pairs, b, cap.scale, out=d)
            np.greater(d, 0, out=bit)
            g <<= 1
            g |= bit
            np.abs(d, out=d)
            np.greater_equal(d, settings.min_bit_contrast, out=bit)
            ok &= bit
            np.less(d, dim, out=bit)
            weak[...] += bit
        return gray_decode(g, len(pairs)), ok

    col, okc = code(cap.col_pairs)
    row, okr = code(cap.row_pairs)
    valid = (contrast >= settings.min_contrast) | ((contrast >= settings.dim_contrast) & (weak <= DIM_MAX_WEAK))
    valid &= okc & okr & (col < cap.projector[0]) & (row < cap.projector[1])
    noise = frame_noise(cap, valid)
    coarse = np.zeros(contrast.shape + (2,), np.int8)
    low = np.zeros(contrast.shape, bool)
    for a, (pairs, c) in enumerate(((cap.col_pairs, col), (cap.row_pairs, row))):
        k = bit_clearance(pairs, contrast, valid, c, noise, scale=cap.scale)
        low |= k > MAX_COARSE_BITS
        coarse[..., a] = np.minimum(k, MAX_COARSE_BITS)
    low &= valid
    valid &= ~low
    col = np.where(valid, col, -1).astype(np.int32)
    row = np.where(valid, row, -1).astype(np.int32)
    log.info("%s: %d of %d pixels decoded (%d dropped: low_modulation)", cap.folder, int(valid.sum()), valid.size,
             int(low.sum()))
    return Decoded(col=col, row=row, valid=valid, contrast=contrast, coarse=coarse, low_modulation=low, noise=noise)


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
    r -= np.median(r)
    guess = 1.4826 * float(np.median(np.abs(r))) + 0.5
    return max(float(np.std(r[np.abs(r) < 4.0 * guess])) / 2.0, 0.25)


def _code_steps(code: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|code step| between decoded neighbours across (camera x) and down (camera y), steps over 2 (depth
    edges, misreads) left out."""
    c = code.astype(np.float64)
    gx = np.abs(np.diff(c, axis=1))[valid[:, 1:] & valid[:, :-1]]
    gy = np.abs(np.diff(c, axis=0))[valid[1:, :] & valid[:-1, :]]
    return gx[gx <= 2], gy[gy <= 2]


def bit_clearance(pairs: np.ndarray, contrast: np.ndarray, valid: np.ndarray, code: np.ndarray,
                  noise: float, *, scale: float = 1.0) -> np.ndarray:
    """(H, W) int: how many of a code's finest bits, counted from the finest, do not stand clear at each pixel.

    A bit stands clear where its modulation |pattern - inverse| near the pixel (the largest within half a
    stripe's width, so that a pixel on a stripe's edge, where the bit flips and has no contrast by nature,
    is judged by the stripe's middle) reaches ``CLEAR_NOISE_SIGMAS`` standard deviations of the
    difference's noise and ``CLEAR_CONTRAST_FRACTION`` of the pixel's white - black. A far, dark, grazing
    or defocused surface blurs the finest stripes into grey: their bits are then read by the noise, a
    zigzag of whole projector pixels along the epipolar line that no calibration check can see. The
    ``MAX_COARSE_BITS + 1`` finest bits are judged (the coarser ones are as wide as the contrast tests).
    """
    bits = pairs.shape[0]
    out = np.zeros(contrast.shape, np.int64)
    # projector px per camera px along the code's fast axis: the finest stripe's period in camera px
    g = np.concatenate(_code_steps(code, valid))
    g = g[g > 0]
    rate = float(np.median(g)) if g.size else 1.0
    thresh = np.maximum(CLEAR_NOISE_SIGMAS * math.sqrt(2.0) * noise, CLEAR_CONTRAST_FRACTION * contrast)
    for j in range(min(bits, MAX_COARSE_BITS + 2)):  # j = 0: the finest bit
        b = bits - 1 - j
        d = np.abs(pair_diff(pairs, b, scale))
        # bit j's stripes are 2**(j + 1) projector px wide: a pixel lies within half that of a stripe's middle
        r = int(min(max(math.ceil(2 ** j / max(rate, 1e-3)), 1), 32))
        near = cv2.dilate(d, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1)))
        out = np.where(near < thresh, j + 1, out)
    return out


def _along_axis(code: np.ndarray, valid: np.ndarray, pairs: np.ndarray, axis: int, max_span: float,
                scale: float = 1.0):
    """Sub-pixel coordinate along ``axis`` (0: camera rows, i.e. down; 1: across): each decoded pixel
    interpolated between the code boundaries around it (one Warp kernel walk a line,
    ``kernels.samples.subpixel_lines``; its figures are the NumPy construction's to the bit)."""
    return subpixel_lines(code, valid, pairs, bits=pairs.shape[0], axis=axis, max_span=max_span, scale=scale)


def _levels(code: np.ndarray, valid: np.ndarray, coarse: np.ndarray, pairs: np.ndarray, axis: int,
            max_span: float, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel coordinate of every pixel from the bits it trusts: a pixel that leaves its ``k`` finest bits
    untrusted is interpolated between the boundaries of blocks of 2**k projector pixels (the code without
    those bits: ``code >> k``, whose Gray bits are the first ``bits - k``), found between the pixels that
    trust at least those bits. A pixel that finds no two boundaries around it at its own level (beside a
    region of coarser pixels, say) takes the next coarser level that has them; where none has, a pixel
    that trusts every bit keeps its integer code (and is not sub-pixel)."""
    out = np.full(code.shape, np.nan)
    ok = np.zeros(code.shape, bool)
    bits = pairs.shape[0]
    top = int(coarse[valid].max()) if valid.any() else 0
    for k in range(0, min(top, bits - 1) + 1):
        todo = valid & (coarse <= k) & ~ok
        if not todo.any():
            continue
        lvl_valid = valid & (coarse <= k)
        lvl_code = np.where(lvl_valid, code >> k, -1)
        res, good = _along_axis(lvl_code, lvl_valid, pairs[:bits - k], axis, max_span * 2 ** k, scale)
        # block c of 2**k projector pixels has its centre at 2**k * c + (2**k - 1) / 2
        take = todo & good
        out = np.where(take, res * 2 ** k + (2 ** k - 1) / 2.0, out)
        ok |= take
    out = np.where(valid & ~ok & (coarse == 0), code, out)
    return out, ok


def subpixel_map(cap: GrayCodeCapture, dec: Decoded, *, settings: GrayCodeSettings = GrayCodeSettings()) -> Decoded:
    """Fill ``dec.u``, ``dec.v`` and ``dec.subpixel`` (see the module docstring); returns ``dec``."""

    def axis_of(code):
        gx, gy = _code_steps(code, dec.valid)
        return 1 if (gx.mean() if gx.size else 0) >= (gy.mean() if gy.size else 0) else 0

    ax_u, ax_v = axis_of(dec.col), axis_of(dec.row)
    coarse = dec.coarse if dec.coarse is not None else np.zeros(dec.valid.shape + (2,), np.int8)
    u, oku = _levels(dec.col, dec.valid, coarse[..., 0], cap.col_pairs, ax_u, settings.max_span_px, cap.scale)
    v, okv = _levels(dec.row, dec.valid, coarse[..., 1], cap.row_pairs, ax_v, settings.max_span_px, cap.scale)
    # a pixel whose finest bits are untrusted has no integer code to fall back on: it is dropped
    lost = dec.valid & (((coarse[..., 0] > 0) & ~oku) | ((coarse[..., 1] > 0) & ~okv))
    if dec.low_modulation is not None:
        dec.low_modulation |= lost
    dec.valid = dec.valid & ~lost
    dec.u = np.where(dec.valid, u, np.nan)
    dec.v = np.where(dec.valid, v, np.nan)
    dec.subpixel = oku & okv & dec.valid
    log.info("%s: sub-pixel u along camera %s, v along camera %s; %d of %d decoded pixels interpolated "
             "(%d from coarser bits)", cap.folder, "x" if ax_u else "y", "x" if ax_v else "y",
             int(dec.subpixel.sum()), int(dec.valid.sum()), int((dec.subpixel & (coarse.max(-1) > 0)).sum()))
    return dec
