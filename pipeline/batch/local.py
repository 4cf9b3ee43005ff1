"""The local backend: a pool of worker processes on this machine.

Each worker is a spawned process started once (:func:`.worker.init_worker` loads
Warp and its kernel cache and picks the worker's device: one CUDA device per worker
where there are GPUs), then fed one scan at a time. Scans are fed lazily, at most
two per worker in flight, so memory is bounded by the scans in flight whatever the
folder's size.

A worker that dies (killed, out of memory, a crash in a library) breaks the whole
pool, and with it every scan in flight: nothing tells which of them killed it. So a
new pool is started and those scans are given again *one at a time*, nothing else
in flight: one that finishes was innocent; one whose worker dies while it runs
alone is the culprit, given once more alone, and reported as failed after
:data:`MAX_DEATHS` such deaths. The other scans then go on as before. An innocent
scan is never failed for sharing a pool with one that crashes.
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

MAX_DEATHS = 2
"""How many times a scan's worker may die while that scan runs alone before it is reported as failed."""


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
    in_flight: dict = {}  # future -> (number, job, deaths while alone)
    suspects: list = []  # in flight when a worker died: given again one at a time
    exhausted = False

    def start_pool():
        q = ctx.Queue()
        for d in devices:
            q.put(d)
        return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=init_worker,
                                   initargs=(None, q, os.getpid(), cpu_threads)), q

    pending: list = []  # taken from ``jobs`` but not running: the pool broke as they were given to it

    def next_item():
        if pending:
            return pending.pop(0)
        try:
            n, job = next(source)
        except StopIteration:
            return None
        return n, job, 0

    pool, queue = start_pool()
    try:
        while True:
            lost: list = []
            alone = False
            try:
                if suspects:
                    if not in_flight:
                        item = suspects.pop(0)
                        try:
                            in_flight[pool.submit(process_scan, item[1])] = item
                        except BrokenProcessPool:
                            suspects.insert(0, item)
                            raise
                else:
                    while len(in_flight) < 2 * workers:
                        item = next_item()
                        if item is None:
                            break
                        try:
                            in_flight[pool.submit(process_scan, item[1])] = item
                        except BrokenProcessPool:
                            pending.insert(0, item)
                            raise
            except BrokenProcessPool:
                pass  # a worker died between scans: the pool is gone, with whatever was in flight
            else:
                if not in_flight:
                    return
                done, _ = wait(in_flight, return_when=FIRST_COMPLETED)
                alone = len(in_flight) == 1
                broken = False
                for f in done:
                    item = in_flight.pop(f)
                    try:
                        entry = f.result()
                    except BrokenProcessPool:
                        broken = True
                        lost.append(item)
                        continue
                    yield item[0], entry
                if not broken:
                    continue
            # The pool is gone with every scan in flight.
            for f, item in in_flight.items():
                f.cancel()
                lost.append(item)
            in_flight.clear()
            pool.shutdown(wait=False, cancel_futures=True)
            queue.close()
            if alone:  # it ran on its own: this scan killed its worker
                n, job, deaths = lost[0]
                lost = [(n, job, deaths + 1)]
                if deaths + 1 >= MAX_DEATHS:
                    lost = []
                    yield n, {"scan": job.rel, "out": job.out, "status": "failed",
                              "error": f"its worker process died {deaths + 1} times while it ran alone "
                                       f"(killed, out of memory, or a crash in a library)"}
            suspects = sorted(suspects + lost, key=lambda it: it[0])
            log.warning("a batch worker died; restarting the pool, %d scan(s) given again one at a time",
                        len(suspects))
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
