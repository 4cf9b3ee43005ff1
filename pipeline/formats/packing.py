"""Packing a scan's image frames into frame stores (one per view), and back.

Both directions are lossless and checked frame by frame before anything is
removed, atomic per view, and resumable (a killed run is finished by running it
again):

1. the new form is written whole (a store into a temporary folder renamed into
   place; image files each atomically) and read back and compared, frame by frame,
   with the frames read from the old form;
2. scan.json is rewritten (atomically) to name the new form;
3. the old form is removed (unless ``keep``).

A run killed between 2 and 3 leaves the old files beside the new ones; the next
run finds them (``<view folder>/<frame>.png|.tif|.tiff`` beside a store,
``<view folder>/frames.zarr`` beside image files), compares them again, and
removes them. Frames are kept as ringscan reads them: a colour PNG frame (which
ringscan reads as grey) is refused rather than packed. A two-camera view's camera-2
frames are converted with it (their store beside them, ``<view>/cam2/frames.zarr``),
and scan.json names both cameras' new form in one write.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import secrets
import shutil
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.atomic import remove_stale_temporaries
from ringscan.pipeline.formats.frame_store import (STORE_NAME, is_store, missing_frames, open_store, read_store,
                                                   remove_stale_stores, write_store)
from ringscan.pipeline.formats.images import read_image, write_image
from ringscan.pipeline.formats.limits import image_header_colour
from ringscan.pipeline.formats.scan import (Scan, View, as_camera2, check_view_frames, check_view_name, load_scan,
                                           packed_view, read_view_frames, save_scan)

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".tif", ".tiff")

__all__ = ["PackResult", "pack_scan", "unpack_scan"]


@dataclass
class PackResult:
    """What :func:`pack_scan` or :func:`unpack_scan` did to one scan."""

    folder: Path
    """The scan folder."""
    converted: list[str] = field(default_factory=list)
    """Views converted by this run."""
    already: list[str] = field(default_factory=list)
    """Views that were in the asked-for form already."""
    removed: int = 0
    """Files removed (old frames; a store counts as one)."""
    bytes_before: int = 0
    """Size of the converted views' old frames."""
    bytes_after: int = 0
    """Size of the converted views' new frames."""


def _size(p: Path) -> int:
    if p.is_dir():
        return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
    return p.stat().st_size if p.is_file() else 0


def _view_folder(view: View) -> str:
    """The folder of a view's frames (their common parent), relative to the scan folder."""
    parents = {PurePosixPath(r).parent.as_posix() for r in view.frames.values()}
    return parents.pop() if len(parents) == 1 else view.name


def _check_grey(path: Path) -> None:
    """Refuse a colour frame, PNG, TIFF, JPEG or BMP alike (ringscan reads it as grey: packing it, then removing
    it, would lose the colour), from the file's header."""
    try:
        colour = image_header_colour(path)
    except OSError:
        colour = None  # unreadable: the read names it
    if colour:
        raise FormatError(path, "colour frame: a packed store keeps frames as ringscan reads them (grey); "
                                "convert it to grey first")


def _remove_leftover_images(scan: Scan, view: View, *, keep: bool, needed: frozenset = frozenset()) -> int:
    """Image files of a packed view's frames left by a run killed before it removed them (``needed``: files
    that views not yet packed name, left in place)."""
    if keep:
        return 0
    vdir = scan.folder / PurePosixPath(view.packed).parent
    found = [(n, vdir / f"{n}{ext}") for n in view.frames for ext in IMAGE_EXTENSIONS
             if (vdir / f"{n}{ext}").is_file() and vdir / f"{n}{ext}" not in needed]
    if not found:
        return 0
    frames = read_store(open_store(scan.folder / view.packed), [n for n, _ in found])
    for (n, p), img in zip(found, frames):
        if not np.array_equal(read_image(p), img):
            raise FormatError(p, f"differs from frame {n!r} of the store {view.packed} (kept; remove it by hand)")
    for _, p in found:
        p.unlink()
    return len(found)


def _cameras(scan: Scan, view: View) -> list[tuple[Scan, View, str]]:
    """A view's frames of each camera: (the scan as that camera sees it, the camera's
    view, its label for the log); camera 2's only in a two-camera view."""
    out = [(scan, view, "camera 1")]
    if view.camera2 is not None:
        out.append((as_camera2(scan), view.camera2, "camera 2"))
    return out


def _with_camera(view: View, cam: int, new: View) -> View:
    """``view`` with camera ``cam``'s frames (1: the view's own, 2: its ``camera2``) replaced by ``new``'s."""
    if cam == 1:
        return dataclasses.replace(new, name=view.name, turntable_deg=view.turntable_deg, camera2=view.camera2)
    return dataclasses.replace(view, camera2=dataclasses.replace(new, name=view.name, camera2=None))


