"""Emulated devices on pseudo-terminals, so the real serial drivers can be tried
(and tested) through the real pyserial stack, and a whole virtual rig.

- :class:`EmulatedTurntable`: a GRBL 1.1 (or Horus 0.2) turntable controller:
  banner on Ctrl-X, ``ok``/``error:N`` per line, ``?`` status reports that say
  ``Run`` during a simulated move and ``Idle`` after it, alarms, ``$X``, ``G90``/
  ``G91``/``G92``/``G0``/``G1``/``G4``, ``M17``/``M18`` on Horus.
- :class:`EmulatedProjector`: a serial pattern projector (protocol in
  :mod:`ringscan.hardware.projector`).
- :class:`CameraServer`: serves a camera on a Unix socket (``SocketCamera``).
- :class:`EmulatedRig`: all three around the virtual rig's renderer, as
  ``ringscan emulate`` and ``ringscan capture --virtual`` start it.

Each device runs in a background thread on the master side of a pty; the host opens
the slave path (or a stable symlink to it, like ``/dev/serial/by-id/...``). Faults
are injected with ``inject(kind, on=..., ...)``: ``error`` (refuse the line),
``silent`` (swallow it), ``alarm`` (mid-move for a motion line), ``vanish`` (the port
disappears, mid-move for a motion line), ``reset`` (the board restarts by itself).
A vanished port comes back with :meth:`replug` (a fresh pty behind the same symlink,
the controller freshly powered up, the table where the motor left it).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import os
import re
import select
import socket
import tempfile
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .projector import IDENT, PROTOCOL_VERSION, FrameStore

log = logging.getLogger(__name__)

__all__ = ["EmulatedTurntable", "EmulatedProjector", "CameraServer", "EmulatedRig", "Fault"]

FAULT_KINDS = ("error", "silent", "alarm", "vanish", "reset")


@dataclass
class Fault:
    """A fault waiting for a matching line."""

    kind: str
    """error, silent, alarm, vanish or reset."""
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


class _PtyDevice:
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
    def _on_bytes(self, data: bytes) -> None:
        raise NotImplementedError

    def _power_on(self) -> None:
        """Reset the controller state (a power cycle)."""


@dataclass
class _Move:
    start: float
    """Machine position at the start."""
    target: float
    """Machine position at the end."""
    t0: float
    t1: float


class EmulatedTurntable(_PtyDevice):
    """A GRBL-like turntable controller on a pty.

    Args:
        flavor: "grbl" (GRBL 1.1h: ``error:N``, ``ALARM:N``, ``<Idle|MPos:...>``) or
            "horus" (Horus 0.2, GRBL 0.9 style: ``error: text``, ``<Idle,MPos:..,WPos:..>``,
            and M17/M18).
        link_path: a stable symlink to create for the port.
        time_scale: simulated moves run this many times faster than real ones.
        start_deg: the table's physical angle at power-up.
        alarm_on_reset: come up in the Alarm state (as GRBL does with homing
            enabled) so the host must send ``$X``.
        max_rate: the G0 rate (deg/min), GRBL's ``$110``.
    """

    BANNERS = {"grbl": "Grbl 1.1h ['$' for help]", "horus": "Horus 0.2 ['$' for help]"}

    def __init__(self, *, flavor: str = "grbl", link_path=None, time_scale: float = 1.0, start_deg: float = 0.0,
                 alarm_on_reset: bool = False, max_rate: float = 3000.0):
        if flavor not in self.BANNERS:
            raise ValueError(f"flavor must be one of {sorted(self.BANNERS)}, got {flavor!r}")
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale}")
        self.flavor = flavor
        self.time_scale = float(time_scale)
        self.alarm_on_reset = alarm_on_reset
        self.max_rate = float(max_rate)
        self.settings = {100: 8.889, 110: max_rate, 120: 200.0}
        self.motor_enabled = False
        self.resets = 0
        """Soft resets (Ctrl-X) received."""
        self._mount = float(start_deg)  # physical angle = machine position + mount
        self._buf = bytearray()
        self._power_on()
        super().__init__(name="turntable", link_path=link_path)

    # ------------------------------------------------------------------ state

    def _power_on(self) -> None:
        if hasattr(self, "_moves"):
            self._mount = self._physical(time.monotonic())
        self._machine = 0.0
        self._wco = 0.0
        self._moves: deque[_Move] = deque()
        self._alarm = self.alarm_on_reset
        self._absolute = True
        self._motion_mode = 0
        self._feed: float | None = None
        self._queue: deque[str] = deque()
        self._sync = None  # token of a G4 waiting for the planner
        self._silent = False
        self._buf = bytearray()

    def _machine_at(self, now: float) -> float:
        while self._moves and self._moves[0].t1 <= now:
            m = self._moves.popleft()
            self._machine = m.target
        if not self._moves:
            return self._machine
        m = self._moves[0]
        if now <= m.t0:
            return m.start
        return m.start + (m.target - m.start) * (now - m.t0) / (m.t1 - m.t0)

    def _physical(self, now: float) -> float:
        return self._machine_at(now) + self._mount

    @property
    def angle_deg(self) -> float:
        """The table's physical angle now (degrees), mid-move included."""
        with self._lock:
            return self._physical(time.monotonic())

    @property
    def moving(self) -> bool:
        with self._lock:
            self._machine_at(time.monotonic())
            return bool(self._moves)

    def _state(self) -> str:
        if self._alarm:
            return "Alarm"
        self._machine_at(time.monotonic())
        return "Run" if self._moves else "Idle"

    # ------------------------------------------------------------------ replies

    def _ok(self) -> None:
        self._send("ok\r\n")

    def _error(self, code: int) -> None:
        from .errors import GRBL_ERRORS

        if self.flavor == "grbl":
            self._send(f"error:{code}\r\n")
        else:
            self._send(f"error: {GRBL_ERRORS.get(code, 'Invalid gcode').capitalize()}\r\n")

    def _raise_alarm(self, code: int) -> None:
        from .errors import GRBL_ALARMS

        now = time.monotonic()
        self._machine = self._machine_at(now)
        self._moves.clear()
        self._alarm = True
        self._sync = None
        self._queue.clear()
        if self.flavor == "grbl":
            self._send(f"ALARM:{code}\r\n")
        else:
            self._send(f"ALARM: {GRBL_ALARMS.get(code, 'Hard/soft limit').capitalize()}\r\n")

    def _status(self) -> None:
        now = time.monotonic()
        m = self._machine_at(now)
        st = self._state()
        if self.flavor == "grbl":
            fs = self._feed if (self._moves and self._feed) else 0
            self._send(f"<{st}|MPos:{m:.3f},0.000,0.000|FS:{fs:.0f},0|WCO:{self._wco:.3f},0.000,0.000>\r\n")
        else:
            self._send(f"<{st},MPos:{m:.3f},0.000,0.000,WPos:{m - self._wco:.3f},0.000,0.000>\r\n")

    def _soft_reset(self) -> None:
        self._machine = self._machine_at(time.monotonic())
        moving = bool(self._moves)
        self._moves.clear()
        self._queue.clear()
        self._buf.clear()
        self._sync = None
        self._absolute, self._motion_mode = True, 0
        self.resets += 1
        if moving:
            self._alarm = True  # GRBL: reset while in motion, position not guaranteed
        elif self.alarm_on_reset:
            self._alarm = True
        self._send(f"\r\n{self.BANNERS[self.flavor]}\r\n")
        if self._alarm:
            self._send("[MSG:'$H'|'$X' to unlock]\r\n" if self.flavor == "grbl" else "['$H'|'$X' to unlock]\r\n")

    # ------------------------------------------------------------------ input

    def _on_bytes(self, data: bytes) -> None:
        for b in data:
            c = bytes([b])
            if c == b"\x18":
                self._silent = False
                self._soft_reset()
            elif c == b"?":
                f = self._take_fault("?")
                if f is not None and f.kind == "silent":
                    continue
                if f is not None and f.kind == "vanish":
                    self._unplug()
                    return
                if not self._silent:
                    self._status()
            elif c in (b"!", b"~"):
                continue  # feed hold / cycle start: not modelled
            elif c in (b"\n", b"\r"):
                if self._buf:
                    line = self._buf.decode("ascii", "replace")
                    self._buf.clear()
                    self.lines.append(line)
                    self._queue.append(line)
                    self._process_queue()
            else:
                self._buf += c

    def _process_queue(self) -> None:
        while self._queue and self._sync is None and self._master is not None:
            self._line(self._queue.popleft())

    def _line(self, raw: str) -> None:
        if self._silent:
            return
        f = self._take_fault(raw)
        if f is not None:
            if f.kind == "error":
                self._error(f.code if f.code is not None else 20)
                return
            if f.kind == "silent":
                return
            if f.kind == "reset":
                self._power_on()
                self._send(f"\r\n{self.BANNERS[self.flavor]}\r\n")
                return
        is_motion = self._execute(raw, fault=f)
        if f is not None and not is_motion:
            if f.kind == "alarm":
                self._raise_alarm(f.code if f.code is not None else 1)
            elif f.kind == "vanish":
                self._unplug()

    def _execute(self, raw: str, *, fault: Fault | None) -> bool:
        """Run one line and answer it; True when it queued a move (faults then strike mid-move)."""
        s = re.sub(r"\(.*?\)", "", raw.upper()).split(";")[0]
        s = re.sub(r"\s+", "", s)
        if not s:
            self._ok()
            return False
        if s.startswith("$"):
            self._dollar(s)
            return False
        if self._alarm:
            self._error(9)
            return False
        words = re.findall(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))", s)
        if "".join(a + b for a, b in words) != s:
            self._error(1 if not re.match(r"^[A-Z]", s) else 2)
            return False
        gs = [float(v) for k, v in words if k == "G"]
        ms = [float(v) for k, v in words if k == "M"]
        val = {k: float(v) for k, v in words if k not in "GM"}
        for k in val:
            if k not in "XFPN":
                self._error(20)
                return False
        dwell = False
        g92 = False
        for g in gs:
            if g in (90.0, 91.0):
                self._absolute = g == 90.0
            elif g in (0.0, 1.0):
                self._motion_mode = int(g)
            elif g == 4.0:
                dwell = True
            elif g == 92.0:
                g92 = True
            elif g in (17.0, 21.0, 54.0, 94.0):
                pass
            else:
                self._error(20)
                return False
        for m in ms:
            if m in (17.0, 18.0) and self.flavor == "horus":
                self.motor_enabled = m == 17.0
            elif m in (2.0, 30.0):
                pass
            else:
                self._error(20)
                return False
        if "F" in val:
            if val["F"] <= 0:
                self._error(4)
                return False
            self._feed = val["F"]
        now = time.monotonic()
        if g92:
            if "X" not in val:
                self._error(26)
                return False
            self._wco = self._planned_end() - val["X"]
            self._ok()
            return False
        if dwell:
            if "P" not in val:
                self._error(28)
                return False
            token = object()
            self._sync = token
            end = max([m.t1 for m in self._moves], default=now) + val["P"] / self.time_scale

            def done(token=token):
                if self._sync is token:
                    self._sync = None
                    self._ok()
                    self._process_queue()

            self._schedule(end - now, done)
            return False
        if "X" in val:
            rate = self.max_rate if self._motion_mode == 0 else self._feed
            if rate is None:
                self._error(22)
                return False
            start = self._planned_end()
            target = (val["X"] + self._wco) if self._absolute else start + val["X"]
            t0 = max([m.t1 for m in self._moves], default=now)
            dur = abs(target - start) / rate * 60.0 / self.time_scale
            move = _Move(start=start, target=target, t0=t0, t1=t0 + dur)
            self._moves.append(move)
            self._ok()
            if fault is not None and fault.kind in ("alarm", "vanish"):
                at = t0 + fault.at_fraction * dur - now
                if fault.kind == "alarm":
                    code = fault.code if fault.code is not None else 1
                    self._schedule(at, lambda: self._raise_alarm(code))
                else:
                    self._schedule(at, self._unplug)
                return True
            return True
        self._ok()
        return False

    def _planned_end(self) -> float:
        self._machine_at(time.monotonic())
        return self._moves[-1].target if self._moves else self._machine

    def _dollar(self, s: str) -> None:
        if s == "$X":
            self._alarm = False
            self._send("[MSG:Caution: Unlocked]\r\n" if self.flavor == "grbl" else "[Caution: Unlocked]\r\n")
            self._ok()
        elif s == "$$":
            for k, v in sorted(self.settings.items()):
                self._send(f"${k}={v:.3f}\r\n")
            self._ok()
        elif s == "$I":
            self._send("[VER:1.1h.20190825:]\r\n[OPT:V,15,128]\r\n" if self.flavor == "grbl" else "[0.2.emulated]\r\n")
            self._ok()
        elif s == "$H":
            self._error(5)
        elif s == "$G":
            mode = "G90" if self._absolute else "G91"
            self._send(f"[GC:G{self._motion_mode} G54 G17 G21 {mode} G94 M5 M9 T0 F{self._feed or 0:g} S0]\r\n")
            self._ok()
        elif m := re.fullmatch(r"\$(\d+)=([-+]?\d*\.?\d+)", s):
            if self._moves:
                self._error(8)
                return
            self.settings[int(m.group(1))] = float(m.group(2))
            self._ok()
        else:
            self._error(3)


