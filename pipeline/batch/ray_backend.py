"""The Ray backend (``ringscan batch --backend ray``; ``pip install '.[ray]'`` in the source tree).

Each scan is one Ray task running :func:`.worker.process_scan`, the function the
local pool runs, so the outputs are the same bytes. A task asks for one GPU where
the cluster has GPUs (else one CPU). A task whose worker process dies is retried
by Ray (``max_retries``); a retry is safe because every file is written atomically
and the scan resumes through the freshness check (views finished by the dead
attempt are kept, the rest redone), so each result is written whole, once.

Scan folders and the output folder must be at the same path on every node (a
shared file system), or URLs of object storage every node reaches (each task then
stages its scan: :mod:`ringscan.pipeline.formats.storage`); nothing is shipped to the
workers but the job's paths or URLs (and its storage options).
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Iterable, Iterator

from ringscan.pipeline.batch.worker import ScanJob, failed_entry, init_worker, process_scan
from ringscan.pipeline.formats.errors import RingscanError

log = logging.getLogger(__name__)

__all__ = ["run_ray", "task_options", "init_ray", "check_address", "MAX_RETRIES", "CONNECT_TIMEOUT_S"]

MAX_RETRIES = 3
"""Retries of a task whose worker process died."""


def _ray():
    try:
        import ray
    except ImportError:
        raise RingscanError("the Ray backend needs Ray: pip install ray "
                            "(or '.[ray]' in ringscan's source tree)") from None
    return ray


CONNECT_TIMEOUT_S = 5.0
"""How long a cluster address given with ``--address`` may take to accept a connection
before the batch stops (Ray itself would retry for minutes)."""


def check_address(address: str, *, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Fail fast when nothing listens at a cluster address (``host:port`` or ``ray://host:port``).

    Raises:
        RingscanError: ``--address 127.0.0.1:1: no Ray cluster answers there (Connection refused)``.
        ValueError: a malformed address (named ``--address`` first: the command's usage error).
    """
    if address in ("auto", "local"):
        return
    hostport = address[len("ray://"):] if address.startswith("ray://") else address
    host, _, port = hostport.rpartition(":")
    host = host.strip("[]")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--address {address!r}: expected HOST:PORT or ray://HOST:PORT (or auto)")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            pass
    except OSError as e:
        why = f"no answer within {timeout_s:g} s" if isinstance(e, TimeoutError) else (e.strerror or str(e))
        raise RingscanError(f"--address {address}: no Ray cluster answers there ({why})") from None


def init_ray(address: str | None = None) -> bool:
    """Join the cluster at ``address`` (None: ``RAY_ADDRESS``, else a new local one) unless this
    process already has; returns whether it joined (and so should leave: ``ray.shutdown()``).

    Raises:
        RingscanError: Ray is not installed; nothing answers at the address (:func:`check_address`).
    """
    ray = _ray()
    if ray.is_initialized():
        return False
    if address:
        check_address(address)
    ray.init(address=address, log_to_driver=False, configure_logging=False)
    return True


def task_options(resources: dict) -> dict:
    """Ray options of a scan's task on a cluster with ``resources`` (``ray.cluster_resources()``):
    one GPU and one CPU where the cluster has GPUs, else one CPU."""
    return {"num_gpus": 1, "num_cpus": 1} if int(resources.get("GPU", 0)) else {"num_cpus": 1}


def _task(job: ScanJob, device: str | None) -> dict:
    try:
        init_worker(device)  # once per Ray worker process (init_warp is idempotent)
    except Exception as e:  # noqa: BLE001 - one scan's failure, whatever raised it, fails that scan alone
        return failed_entry(job, e)
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
    started = init_ray(address)
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
                except ray.exceptions.RayTaskError as e:  # raised in the task (not retried: retry_exceptions=False)
                    cause = getattr(e, "cause", None) or e
                    log.debug("%s: %s", job.folder, e)
                    yield n, failed_entry(job, cause)
                except ray.exceptions.RayError as e:  # the task's worker died (retried up to max_retries times)
                    log.debug("%s: %s", job.folder, e)
                    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
                    yield n, {"scan": job.rel, "out": job.out, "status": "failed",
                              "error": f"its Ray task failed ({type(e).__name__}: {first[:300]}); Ray gives a task "
                                       f"whose worker dies up to {max_retries} more tries"}
    finally:
        if started:
            ray.shutdown()