def pack_scan(folder: str | os.PathLike, *, keep: bool = False) -> PackResult:
    """Pack every view of a scan whose frames are image files into ``<view folder>/frames.zarr``
    (camera 2's frames of a two-camera view into a store beside them, ``<view>/cam2/frames.zarr``).

    Args:
        folder: the scan folder.
        keep: leave the image files where they are (scan.json names the store all the same).

    Raises:
        FormatError: naming the file: an unreadable or colour frame, frames of
            different sizes, a damaged store; the views before it stay packed.
    """
    scan = load_scan(folder)
    res = PackResult(folder=scan.folder)
    for i, v in enumerate(scan.views):
        for _, cv, _ in _cameras(scan, v):
            if cv.packed is None:
                where = f"views[{i}]{'.camera2' if cv is v.camera2 else ''}.frames: frame name"
                for n, rel in cv.frames.items():
                    check_view_name(n, source=scan.path, where=where)  # scan/2 asks it
                    _check_grey(scan.folder / rel)
    views = list(scan.views)
    # each camera's frame folder: a store goes beside its frames, unless other frames share the folder
    folders = [_view_folder(cv) for v in views for _, cv, _ in _cameras(scan, v)]

    def needed() -> frozenset:
        """The image files that views not packed yet name (two views may name one file): kept until the last
        of them is packed."""
        return frozenset(scan.folder / r for v in views for _, cv, _ in _cameras(scan, v) if cv.packed is None
                         for r in cv.frames.values())

    for i, v in enumerate(views):
        units = _cameras(scan, v)
        if all(cv.packed is not None for _, cv, _ in units):
            res.already.append(v.name)
            for _, cv, _ in units:
                res.removed += _remove_leftover_images(scan, cv, keep=keep, needed=needed())
            continue
        new, old, stores = v, [], []
        for cam, (cscan, cv, label) in enumerate(units, 1):
            if cv.packed is not None:
                res.removed += _remove_leftover_images(scan, cv, keep=keep, needed=needed())
                continue
            names = list(cv.frames)
            f = _view_folder(cv)
            vdir = f if f != "." and folders.count(f) == 1 else (v.name if cam == 1 else f"{v.name}/cam2")
            store_rel = f"{vdir}/{STORE_NAME}"
            old += [scan.folder / r for r in dict.fromkeys(cv.frames.values())]
            frames = read_view_frames(cscan, cv, names, raw=True)  # as stored: frame_bits stays in scan.json
            remove_stale_stores((scan.folder / store_rel).parent)
            write_store(scan.folder / store_rel, frames, names)  # read back and compared before the rename
            new = _with_camera(new, cam, packed_view(cv, store_rel, names))
            stores.append(store_rel)
            log.info("%s: packed %s, %s (%d frames)", scan.folder, v.name, label, len(names))
        # scan.json names the new stores of both cameras at once: the view is packed or it is not
        views[i] = new
        scan = dataclasses.replace(scan, views=tuple(views))
        save_scan(scan)
        res.converted.append(v.name)
        res.bytes_before += sum(_size(p) for p in old)
        res.bytes_after += sum(_size(scan.folder / r) for r in stores)
        if not keep:
            still = needed()  # a file a later view names too goes with that view
            gone = [p for p in dict.fromkeys(old) if p not in still]
            for p in gone:
                p.unlink(missing_ok=True)
            res.removed += len(gone)
    return res


def _remove_store(store: Path) -> None:
    """Remove a store folder: renamed first to a temporary name (:func:`remove_stale_stores` removes what a killed
    run leaves of it), so that a run killed while deleting never leaves a store without its chunks under its
    own name."""
    tmp = store.parent / f".{store.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp"
    os.replace(store, tmp)
    shutil.rmtree(tmp)


def _remove_leftover_store(scan: Scan, view: View, *, keep: bool) -> int:
    """The store of an unpacked view left by a run killed before it removed it (``scan``
    as the view's camera sees it). Its frames whose chunks are there are compared with
    the image files; chunks already removed (a run killed while deleting it with an older
    ringscan) were compared before scan.json named the image files."""
    if keep:
        return 0
    store = scan.folder / _view_folder(view) / STORE_NAME
    if not is_store(store):
        return 0
    info = open_store(store)
    if set(info.names) != set(view.frames):
        return 0  # not this view's store: leave it
    there = [n for n in info.names if n not in missing_frames(info)]
    if there:
        frames = read_view_frames(scan, view, there, raw=True)
        if not np.array_equal(read_store(info, there), frames):
            raise FormatError(store, f"differs from the image frames of {view.name} (kept; remove it by hand)")
    _remove_store(store)
    return 1


