"""The local backend: a pool of worker processes on this machine.

Each worker is a spawned process started once (:func:`.worker.init_worker` loads
Warp and its kernel cache and picks the worker's device: one CUDA device per worker
where there are GPUs), then fed one scan at a time. Scans are fed lazily, at most
two per worker in flight, so memory is bounded by the scans in flight whatever the
folder's size. A worker that dies (killed, out of memory) breaks the pool: a new
pool is started and the scans that were in flight are given once more; a scan
whose worker dies twice is reported as failed.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

from ringscan.pipeline.batch.worker import ScanJob, init_worker, process_scan

log = logging.getLogger(__name__)

__all__ = ["run_local"]

MAX_TRIES = 3
"""How many times a scan is given to a worker before a dying worker fails it."""


def run_local(jobs: Iterable[ScanJob], *, workers: int, devices: list[str | None],
              cpu_threads: int | None = None) -> Iterator[tuple[int, dict]]:
    """Run ``jobs`` on ``workers`` processes; yield ``(job number, entry)`` as each finishes.

    Args:
        jobs: the scans, consumed lazily.
        workers: number of worker processes.
        devices: one device name per worker (None: the best available).
        cpu_threads: CPU threads of each worker (None: the cores shared out among
            the workers, at least one each), so that N workers do not fight over
            the cores that one would use alone.
    """
    if cpu_threads is None:
        cpu_threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    ctx = mp.get_context("spawn")
    source = enumerate(jobs)
    in_flight: dict = {}  # future -> (number, job, tries)
    retry: list = []
    exhausted = False

    def start_pool():
        q = ctx.Queue()
        for d in devices:
            q.put(d)
        return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=init_worker,
                                   initargs=(None, q, os.getpid(), cpu_threads)), q

    pool, queue = start_pool()
    try:
        while True:
            while len(in_flight) < 2 * workers and (retry or not exhausted):
                if retry:
                    n, job, tries = retry.pop(0)
                else:
                    try:
                        n, job = next(source)
                    except StopIteration:
                        exhausted = True
                        break
                    tries = 0
                in_flight[pool.submit(process_scan, job)] = (n, job, tries + 1)
            if not in_flight:
                return
            done, _ = wait(in_flight, return_when=FIRST_COMPLETED)
            broken = False
            for f in done:
                n, job, tries = in_flight.pop(f)
                try:
                    yield n, f.result()
                except BrokenProcessPool:
                    broken = True
                    retry.append((n, job, tries))
            if broken:
                # Every scan in flight is lost with the pool; none of them is known to be the one that killed it.
                for f, item in in_flight.items():
                    f.cancel()
                    retry.append(item)
                in_flight.clear()
                pool.shutdown(wait=False, cancel_futures=True)
                queue.close()
                retry.sort(key=lambda it: it[0])
                failed = [it for it in retry if it[2] >= MAX_TRIES]
                retry = [it for it in retry if it[2] < MAX_TRIES]
                for n, job, tries in failed:
                    yield n, {"scan": job.rel, "out": job.out, "status": "failed",
                              "error": f"its worker process died {tries} times while processing it"}
                log.warning("a batch worker died; restarting the pool, %d scan(s) given again", len(retry))
                pool, queue = start_pool()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        queue.close()


def run_inline(jobs: Iterable[ScanJob], *, device: str | None,
               call: Callable[[ScanJob], dict] = process_scan) -> Iterator[tuple[int, dict]]:
    """Run ``jobs`` one after another in this process (``--workers 0``)."""
    init_worker(device)
    for n, job in enumerate(jobs):
        yield n, call(job)
