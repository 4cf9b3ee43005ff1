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
ringscan reads as grey) is refused rather than packed.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.frame_store import (STORE_NAME, is_store, open_store, read_store,
                                                   remove_stale_stores, write_store)
from ringscan.pipeline.formats.images import read_image, write_image
from ringscan.pipeline.formats.scan import (Scan, View, check_view_name, load_scan, packed_view, read_view_frames,
                                           save_scan)

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


def _check_grey_png(path: Path) -> None:
    """Refuse a colour PNG (ringscan reads it as grey: packing it would lose the colour)."""
    if path.suffix.lower() != ".png":
        return
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) == 26 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[25] in (2, 3, 6):
        raise FormatError(path, "colour frame: a packed store keeps frames as ringscan reads them (grey); "
                                "convert it to grey first")


def _remove_leftover_images(scan: Scan, view: View, *, keep: bool) -> int:
    """Image files of a packed view's frames left by a run killed before it removed them."""
    if keep:
        return 0
    vdir = scan.folder / PurePosixPath(view.packed).parent
    found = [(n, vdir / f"{n}{ext}") for n in view.frames for ext in IMAGE_EXTENSIONS
             if (vdir / f"{n}{ext}").is_file()]
    if not found:
        return 0
    frames = read_store(open_store(scan.folder / view.packed), [n for n, _ in found])
    for (n, p), img in zip(found, frames):
        if not np.array_equal(read_image(p), img):
            raise FormatError(p, f"differs from frame {n!r} of the store {view.packed} (kept; remove it by hand)")
    for _, p in found:
        p.unlink()
    return len(found)


def _refuse_two_cameras(scan) -> None:
    # Checked before anything is written: half a two-camera scan converted would be worse than none.
    if any(v.camera2 is not None for v in scan.views):
        raise FormatError(scan.path, "a two-camera scan: pack and unpack convert one-camera scans only for now "
                                     "(camera 2's frames would be left behind); the scan is unchanged")


def pack_scan(folder: str | os.PathLike, *, keep: bool = False) -> PackResult:
    """Pack every view of a scan whose frames are image files into ``<view folder>/frames.zarr``.

    Args:
        folder: the scan folder.
        keep: leave the image files where they are (scan.json names the store all the same).

    Raises:
        FormatError: naming the file: an unreadable or colour frame, frames of
            different sizes, a damaged store; the views before it stay packed.
    """
    scan = load_scan(folder)
    _refuse_two_cameras(scan)
    res = PackResult(folder=scan.folder)
    for i, v in enumerate(scan.views):
        if v.packed is None:
            for n, rel in v.frames.items():
                check_view_name(n, source=scan.path, where=f"views[{i}].frames: frame name")  # scan/2 asks it
                _check_grey_png(scan.folder / rel)
    views = list(scan.views)
    folders = [_view_folder(v) for v in views]
    for i, v in enumerate(views):
        if v.packed is not None:
            res.already.append(v.name)
            res.removed += _remove_leftover_images(scan, v, keep=keep)
            continue
        names = list(v.frames)
        # A view's store goes beside its frames, unless other views' frames share the folder.
        vdir = folders[i] if folders[i] != "." and folders.count(folders[i]) == 1 else v.name
        store_rel = f"{vdir}/{STORE_NAME}"
        old = [scan.folder / r for r in dict.fromkeys(v.frames.values())]
        frames = read_view_frames(scan, v, names)
        remove_stale_stores((scan.folder / store_rel).parent)
        write_store(scan.folder / store_rel, frames, names)  # read back and compared before the rename
        views[i] = packed_view(v, store_rel, names)
        scan = dataclasses.replace(scan, views=tuple(views))
        save_scan(scan)
        res.converted.append(v.name)
        res.bytes_before += sum(_size(p) for p in old)
        res.bytes_after += _size(scan.folder / store_rel)
        if not keep:
            for p in old:
                p.unlink(missing_ok=True)
            res.removed += len(old)
        log.info("%s: packed %s (%d frames)", scan.folder, v.name, len(names))
    return res


def _remove_leftover_store(scan: Scan, view: View, *, keep: bool) -> int:
    """The store of an unpacked view left by a run killed before it removed it."""
    if keep:
        return 0
    store = scan.folder / _view_folder(view) / STORE_NAME
    if not is_store(store):
        return 0
    info = open_store(store)
    if set(info.names) != set(view.frames):
        return 0  # not this view's store: leave it
    frames = read_view_frames(scan, view, list(info.names))
    if not np.array_equal(read_store(info), frames):
        raise FormatError(store, f"differs from the image frames of {view.name} (kept; remove it by hand)")
    shutil.rmtree(store)
    return 1


def unpack_scan(folder: str | os.PathLike, *, image_format: str = "png", keep: bool = False) -> PackResult:
    """Write every packed view's frames back as image files ``<view folder>/<frame>.<png|tiff>``.

    An image file already there (a pack with ``keep``) is kept when it holds the
    same frame, and is an error otherwise.

    Raises:
        FormatError: naming the file: a damaged store, an image file in the way.
    """
    if image_format not in ("png", "tiff"):
        raise ValueError(f"image_format: expected 'png' or 'tiff', got {image_format!r}")
    scan = load_scan(folder)
    _refuse_two_cameras(scan)
    res = PackResult(folder=scan.folder)
    views = list(scan.views)
    for i, v in enumerate(views):
        if v.packed is None:
            res.already.append(v.name)
            res.removed += _remove_leftover_store(scan, v, keep=keep)
            continue
        names = list(v.frames)
        frames = read_view_frames(scan, v, names)  # every checksum checked before a file is written
        vdir = PurePosixPath(v.packed).parent
        rel = {n: (vdir / f"{n}.{image_format}").as_posix() for n in names}
        for n, img in zip(names, frames):
            p = scan.folder / rel[n]
            if p.exists():
                if p.is_file() and np.array_equal(read_image(p), img):
                    continue
                raise FormatError(p, f"is in the way of frame {n!r} of the store {v.packed} (and differs from it)")
            write_image(p, img)
            if not np.array_equal(read_image(p), img):
                raise FormatError(p, f"does not read back as frame {n!r} of the store {v.packed}")
        store = scan.folder / v.packed
        views[i] = View(name=v.name, turntable_deg=v.turntable_deg, frames=rel)
        scan = dataclasses.replace(scan, views=tuple(views))
        save_scan(scan)
        res.converted.append(v.name)
        res.bytes_before += _size(store)
        res.bytes_after += sum(_size(scan.folder / r) for r in rel.values())
        if not keep:
            shutil.rmtree(store)
            res.removed += 1
        log.info("%s: unpacked %s (%d frames)", scan.folder, v.name, len(names))
    return res
