"""From a scan folder to one point cloud per view (``ringscan reconstruct``).

Per view: read the frames, upload them to the device, decode (per pixel), sample
the rings to sub-pixel precision, triangulate every sample against its ring's
quadric (docs/design.md §3, §4), keep the valid points in sample order and write

- ``<out>/<view>.ply``: binary PLY in the world frame (mm): x, y, z, ring (band
  boundary or ring index), rho (projector px), view, confidence, u, v (camera px);
- ``<out>/report.json``: counts (pixels decoded, samples, points, roots dropped by
  reason), seconds per stage, the rig, the patterns and the resolved settings;
- ``<out>/settings.json``: the resolved settings.

The report is rewritten (atomically) after every view's PLY (the last view's
report being the final one; both written on a writer thread behind the next
view's compute), so ``resume=True`` keeps
views that are already done after an interrupted run: done means made from the
same inputs with the same settings, files whole (:mod:`.freshness` decides);
every other view is redone and the report's ``resume`` block says why.

A view that gives no point says why in its entry (``no_points``) and in the log
(no contrast between the white and black frames, no ring line found, every
sample dropped...).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from pathlib import Path

import numpy as np

from ringscan.kernels import resolve_device
from ringscan.kernels.launch import cpu_threads
from ringscan.kernels.process import freed_memory_kept_mb
from ringscan.pipeline.formats.atomic import (
    atomic_write_json,
    check_no_overwrite,
    check_output_file,
    check_output_folder,
    lock_folder,
    remove_stale_temporaries,
)
from ringscan.pipeline.formats.buffers import FrameBuffers
from ringscan.pipeline.formats.rig import rig_to_dict
from ringscan.pipeline.formats.scan import (
    Scan,
    View,
    check_view_frames,
    check_view_name,
    load_scan,
    read_view_frames,
)
from ringscan.pipeline.formats.settings import check_finite_settings, check_settings_types, settings_to_dict
from ringscan.pipeline.reconstruct.freshness import REPORT_FORMAT, check_done, hash_inputs
from ringscan.pipeline.reconstruct.settings import ReconstructSettings, check_setting_ranges
from ringscan.pipeline.reconstruct.view import check_rays, load_view_modules, reconstruct_view, write_view_ply

log = logging.getLogger(__name__)

LOW_YIELD_SHARE = 0.25
"""A view that keeps fewer points than this share of its decoded samples warns, naming the main reason."""

__all__ = ["REPORT_FORMAT", "LOW_YIELD_SHARE", "reconstruct_scan", "scan_inputs", "low_yield"]


def reconstruct_scan(
    scan: Scan | str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    settings: ReconstructSettings = ReconstructSettings(),
    device: str | None = None,
    views: list[str] | None = None,
    resume: bool = False,
    progress: bool = True,
    lock: bool = True,
) -> dict:
    """Reconstruct every view of a scan; write PLYs, report.json and settings.json.

    Args:
        scan: a loaded :class:`Scan` or its folder.
        out_dir: output folder (created).
        settings: stage settings.
        device: Warp device (None: CUDA when present, else CPU).
        views: names of the views to do (default: all).
        resume: keep views already done in an earlier run into the same folder:
            made from the same inputs with the same settings, files whole
            (:func:`~ringscan.pipeline.reconstruct.freshness.check_done`); the
            report's ``resume`` block lists the views kept and why the others were
            redone.
        progress: show a progress bar.
        lock: hold ``out_dir`` for this run (:func:`~ringscan.pipeline.formats.atomic.lock_folder`):
            another run into the same folder is refused while this one runs. A batch
            worker passes False (the batch holds its whole output folder).

    Returns:
        The report (also written to ``out_dir/report.json``).

    Raises:
        ValueError: a setting of the wrong type, not finite or outside its range
            (:data:`~ringscan.pipeline.reconstruct.settings.SETTING_RANGES`), naming it.
        FormatError: ``out_dir`` cannot be a folder (a file, a device, under a
            file), or writing into it would overwrite one of the scan's own files;
            another run holds ``out_dir``.
    """
    check_settings_types(settings)
    check_finite_settings(settings)
    check_setting_ranges(settings)
    with contextlib.ExitStack() as held:
        return _reconstruct(scan, out_dir, settings=settings, device=device, views=views, resume=resume,
                            progress=progress, held=held if lock else None)


def _reconstruct(scan, out_dir, *, settings, device, views, resume, progress, held) -> dict:
    """Check the inputs and outputs, prepare the folder, then reconstruct the views and write the report."""
    if not isinstance(scan, Scan):
        scan = load_scan(scan)
    out = check_output_folder(out_dir, what="reconstruction's output folder")
    chosen = _check_views(scan, out, views, settings)
    device = resolve_device(device)
    _prepare_folder(out, held)
    names = [v.name for v in chosen]
    if resume:
        check = check_done(scan, out, settings=settings, views=names)
        hashes, done = check.hashes, check.kept
        for n, why in check.redo.items():
            log.info("%s: not kept from the earlier run (%s)", n, why)
    else:
        hashes, done = hash_inputs(scan, settings, views=names), {}
    report = _new_report(scan, device, settings, hashes)
    if resume:
        report["resume"] = {"kept": [n for n in names if n in done], "redone": dict(check.redo)}
    t_all = time.perf_counter()
    _reconstruct_views(scan, out, chosen, done, report, hashes, settings, progress)
    report["totals"] = _totals(report["views"])
    report["time_s"] = time.perf_counter() - t_all
    atomic_write_json(out / "report.json", report)
    return report


def _check_views(scan: Scan, out: Path, views, settings) -> list[View]:
    """The views chosen, after checking their names, the files to write, their frames and rays."""
    chosen = list(scan.views) if views is None else [v for v in scan.views if v.name in set(views)]
    if views is not None and len(chosen) != len(set(views)):
        unknown = sorted(set(views) - {v.name for v in scan.views})
        raise ValueError(f"unknown view(s) {', '.join(unknown)} in {scan.path}")
    for v in chosen:
        check_view_name(v.name, source=scan.path, where=f"views[{scan.views.index(v)}].name")
    outputs = [out / "report.json", out / "settings.json", *(out / f"{v.name}.ply" for v in chosen)]
    for o in outputs:
        check_output_file(o, what="file the reconstruction writes")
    check_no_overwrite(outputs, scan_inputs(scan))
    for v in chosen:
        check_view_frames(scan, v)  # every frame's header, before anything is written
    check_rays(scan, chosen, settings)
    return chosen


def _prepare_folder(out: Path, held) -> None:
    """Create the output folder, lock it (unless ``held`` is None) and remove stale temporaries."""
    out.mkdir(parents=True, exist_ok=True)
    if held is not None:
        held.enter_context(lock_folder(out, what="reconstruct"))
    remove_stale_temporaries(out)


def _new_report(scan: Scan, device: str, settings, hashes) -> dict:
    """The report's header: the scan, codec, device, patterns, rig, settings and input hashes; no views yet."""
    return {
        "format": REPORT_FORMAT,
        "scan": str(scan.folder.resolve()),
        "codec": scan.patterns.codec,
        "device": device,
        "patterns": scan.patterns.to_dict(),
        "rig": rig_to_dict(scan.rig),
        "settings": settings_to_dict(settings),
        "inputs": hashes.to_dict(),
        "views": [],
    }


