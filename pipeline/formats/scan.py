"""The scan folder (docs/design.md §11): ``scan.json`` plus one image per frame per view.

::

    {"format": "ringscan.scan/1", "rig": {...} or "rig.json",
     "patterns": {"codec": ..., "width": 800, "height": 600,
                  "center": [400, 300], "rho0": 20.0, "pitch": 4.0, ...},
     "views": [{"name": "view_000", "turntable_deg": 0.0,
                "frames": {"white": "view_000/white.png", ...}}]}

Every path is relative to the scan folder and must stay inside it. Frames are 8- or
16-bit PNG or TIFF, grey or colour (converted to grey), all of the camera's size; or
a view's frames are one packed frame store (``ringscan.scan/2``, see
:mod:`ringscan.pipeline.formats.frame_store`)::

     "views": [{"name": "view_000", "turntable_deg": 0.0,
                "packed": {"store": "view_000/frames.zarr", "frames": ["white", ...]}}]

A two-camera rig (``camera2`` in the rig) adds camera 2's frames of a view under the
view's ``camera2`` key, as files or as a store (docs/formats.md)::

     "views": [{"name": "view_000", "frames": {...},
                "camera2": {"frames": {"white": "view_000/cam2/white.png", ...}}}]

``frame_bits`` (optional, 8 for 8-bit frames, 9..16 for 16-bit ones; default the
frames' own bits) says how many bits a 16-bit frame holds, LSB-aligned (a 12-bit
camera's frames: 0..4095); such frames are scaled to the full 16-bit range as they
are read (:func:`read_view_frames`).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.buffers import FrameBuffers
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.frame_store import check_chunk_files, open_store, read_store
from ringscan.pipeline.formats.images import FRAME_BITS_RANGE, expand_frame_bits, read_image
from ringscan.pipeline.formats.limits import check_image_header
from ringscan.pipeline.formats.patterns import PatternSpec, frame_names, parse_patterns
from ringscan.pipeline.formats.rig import Rig, parse_rig, rig_to_dict

SCAN_FORMAT = "ringscan.scan/1"
SCAN_FORMAT_PACKED = "ringscan.scan/2"
"""scan/1 plus views whose frames are a packed frame store; written only when a view is packed,
so that scans of image files stay readable by earlier versions."""
SCAN_FORMATS = (SCAN_FORMAT, SCAN_FORMAT_PACKED)

__all__ = ["SCAN_FORMAT", "SCAN_FORMAT_PACKED", "View", "Scan", "load_scan", "save_scan", "read_view_frames",
           "read_view_frame", "frame_files", "scan_to_dict", "check_view_name", "check_truth", "check_view_frames",
           "packed_view", "as_camera2", "check_frame_bits"]


@dataclass(frozen=True)
class View:
    """One view of a scan: a turntable angle and one image file per frame."""

    name: str
    """Folder-safe view name, e.g. ``view_000``."""
    turntable_deg: float
    """Turntable angle of this view in degrees (docs/design.md §11)."""
    frames: dict[str, str]
    """Frame name -> path relative to the scan folder (POSIX separators); for a packed
    view, every frame maps to the store folder, in store order."""
    packed: str | None = None
    """The packed frame store (path relative to the scan folder) holding this view's
    frames, or None for image files."""
    camera2: View | None = None
    """Camera 2's frames of this view (a two-camera rig; same name and frame names,
    its own files or store), or None. Read them with ``as_camera2(scan)``."""


@dataclass(frozen=True)
class Scan:
    """A loaded, validated scan folder."""

    folder: Path
    """The scan folder."""
    rig: Rig
    """The rig (calibration)."""
    patterns: PatternSpec
    """The projected pattern set."""
    views: tuple[View, ...]
    """The views in capture order."""
    rig_ref: str | None = None
    """The rig file name when scan.json refers to one (``"rig.json"``), else None."""
    extra: dict = field(default_factory=dict)
    """Other top-level keys of scan.json, kept as they were (e.g. ``truth``)."""
    frame_bits: int | None = None
    """Significant bits of the frames (scan.json ``frame_bits``): 8 for 8-bit frames, 9..16
    for 16-bit frames holding values 0..2^frame_bits - 1 (a 10- or 12-bit camera's), which
    are read scaled to 0..65535; None: the frames' own bits (8 or 16)."""

    @property
    def path(self) -> Path:
        return self.folder / "scan.json"

    def frame_path(self, view: View, name: str) -> Path:
        return self.folder / view.frames[name]


_NAME_FORBIDDEN = set('/\\<>:"|?*')


def check_view_name(name, *, source=None, where: str = "name") -> str:
    """Check that a view name is safe as a file and folder name (its PLY is
    ``<name>.ply``, its frames usually live in ``<name>/``): a non-empty string of at
    most 200 characters, not starting with a dot (no ``.``, ``..`` or hidden files),
    without control characters or any of ``/ \\ < > : " | ? *``.

    Raises:
        FormatError: naming ``source`` and ``where``.
    """
    if not isinstance(name, str) or not name:
        raise FormatError(source, f"{where}: expected a non-empty name, got {name!r}")
    bad = sorted({c for c in name if c in _NAME_FORBIDDEN or not c.isprintable()})
    if name.startswith(".") or bad or len(name) > 200:
        why = ("starts with a dot" if name.startswith(".") else
               f"contains {', '.join(repr(c) for c in bad)}" if bad else "is longer than 200 characters")
        raise FormatError(source, f"{where}: {name!r} is not a folder-safe name ({why})")
    return name


def _safe_rel(folder: Path, src: Path, where: str, rel) -> str:
    if not isinstance(rel, str) or not rel:
        raise FormatError(src, f"{where}: expected a relative path, got {rel!r}")
    if "\0" in rel or not rel.isprintable():
        raise FormatError(src, f"{where}: path {rel!r} contains a control character (a NUL, a newline...)")
    p = PurePosixPath(rel.replace("\\", "/"))
    if p.is_absolute() or ".." in p.parts or (len(rel) > 1 and rel[1] == ":"):
        raise FormatError(src, f"{where}: path {rel!r} leaves the scan folder")
    # Without ".." the path can only leave the folder through a link: look for one
    # among its own components (one lstat each) and resolve the whole path only then.
    cur = folder
    for part in p.parts:
        cur = cur / part
        if cur.is_symlink():
            try:
                full = (folder / p).resolve()
                root = folder.resolve()
            except (RuntimeError, OSError):  # a link loop (Python 3.11: RuntimeError; later: OSError)
                raise FormatError(src, f"{where}: path {rel!r} cannot be followed: {cur} is a loop of symbolic "
                                       "links") from None
            if full != root and root not in full.parents:
                raise FormatError(src, f"{where}: path {rel!r} leaves the scan folder (through a link)")
            break
    return str(p)


def load_scan(folder: str | os.PathLike, *, check_files: bool = True, allow_incomplete: bool = False) -> Scan:
    """Read and validate a scan folder (or its scan.json).

    Args:
        folder: the scan folder, or the path of its scan.json.
        check_files: also check that every frame file exists.
        allow_incomplete: accept views that lack frames (a capture in progress).

    Raises:
        FormatError: naming the file and the field for every problem.
    """
    folder = Path(folder)
    if folder.name == "scan.json" and folder.is_file():
        folder = folder.parent
    src = folder / "scan.json"
    if not folder.is_dir():
        raise FormatError(folder, "scan folder not found")
    d = read_json(src)
    fmt = d.get("format")
    if fmt not in SCAN_FORMATS:
        raise FormatError(src, f"format: unknown scan format {fmt!r} (this version reads "
                               f"{' and '.join(map(repr, SCAN_FORMATS))})")

    rig_d = d.get("rig")
    rig_ref = None
    if isinstance(rig_d, str):
        rig_ref = _safe_rel(folder, src, "rig", rig_d)
        rig_path = folder / rig_ref
        rig = parse_rig(read_json(rig_path), source=rig_path)
    elif isinstance(rig_d, dict):
        rig = parse_rig(rig_d, source=f"{src} (rig)")
    else:
        raise FormatError(src, "rig: expected an object or the name of a rig file")

    patterns = parse_patterns(d.get("patterns"), source=src)
    light_w = getattr(rig.light, "width", 0)
    light_h = getattr(rig.light, "height", 0)
    if light_w and (patterns.width, patterns.height) != (light_w, light_h):
        raise FormatError(src, f"patterns: {patterns.width}x{patterns.height} does not match the rig's "
                               f"{light_w}x{light_h} projector")
    needed = frame_names(patterns)

    views_d = d.get("views")
    if not isinstance(views_d, list):
        raise FormatError(src, "views: expected a list")
    views, names = [], set()
    for i, vd in enumerate(views_d):
        where = f"views[{i}]"
        if not isinstance(vd, dict):
            raise FormatError(src, f"{where}: expected an object")
        name = check_view_name(vd.get("name", f"view_{i:03d}"), source=src, where=f"{where}.name")
        if name.casefold() in names:
            raise FormatError(src, f"{where}.name: {name!r} is not unique (names are compared ignoring case)")
        names.add(name.casefold())
        deg = vd.get("turntable_deg", 0.0)
        if isinstance(deg, bool) or not isinstance(deg, (int, float)) or not math.isfinite(deg):
            raise FormatError(src, f"{where}.turntable_deg: expected a finite number, got {deg!r}")
        parse = dict(folder=folder, src=src, fmt=fmt, name=name, needed=needed, codec=patterns.codec,
                     check_files=check_files, allow_incomplete=allow_incomplete)
        frames, store = _parse_frames(vd, where, **parse)
        second = None
        if "camera2" in vd:
            c2 = vd["camera2"]
            if rig.camera2 is None:
                raise FormatError(src, f"{where}.camera2: the rig has one camera (no camera2): a two-camera view "
                                       "needs a two-camera rig")
            if not isinstance(c2, dict):
                raise FormatError(src, f"{where}.camera2: expected an object with frames or packed")
            f2, s2 = _parse_frames(c2, f"{where}.camera2", **{**parse, "name": f"{name} (camera 2)"})
            second = View(name=name, turntable_deg=float(deg), frames=f2, packed=s2)
        views.append(View(name=name, turntable_deg=float(deg), frames=frames, packed=store, camera2=second))
    bits = d.get("frame_bits")
    if bits is not None:
        check_frame_bits(bits, source=src)
    if bits is not None and bits != 16 and patterns.codec == "decoded":
        raise FormatError(src, f"frame_bits: {bits}, but the decoded codec's frames are projector coordinates, not "
                               "grey levels (leave frame_bits out, or 16)")
    extra = {k: v for k, v in d.items() if k not in ("format", "rig", "patterns", "views", "frame_bits")}
    return Scan(folder=folder, rig=rig, patterns=patterns, views=tuple(views), rig_ref=rig_ref, extra=extra,
                frame_bits=bits)


def check_frame_bits(bits, *, source=None, where: str = "frame_bits") -> int:
    """Check a ``frame_bits`` value: a whole number, 8 (8-bit frames) or 9..16 (16-bit frames).

    Raises:
        FormatError: naming ``source`` and ``where``.
    """
    lo, hi = FRAME_BITS_RANGE
    if isinstance(bits, bool) or not isinstance(bits, int) or not (bits == 8 or lo <= bits <= hi):
        raise FormatError(source, f"{where}: expected a whole number, 8 for 8-bit frames or {lo}..{hi} for 16-bit "
                                  f"frames (the bits a camera's frame holds), got {bits!r:.60}")
    return bits


def _parse_frames(vd: dict, where: str, *, folder: Path, src: Path, fmt: str, name: str, needed: list[str],
                  codec: str, check_files: bool, allow_incomplete: bool) -> tuple[dict[str, str], str | None]:
    """One camera's frames of a view: (frame name -> path, store or None).

    Size: a private step of the scan parser: the camera's block and where it is (for messages), and as
    keyword-only arguments the context the scan parser builds once per view (one dict, passed for each camera):
    the scan folder and scan.json's path, the format, the view's name, the frames the codec needs, the checks to
    make.
    """
    store = None
    if "packed" in vd:
        store, frames = _parse_packed(folder, src, where, vd, fmt)
    else:
        fr = vd.get("frames")
        if not isinstance(fr, dict):
            raise FormatError(src, f"{where}.frames: expected an object")
        frames = {k: _safe_rel(folder, src, f"{where}.frames.{k}", v) for k, v in fr.items()}
    missing = [n for n in needed if n not in frames]
    if missing and not allow_incomplete:
        raise FormatError(src, f"{where}.frames: missing frame(s) {', '.join(missing)} of the {codec} codec")
    if check_files and store is not None:
        if not (folder / store / "zarr.json").is_file():
            raise FormatError(folder / store, f"frame store of {name} not found (listed in scan.json "
                                              f"{where}.packed.store)")
    elif check_files:
        for k, rel in frames.items():
            if not (folder / rel).is_file():
                raise FormatError(folder / rel, f"frame {k!r} of {name} not found (listed in scan.json {where}.frames)")
    return frames, store


def as_camera2(scan: Scan) -> Scan:
    """The same scan seen from camera 2: the rig's cameras swapped, so that every
    one-camera function (frame checks, reading, decoding) works on camera 2's frames
    (``view.camera2``) unchanged.

    Raises:
        FormatError: the rig has no second camera.
    """
    rig = scan.rig
    if rig.camera2 is None:
        raise FormatError(scan.path, "the rig has one camera (no camera2)")
    return replace(scan, rig=replace(rig, camera=rig.camera2, camera2=rig.camera))


def check_truth(scan: Scan) -> dict:
    """The scan's ``truth`` block (the virtual rig's ground truth), checked: ``mesh`` a path
    inside the scan folder; ``views`` an object of ``{"depth": path, "lit": path}`` inside
    it (and camera 2's likewise under ``camera2``); ``reference_plane_z`` a finite number; ``reference_plane`` true or false.

    Returns:
        A checked copy: mesh, views, reference_plane_z, reference_plane, settings, scene.

    Raises:
        FormatError: naming scan.json and the field (no truth block, a wrong type, a path
            that leaves the scan folder).
    """
    src = scan.path
    t = scan.extra.get("truth")
    if not isinstance(t, dict):
        raise FormatError(src, "no 'truth' block: this scan has no ground truth (simulate it with `ringscan simulate`)")
    out = {"mesh": _safe_rel(scan.folder, src, "truth.mesh", t.get("mesh"))}
    views = t.get("views", {})
    if not isinstance(views, dict):
        raise FormatError(src, f"truth.views: expected an object {{view: {{\"depth\": path, \"lit\": path}}}}, "
                               f"got {views!r:.60}")
    out["views"] = {}
    for name, v in views.items():
        if not isinstance(v, dict):
            raise FormatError(src, f"truth.views.{name}: expected an object {{\"depth\": path, \"lit\": path}}")
        out["views"][name] = {k: _safe_rel(scan.folder, src, f"truth.views.{name}.{k}", v.get(k))
                              for k in ("depth", "lit")}
        if "camera2" in v:  # camera 2's truth of a two-camera scan
            c2 = v["camera2"]
            if not isinstance(c2, dict):
                raise FormatError(src, f"truth.views.{name}.camera2: expected an object {{\"depth\": path, \"lit\": path}}")
            out["views"][name]["camera2"] = {k: _safe_rel(scan.folder, src, f"truth.views.{name}.camera2.{k}",
                                                          c2.get(k)) for k in ("depth", "lit")}
    z = t.get("reference_plane_z", 0.0)
    if isinstance(z, bool) or not isinstance(z, (int, float)) or not math.isfinite(z):
        raise FormatError(src, f"truth.reference_plane_z: expected a finite number, got {z!r:.60}")
    out["reference_plane_z"] = float(z)
    plane = t.get("reference_plane", True)
    if not isinstance(plane, bool):
        raise FormatError(src, f"truth.reference_plane: expected true or false, got {plane!r:.60}")
    out["reference_plane"] = plane
    settings = t.get("settings", {})
    out["settings"] = dict(settings) if isinstance(settings, dict) else {}
    out["scene"] = str(t.get("scene", ""))
    return out


def _parse_packed(folder: Path, src: Path, where: str, vd: dict, fmt: str) -> tuple[str, dict[str, str]]:
    if fmt != SCAN_FORMAT_PACKED:
        raise FormatError(src, f"{where}.packed: packed frames need format {SCAN_FORMAT_PACKED!r}, not {fmt!r}")
    if "frames" in vd:
        raise FormatError(src, f"{where}: both frames and packed (a view's frames are files or one store)")
    pk = vd["packed"]
    if not isinstance(pk, dict):
        raise FormatError(src, f"{where}.packed: expected an object with store and frames")
    store = _safe_rel(folder, src, f"{where}.packed.store", pk.get("store"))
    names = pk.get("frames")
    if (not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names)
            or len(set(names)) != len(names)):
        raise FormatError(src, f"{where}.packed.frames: expected a list of distinct frame names")
    for i, n in enumerate(names):  # `ringscan unpack` writes <view folder>/<name>.png
        check_view_name(n, source=src, where=f"{where}.packed.frames[{i}]")
    return store, {n: store for n in names}


