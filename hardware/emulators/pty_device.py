"""A serial device behind a pseudo-terminal: the base of the emulators, with
injectable faults (:class:`Fault`: an error reply, silence, an alarm, the port
vanishing, a reset, a lost reply).
"""

from __future__ import annotations

import abc
import heapq
import itertools
import logging
import os
import re
import select
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

__all__ = ["FAULT_KINDS", "Fault"]


FAULT_KINDS = ("error", "silent", "alarm", "vanish", "reset", "lose_ok", "garble")


@dataclass
class Fault:
    """A fault waiting for a matching line."""

    kind: str
    """error (refuse the line), silent (swallow it), alarm (mid-move for a motion line),
    vanish (the port disappears), reset (the board restarts by itself) or lose_ok (the
    line is executed, its reply is lost on the way) or garble (the reply arrives cut:
    a status report without its closing ``>``; turntable ``?`` only)."""
    on: str
    """Matches a line starting with this (case and spaces ignored); ``?`` matches status queries."""
    code: int | None = None
    """error / alarm code."""
    at_fraction: float = 0.5
    """For alarm / vanish on a motion line: how far through the move it strikes."""
    times: int = 1
    """How many matching lines it hits."""
    skip: int = 0
    """Matching lines let through before it hits."""

    def matches(self, line: str) -> bool:
        return _norm(line).startswith(_norm(self.on))


def _norm(s: str) -> str:
    return re.sub(r"\s+", "", s).upper()


class _PtyDevice(abc.ABC):
    """A device on a pseudo-terminal, run by one background thread.

    All state changes happen under ``self._lock``; the thread reads the master side
    without blocking, so ``unplug``/``replug`` from another thread are safe.
    """

    def __init__(self, *, name: str, link_path: str | os.PathLike | None = None):
        self.name = name
        self.link_path = None if link_path is None else Path(link_path)
        self.received = bytearray()
        """Every byte the host sent, in order (what the tests compare)."""
        self.lines: list[str] = []
        """Every complete line the host sent, in order."""
        self.faults: list[Fault] = []
        self._lock = threading.RLock()
        self._master: int | None = None
        self._slave: int | None = None
        self._tty: str | None = None
        self._timers: list = []
        self._seq = itertools.count()
        self._stop = False
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        self._plug()
        self._thread = threading.Thread(target=self._run, name=f"emulated-{name}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ port

    @property
    def port(self) -> str:
        """The path a host opens (the stable symlink when there is one)."""
        return str(self.link_path) if self.link_path is not None else self._tty

    @property
    def tty(self) -> str | None:
        """The pty slave behind the port now (None while unplugged)."""
        return self._tty

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave, self._tty = master, slave, os.ttyname(slave)
        if self.link_path is not None:
            tmp = self.link_path.with_name(f".{self.link_path.name}.tmp")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            os.symlink(self._tty, tmp)
            os.replace(tmp, self.link_path)
        log.debug("emulated %s on %s", self.name, self._tty)

    def _unplug(self) -> None:
        # The port's name goes first, then the pty: a host that sees the line drop
        # (EIO at once) must also find the port gone, as with a pulled USB cable.
        if self.link_path is not None and self.link_path.is_symlink():
            self.link_path.unlink()
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = self._tty = None
        log.debug("emulated %s unplugged", self.name)

    def unplug(self) -> None:
        """Make the port vanish (the host sees its port disappear)."""
        with self._lock:
            self._unplug()
        self._wake()

    def replug(self) -> None:
        """Plug back in: a fresh pty (same symlink), the device powered up again."""
        with self._lock:
            if self._master is not None:
                self._unplug()
            self._power_on()
            self._plug()
        self._wake()

    def close(self) -> None:
        """Stop the thread and remove the port."""
        with self._lock:
            self._stop = True
        self._wake()
        self._thread.join(timeout=2.0)
        with self._lock:
            self._unplug()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ faults

    def inject(self, kind: str, *, on: str, code: int | None = None, at_fraction: float = 0.5, times: int = 1,
               skip: int = 0) -> Fault:
        """Arm a fault for the next line(s) starting with ``on`` (see the module doc)."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault kind must be one of {FAULT_KINDS}, got {kind!r}")
        f = Fault(kind=kind, on=on, code=code, at_fraction=at_fraction, times=times, skip=skip)
        with self._lock:
            self.faults.append(f)
        return f

    def _take_fault(self, line: str) -> Fault | None:
        for f in self.faults:
            if f.matches(line):
                if f.skip > 0:
                    f.skip -= 1
                    return None
                f.times -= 1
                if f.times <= 0:
                    self.faults.remove(f)
                return f
        return None

    # ------------------------------------------------------------------ thread

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    def _send(self, data: bytes | str) -> None:
        if isinstance(data, str):
            data = data.encode("ascii")
        with self._lock:
            if self._master is None:
                return
            view = memoryview(data)
            deadline = time.monotonic() + 1.0
            while view:
                try:
                    n = os.write(self._master, view)
                    view = view[n:]
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        log.warning("emulated %s: host not reading; reply dropped", self.name)
                        return
                    time.sleep(0.001)
                except OSError:
                    return

    def _schedule(self, delay_s: float, fn) -> None:
        heapq.heappush(self._timers, (time.monotonic() + max(delay_s, 0.0), next(self._seq), fn))
        self._wake()

    def _run(self) -> None:
        while True:
            with self._lock:
                if self._stop:
                    return
                master = self._master
                timeout = None
                if self._timers:
                    timeout = max(self._timers[0][0] - time.monotonic(), 0.0)
            fds = [self._wake_r] + ([master] if master is not None else [])
            try:
                ready, _, _ = select.select(fds, [], [], timeout)
            except (OSError, ValueError):
                ready = []
            if self._wake_r in ready:
                try:
                    os.read(self._wake_r, 4096)
                except OSError:
                    pass
            with self._lock:
                if self._stop:
                    return
                if self._master is not None:
                    try:
                        data = os.read(self._master, 4096)
                    except OSError:  # nothing there (EAGAIN) or no host (EIO)
                        data = b""
                    if data:
                        self.received += data
                        try:
                            self._on_bytes(data)
                        except Exception:  # an emulator bug must not hang the host silently
                            log.exception("emulated %s failed on %r", self.name, data)
                now = time.monotonic()
                while self._timers and self._timers[0][0] <= now:
                    _, _, fn = heapq.heappop(self._timers)
                    try:
                        fn()
                    except Exception:
                        log.exception("emulated %s timer failed", self.name)

    # hooks
    @abc.abstractmethod
    def _on_bytes(self, data: bytes) -> None:
        """Handle bytes the host wrote (each emulated device parses its own protocol)."""

    def _power_on(self) -> None:
        """Reset the controller state (a power cycle)."""