class EmulatedProjector(_PtyDevice, FrameStore):
    """A serial pattern projector (``ringscan-projector/1``) holding frames in memory.

    Args:
        frames: name -> (H_p, W_p) uint8 image, in index order (or a sequence).
        link_path: a stable symlink to create for the port.
        latency_s: time between a SHOW and its OK (the display latching the frame).
        names_supported: answer ``NAME <i>`` (else ``ERR 1``, as a minimal firmware).
    """

    def __init__(self, frames, *, link_path=None, latency_s: float = 0.0, names_supported: bool = True):
        FrameStore.__init__(self, frames)
        self.latency_s = float(latency_s)
        self.names_supported = names_supported
        self._buf = bytearray()
        _PtyDevice.__init__(self, name="projector", link_path=link_path)

    def _power_on(self) -> None:
        self.current_index = -1
        self._buf = bytearray()

    def _on_bytes(self, data: bytes) -> None:
        for b in data:
            c = bytes([b])
            if c == b"\n":
                line = self._buf.decode("ascii", "replace").strip()
                self._buf.clear()
                if line:
                    self.lines.append(line)
                    self._line(line)
                if self._master is None:
                    return
            elif c != b"\r":
                self._buf += c

    def _reply(self, text: str, then=None) -> None:
        def go():
            if then is not None:
                then()
            self._send(text + "\n")

        if self.latency_s > 0:
            self._schedule(self.latency_s, go)
        else:
            go()

    def _line(self, line: str) -> None:
        f = self._take_fault(line)
        if f is not None:
            if f.kind == "error":
                self._reply(f"ERR {f.code if f.code is not None else 3} display fault")
                return
            if f.kind == "silent":
                return
            if f.kind == "vanish":
                self._unplug()
                return
            if f.kind == "reset":
                self._power_on()
                return
        parts = line.split()
        cmd = parts[0].upper()
        n = len(self.images)
        if cmd == "HELLO" and len(parts) == 1:
            self._reply(f"{IDENT} {PROTOCOL_VERSION} {n} {self.width} {self.height}")
        elif cmd == "BLANK" and len(parts) == 1:
            self._reply("OK BLANK", then=lambda: setattr(self, "current_index", -1))
        elif cmd in ("SHOW", "NAME") and len(parts) == 2:
            try:
                i = int(parts[1])
            except ValueError:
                self._reply(f"ERR 1 bad index {parts[1]!r}")
                return
            if not 0 <= i < n:
                self._reply(f"ERR 2 index {i} out of range 0..{n - 1}")
            elif cmd == "SHOW":
                self._reply(f"OK {i}", then=lambda: setattr(self, "current_index", i))
            elif self.names_supported:
                self._reply(f"NAME {i} {self.names[i]}")
            else:
                self._reply(f"ERR 1 unknown command {cmd}")
        else:
            self._reply(f"ERR 1 unknown command {cmd}" if cmd not in ("HELLO", "BLANK", "SHOW", "NAME")
                        else f"ERR 1 bad syntax {line!r}")


