"""Finding the scan folders of a batch, and what a run would do with each (``--dry-run``)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from ringscan.pipeline.formats.errors import RingscanError
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.freshness import check_done
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

__all__ = ["find_scans", "iter_scans", "out_folder", "ScanPlan", "plan_scan"]


def iter_scans(root: str | os.PathLike) -> Iterator[Path]:
    """Scan folders (holding scan.json) below ``root``, one at a time, in sorted order.

    The walk is lazy (a folder of a million scans is never listed whole in memory
    beyond one folder's entries). Symbolic links to folders are followed (a batch
    folder of links to scans kept elsewhere works); a folder reached twice through
    links is listed once. A scan folder's own subfolders are not searched.
    """
    root = Path(root)
    if (root / "scan.json").is_file():
        yield root
        return
    seen: set[str] = set()

    def walk(folder: Path) -> Iterator[Path]:
        real = os.path.realpath(folder)
        if real in seen:
            return
        seen.add(real)
        if (folder / "scan.json").is_file():
            yield folder
            return
        try:
            names = sorted(e.name for e in os.scandir(folder) if e.is_dir(follow_symlinks=True))
        except OSError:
            return
        for name in names:
            yield from walk(folder / name)

    yield from walk(root)


def find_scans(root: str | os.PathLike) -> list[Path]:
    """Scan folders (holding scan.json) below ``root``, sorted (see :func:`iter_scans`)."""
    return sorted(iter_scans(root))


def out_folder(folder: Path, root: Path, out_root: Path) -> tuple[str, Path]:
    """A scan's name in the batch (its path relative to ``root``) and its output folder."""
    rel = folder.relative_to(root) if folder != root else Path(folder.name)
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


def plan_scan(folder: Path, rel: str, out: Path, *, settings: ReconstructSettings) -> ScanPlan:
    """Decide, as a run would (:func:`~ringscan.pipeline.reconstruct.freshness.check_done`), what to do with a scan."""
    try:
        scan = load_scan(folder)
        check = check_done(scan, out, settings=settings)
    except (RingscanError, ValueError, OSError) as e:
        return ScanPlan(rel, "run", "unreadable", str(e))
    if check.done and check.kept:
        return ScanPlan(rel, "skip", "done")
    if check.report is None and not (out / "report.json").exists():
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
