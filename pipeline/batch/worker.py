"""One scan of a batch, as a worker runs it: reconstruct (resuming), optionally fuse
and mesh, and return the scan's entry of the batch report.

The same function runs in the local process pool (:mod:`.local`) and in a Ray task
(:mod:`.ray_backend`), so both backends write the same bytes. Every file is written
atomically (``pipeline.formats.atomic``) and a scan is resumed through
:func:`~ringscan.pipeline.reconstruct.freshness.check_done`: running a scan again
after its worker died keeps the views it finished and redoes the rest, so a retried
task cannot leave a half-written or doubled result.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ringscan.kernels import init_warp, resolve_device, retain_freed_memory
from ringscan.kernels.launch import set_cpu_threads
from ringscan.kernels.process import freeze_imported_objects, one_blas_thread, skip_final_collection
from ringscan.pipeline.formats.atomic import atomic_write_json, read_json, remove_stale_temporaries
from ringscan.pipeline.formats.errors import RingscanError
from ringscan.pipeline.formats.meshes import write_cloud
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.formats.storage import stage
from ringscan.pipeline.fusion.recon import fuse_recon
from ringscan.pipeline.fusion.workflow import fuse_and_mesh
from ringscan.pipeline.reconstruct.freshness import check_done
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.reconstruct.view import CALIBRATION_WARN_PX

log = logging.getLogger(__name__)

__all__ = ["ScanJob", "STAGES", "STORAGE_STAGES", "FAULT_ENV", "CRASH_ENV", "RAISE_ENV", "init_worker", "worker_device", "process_scan",
           "failed_entry", "describe_error"]

STAGES = ("read", "decode", "sample", "triangulate", "write")
"""The per-view time split the batch report sums (the rest of a view's stages are listed as ``other``)."""

STORAGE_STAGES = ("fetch", "store")
"""A scan's seconds on object storage (downloading its objects, uploading its results), in its ``times_s``
only where the scan or its output folder is a URL."""

FAULT_ENV = "RINGSCAN_BATCH_FAULT"
"""Fault injection for tests and benchmarks: the path of a marker file. The first
worker that claims it (renames it away) finishes one view of its scan and then
kills its own process with SIGKILL, as a crash or an out-of-memory kill would."""

CRASH_ENV = "RINGSCAN_BATCH_CRASH_SCAN"
"""Fault injection for tests and benchmarks: the name of a scan in the batch (its
path relative to the root) whose worker kills itself with SIGKILL every time it
starts that scan, as a scan that crashes a library would."""

RAISE_ENV = "RINGSCAN_BATCH_RAISE_SCAN"
"""Fault injection for tests: the name of a scan in the batch whose worker raises OpenCV's own exception
(``cv2.error``, not one of ringscan's) when it starts that scan, as a library that fails on a scan would."""

_device: str | None = None
_start_s: float | None = None
_started = False
"""This worker's start-up (seconds, :func:`init_worker`), until its first scan's entry reports it."""


@dataclass(frozen=True)
class ScanJob:
    """One scan to process."""

    folder: str
    """The scan folder."""
    rel: str
    """Its name in the batch (path relative to the root)."""
    out: str
    """Its output folder."""
    settings: ReconstructSettings = ReconstructSettings()
    """Reconstruction settings."""
    fuse: bool = False
    """Fuse the views into ``out/fused/fused.ply``."""
    mesh: bool = False
    """Fuse and mesh into ``out/mesh/`` (fused.ply, mesh.ply, fuse_report.json)."""
    storage_options: dict | None = None
    """fsspec options of ``folder`` and ``out`` where they are URLs (``s3://``, ``gs://``: docs/batch.md)."""


def _exit_with_parent(parent: int) -> None:
    """Exit this worker when its parent is gone (a SIGKILLed ringscan leaves no worker behind)."""
    while True:
        time.sleep(0.5)
        if os.getppid() != parent:
            os._exit(1)


def init_child(parent: int) -> None:
    """Start a pool worker process: Ctrl-C is left to the parent (the terminal sends it to every process of the
    group; the parent ends the pool and says so in one line, where each worker printed a KeyboardInterrupt
    traceback), and the worker exits when the parent is gone (a SIGKILLed parent leaves no worker behind)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True, name="ringscan-parent").start()


def init_worker(device: str | None = None, devices=None, parent: int | None = None,
                cpu_threads: int | None = None, spawned_at: float | None = None, record_start: bool = True) -> None:
    """Start a worker: load Warp (and its kernel cache) once, choose its device.

    Args:
        device: the device for this worker (None: the best available).
        devices: a queue of device names, one taken per worker (one CUDA device each).
        parent: the process id of the parent; the worker exits when the parent is gone.
        cpu_threads: this worker's share of the CPU (Warp CPU launches, frame
            reading); None: every core.
        spawned_at: the parent's ``time.time()`` when it started this worker's
            process: the worker's start-up is then counted from there (the
            interpreter, ringscan's imports, Warp); None: from this call on.
        record_start: report the start-up with the worker's first scan (False where
            the "worker" is the ringscan process itself: ``--workers 0``).
    """
    global _device, _start_s, _started
    t = time.perf_counter()
    set_cpu_threads(cpu_threads)
    retain_freed_memory()  # a worker process is ringscan's own: keep freed arrays' pages for the next view
    one_blas_thread()  # (two workers' BLAS threads spinning took the cores from each other's kernels)
    if record_start:
        skip_final_collection()  # a worker process (pool or Ray): it ends without a last collection
        freeze_imported_objects()  # (its modules are imported: every view's collections skip them)
    if parent is not None:
        init_child(parent)
    init_warp()
    if devices is not None:
        device = devices.get()
    _device = resolve_device(device)
    took = time.time() - spawned_at if spawned_at is not None else time.perf_counter() - t
    if record_start and not _started:  # a Ray worker process runs this for every task: its start-up is its first
        _started, _start_s = True, took
    log.info("batch worker %d on %s, started in %.2f s", os.getpid(), _device, took)


def worker_device() -> str:
    """The device of this worker (initialised on first use)."""
    if _device is None:
        init_worker()
    return _device


def _maybe_fault(scan, rel: str, out: Path, settings) -> None:
    if os.environ.get(RAISE_ENV) == rel:
        import cv2

        raise cv2.error(f"{RAISE_ENV}: OpenCV's own exception, raised on purpose")
    if os.environ.get(CRASH_ENV) == rel:
        log.warning("%s: killing this worker (%d) on purpose", CRASH_ENV, os.getpid())
        os.kill(os.getpid(), signal.SIGKILL)
    marker = os.environ.get(FAULT_ENV)
    if not marker:
        return
    try:
        os.rename(marker, marker + ".taken")
    except OSError:
        return
    reconstruct_scan(scan, out, settings=settings, device=worker_device(), views=[scan.views[0].name], resume=True,
                     progress=False, lock=False)
    log.warning("%s: killing this worker (%d) on purpose", FAULT_ENV, os.getpid())
    os.kill(os.getpid(), signal.SIGKILL)


def _split(views: list[dict]) -> dict:
    tot = dict.fromkeys((*STAGES, "other"), 0.0)
    for v in views:
        for k, s in v.get("times_s", {}).items():
            tot[k if k in STAGES else "other"] += float(s)
    return tot


def process_scan(job: ScanJob) -> dict:
    """Process one scan; never raises for a bad scan (the entry says ``failed`` and why).

    A scan or output folder given as a URL is staged (:func:`~ringscan.pipeline.formats.storage.stage`): the
    frames are downloaded only when a view is computed, the results uploaded whole once the scan is done.
    """
    t, cpu = time.perf_counter(), time.process_time()
    entry: dict = {"scan": job.rel, "out": job.out}
    try:
        with stage(job.folder, job.out, options=job.storage_options) as st:
            _process(job, st, entry)
            st.commit()
            if st.remote_scan or st.remote_out:  # object storage: the scan's downloads and uploads
                entry["times_s"].update(st.seconds)
    except Exception as e:  # noqa: BLE001 - one scan's failure of any kind (a library's own exception too) fails
        # that scan alone; the batch goes on
        log.info("%s: %s", job.folder, e)  # the batch logs it once, with the scan's name
        entry.update(status="failed", error=describe_error(e))
    entry["time_s"] = time.perf_counter() - t
    entry["cpu_s"] = time.process_time() - cpu  # the worker's CPU seconds on it, every thread (one scan at a time)
    global _start_s
    if _start_s is not None:  # once per worker: the batch gathers them into its totals (``worker_start_s``)
        entry["worker_start_s"], _start_s = _start_s, None
    return entry


def _process(job: ScanJob, st, entry: dict) -> None:
    out = st.out_dir
    scan = load_scan(st.scan_dir, check_files=not st.remote_scan)
    st.check_scan(scan)
    if not scan.views:
        raise RingscanError(f"{job.folder}/scan.json: the scan has no views")
    check = check_done(scan, out, settings=job.settings, stat=st.stat)
    if check.done and check.kept:
        # A worker killed with the pool (another scan crashed it) may have left a temporary file here
        # after this scan's last write (reconstruct_scan clears them where the scan is (re)done).
        remove_stale_temporaries(out)
        views = list(check.kept.values())
        computed: list[dict] = []
        entry["status"] = "skipped (already done)"
    else:
        if check.report is not None:
            entry["redone"] = check.redo
        st.fetch_frames(scan)
        _maybe_fault(scan, job.rel, out, job.settings)
        rep = reconstruct_scan(scan, out, settings=job.settings, device=worker_device(), resume=True,
                               progress=False, lock=False)  # the batch holds its output folder
        views = rep["views"]
        kept = set(rep.get("resume", {}).get("kept", []))
        computed = [v for v in views if v["name"] not in kept]
        entry["status"] = "done"
    entry["views"] = len(views)
    entry["computed_views"] = len(computed)
    entry["points"] = sum(int(v.get("points", 0)) for v in views)
    entry["times_s"] = _split(computed)
    worst = worst_calibration_check(views)
    if worst:
        entry["calibration_check"] = worst
    st.commit()  # on object storage: the reconstruction stored, as it is on disk by now
    if entry["points"] == 0:
        reasons = list(dict.fromkeys(v.get("no_points", "no points") for v in views))
        raise RingscanError(f"no view gave any point: {'; '.join(reasons)}")
    if job.mesh or job.fuse:
        entry.update(_fuse(out, redo=bool(computed), mesh=job.mesh))
        if st.remote_out:
            entry["fused_out"] = job.out.rstrip("/") + "/" + ("mesh" if job.mesh else "fused")


def worst_calibration_check(views: list[dict]) -> dict:
    """A scan's calibration check for the batch report: the check (report.json
    ``calibration_check``) of its view with the largest median, with that view's
    ``view`` name and ``rays``, and ``views_not_fitting`` (how many views warn); with three rays
    ``projector_check``: the projector against the two cameras' points in the view where it misses most
    (``view``, ``residual_px_median``, ``residual_px_p95``), ``views_discounted`` (its ray discounted) and
    ``views_not_fitting`` (a median miss above 1 px, which warns); {} where no view has a check."""
    checked = [v for v in views if isinstance(v.get("calibration_check"), dict) and v["calibration_check"]]
    if not checked:
        return {}
    w = max(checked, key=lambda v: float(v["calibration_check"].get("median_px", 0.0)))
    out = {"view": w["name"], "rays": w.get("rays", "camera-projector"), **w["calibration_check"],
           "views_not_fitting": sum(not v["calibration_check"].get("fits", True) for v in checked)}
    # three rays: the projector against the two cameras' points (report.json stereo.projector_check)
    proj = [v for v in views if isinstance(v.get("stereo"), dict) and v["stereo"].get("projector_check")]
    if proj:
        p = max(proj, key=lambda v: float(v["stereo"]["projector_check"]["residual_px_median"]))
        c = p["stereo"]["projector_check"]
        out["projector_check"] = {"view": p["name"], "residual_px_median": c["residual_px_median"],
                                  "residual_px_p95": c["residual_px_p95"],
                                  "views_discounted": sum(bool(v["stereo"]["projector_check"]["floor_applied"])
                                                          for v in proj),
                                  "views_not_fitting": sum(v["stereo"]["projector_check"]["residual_px_median"]
                                                           > CALIBRATION_WARN_PX for v in proj)}
    return out


def describe_error(e: BaseException) -> str:
    """One line for a scan's error: ringscan's own errors as they are (they name the file); another
    exception (a library's: cv2.error, MemoryError, ...) with its type, its message on one line."""
    text = " ".join(str(e).split())
    if isinstance(e, (RingscanError, ValueError, OSError)) and text:
        return text
    module = type(e).__module__.split(".")[0]
    name = type(e).__name__ if module in ("builtins", "__main__") else f"{module}.{type(e).__name__}"
    return f"{name}: {text[:500] or '(no message)'}"


def failed_entry(job: ScanJob, e: BaseException) -> dict:
    """A scan's entry in the batch report when it failed with ``e``."""
    return {"scan": job.rel, "out": job.out, "status": "failed", "error": describe_error(e)}


def _fuse(out: Path, *, redo: bool, mesh: bool) -> dict:
    """Fuse (and mesh) a scan's reconstruction, unless its result is there and the reconstruction did not change."""
    if mesh:
        folder, files = out / "mesh", ("fuse_report.json", "fused.ply", "mesh.ply")
    else:
        folder, files = out / "fused", ("fuse.json", "fused.ply")
    if not redo and all((folder / f).is_file() for f in files):
        try:
            read_json(folder / files[0])
            return {"fused": "kept", "fused_out": str(folder)}
        except RingscanError:
            pass
    if mesh:
        fuse_and_mesh(out, folder, preview=False)
    else:
        res = fuse_recon(out)
        folder.mkdir(parents=True, exist_ok=True)
        write_cloud(folder / "fused.ply", res.cloud, view=res.point_view, confidence=res.point_confidence)
        atomic_write_json(folder / "fuse.json", {"source": str(out), "fusion": res.report()})
    return {"fused": "done", "fused_out": str(folder)}