def _view_to_dict(v: View) -> dict:
    d = {"name": v.name, "turntable_deg": v.turntable_deg, **_frames_to_dict(v)}
    if v.camera2 is not None:
        d["camera2"] = _frames_to_dict(v.camera2)
    return d


def _frames_to_dict(v: View) -> dict:
    if v.packed is not None:
        return {"packed": {"store": v.packed, "frames": list(v.frames)}}
    return {"frames": dict(v.frames)}


def packed_view(view: View, store: str, names: list[str]) -> View:
    """``view`` with its frames in the store ``store`` (relative to the scan folder); camera 2's
    frames (if any) as they were."""
    return View(name=view.name, turntable_deg=view.turntable_deg, frames={n: store for n in names}, packed=store,
                camera2=view.camera2)


def scan_to_dict(scan: Scan) -> dict:
    packed = any(v.packed is not None or (v.camera2 is not None and v.camera2.packed is not None) for v in scan.views)
    d = {"format": SCAN_FORMAT_PACKED if packed else SCAN_FORMAT,
         "rig": scan.rig_ref if scan.rig_ref else rig_to_dict(scan.rig),
         "patterns": scan.patterns.to_dict(),
         **({} if scan.frame_bits is None else {"frame_bits": scan.frame_bits}),
         "views": [_view_to_dict(v) for v in scan.views]}
    d.update(scan.extra)
    return d


