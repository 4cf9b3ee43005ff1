"""A GRBL 1.1 turntable behind a pseudo-terminal: the firmware's line protocol,
status reports, alarms and resets, moving in simulated time.
"""

from __future__ import annotations

import logging
import re
import time
from collections import deque
from dataclasses import dataclass

from ringscan.hardware.emulators.pty_device import Fault, _PtyDevice
from ringscan.hardware.errors import GRBL_ALARMS, GRBL_ERRORS

log = logging.getLogger(__name__)

__all__ = ["EmulatedTurntable"]


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

        if self.flavor == "grbl":
            self._send(f"error:{code}\r\n")
        else:
            self._send(f"error: {GRBL_ERRORS.get(code, 'Invalid gcode').capitalize()}\r\n")

    def _raise_alarm(self, code: int) -> None:

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
