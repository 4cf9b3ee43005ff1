"""Which files make a Gray-code capture (:mod:`~ringscan.pipeline.calibrate.graycode`), per camera, in
capture order: checked against the projector size and layout, nothing decoded.

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

PNG, TIFF, JPEG and BMP frames are read.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import LAYOUTS, graycode_bits

__all__ = ["CAPTURE_INPUTS", "LIST_SUFFIXES", "TEXT_LIST_SUFFIXES", "CaptureFiles", "natural_key", "list_capture",
           "check_capture_sizes", "open_filestorage"]

log = logging.getLogger(__name__)

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