def _reconstruct_views(scan: Scan, out: Path, chosen: list[View], done: dict, report: dict, hashes, settings,
                       progress: bool) -> None:
    """Reconstruct the views not done (frames read ahead, files written behind), appending each entry to ``report``."""
    from ringscan.pipeline.formats.progress import progress_bar

    device = report["device"]  # the resolved device, as the report records it
    report_path = out / "report.json"
    todo = [v for v in chosen if v.name not in done]
    # Read the next view's frames while this one is reconstructed, and write
    # settings.json, each view's PLY and the report behind the compute (image
    # decoding, Warp launches and fsync all release the GIL): a view does not wait
    # for the disk. One writer thread keeps the order (a view's PLY is in place
    # before the report that lists it), each file atomic and flushed as before.
    from concurrent.futures import ThreadPoolExecutor

    buffers = _frame_buffers()
    reader = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ringscan-read")
    writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ringscan-write")
    pending = {}
    # settings.json goes with the first view computed (or at once when every view is done): a frame whose
    # header passed but whose body is corrupt stops the run before anything is written
    written = [] if todo else [writer.submit(atomic_write_json, out / "settings.json", report["settings"])]
    settings_pending = bool(todo)

    def prefetch(k):
        if k < len(todo) and todo[k].name not in pending:
            pending[todo[k].name] = reader.submit(_timed_read, scan, todo[k], settings.threads or cpu_threads(),
                                                  buffers)

    bar = progress_bar(chosen, desc=f"reconstruct {scan.folder.name}", unit="view", disable=not progress, leave=False)
    try:
        for view in bar:
            index = scan.views.index(view)
            if view.name in done:
                report["views"].append(done[view.name])
                continue
            k = todo.index(view)
            prefetch(k)
            if k == 0:
                load_view_modules(scan)  # while the first frames are read
            frames, read_s = pending.pop(view.name).result()
            prefetch(k + 1)
            cloud = reconstruct_view(scan, view, settings=settings, device=device, frames=frames)
            buffers.give(frames)  # the view is done with its frames (the cloud holds none of them)
            del frames
            cloud.stats["times_s"]["read"] = read_s  # read ahead, while the previous view was reconstructed
            entry = _view_entry(scan, view, index=index, cloud=cloud, inputs_hash=hashes.views[view.name])
            report["views"].append(entry)
            for f in written:  # a failed write stops the run before the next view
                f.result()
            # the last view's report is the final one, written by _reconstruct
            snapshot = {**report, "views": list(report["views"])} if k + 1 < len(todo) else None
            written = []
            if settings_pending:
                written.append(writer.submit(atomic_write_json, out / "settings.json", report["settings"]))
                settings_pending = False
            written.append(writer.submit(_write_view, out, cloud, entry, index, report_path, snapshot))
        for f in written:
            f.result()
    finally:
        for f in pending.values():
            f.cancel()
        reader.shutdown(wait=True)
        writer.shutdown(wait=True)