def save_scan(scan: Scan) -> None:
    """Write ``scan.json`` atomically (frames are written by the caller).

    Raises:
        FormatError: a view name that is not folder-safe (see :func:`check_view_name`).
    """
    for i, v in enumerate(scan.views):
        check_view_name(v.name, source=scan.path, where=f"views[{i}].name")
    scan.folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(scan.path, scan_to_dict(scan))


def check_view_frames(scan: Scan, view: View) -> None:
    """Check a view's frame files from their headers, without decoding them: regular image
    files within the size limits (:func:`~.limits.check_image_header`), of the camera's size;
    a packed view's store from its metadata (every frame there, the camera's size) and its
    chunk files (there, regular, of a possible size; their checksums as they are decoded).
    A reconstruction calls it for every view before it writes anything.

    Raises:
        FormatError: naming the frame file.
    """
    cam = scan.rig.camera
    if view.packed is not None:  # one store: its metadata says the size of every frame
        info = open_store(scan.folder / view.packed)
        meta = scan.folder / view.packed / "zarr.json"
        missing = [n for n in frame_names(scan.patterns) if n not in info.names]
        if missing:
            raise FormatError(meta, f"frame {missing[0]!r} is not in the store")
        if [n for n in info.names if n in view.frames] != list(view.frames):  # as a read checks it
            raise FormatError(meta, f"frames {', '.join(info.names)} do not match scan.json's list for {view.name} "
                                    f"({', '.join(view.frames)})")
        if (info.width, info.height) != (cam.width, cam.height):
            raise FormatError(meta, f"frames are {info.width}x{info.height}, but the camera is {cam.width}x{cam.height}")
        bits = scan.frame_bits
        if bits is not None and (bits == 8) != (info.dtype == np.uint8):
            raise FormatError(meta, f"frames are {info.dtype}, but frame_bits in {scan.path} says {bits}")
        check_chunk_files(info, frame_names(scan.patterns))
        if view.camera2 is not None:
            check_view_frames(as_camera2(scan), view.camera2)
        return
    for n in frame_names(scan.patterns):
        if n not in view.frames:
            raise FormatError(scan.path, f"view {view.name}: frame {n!r} is not listed")
        p = scan.frame_path(view, n)
        w, h = check_image_header(p)
        if (w, h) != (cam.width, cam.height):
            raise FormatError(p, f"frame is {w}x{h}, but the camera is {cam.width}x{cam.height}")
    if view.camera2 is not None:
        check_view_frames(as_camera2(scan), view.camera2)


