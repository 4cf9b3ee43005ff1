"""Finding the scan folders of a batch, and what a run would do with each (``--dry-run``)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from ringscan.pipeline.formats.errors import RingscanError
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.formats.storage import is_url, join_location, stage
from ringscan.pipeline.reconstruct.freshness import check_done
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

__all__ = ["find_scans", "iter_scans", "out_folder", "ScanPlan", "plan_scan"]


def iter_scans(root: str | os.PathLike, *, skipped: list | None = None) -> Iterator[Path]:
    """Scan folders (holding scan.json) below ``root``, one at a time, in sorted order.

    The walk is lazy (a folder of a million scans is never listed whole in memory
    beyond one folder's entries). Symbolic links to folders are followed (a batch
    folder of links to scans kept elsewhere works); a folder reached twice through
    links is listed once. A scan folder's own subfolders are not searched for scans.

    Args:
        root: the folder to search.
        skipped: when given, ``(path, why)`` is appended for what the walk passes over
            that could hold scans: a symbolic link loop or a broken link, a folder it
            cannot list, a scan.json nested inside a scan folder (not processed).
    """
    root = Path(root)
    note = skipped.append if skipped is not None else (lambda item: None)
    if (root / "scan.json").is_file():
        _note_nested(root, note)
        yield root
        return
    seen: set[str] = set()

    def walk(folder: Path) -> Iterator[Path]:
        real = os.path.realpath(folder)
        if real in seen:
            return
        seen.add(real)
        if (folder / "scan.json").is_file():
            _note_nested(folder, note)
            yield folder
            return
        try:
            entries = sorted(os.scandir(folder), key=lambda e: e.name)
        except OSError as e:
            note((str(folder), f"cannot list this folder: {e.strerror}"))
            return
        for e in entries:
            try:
                is_dir = e.is_dir(follow_symlinks=True)
            except OSError as err:  # ELOOP: a link loop
                note((e.path, f"cannot follow this link: {(err.strerror or str(err)).lower()}"))
                continue
            if is_dir:
                yield from walk(folder / e.name)
            elif e.is_symlink() and not os.path.exists(e.path):
                note((e.path, "a broken symbolic link"))

    yield from walk(root)


def _note_nested(scan: Path, note, *, max_depth: int = 8) -> None:
    """Note the scan.json files inside a scan folder's subfolders (links not followed): a batch does not process
    them (a scan folder's frames live in its subfolders), so it says so."""
    def walk(folder: Path, depth: int) -> None:
        try:
            subs = sorted(e.name for e in os.scandir(folder) if e.is_dir(follow_symlinks=False))
        except OSError:
            return
        for name in subs:
            sub = folder / name
            if (sub / "scan.json").is_file():
                note((str(sub), f"a scan folder inside the scan folder {scan}: not processed (a scan folder's "
                                "subfolders are not searched; give it as a ROOT of its own)"))
            elif depth < max_depth:
                walk(sub, depth + 1)

    walk(scan, 1)


def find_scans(root: str | os.PathLike, *, skipped: list | None = None) -> list[Path]:
    """Scan folders (holding scan.json) below ``root``, sorted (see :func:`iter_scans`)."""
    return sorted(iter_scans(root, skipped=skipped))


def out_folder(folder, root, out_root):
    """A scan's name in the batch (its path relative to ``root``) and its output folder (a URL below a URL)."""
    if isinstance(folder, str) and is_url(folder):
        rel = folder[len(root):].strip("/") if folder != root else folder.rstrip("/").rsplit("/", 1)[-1]
        if not rel or any(p in ("", ".", "..") for p in rel.split("/")):
            raise RingscanError(f"{folder}: cannot name its output folder below {out_root}")
        return rel, (join_location(out_root, rel) if is_url(out_root) else Path(out_root) / rel)
    # the root itself is named by its real name: a ROOT given as ``.`` or ``SCAN/view_000/..`` has none of its own,
    # and ``out_root / ".."`` would write above the output folder
    rel = folder.relative_to(root) if folder != root else Path(Path(os.path.abspath(folder)).resolve().name)
    if not rel.parts or any(p in ("", ".", "..") for p in rel.parts):
        raise RingscanError(f"{folder}: cannot name its output folder below {out_root} (give the scan folder by "
                            "its own name)")
    if is_url(out_root):
        return rel.as_posix(), join_location(out_root, rel.as_posix())
    return rel.as_posix(), out_root / rel


@dataclass(frozen=True)
class ScanPlan:
    """What a run would do with one scan."""

    scan: str
    """The scan's path relative to the batch root."""
    action: str
    """``run`` or ``skip``."""
    why: str
    """``new``, ``changed settings``, ``changed inputs``, ``incomplete``, ``done`` or ``unreadable``."""
    detail: str = ""
    """The views to redo and why, or the error."""


def plan_scan(folder, rel: str, out, *, settings: ReconstructSettings,
              storage_options: dict | None = None) -> ScanPlan:
    """Decide, as a run would (:func:`~ringscan.pipeline.reconstruct.freshness.check_done`), what to do with a scan
    (on object storage: from its listing and its results, without downloading its frames)."""
    try:
        with stage(folder, out, options=storage_options) as st:
            scan = load_scan(st.scan_dir, check_files=not st.remote_scan)
            st.check_scan(scan)
            check = check_done(scan, st.out_dir, settings=settings, stat=st.stat)
            had_report = (st.out_dir / "report.json").exists()
    except (RingscanError, ValueError, OSError) as e:
        return ScanPlan(rel, "run", "unreadable", str(e))
    if check.done and check.kept:
        return ScanPlan(rel, "skip", "done")
    if check.report is None and not had_report:
        return ScanPlan(rel, "run", "new")
    reasons = list(dict.fromkeys(check.redo.values()))
    detail = "; ".join(f"{n}: {why}" for n, why in check.redo.items())
    if not check.finished and not reasons:
        return ScanPlan(rel, "run", "incomplete", "every view is done; the earlier run stopped before its report was "
                                                  "finished (the report is written again, no view is redone)")
    if any("settings" in r for r in reasons):
        why = "changed settings"
    elif check.kept:
        why = "incomplete"
    elif any("changed" in r for r in reasons):
        why = "changed inputs"
    else:
        why = "incomplete"
    return ScanPlan(rel, "run", why, detail if len(detail) < 300 else "; ".join(reasons))