class CameraServer:
    """Serves a camera on a Unix socket (``GRAB`` -> ``FRAME h w dtype`` + raw bytes).

    Args:
        camera: the camera (grabs are serialised).
        path: the socket path; clients use the camera spec ``unix:PATH``.
    """

    def __init__(self, camera, path: str | os.PathLike):
        self.camera = camera
        self.path = Path(path)
        if self.path.exists() or self.path.is_symlink():
            self.path.unlink()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.bind(str(self.path))
        self._sock.listen(4)
        self._grab_lock = threading.Lock()
        self._closed = False
        self._thread = threading.Thread(target=self._accept, name="camera-server", daemon=True)
        self._thread.start()

    @property
    def spec(self) -> str:
        return f"unix:{self.path}"

    def _accept(self) -> None:
        while not self._closed:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, conn.makefile("rb") as f:
            for line in f:
                if line.strip() != b"GRAB":
                    conn.sendall(b"ERR unknown request\n")
                    continue
                try:
                    with self._grab_lock:
                        img = np.ascontiguousarray(self.camera.grab())
                except Exception as e:
                    log.warning("camera server: grab failed: %s", e)
                    conn.sendall(f"ERR {e}".replace("\n", " ").encode("utf-8", "replace") + b"\n")
                    continue
                conn.sendall(f"FRAME {img.shape[0]} {img.shape[1]} {img.dtype.str}\n".encode() + img.tobytes())

    def close(self) -> None:
        self._closed = True
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
        if self.path.exists():
            self.path.unlink()


