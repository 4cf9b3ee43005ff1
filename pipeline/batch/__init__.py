"""Batch processing of many scan folders (``ringscan batch``): see docs/batch.md.

Every folder below ROOT that holds a scan.json is reconstructed into the same
relative path below OUT, by a pool of worker processes (:mod:`.local`) or a Ray
cluster (:mod:`.ray_backend`), each scan by :func:`.worker.process_scan`. A scan
that is done (every view made from the same inputs with the same settings, files
whole: :func:`ringscan.pipeline.reconstruct.check_done`) is skipped, so a batch that
stopped is resumed by running it again; any other is (re)done, its views that are
done kept, and ``batch_report.json`` says why. A scan that fails, or where no view
gives a point, is listed in ``OUT/batch_report.json`` and the batch goes on.
"""

from __future__ import annotations

import functools
import logging
import os
import statistics
import time

from ringscan.kernels import init_warp, resolve_device
from ringscan.pipeline.batch.discover import ScanPlan, find_scans, iter_scans, out_folder, plan_scan
from ringscan.pipeline.batch.local import run_inline, run_local
from ringscan.pipeline.batch.ray_backend import init_ray, run_ray, shutdown_ray
from ringscan.pipeline.batch.report import BATCH_REPORT_FORMAT, TIME_FIELDS, format_table, summarise
from ringscan.pipeline.batch.worker import ScanJob
from ringscan.pipeline.formats.atomic import (
    check_output_folder,
    lock_folder,
    remove_stale_temporaries,
)
from ringscan.pipeline.formats.errors import RingscanError
from ringscan.pipeline.formats.settings import check_finite_settings, check_settings_types, settings_to_dict
from ringscan.pipeline.formats.storage import (
    check_location,
    check_url,
    find_scan_urls,
    is_url,
    join_location,
    local_path,
    write_json_to,
)
from ringscan.pipeline.reconstruct.settings import ReconstructSettings, check_setting_ranges

log = logging.getLogger(__name__)

__all__ = ["find_scans", "iter_scans", "batch_reconstruct", "plan_batch", "default_workers", "ScanPlan",
           "format_table", "TIME_FIELDS"]

BACKENDS = ("local", "ray")

REPORT_EVERY_S = 2.0
"""Least seconds between two rewrites of ``batch_report.json`` while a batch runs (after the
first scan and at the end it is always written): the report grows with the scans, and
rewriting it after every one of ten thousand would cost more than the scans."""
REPORT_SHARE = 0.05
"""Largest share of the batch's wall time spent rewriting the report: the next rewrite waits
at least 1 / REPORT_SHARE times as long as the last one took."""


def default_workers(device: str | None = None) -> tuple[int, list[str | None]]:
    """Workers and their devices by default.

    ``None``/``auto``: one worker per CUDA device where there are GPUs, else one per CPU
    core. ``cuda``: one per CUDA device. ``cuda:N``: one worker, on that device (more
    processes on one GPU only share it). ``cpu``: one per core.
    """
    import warp as wp

    dev = str(device) if device not in (None, "", "auto") else None
    if dev is None or dev.startswith("cuda"):
        init_warp()
        n = wp.get_cuda_device_count()
        if n and dev in (None, "cuda"):
            return n, [f"cuda:{i}" for i in range(n)]
        if dev is not None and dev != "cuda":
            return 1, [dev]
    return max(1, os.cpu_count() or 1), [device]


def _root_and_scans(root, skipped: list | None = None, storage_options: dict | None = None):
    notes: list = []
    if is_url(root):
        root = check_url(str(root)).rstrip("/")
        scans = find_scan_urls(root, storage_options, skipped=notes)
        if skipped is not None:
            skipped.extend({"path": path, "why": why} for path, why in notes)
        if not scans:
            raise RingscanError(f"{root}: no scan.json found below this location")
        return root, scans
    root = local_path(root)
    if not root.is_dir():
        raise RingscanError(f"{root}: not a folder" if root.exists() else f"{root}: not found")
    scans = find_scans(root, skipped=notes)
    for path, why in notes:
        log.warning("%s: %s", path, why)
    if skipped is not None:
        skipped.extend({"path": path, "why": why} for path, why in notes)
    if not scans:
        raise RingscanError(f"{root}: no scan.json found below this folder"
                            + (f" ({len(notes)} path(s) not searched, see above)" if notes else ""))
    return root, scans