def _image_paths(scan: Scan, view: View, image_format: str) -> dict[str, str]:
    """Frame name -> the image file (relative) that unpacking a packed view writes."""
    vdir = PurePosixPath(view.packed).parent
    return {n: (vdir / f"{n}.{image_format}").as_posix() for n in view.frames}


def _check_unpack(scan: Scan, view: View, image_format: str) -> None:
    """Before anything of a scan is written: a packed view's store (metadata, chunk files) and the paths its
    image files go to, of which none may be a link, a folder or anything but a plain file (a link out of the
    scan folder kept as a frame would leave a scan that does not load)."""
    check_view_frames(scan, view)
    for n, rel in _image_paths(scan, view, image_format).items():
        p = scan.folder / rel
        if p.is_symlink():
            raise FormatError(p, f"is a symbolic link (to {os.readlink(p)}) in the way of frame {n!r} of the store "
                                 f"{view.packed}: remove it, then unpack again")
        if p.exists() and not p.is_file():
            raise FormatError(p, f"is in the way of frame {n!r} of the store {view.packed} (not a file)")


def _write_images(scan: Scan, view: View, frames: np.ndarray, image_format: str) -> dict[str, str]:
    """A packed view's frames (``scan`` as its camera sees it; ``frames`` read from its store, every checksum
    checked) written beside its store as image files, each read back and compared; returns frame name -> path."""
    names = list(view.frames)
    rel = _image_paths(scan, view, image_format)
    for n, img in zip(names, frames):
        p = scan.folder / rel[n]
        if p.exists():
            if p.is_file() and not p.is_symlink() and np.array_equal(read_image(p), img):
                continue
            raise FormatError(p, f"is in the way of frame {n!r} of the store {view.packed} (and differs from it)")
        write_image(p, img)
        if not np.array_equal(read_image(p), img):
            raise FormatError(p, f"does not read back as frame {n!r} of the store {view.packed}")
    return rel


def unpack_scan(folder: str | os.PathLike, *, image_format: str = "png", keep: bool = False) -> PackResult:
    """Write every packed view's frames back as image files ``<view folder>/<frame>.<png|tiff>``
    (camera 2's beside its store, ``<view>/cam2/<frame>.png``).

    Every store's metadata and chunk files, and the paths the images go to, are checked
    before anything is written; a view's frames (both cameras') are read and their
    checksums checked before any of its images is written. An image file already there
    (a pack with ``keep``) is kept when it holds the same frame, and is an error otherwise.
    Temporary files and store folders left by a killed run are removed.

    Raises:
        FormatError: naming the file: a damaged store, an image file in the way.
    """
    if image_format not in ("png", "tiff"):
        raise ValueError(f"image_format: expected 'png' or 'tiff', got {image_format!r}")
    scan = load_scan(folder)
    res = PackResult(folder=scan.folder)
    views = list(scan.views)
    for v in views:
        for cscan, cv, _ in _cameras(scan, v):
            if cv.packed is not None:
                _check_unpack(cscan, cv, image_format)
    for i, v in enumerate(views):
        units = _cameras(scan, v)
        for _, cv, _ in units:  # what killed runs left: temporary image files, stores renamed for deletion
            vdir = scan.folder / (PurePosixPath(cv.packed).parent if cv.packed else _view_folder(cv))
            remove_stale_temporaries(vdir)
            remove_stale_stores(vdir)
        if all(cv.packed is None for _, cv, _ in units):
            res.already.append(v.name)
            for cscan, cv, _ in units:
                res.removed += _remove_leftover_store(cscan, cv, keep=keep)
            continue
        # both cameras' frames read (every checksum) before an image of the view is written
        frames = {cam: read_view_frames(cscan, cv, list(cv.frames), raw=True)
                  for cam, (cscan, cv, _) in enumerate(units, 1) if cv.packed is not None}
        new, stores = v, []
        for cam, (cscan, cv, label) in enumerate(units, 1):
            if cv.packed is None:
                res.removed += _remove_leftover_store(cscan, cv, keep=keep)
                continue
            rel = _write_images(cscan, cv, frames.pop(cam), image_format)
            new = _with_camera(new, cam, View(name=v.name, turntable_deg=v.turntable_deg, frames=rel))
            stores.append(scan.folder / cv.packed)
            res.bytes_after += sum(_size(scan.folder / r) for r in rel.values())
            log.info("%s: unpacked %s, %s (%d frames)", scan.folder, v.name, label, len(rel))
        views[i] = new
        scan = dataclasses.replace(scan, views=tuple(views))
        save_scan(scan)
        res.converted.append(v.name)
        res.bytes_before += sum(_size(p) for p in stores)
        if not keep:
            for p in stores:
                _remove_store(p)
            res.removed += len(stores)
    return res
