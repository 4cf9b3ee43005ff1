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

import contextlib
import logging
import multiprocessing as mp
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

from ringscan.pipeline.batch.worker import ScanJob, init_worker, process_scan

log = logging.getLogger(__name__)

__all__ = ["run_local", "end_pool", "children_without_ctrl_c"]

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
    yield from _LocalRun(jobs, workers=workers, devices=devices, cpu_threads=cpu_threads).results()


class _LocalRun:
    """One run of the local backend: the pool, the scans in flight, and the scans given
    again one at a time after a worker died (the module docstring tells the rule)."""

    def __init__(self, jobs: Iterable[ScanJob], *, workers: int, devices: list[str | None], cpu_threads: int):
        self.workers, self.devices, self.cpu_threads = workers, devices, cpu_threads
        self.ctx = mp.get_context("spawn")
        self.source = enumerate(jobs)
        self.in_flight: dict = {}  # future -> (number, job, deaths while alone)
        self.suspects: list = []  # in flight when a worker died: given again one at a time
        self.pending: list = []  # taken from ``jobs`` but not running: the pool broke as they were given to it
        self.pool = self.queue = None

    def results(self) -> Iterator[tuple[int, dict]]:
        """Feed the pool, yield each scan's entry as it finishes, restart the pool when a worker dies.
        Stopped early (Ctrl-C, an error, the generator closed), it ends the workers at once: they leave
        Ctrl-C to this process (:func:`~.worker.init_child`), and waiting would wait for their scans."""
        self.pool, self.queue = self._new_pool()
        finished = False
        try:
            while True:
                try:
                    self._submit()
                except BrokenProcessPool:  # a worker died between scans: the pool is gone, with whatever was in flight
                    lost, alone = [], False
                else:
                    if not self.in_flight:
                        finished = True
                        return
                    alone = len(self.in_flight) == 1
                    lost = yield from self._collect()
                    if not lost:
                        continue
                yield from self._restart(lost, alone=alone)
        finally:
            if not finished:
                end_pool(self.pool)
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.queue.close()

    def _new_pool(self):
        with children_without_ctrl_c():
            q = self.ctx.Queue()
            for d in self.devices:
                q.put(d)
        return ProcessPoolExecutor(max_workers=self.workers, mp_context=self.ctx, initializer=init_worker,
                                   initargs=(None, q, os.getpid(), self.cpu_threads, time.time())), q

    def _next_item(self):
        if self.pending:
            return self.pending.pop(0)
        try:
            n, job = next(self.source)
        except StopIteration:
            return None
        return n, job, 0

    def _submit(self) -> None:
        """Give the pool work (a submit starts a worker process where the pool has fewer than it may), with
        Ctrl-C kept from the processes it starts (:func:`children_without_ctrl_c`)."""
        with children_without_ctrl_c():
            self._submit_some()

    def _submit_some(self) -> None:
        """Give the pool work: the next suspect alone once nothing else runs, else new scans up
        to two per worker. Raises BrokenProcessPool (the scan kept to be given again) if a worker died."""
        if self.suspects:
            if not self.in_flight:
                item = self.suspects.pop(0)
                try:
                    self.in_flight[self.pool.submit(process_scan, item[1])] = item
                except BrokenProcessPool:
                    self.suspects.insert(0, item)
                    raise
            return
        while len(self.in_flight) < 2 * self.workers:
            item = self._next_item()
            if item is None:
                break
            try:
                self.in_flight[self.pool.submit(process_scan, item[1])] = item
            except BrokenProcessPool:
                self.pending.insert(0, item)
                raise

    def _collect(self):
        """Wait for the first scans to finish and yield their entries; return the scans the pool broke under."""
        done, _ = wait(self.in_flight, return_when=FIRST_COMPLETED)
        lost: list = []
        for f in done:
            item = self.in_flight.pop(f)
            try:
                entry = f.result()
            except BrokenProcessPool:
                lost.append(item)
                continue
            yield item[0], entry
        return lost

    def _restart(self, lost: list, *, alone: bool) -> Iterator[tuple[int, dict]]:
        """The pool is gone with every scan in flight: count a death against a scan that ran
        alone (yield it as failed after MAX_DEATHS), queue the rest as suspects, start a new pool."""
        for f, item in self.in_flight.items():
            f.cancel()
            lost.append(item)
        self.in_flight.clear()
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.queue.close()
        if alone:  # it ran on its own: this scan killed its worker
            n, job, deaths = lost[0]
            lost = [(n, job, deaths + 1)]
            if deaths + 1 >= MAX_DEATHS:
                lost = []
                yield n, {"scan": job.rel, "out": job.out, "status": "failed",
                          "error": f"its worker process died {deaths + 1} times while it ran alone "
                                   f"(killed, out of memory, or a crash in a library)"}
        self.suspects = sorted(self.suspects + lost, key=lambda it: it[0])
        log.warning("a batch worker died; restarting the pool, %d scan(s) given again one at a time",
                    len(self.suspects))
        self.pool, self.queue = self._new_pool()


@contextlib.contextmanager
def children_without_ctrl_c():
    """Processes started inside the block (a pool's workers, its resource tracker) start with SIGINT blocked:
    the signal mask is inherited across exec, so they never see the Ctrl-C the terminal sends to the whole
    process group, from their first instruction on (an initializer comes too late: a worker importing Warp
    printed a KeyboardInterrupt traceback). This process ends them instead (:func:`end_pool`). A Ctrl-C that
    arrives inside the block is held until it ends (raised half-way through starting a worker, it left one
    that read a truncated start-up message and printed an EOFError traceback), then raised."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    held: list = []
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    old_handler = signal.signal(signal.SIGINT, lambda sig, frame: held.append(sig))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old_handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
    if held:
        if callable(old_handler):
            old_handler(signal.SIGINT, None)
        elif old_handler != signal.SIG_IGN:
            raise KeyboardInterrupt


def end_pool(pool: ProcessPoolExecutor) -> None:
    """End a process pool's workers now (SIGTERM), whatever they are running, and cancel what waits."""
    for p in list((getattr(pool, "_processes", None) or {}).values()):
        with contextlib.suppress(OSError, ValueError):
            p.terminate()
    pool.shutdown(wait=False, cancel_futures=True)


def run_inline(jobs: Iterable[ScanJob], *, device: str | None,
               call: Callable[[ScanJob], dict] = process_scan) -> Iterator[tuple[int, dict]]:
    """Run ``jobs`` one after another in this process (``--workers 0``)."""
    init_worker(device, record_start=False)  # this process's own start-up is not a worker's
    for n, job in enumerate(jobs):
        yield n, call(job)