def plan_batch(root, out_root, *, settings: ReconstructSettings = ReconstructSettings(),
               skipped: list | None = None, storage_options: dict | None = None) -> list[ScanPlan]:
    """What ``batch_reconstruct`` would do with each scan and why (``--dry-run``); writes nothing.

    ``skipped``, when given, receives what the search passed over (see the report's ``not_searched``).
    ``storage_options``: fsspec options where ``root`` or ``out_root`` is a URL.
    """
    root, scans = _root_and_scans(root, skipped, storage_options)
    out_root = out_root.rstrip("/") if is_url(out_root) else local_path(out_root)
    plans = []
    for folder in scans:
        rel, out = out_folder(folder, root, out_root)
        plans.append(plan_scan(folder, rel, out, settings=settings, storage_options=storage_options))
    return plans


def batch_reconstruct(root, out_root, *, settings: ReconstructSettings = ReconstructSettings(),
                      device: str | None = None, workers: int | None = None, backend: str = "local",
                      address: str | None = None, fuse: bool = False, mesh: bool = False,
                      cpu_threads: int | None = None, progress: bool = True,
                      storage_options: dict | None = None) -> dict:
    """Reconstruct every scan below ``root`` into ``out_root``; returns the batch report.

    Args:
        root: a folder of scan folders (or one scan folder).
        out_root: the output folder; each scan goes to its relative path below it.
        settings: reconstruction settings.
        device: Warp device of every worker (None: one CUDA device per worker where
            there are GPUs, else the CPU).
        workers: worker processes (None: :func:`default_workers`; 0: in this process).
        backend: ``local`` (a process pool) or ``ray`` (a Ray cluster).
        address: the Ray cluster's address (``ray`` backend only).
        fuse: also fuse each scan's views into ``<out>/fused/fused.ply``.
        mesh: also fuse and mesh each scan into ``<out>/mesh/``.
        cpu_threads: CPU threads of each local worker (None: the cores shared out
            among the workers). Results do not depend on it.
        progress: show a progress bar.
        storage_options: fsspec options (credentials, ``endpoint_url`` ...) where ``root`` or ``out_root``
            is a URL (``s3://bucket/prefix``, ``gs://``...; docs/batch.md, "Scans on S3"). On object storage
            OUT is not locked (one run at a time is the user's to keep) and every result is one whole object.

    Returns:
        The report (also ``out_root/batch_report.json``): ``scans`` (one entry per
        scan, in the order of :func:`find_scans`), ``not_searched`` (paths below
        ``root`` the search passed over and why: a link loop, a scan folder inside a
        scan folder) and ``totals``.

    Raises:
        FormatError: ``out_root`` cannot be an output folder, or another run holds it
            (:func:`~ringscan.pipeline.formats.atomic.lock_folder`).
        RingscanError: no scan below ``root``; the Ray cluster at ``address`` does not
            answer; a bucket that is not there, credentials refused, a storage endpoint
            that does not answer (:class:`~ringscan.pipeline.formats.storage.StorageError`).
            Nothing is written then. The output bucket going away mid-batch stops the batch
            with a StorageError naming the URL.

    Size: a public function (ringscan batch's): the input and output roots and its documented keyword-only
    options, one per user-facing setting (settings, device, workers, backend and address, fusing and meshing,
    CPU threads, progress, storage options).
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend {backend!r}: expected one of {', '.join(BACKENDS)}")
    check_settings_types(settings)
    check_finite_settings(settings)
    check_setting_ranges(settings)  # every scan would fail alike: the batch's error, before anything is written
    if workers is not None and (not isinstance(workers, int) or workers < 0):
        raise ValueError(f"workers: expected a whole number >= 0, got {workers!r}")
    if cpu_threads is not None and (isinstance(cpu_threads, bool) or not isinstance(cpu_threads, int)
                                    or cpu_threads < 1):
        raise ValueError(f"cpu_threads: expected a whole number >= 1, got {cpu_threads!r}")
    if backend == "ray" and str(device or "").startswith("cuda:"):
        # Ray gives each task its own GPU, which the task sees as cuda:0: a device number means nothing there
        raise ValueError(f"device {device!r} with the Ray backend: Ray gives each scan's task a GPU of its own; "
                         "use --device cuda (or leave it out: a task's GPU where it has one, else the CPU)")
    skipped: list = []
    root, scans = _root_and_scans(root, skipped, storage_options)
    remote_out = is_url(out_root)
    if remote_out:
        out_root = str(out_root).rstrip("/")
        check_location(out_root, storage_options, what="batch's output folder")
    else:
        out_root = check_output_folder(local_path(out_root), what="batch's output folder")
    for folder in scans:
        out_folder(folder, root, out_root)  # every scan's output folder has a name below out_root
    if backend == "local" and device not in (None, "", "auto", "cpu"):
        resolve_device(device)  # an unknown device is the command's error, not every scan's (Ray: on the nodes)
    ray_started = init_ray(address) if backend == "ray" else False  # fails fast, before anything is written
    run = functools.partial(_batch, root, scans, skipped, out_root, settings=settings, device=device,
                            workers=workers, backend=backend, address=address, fuse=fuse, mesh=mesh,
                            cpu_threads=cpu_threads, progress=progress, storage_options=storage_options)
    try:
        if remote_out:  # no lock on object storage (docs/batch.md)
            return run()
        out_root.mkdir(parents=True, exist_ok=True)
        with lock_folder(out_root, what="batch"):
            return run()
    finally:
        if ray_started:
            shutdown_ray()


def _batch(root, scans, skipped, out_root, *, settings, device, workers, backend, address, fuse, mesh, cpu_threads,
           progress, storage_options) -> dict:
    """Run the jobs on the chosen backend and write the batch report as the results come in.

    Size: the body of batch_reconstruct after its checks: it takes the scans found, the folders skipped, and
    batch_reconstruct's own options, passed on one by one.
    """
    from ringscan.pipeline.formats.progress import progress_bar

    remote_out = is_url(out_root)
    if not remote_out:
        remove_stale_temporaries(out_root)
    report_path = join_location(out_root, "batch_report.json") if remote_out else out_root / "batch_report.json"

    def jobs():
        for folder in scans:
            rel, out = out_folder(folder, root, out_root)
            yield ScanJob(folder=str(folder), rel=rel, out=str(out), settings=settings, fuse=fuse, mesh=mesh,
                          storage_options=storage_options)

    if backend == "ray":
        n_workers = None
        results = run_ray(jobs(), address=address, device=device)
    else:
        n_workers, devices = default_workers(device)
        if workers is not None:
            n_workers = workers
        if n_workers == 0:
            results = run_inline(jobs(), device=devices[0])
        else:
            devices = [devices[i % len(devices)] for i in range(n_workers)]
            results = run_local(jobs(), workers=n_workers, devices=devices, cpu_threads=cpu_threads)
    report = {"format": BATCH_REPORT_FORMAT, "root": root if is_url(root) else str(root.resolve()),
              "backend": backend,
              "workers": n_workers, "settings": settings_to_dict(settings), "not_searched": skipped, "scans": []}
    entries: dict[int, dict] = {}
    t0 = time.perf_counter()
    bar = progress_bar(total=len(scans), desc="batch", unit="scan", disable=not progress)
    computed = 0
    first = last = None
    starts: list[float] = []
    next_write = 0.0  # the first scan's result is written at once (an unwritable OUT shows early)
    try:
        for n, entry in results:
            last = time.perf_counter() - t0
            first = last if first is None else first
            if "worker_start_s" in entry:  # a worker's first scan: its start-up, for the totals
                starts.append(float(entry.pop("worker_start_s")))
            entries[n] = entry
            computed += int(entry.get("computed_views", 0))
            if entry.get("status") == "failed":
                log.error("%s: %s", entry["scan"], entry.get("error"))
            bar.update(1)
            el = time.perf_counter() - t0
            bar.set_postfix_str(f"{computed / el if el > 0 else 0:.2f} views/s")
            if el >= next_write:
                report["scans"] = [entries[k] for k in sorted(entries)]
                write_json_to(report_path, report, storage_options)
                took = time.perf_counter() - t0 - el
                next_write = el + took + max(REPORT_EVERY_S, took / REPORT_SHARE)
    finally:
        bar.close()
        close = getattr(results, "close", None)
        if close is not None:  # stopped early (Ctrl-C, a failed report write): the backend ends its workers now
            close()
    report["scans"] = [entries[k] for k in sorted(entries)]
    report["totals"] = summarise(report["scans"], wall_s=time.perf_counter() - t0)
    report["totals"]["first_result_s"] = first  # starting the workers (Warp, kernel cache) and the first scan
    report["totals"]["last_result_s"] = last  # the rest of wall_s: closing the workers, the last report write
    if starts:
        report["totals"]["worker_start_s"] = {"workers": len(starts), "median": float(statistics.median(starts)),
                                              "max": max(starts)}
    write_json_to(report_path, report, storage_options)
    return report
