"""From a scan folder to one point cloud per view (``ringscan reconstruct``).

Per view: read the frames, upload them to the device, decode (per pixel), sample
the rings to sub-pixel precision, triangulate every sample against its ring's
quadric (DESIGN §3, §4), keep the valid points in sample order and write

- ``<out>/<view>.ply``: binary PLY in the world frame (mm): x, y, z, ring (band
  boundary or ring index), rho (projector px), view, confidence, u, v (camera px);
- ``<out>/report.json``: counts (pixels decoded, samples, points, roots dropped by
  reason), seconds per stage, the rig, the patterns and the resolved settings;
- ``<out>/settings.json``: the resolved settings.

The report is rewritten (atomically) after every view, so ``resume=True`` skips
views that are already done after an interrupted run.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np

from ringscan.kernels import resolve_device
from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.rig import rig_to_dict
from ringscan.pipeline.formats.scan import Scan, View, load_scan, read_view_frames
from ringscan.pipeline.formats.settings import settings_to_dict
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.reconstruct.view import reconstruct_view, write_view_ply

log = logging.getLogger(__name__)

REPORT_FORMAT = "ringscan.report/1"

__all__ = ["REPORT_FORMAT", "reconstruct_scan"]


def reconstruct_scan(
    scan: Scan | str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    settings: ReconstructSettings = ReconstructSettings(),
    device: str | None = None,
    views: list[str] | None = None,
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """Reconstruct every view of a scan; write PLYs, report.json and settings.json.

    Args:
        scan: a loaded :class:`Scan` or its folder.
        out_dir: output folder (created).
        settings: stage settings.
        device: Warp device (None: CUDA when present, else CPU).
        views: names of the views to do (default: all).
        resume: keep views already finished in an earlier run of the same output.
        progress: show a progress bar.

    Returns:
        The report (also written to ``out_dir/report.json``).
    """
    if not isinstance(scan, Scan):
        scan = load_scan(scan)
    device = resolve_device(device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    chosen = list(scan.views) if views is None else [v for v in scan.views if v.name in set(views)]
    if views is not None and len(chosen) != len(set(views)):
        unknown = sorted(set(views) - {v.name for v in scan.views})
        raise ValueError(f"unknown view(s) {', '.join(unknown)} in {scan.path}")
    report_path = out / "report.json"
    done = {}
    if resume and report_path.is_file():
        try:
            old = read_json(report_path)
            if old.get("format") == REPORT_FORMAT and Path(old.get("scan", "")) == scan.folder.resolve():
                done = {v["name"]: v for v in old.get("views", []) if (out / v.get("ply", "")).is_file()}
        except FormatError as e:
            log.warning("cannot resume from %s (%s): starting again", report_path, e)
    report = {
        "format": REPORT_FORMAT,
        "scan": str(scan.folder.resolve()),
        "codec": scan.patterns.codec,
        "device": device,
        "patterns": scan.patterns.to_dict(),
        "rig": rig_to_dict(scan.rig),
        "settings": settings_to_dict(settings),
        "views": [],
    }
    atomic_write_json(out / "settings.json", report["settings"])
    t_all = time.perf_counter()
    from tqdm import tqdm

    todo = [v for v in chosen if v.name not in done]
    # Read the next view's frames while this one is reconstructed (image decoding
    # and Warp launches both release the GIL).
    from concurrent.futures import ThreadPoolExecutor

    reader = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ringscan-read")
    pending = {}

    def prefetch(k):
        if k < len(todo) and todo[k].name not in pending:
            pending[todo[k].name] = reader.submit(_timed_read, scan, todo[k])

    bar = tqdm(chosen, desc=f"reconstruct {scan.folder.name}", unit="view", disable=not progress, leave=False)
    try:
        for view in bar:
            index = scan.views.index(view)
            if view.name in done:
                report["views"].append(done[view.name])
                continue
            k = todo.index(view)
            prefetch(k)
            frames, read_s = pending.pop(view.name).result()
            prefetch(k + 1)
            _reconstruct_one(scan, view, index, frames, read_s, out, report, report_path, settings, device)
    finally:
        for f in pending.values():
            f.cancel()
        reader.shutdown(wait=True)
    report["totals"] = _totals(report["views"])
    report["time_s"] = time.perf_counter() - t_all
    atomic_write_json(report_path, report)
    return report


def _timed_read(scan: Scan, view: View) -> tuple[np.ndarray, float]:
    t = time.perf_counter()
    frames = read_view_frames(scan, view)
    return frames, time.perf_counter() - t


def _reconstruct_one(scan, view, index, frames, read_s, out, report, report_path, settings, device) -> None:
    """Reconstruct one view from its frames; write its PLY and the updated report."""
    cloud = reconstruct_view(scan, view, settings=settings, device=device, frames=frames)
    cloud.stats["times_s"]["read"] = read_s  # read ahead, while the previous view was reconstructed
    ply = f"{view.name}.ply"
    write_view_ply(out / ply, cloud, index)
    entry = {"name": view.name, "index": index, "turntable_deg": view.turntable_deg, "ply": ply,
             "camera_center": scan.rig.camera.center.tolist(), **cloud.stats}
    report["views"].append(entry)
    log.info("%s: %d samples -> %d points (%s)", view.name, cloud.stats.get("samples", 0), cloud.stats["points"],
             ", ".join(f"{k} {v}" for k, v in cloud.stats["dropped"].items()))
    atomic_write_json(report_path, report)


def _totals(views: list[dict]) -> dict:
    tot: dict = {"points": 0, "samples": 0, "pixels_decoded": 0, "dropped": {}}
    for v in views:
        for k in ("points", "samples", "pixels_decoded"):
            tot[k] += int(v.get(k, 0))
        for k, n in v.get("dropped", {}).items():
            tot["dropped"][k] = tot["dropped"].get(k, 0) + int(n)
    return tot


