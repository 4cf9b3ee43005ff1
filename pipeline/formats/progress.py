"""Progress for long steps: a bar on a terminal, a plain line per step in logs.

Every stage that loops over views, frames or scans, and every single step that
can take more than a couple of seconds (Poisson meshing, rendering, a calibration
fit), reports through these two helpers rather than tqdm directly, so that:

- on a terminal (stderr is a TTY) the user sees tqdm bars (or an elapsed-time
  line for a single step);
- elsewhere (a log file, CI, a pipe) no ``\\r`` frames are written: plain lines
  go to the ``ringscan.progress`` logger at INFO level (the ``ringscan`` command
  shows them unless ``-q`` or ``--no-progress``): a loop's first and last steps
  and at most one line every ``LOG_INTERVAL_S`` between; a single step's start and end.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections.abc import Iterable, Iterator

log = logging.getLogger("ringscan.progress")

REFRESH_S = 0.5
"""How often a single step's elapsed time is redrawn on a terminal."""
LOG_INTERVAL_S = 5.0
"""Off a terminal, the least time between two progress lines of one loop (its first
and last steps are always logged), so that a log holds no more than a line every
few seconds."""


def on_terminal() -> bool:
    """Whether stderr is an interactive terminal (bars make sense there)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


class _LineBar:
    """tqdm's small interface used here, writing a plain log line per update."""

    def __init__(self, iterable: Iterable | None, total: int | None, desc: str, unit: str, initial: int):
        self.iterable = iterable
        self.total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.desc, self.unit, self.n, self.postfix = desc, unit, initial, ""
        self.t0 = time.perf_counter()
        self.logged_at = None

    def __iter__(self) -> Iterator:
        for item in self.iterable:
            yield item
            self.update(1)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.perf_counter()
        last = self.total is not None and self.n >= self.total
        if not last and self.logged_at is not None and now - self.logged_at < LOG_INTERVAL_S:
            return
        self.logged_at = now
        of = f"/{self.total}" if self.total is not None else ""
        extra = f" ({self.postfix})" if self.postfix else ""
        log.info("%s: %d%s %s(s), %.1f s%s", self.desc, self.n, of, self.unit, time.perf_counter() - self.t0, extra)

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = s

    def close(self) -> None:
        pass


def progress_bar(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "", unit: str = "it",
                 disable: bool = False, leave: bool = True, initial: int = 0):
    """A tqdm bar on a terminal; elsewhere an object with the same ``update``,
    ``set_postfix_str``, ``close`` and iteration that logs plain lines (the first
    and last steps, and one every ``LOG_INTERVAL_S`` between).

    Args:
        iterable: what to iterate over (or None, and call ``update``).
        total: number of steps (default ``len(iterable)`` where it has one).
        desc: what is being done, e.g. ``"reconstruct cup"``.
        unit: the step's name (``"view"``, ``"frame"``).
        disable: no progress at all (``--no-progress``): a silent tqdm.
        leave: keep the finished bar on the terminal.
        initial: steps already done (a resumed run).
    """
    if disable or on_terminal():
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, disable=disable, leave=leave, initial=initial)
    return _LineBar(iterable, total, desc, unit, initial)


@contextlib.contextmanager
def progress_step(desc: str, *, enabled: bool = True):
    """Report one long step (no sub-steps to count): on a terminal the elapsed
    time is redrawn until it ends; elsewhere one line when it starts and one when
    it ends, with its time. Nothing when ``enabled`` is False."""
    if not enabled:
        yield
        return
    t0 = time.perf_counter()
    if not on_terminal():
        log.info("%s ...", desc)
        yield
        log.info("%s: done in %.1f s", desc, time.perf_counter() - t0)
        return
    from tqdm import tqdm

    bar = tqdm(total=None, desc=desc, bar_format="{desc}: {elapsed}", leave=False)
    stop = threading.Event()

    def tick() -> None:
        while not stop.wait(REFRESH_S):
            bar.refresh()

    t = threading.Thread(target=tick, daemon=True)
    t.start()
    try:
        yield
    finally:
        stop.set()
        t.join()
        bar.close()
