"""Batch processing of many scan folders (``ringscan batch``).

Every folder below ROOT that holds a scan.json is reconstructed into the same
relative path below OUT. A scan whose report.json is complete is skipped, so a
batch that stopped is resumed by running it again; a scan that fails is logged and
listed in ``OUT/batch_report.json`` and the batch goes on with the next.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.errors import RingscanError
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.scan import REPORT_FORMAT, reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

log = logging.getLogger(__name__)

__all__ = ["find_scans", "batch_reconstruct"]


def find_scans(root: str | os.PathLike) -> list[Path]:
    """Scan folders (holding scan.json) below ``root``, sorted.

    Symbolic links to folders are followed (a batch folder of links to scans kept
    elsewhere works); a folder reached twice through links is listed once.
    A scan folder's own subfolders are not searched.
    """
    root = Path(root)
    if (root / "scan.json").is_file():
        return [root]
    found, seen = [], set()
    for dirpath, dirnames, filenames in os.walk(root, followlinks=True):
        real = os.path.realpath(dirpath)
        if real in seen:
            dirnames[:] = []
            continue
        seen.add(real)
        if "scan.json" in filenames:
            found.append(Path(dirpath))
            dirnames[:] = []
    return sorted(found)


def _complete(out: Path, n_views: int) -> bool:
    try:
        rep = read_json(out / "report.json")
    except RingscanError:
        return False
    return (rep.get("format") == REPORT_FORMAT and "totals" in rep and len(rep.get("views", [])) == n_views
            and all((out / v["ply"]).is_file() for v in rep["views"]))


def batch_reconstruct(root, out_root, *, settings: ReconstructSettings = ReconstructSettings(), device=None,
                      progress: bool = True) -> dict:
    """Reconstruct every scan below ``root`` into ``out_root``; returns the batch report."""
    from tqdm import tqdm

    root, out_root = Path(root), Path(out_root)
    scans = find_scans(root)
    if not scans:
        raise RingscanError(f"{root}: no scan.json found below this folder")
    report = {"root": str(root.resolve()), "scans": []}
    for folder in tqdm(scans, desc="batch", unit="scan", disable=not progress):
        rel = folder.relative_to(root) if folder != root else Path(folder.name)
        out = out_root / rel
        entry = {"scan": str(rel), "out": str(out)}
        t = time.perf_counter()
        try:
            scan = load_scan(folder)
            if _complete(out, len(scan.views)):
                entry["status"] = "skipped (already done)"
            else:
                rep = reconstruct_scan(scan, out, settings=settings, device=device, resume=True, progress=False)
                entry.update(status="done", points=rep["totals"]["points"])
        except (RingscanError, ValueError, OSError) as e:
            log.error("%s: %s", folder, e)
            entry.update(status="failed", error=str(e))
        entry["time_s"] = time.perf_counter() - t
        report["scans"].append(entry)
        atomic_write_json(out_root / "batch_report.json", report)
    return report