def read_view_frames(scan: Scan, view: View, names: list[str] | None = None, *, threads: int | None = None,
                     buffers: FrameBuffers | None = None, raw: bool = False) -> np.ndarray:
    """Read a view's frames as one (n_frames, H, W) array (uint8 or uint16).

    Frames are read in the order of ``names`` (default: the codec's frame order),
    ``threads`` at a time (default: the CPU count, at most 8; image decoding
    releases the GIL, and decoding PNGs costs more than reconstructing them).
    Raises :class:`FormatError` naming the file for a missing or unreadable frame,
    frames of different sizes or bit depths, or a size other than the camera's
    (the first such frame in frame order). A packed view is read from its frame
    store, ``threads`` frames decoded at a time, every chunk's checksum checked; its
    frame names (as scan.json lists them), size and dtype must match. With
    ``buffers`` the stack is taken from that pool (give it back when done with it).

    A scan whose ``frame_bits`` is below 16 has its 16-bit frames scaled to the full
    16-bit range in place (:func:`~.images.expand_frame_bits`), so that every threshold
    and the saturation level hold as for 16-bit frames; ``raw=True`` reads the values
    as stored (packing, replaying a scan). Raises :class:`FormatError` naming the frame
    file for a value above the range ``frame_bits`` says, or frames of another bit depth
    than it says.
    """
    names = frame_names(scan.patterns) if names is None else names
    cam = scan.rig.camera
    for n in names:
        if n not in view.frames:
            raise FormatError(scan.path, f"view {view.name}: frame {n!r} is not listed")
    if view.packed is not None:
        out, paths = _read_packed(scan, view, names, buffers=buffers,
                                  threads=min(8, os.cpu_count() or 1) if threads is None else threads)
        return out if raw else _apply_frame_bits(scan, out, paths)
    paths = [scan.frame_path(view, n) for n in names]
    threads = min(8, os.cpu_count() or 1) if threads is None else max(1, int(threads))

    def read(p):
        try:
            return read_image(p)
        except FormatError as e:
            return e

    if threads > 1 and len(paths) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=min(threads, len(paths))) as ex:
            images = list(ex.map(read, paths))
    else:
        images = [read(p) for p in paths]
    out = None
    for i, (p, img) in enumerate(zip(paths, images)):
        if isinstance(img, FormatError):
            raise img
        if img.shape != (cam.height, cam.width):
            raise FormatError(p, f"frame is {img.shape[1]}x{img.shape[0]}, but the camera is {cam.width}x{cam.height}")
        if out is None:
            shape = (len(names), cam.height, cam.width)
            out = np.empty(shape, img.dtype) if buffers is None else buffers.take(shape, img.dtype)
        elif img.dtype != out.dtype:
            raise FormatError(p, f"frame is {img.dtype}, other frames of {view.name} are {out.dtype}")
        out[i] = img
    return out if raw else _apply_frame_bits(scan, out, paths)