_FRAME_BUFFERS = FrameBuffers(keep=2)
"""The process's frame stacks, kept from scan to scan where the process keeps freed memory
(:func:`~ringscan.kernels.process.retain_freed_memory`: the ringscan command, batch workers,
Ray tasks), within the memory it keeps (``RINGSCAN_KEEP_FREED_MB``, 512 MiB by default):
one being reconstructed, one being read ahead."""


def _frame_buffers() -> FrameBuffers:
    kept = freed_memory_kept_mb()
    if kept <= 0:
        return FrameBuffers(keep=2)  # this call's views only (a view and the one read ahead: the peak anyway)
    _FRAME_BUFFERS.max_bytes = kept << 20
    return _FRAME_BUFFERS


def _timed_read(scan: Scan, view: View, threads: int, buffers: FrameBuffers) -> tuple[np.ndarray, float]:
    t = time.perf_counter()
    frames = read_view_frames(scan, view, threads=threads, buffers=buffers)
    return frames, time.perf_counter() - t


def _view_entry(scan: Scan, view: View, *, index: int, cloud, inputs_hash: str) -> dict:
    """A reconstructed view's entry of the report (its ``times_s`` gains ``write`` once its PLY is written)."""
    entry = {"name": view.name, "index": index, "turntable_deg": view.turntable_deg, "ply": f"{view.name}.ply",
             "camera_center": scan.rig.camera.center.tolist(), "inputs_hash": inputs_hash, **cloud.stats}
    log.info("%s: %d samples -> %d points (%s)", view.name, cloud.stats.get("samples", 0), cloud.stats["points"],
             ", ".join(f"{k} {v}" for k, v in cloud.stats["dropped"].items()))
    if "no_points" in cloud.stats:
        log.warning("%s of %s: no points: %s", view.name, scan.folder, cloud.stats["no_points"])
    else:
        few = low_yield(cloud.stats)
        if few:
            log.warning("%s of %s: %s", view.name, scan.folder, few)
    return entry


def low_yield(stats: dict) -> str | None:
    """What a view that keeps under ``LOW_YIELD_SHARE`` of its samples lost most of them to, in one
    line (None when it keeps more): the largest reason in ``dropped``, and for ``unmatched`` the
    matching's own (``stereo.unmatched``: discontinuity, extrapolated, ...)."""
    samples, points = int(stats.get("samples", 0)), int(stats.get("points", 0))
    dropped = {k: int(v) for k, v in stats.get("dropped", {}).items() if v}
    if samples <= 0 or points >= LOW_YIELD_SHARE * samples or not dropped:
        return None
    reason, count = max(dropped.items(), key=lambda kv: kv[1])
    why = f"{reason} {count}"
    sub = {k: int(v) for k, v in stats.get("stereo", {}).get("unmatched", {}).items() if v}
    if reason == "unmatched" and sub:
        r2, c2 = max(sub.items(), key=lambda kv: kv[1])
        why = f"unmatched in camera 2 {count} ({r2} {c2})"
    return (f"keeps {points} of its {samples} decoded samples ({100 * points / samples:.1f} %); most dropped as "
            f"{why} (report.json 'dropped'; docs/reconstruction.md, 'When a view keeps few points')")


def _write_view(out_dir: Path, cloud, entry: dict, index: int, report_path: Path, report: dict | None) -> None:
    """Write a view's PLY, then (``report`` not None) the report that lists it (on the writer thread)."""
    t = time.perf_counter()
    write_view_ply(out_dir / entry["ply"], cloud, index)
    entry["times_s"]["write"] = time.perf_counter() - t
    if report is not None:
        atomic_write_json(report_path, report)


def scan_inputs(scan: Scan) -> list[Path]:
    """The files a scan is made of: scan.json, its rig file, every frame."""
    files = [scan.path]
    if scan.rig_ref:
        files.append(scan.folder / scan.rig_ref)
    files += [scan.frame_path(v, n) for v in scan.views for n in v.frames]
    return files


def _totals(views: list[dict]) -> dict:
    tot: dict = {"points": 0, "samples": 0, "pixels_decoded": 0, "dropped": {}}
    for v in views:
        for k in ("points", "samples", "pixels_decoded"):
            tot[k] += int(v.get(k, 0))
        for k, n in v.get("dropped", {}).items():
            tot["dropped"][k] = tot["dropped"].get(k, 0) + int(n)
    return tot


