"""The Ray backend (``ringscan batch --backend ray``; ``pip install '.[ray]'`` in the source tree).

Each scan is one Ray task running :func:`.worker.process_scan`, the function the
local pool runs, so the outputs are the same bytes. A task asks for one GPU where
the cluster has GPUs (else one CPU). A task whose worker process dies is retried
by Ray (``max_retries``); a retry is safe because every file is written atomically
and the scan resumes through the freshness check (views finished by the dead
attempt are kept, the rest redone), so each result is written whole, once.

Scan folders and the output folder must be at the same path on every node (a
shared file system); nothing is shipped to the workers but the job's paths.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator

from ringscan.pipeline.batch.worker import ScanJob, init_worker, process_scan

log = logging.getLogger(__name__)

__all__ = ["run_ray", "task_options", "MAX_RETRIES"]

MAX_RETRIES = 3
"""Retries of a task whose worker process died."""


def _ray():
    try:
        import ray
    except ImportError:
        raise RuntimeError("the Ray backend needs Ray: pip install ray "
                           "(or '.[ray]' in ringscan's source tree)") from None
    return ray


def task_options(resources: dict) -> dict:
    """Ray options of a scan's task on a cluster with ``resources`` (``ray.cluster_resources()``):
    one GPU and one CPU where the cluster has GPUs, else one CPU."""
    return {"num_gpus": 1, "num_cpus": 1} if int(resources.get("GPU", 0)) else {"num_cpus": 1}


def _task(job: ScanJob, device: str | None) -> dict:
    init_worker(device)  # once per Ray worker process (init_warp is idempotent)
    entry = process_scan(job)
    ray = _ray()
    # what Ray gave the task (its GPU, if any): in the batch report, next to the device the worker used
    entry["ray_resources"] = {k: float(v) for k, v in ray.get_runtime_context().get_assigned_resources().items()}
    return entry


def run_ray(jobs: Iterable[ScanJob], *, address: str | None = None, device: str | None = None,
            in_flight: int | None = None, max_retries: int = MAX_RETRIES) -> Iterator[tuple[int, dict]]:
    """Run ``jobs`` as Ray tasks; yield ``(job number, entry)`` as each finishes.

    Args:
        jobs: the scans, consumed lazily.
        address: a running cluster's address (``ray://host:10001`` or ``host:6379``);
            None joins the cluster of ``RAY_ADDRESS`` or starts a local one.
        device: the device inside each task (None: the task's GPU when it got one, else the CPU).
        in_flight: most tasks submitted at once (default: twice the cluster's CPUs or GPUs).
        max_retries: retries of a task whose worker died.
    """
    ray = _ray()
    started = False
    if not ray.is_initialized():
        ray.init(address=address, log_to_driver=False, configure_logging=False)
        started = True
    try:
        res = ray.cluster_resources()
        gpus = int(res.get("GPU", 0))
        remote = ray.remote(max_retries=max_retries, retry_exceptions=False, **task_options(res))(_task)
        limit = in_flight or max(2, 2 * (gpus or int(res.get("CPU", 1))))
        source = enumerate(jobs)
        refs: dict = {}
        exhausted = False
        while True:
            while len(refs) < limit and not exhausted:
                try:
                    n, job = next(source)
                except StopIteration:
                    exhausted = True
                    break
                refs[remote.remote(job, device)] = (n, job)
            if not refs:
                return
            ready, _ = ray.wait(list(refs), num_returns=1)
            for r in ready:
                n, job = refs.pop(r)
                try:
                    yield n, ray.get(r)
                except ray.exceptions.RayError as e:
                    log.error("%s: %s", job.folder, e)
                    yield n, {"scan": job.rel, "out": job.out, "status": "failed",
                              "error": f"Ray task failed after {max_retries} retries: {type(e).__name__}"}
    finally:
        if started:
            ray.shutdown()