def _apply_frame_bits(scan: Scan, frames: np.ndarray, files: list[Path]) -> np.ndarray:
    """``frames`` ((n, H, W), ``files[i]`` holding frame i) scaled to 16 bits where
    scan.json's ``frame_bits`` says they hold fewer, after checking that they do."""
    bits = scan.frame_bits
    if bits is None or len(frames) == 0:
        return frames
    if frames.dtype == np.uint8:
        if bits != 8:
            raise FormatError(files[0], f"frame is 8-bit, but frame_bits in {scan.path} says {bits}")
        return frames
    if bits == 8:
        raise FormatError(files[0], f"frame is 16-bit, but frame_bits in {scan.path} says 8 (9..16 for 16-bit frames)")
    if bits == 16:
        return frames
    top = (1 << bits) - 1
    for f, p in zip(frames, files):  # every frame: a max costs little beside its decoding
        m = int(f.max())
        if m > top:
            raise FormatError(p, f"frame holds {m}, above the {bits}-bit range frame_bits says ({top}) in "
                                 f"{scan.path}: set frame_bits to the camera's bits")
    return expand_frame_bits(frames, bits)


def _read_packed(scan: Scan, view: View, names: list[str], *, threads: int,
                 buffers: FrameBuffers | None = None) -> tuple[np.ndarray, list[Path]]:
    info = open_store(scan.folder / view.packed)
    meta = info.path / "zarr.json"
    # scan.json lists the store's frames in store order (only those captured so far, during a capture)
    if [n for n in info.names if n in view.frames] != list(view.frames):
        raise FormatError(meta, f"frames {', '.join(info.names)} do not match scan.json's list for {view.name} "
                                f"({', '.join(view.frames)})")
    cam = scan.rig.camera
    if (info.height, info.width) != (cam.height, cam.width):
        raise FormatError(meta, f"frames are {info.width}x{info.height}, but the camera is {cam.width}x{cam.height}")
    out = None if buffers is None else buffers.take((len(names), info.height, info.width), info.dtype)
    return (read_store(info, names, threads=max(1, int(threads)), out=out),
            [info.chunk_path(info.index(n)) for n in names])


def frame_files(scan: Scan, view: View) -> dict[str, Path]:
    """Frame name -> the file holding it: the image file, or for a packed view the frame's
    chunk file in the store (the store folder when its metadata cannot be read)."""
    if view.packed is None:
        return {n: scan.frame_path(view, n) for n in view.frames}
    try:
        info = open_store(scan.folder / view.packed)
    except FormatError:
        return {n: scan.folder / view.packed for n in view.frames}
    return {n: info.chunk_path(info.index(n)) if n in info.names else info.path for n in view.frames}


def read_view_frame(scan: Scan, view: View, name: str, *, raw: bool = False) -> np.ndarray:
    """Read one frame of a view (an image file or a frame of its store) as a 2D array,
    scaled as :func:`read_view_frames` scales it (``raw``: as stored)."""
    if view.packed is None:
        if name not in view.frames:
            raise FormatError(scan.path, f"view {view.name}: frame {name!r} is not listed")
        p = scan.frame_path(view, name)
        img = read_image(p)
        return img if raw else _apply_frame_bits(scan, img[None], [p])[0]
    return read_view_frames(scan, view, [name], threads=1, raw=raw)[0]