class EmulatedRig:
    """A whole virtual rig: emulated turntable and projector on ptys, a virtual camera.

    Args:
        rig: the rig (pipeline.rig.Rig) to render.
        patterns: the PatternSpec whose frames the projector holds (index = frame order).
        scene: scene name or mesh path (pipeline.scenes.make_scene), or a mesh.
        folder: where the port symlinks and the camera socket go (default: a new
            temporary folder, removed by :meth:`close`).
        flavor: turntable firmware, "grbl" or "horus".
        time_scale: the turntable moves this many times faster than a real one.
        start_deg: the table's physical angle at start.
        seed: camera noise seed (see VirtualCamera).
        size_mm: scene size for make_scene.
        device: Warp device of the renderer.
        serve_camera: also serve the camera on ``folder/camera.sock``.
        virtual_rig: an already-built renderer (then rig/scene/size_mm/device are unused).
        latency_s: projector acknowledgement latency.
    """

    def __init__(self, rig, patterns, scene=None, *, folder=None, flavor: str = "grbl", time_scale: float = 1.0,
                 start_deg: float = 0.0, seed: int | None = None, size_mm: float = 80.0, device=None,
                 serve_camera: bool = False, virtual_rig=None, latency_s: float = 0.0):
        from ringscan.pipeline.patterns import frame_names, render_frame

        from .camera import VirtualCamera, make_virtual_rig

        self._own_folder = folder is None
        self.folder = Path(tempfile.mkdtemp(prefix="ringscan-emu-")) if folder is None else Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        frames = {n: render_frame(patterns, n) for n in frame_names(patterns)}
        self.turntable = self.projector = self.camera_server = None
        try:
            self.turntable = EmulatedTurntable(flavor=flavor, link_path=self.folder / "turntable",
                                               time_scale=time_scale, start_deg=start_deg)
            self.projector = EmulatedProjector(frames, link_path=self.folder / "projector", latency_s=latency_s)
            if virtual_rig is None:
                virtual_rig = make_virtual_rig(rig, scene, size_mm=size_mm, device=device)
            self.virtual_rig = virtual_rig
            self.camera = VirtualCamera(virtual_rig, self.projector, self.turntable, seed=seed)
            if serve_camera:
                self.camera_server = CameraServer(self.camera, self.folder / "camera.sock")
        except BaseException:
            self.close()
            raise

    @property
    def turntable_port(self) -> str:
        return self.turntable.port

    @property
    def projector_port(self) -> str:
        return self.projector.port

    @property
    def camera_spec(self) -> str | None:
        return None if self.camera_server is None else self.camera_server.spec

    def close(self) -> None:
        for dev in (self.camera_server, self.projector, self.turntable):
            if dev is not None:
                dev.close()
        if self._own_folder:
            for p in self.folder.iterdir():
                if p.is_symlink() or p.is_file() or p.is_socket():
                    p.unlink()
            try:
                self.folder.rmdir()
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
