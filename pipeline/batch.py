"""Batch processing of many scan folders (``ringscan batch``).

Every folder below ROOT that holds a scan.json is reconstructed into the same
relative path below OUT. A scan that is done (every view made from the same inputs
with the same settings, files whole: :func:`ringscan.pipeline.reconstruct.check_done`)
is skipped, so a batch that stopped is resumed by running it again; any other is
(re)done, its views that are done kept, and ``batch_report.json`` says why. A scan
that fails, or where no view gives a point, is logged and listed in
``OUT/batch_report.json`` and the batch goes on with the next.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from ringscan.pipeline.formats.atomic import atomic_write_json, check_output_folder, remove_stale_temporaries
from ringscan.pipeline.formats.errors import RingscanError
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.freshness import check_done
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
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


def batch_reconstruct(root, out_root, *, settings: ReconstructSettings = ReconstructSettings(), device=None,
                      progress: bool = True) -> dict:
    """Reconstruct every scan below ``root`` into ``out_root``; returns the batch report."""
    from tqdm import tqdm

    root = Path(root)
    out_root = check_output_folder(out_root, what="batch's output folder")
    scans = find_scans(root)
    if not scans:
        raise RingscanError(f"{root}: no scan.json found below this folder")
    remove_stale_temporaries(out_root)
    report = {"root": str(root.resolve()), "scans": []}
    for folder in tqdm(scans, desc="batch", unit="scan", disable=not progress):
        rel = folder.relative_to(root) if folder != root else Path(folder.name)
        out = out_root / rel
        entry = {"scan": str(rel), "out": str(out)}
        t = time.perf_counter()
        try:
            scan = load_scan(folder)
            check = check_done(scan, out, settings=settings)
            if check.done and check.kept:
                views = list(check.kept.values())
                entry["status"] = "skipped (already done)"
            else:
                if check.report is not None:
                    entry["redone"] = check.redo
                    log.info("%s: %s", folder, "; ".join(f"{n}: {why}" for n, why in check.redo.items()))
                views = reconstruct_scan(scan, out, settings=settings, device=device, resume=True,
                                         progress=False)["views"]
                entry["status"] = "done"
            points = sum(int(v.get("points", 0)) for v in views)
            entry["points"] = points
            if not views:
                raise RingscanError(f"{folder / 'scan.json'}: the scan has no views")
            if points == 0:
                reasons = list(dict.fromkeys(v.get("no_points", "no points") for v in views))
                raise RingscanError(f"no view gave any point: {'; '.join(reasons)}")
        except (RingscanError, ValueError, OSError) as e:
            log.error("%s: %s", folder, e)
            entry.update(status="failed", error=str(e))
        entry["time_s"] = time.perf_counter() - t
        report["scans"].append(entry)
        atomic_write_json(out_root / "batch_report.json", report)
    return report
