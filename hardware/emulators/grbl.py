"""A GRBL 1.1 turntable behind a pseudo-terminal: the firmware's line protocol,
status reports, alarms and resets, moving in simulated time.

What it does as the firmware does (GRBL 1.1h source and its interface notes):

- positions are whole motor steps (``$100`` steps per degree): a move's target is
  rounded to a step, and ``MPos`` is steps / ``$100``, printed with 3 decimals;
- the parser keeps the commanded position; ``G92 X<v>`` sets the work offset from
  it (WCO = commanded position - v); a reset (Ctrl-X) clears the offset and takes
  the commanded position from the steps;
- status reports carry ``WCO`` only now and then: in the first report after a
  reset or a change of the offset, then every 10th report when idle and every 30th
  when busy (``Ov`` likewise every 10th / 20th); WPos = MPos - WCO;
- a G1 runs at its F word, capped at ``$110`` (deg/min); G0 at ``$110``;
- a reset while the table turns kills the steps: ``ALARM:3`` before the banner,
  then the Alarm state (``[MSG:'$H'|'$X' to unlock]``) until ``$X``;
- a reset keeps an Alarm state (reset in Alarm: banner, unlock message, still Alarm);
- ``ALARM:1`` / ``ALARM:2`` (hard / soft limit) are followed by ``[MSG:Reset to
  continue]``, and then everything but a reset is ignored (no ``ok``, no status);
- with homing enabled (``homing_lock``) the board powers up in Alarm (the start-up
  homing lock) at machine position 0;
- ``!`` (feed hold) stops a move (``Hold:0``), ``~`` resumes it; a reset in a
  completed hold keeps the position and raises no alarm;
- :meth:`EmulatedTurntable.reboot` restarts the board on its own (a brown-out, a USB
  glitch): the banner arrives unasked, the machine position starts again at 0 while
  the table stays where it stood (a reset in motion leaves it part way);
- line noise: the ``garble`` fault cuts a status report (no closing ``>``), the
  fields GRBL sends there are kept (``|Pn:...`` with pins).
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import deque
from dataclasses import dataclass

from ringscan.hardware.emulators.pty_device import Fault, _PtyDevice
from ringscan.hardware.errors import GRBL_ALARMS, GRBL_ERRORS

log = logging.getLogger(__name__)

__all__ = ["EmulatedTurntable"]

# GRBL 1.1h config.h: status reports between WCO / override fields.
WCO_REFRESH_BUSY, WCO_REFRESH_IDLE = 30, 10
OVR_REFRESH_BUSY, OVR_REFRESH_IDLE = 20, 10
CRITICAL_ALARMS = (1, 2)  # hard and soft limit: "[MSG:Reset to continue]"


@dataclass
class _Move:
    start: int
    """Machine position at the start (steps)."""
    target: int
    """Machine position at the end (steps)."""
    t0: float
    t1: float
    rate: float
    """deg/min."""


def _lround(x: float) -> int:
    """C's lround (half away from zero), as GRBL's planner rounds a target to steps."""
    return int(math.floor(abs(x) + 0.5)) * (1 if x >= 0 else -1)



class _Refused(Exception):
    """A line the firmware answers with ``error:<code>``."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def _parse_words(s: str) -> tuple[list[float], list[float], dict[str, float]]:
    """A line without spaces and comments -> its G words, its M words and the other words by letter."""
    words = re.findall(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))", s)
    if "".join(a + b for a, b in words) != s:
        raise _Refused(1 if not re.match(r"^[A-Z]", s) else 2)
    gs = [float(v) for k, v in words if k == "G"]
    ms = [float(v) for k, v in words if k == "M"]
    val = {k: float(v) for k, v in words if k not in "GM"}
    for k in val:
        if k not in "XFPN":
            raise _Refused(20)
    return gs, ms, val


class EmulatedTurntable(_PtyDevice):
    """A GRBL-like turntable controller on a pty.

    Args:
        flavor: "grbl" (GRBL 1.1h: ``error:N``, ``ALARM:N``, ``<Idle|MPos:...|WCO:...>``) or
            "horus" (Horus 0.2, GRBL 0.9 style: ``error: text``, ``<Idle,MPos:..,WPos:..>``,
            and M17/M18).
        link_path: a stable symlink to create for the port.
        time_scale: simulated moves run this many times faster than real ones.
        start_deg: the table's physical angle at power-up.
        homing_lock: power up in the Alarm state (GRBL with homing enabled, ``$22=1``:
            the start-up homing lock), so the host must send ``$X``.
        max_rate: ``$110``, the highest rate (deg/min); G1 feeds above it are capped.
        steps_per_deg: ``$100``.
    """

    BANNERS = {"grbl": "Grbl 1.1h ['$' for help]", "horus": "Horus 0.2 ['$' for help]"}

    def __init__(self, *, flavor: str = "grbl", link_path=None, time_scale: float = 1.0, start_deg: float = 0.0,
                 homing_lock: bool = False, max_rate: float = 3000.0, steps_per_deg: float = 8.889):
        if flavor not in self.BANNERS:
            raise ValueError(f"flavor must be one of {sorted(self.BANNERS)}, got {flavor!r}")
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale}")
        if not (max_rate > 0 and steps_per_deg > 0):
            raise ValueError(f"max_rate and steps_per_deg must be > 0, got {max_rate}, {steps_per_deg}")
        self.flavor = flavor
        self.time_scale = float(time_scale)
        self.homing_lock = bool(homing_lock)
        self.settings = {22: float(self.homing_lock), 100: float(steps_per_deg), 110: float(max_rate), 120: 200.0}
        self.motor_enabled = False
        self.resets = 0
        """Soft resets (Ctrl-X) received."""
        self.resets_in_motion = 0
        """Soft resets that stopped a turning table (each answered with ALARM:3)."""
        self.alarms: list[int] = []
        """Every alarm code raised, in order."""
        self._mount = float(start_deg)  # physical angle = machine position + mount
        self._buf = bytearray()
        self._power_on()
        super().__init__(name="turntable", link_path=link_path)

    # ------------------------------------------------------------------ state

    @property
    def steps_per_deg(self) -> float:
        return self.settings[100]

    @property
    def max_rate(self) -> float:
        return self.settings[110]

    def _power_on(self) -> None:
        if hasattr(self, "_moves"):
            self._mount = self._physical(time.monotonic())
        self._steps = 0
        self._moves: deque[_Move] = deque()
        self._held: list[tuple[int, int, float]] | None = None  # (start, target, rate) of moves a feed hold stopped
        self._alarm = self.homing_lock
        self._critical = False  # waiting in "[MSG:Reset to continue]"
        self._lose_ok = False
        self._buf = bytearray()
        self._reset_parser()

    def _reset_parser(self) -> None:
        """gc_init + gc_sync_position: modal state to defaults, no G92 offset, the
        commanded position taken from the steps."""
        self._absolute = True
        self._motion_mode = 0
        self._feed: float | None = None
        self._offset = 0.0  # G92 offset = WCO (no G54 offset here)
        self._gc = self._steps / self.steps_per_deg
        self._queue: deque[str] = deque()
        self._sync = None  # token of a G4 waiting for the planner
        self._silent = False
        self._wco_counter = 0  # the next report carries WCO
        self._ovr_counter = 0

    def _steps_at(self, now: float) -> int:
        while self._moves and self._moves[0].t1 <= now:
            self._steps = self._moves.popleft().target
        if not self._moves:
            return self._steps
        m = self._moves[0]
        if now <= m.t0:
            return m.start
        return m.start + int((m.target - m.start) * (now - m.t0) / (m.t1 - m.t0))

    def _physical(self, now: float) -> float:
        return self._steps_at(now) / self.steps_per_deg + self._mount

    @property
    def angle_deg(self) -> float:
        """The table's physical angle now (degrees, to 0.001 as a status report gives
        it), mid-move included."""
        with self._lock:
            return round(self._physical(time.monotonic()), 3) + 0.0

    @property
    def moving(self) -> bool:
        with self._lock:
            self._steps_at(time.monotonic())
            return bool(self._moves)

    def _state(self) -> str:
        if self._alarm:
            return "Alarm"
        if self._held is not None:
            return "Hold:0"
        self._steps_at(time.monotonic())
        return "Run" if self._moves else "Idle"

    # ------------------------------------------------------------------ replies

    def _ok(self) -> None:
        if self._lose_ok:  # a lost reply (line noise): the line was executed all the same
            self._lose_ok = False
            return
        self._send("ok\r\n")

    def _error(self, code: int) -> None:
        if self.flavor == "grbl":
            self._send(f"error:{code}\r\n")
        else:
            self._send(f"error: {GRBL_ERRORS.get(code, 'Invalid gcode').capitalize()}\r\n")

    def _alarm_text(self, code: int) -> str:
        if self.flavor == "grbl":
            return f"ALARM:{code}\r\n"
        return f"ALARM: {GRBL_ALARMS.get(code, 'Hard/soft limit').capitalize()}\r\n"

    def _msg(self, text: str) -> str:
        return f"[MSG:{text}]\r\n" if self.flavor == "grbl" else f"[{text}]\r\n"

    def _raise_alarm(self, code: int) -> None:
        self._steps = self._steps_at(time.monotonic())
        self._moves.clear()
        self._held = None
        self._alarm = True
        self._sync = None
        self._queue.clear()
        self.alarms.append(code)
        self._send(self._alarm_text(code))
        if code in CRITICAL_ALARMS:
            self._send(self._msg("Reset to continue"))
            self._critical = True

    def reboot(self) -> None:
        """The board restarts by itself now (power or USB glitch): its banner comes
        unasked; the table stays where its steps left it."""
        with self._lock:
            self._power_on()
            self._send(f"\r\n{self.BANNERS[self.flavor]}\r\n")
            if self._alarm:
                self._send(self._msg("'$H'|'$X' to unlock"))

    def _status(self, *, garble: bool = False) -> None:
        now = time.monotonic()
        steps = self._steps_at(now)
        m = steps / self.steps_per_deg
        st = self._state()
        if self.flavor != "grbl":
            self._send(f"<{st.split(':')[0]},MPos:{m:.3f},0.000,0.000,WPos:{m - self._offset:.3f},0.000,0.000>\r\n")
            return
        busy = st.split(":")[0] in ("Run", "Hold", "Jog", "Home")
        fs = self._moves[0].rate if self._moves else 0.0
        out = f"<{st}|MPos:{m:.3f},0.000,0.000|FS:{fs:.0f},0"
        if self._wco_counter > 0:
            self._wco_counter -= 1
        else:
            self._wco_counter = (WCO_REFRESH_BUSY if busy else WCO_REFRESH_IDLE) - 1
            if self._ovr_counter == 0:
                self._ovr_counter = 1  # GRBL: the override values come in the next report
            out += f"|WCO:{self._offset:.3f},0.000,0.000"
        if self._ovr_counter > 0:
            self._ovr_counter -= 1
        else:
            self._ovr_counter = (OVR_REFRESH_BUSY if busy else OVR_REFRESH_IDLE) - 1
            out += "|Ov:100,100,100"
        if garble:  # line noise ate the end of the report
            self._send(out + "|Pn:PXYZRHSS\r\n")
            return
        self._send(out + ">\r\n")

    def _soft_reset(self) -> None:
        self._steps = self._steps_at(time.monotonic())
        moving = bool(self._moves)
        self._moves.clear()
        self._held = None  # a completed hold: the rest of the move is dropped, no alarm
        self._buf.clear()
        self.resets += 1
        if moving:  # GRBL: reset while in motion, position not guaranteed
            self.resets_in_motion += 1
            self.alarms.append(3)
            self._alarm = True
            self._send(self._alarm_text(3))
        self._critical = False
        self._lose_ok = False
        self._reset_parser()
        self._send(f"\r\n{self.BANNERS[self.flavor]}\r\n")
        if self._alarm:  # the Alarm state survives a reset
            self._send(self._msg("'$H'|'$X' to unlock"))

    def _feed_hold(self) -> None:
        now = time.monotonic()
        cur = self._steps_at(now)
        if not self._moves or self._alarm:
            return
        first = self._moves[0]
        self._held = [(cur, first.target, first.rate)] + [(m.start, m.target, m.rate) for m in list(self._moves)[1:]]
        self._moves.clear()
        self._steps = cur

    def _cycle_start(self) -> None:
        if self._held is None:
            return
        held, self._held = self._held, None
        t = time.monotonic()
        for start, target, rate in held:
            dur = abs(target - start) / self.steps_per_deg / rate * 60.0 / self.time_scale
            self._moves.append(_Move(start=start, target=target, t0=t, t1=t + dur, rate=rate))
            t += dur
        if self._sync is not None:
            self._schedule(t - time.monotonic(), self._sync_check)

    # ------------------------------------------------------------------ input

    def _on_bytes(self, data: bytes) -> None:
        for b in data:
            c = bytes([b])
            if c == b"\x18":
                self._silent = False
                self._soft_reset()
            elif self._critical:
                continue  # "Reset to continue": everything else is ignored
            elif c == b"?":
                f = self._take_fault("?")
                if f is not None and f.kind == "silent":
                    continue
                if f is not None and f.kind == "vanish":
                    self._unplug()
                    return
                if not self._silent:
                    self._status(garble=f is not None and f.kind == "garble")
            elif c == b"!":
                self._feed_hold()
            elif c == b"~":
                self._cycle_start()
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
        while self._queue and self._sync is None and self._master is not None and not self._critical:
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
                if self._alarm:
                    self._send(self._msg("'$H'|'$X' to unlock"))
                return
            if f.kind == "lose_ok":
                self._lose_ok = True
        is_motion = self._execute(raw, fault=f)
        if self._sync is None:
            self._lose_ok = False  # only this line's reply is lost
        if f is not None and not is_motion:
            if f.kind == "alarm":
                self._raise_alarm(f.code if f.code is not None else 1)
            elif f.kind == "vanish":
                self._unplug()

    def _rate(self, motion_mode: int) -> float | None:
        """deg/min of a move: G0 at $110, G1 at F capped at $110."""
        if motion_mode == 0:
            return self.max_rate
        return None if self._feed is None else min(self._feed, self.max_rate)

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
        try:
            gs, ms, val = _parse_words(s)
            dwell, g92 = self._apply_g_words(gs)
            self._apply_m_words(ms)
            if "F" in val:
                if val["F"] <= 0:
                    raise _Refused(4)
                self._feed = val["F"]
            now = time.monotonic()
            if g92:
                self._set_work_offset(val)
                return False
            if dwell:
                self._queue_dwell(val, now)
                return False
            if "X" in val:
                self._queue_move(val["X"], now, fault=fault)
                return True
        except _Refused as e:
            self._error(e.code)
            return False
        self._ok()
        return False

    def _apply_g_words(self, gs: list[float]) -> tuple[bool, bool]:
        """Set the modes the G words set, in order; return whether the line is a dwell (G4) and a G92."""
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
                raise _Refused(20)
        return dwell, g92

    def _apply_m_words(self, ms: list[float]) -> None:
        for m in ms:
            if m in (17.0, 18.0) and self.flavor == "horus":
                self.motor_enabled = m == 17.0
            elif m in (2.0, 30.0):
                pass
            else:
                raise _Refused(20)

    def _set_work_offset(self, val: dict[str, float]) -> None:
        """``G92 X<v>``."""
        if "X" not in val:
            raise _Refused(26)
        self._offset = self._gc - val["X"]  # GRBL: from the commanded position, not the steps
        self._wco_counter = 0  # the next report carries the new WCO
        self._ok()

    def _queue_dwell(self, val: dict[str, float], now: float) -> None:
        """``G4 P<s>``: answered by :meth:`_sync_check` once the moves before it are done."""
        if "P" not in val:
            raise _Refused(28)
        token = object()
        self._sync = (token, val["P"])
        end = max([m.t1 for m in self._moves], default=now)
        self._schedule(end - now, self._sync_check)

    def _queue_move(self, x: float, now: float, *, fault: Fault | None) -> None:
        """A move to ``X`` after the moves queued; an ``alarm`` or ``vanish`` fault strikes part way through it."""
        rate = self._rate(self._motion_mode)
        if rate is None:
            raise _Refused(22)
        target_deg = (x + self._offset) if self._absolute else self._gc + x
        start = self._planned_end()
        target = _lround(target_deg * self.steps_per_deg)
        self._gc = target_deg
        t0 = max([m.t1 for m in self._moves], default=now)
        dur = abs(target - start) / self.steps_per_deg / rate * 60.0 / self.time_scale
        self._moves.append(_Move(start=start, target=target, t0=t0, t1=t0 + dur, rate=rate))
        self._ok()
        if fault is not None and fault.kind in ("alarm", "vanish"):
            at = t0 + fault.at_fraction * dur - now
            if fault.kind == "alarm":
                code = fault.code if fault.code is not None else 1
                self._schedule(at, lambda: self._raise_alarm(code))
            else:
                self._schedule(at, self._unplug)

    def _sync_check(self) -> None:
        """A G4 answers once the planner is empty (not during a feed hold), after its dwell."""
        if self._sync is None:
            return
        token, dwell = self._sync
        now = time.monotonic()
        self._steps_at(now)
        if self._moves or self._held is not None:
            if self._moves:
                self._schedule(self._moves[-1].t1 - now, self._sync_check)
            return  # held: ~ reschedules it

        def done(token=token):
            if self._sync is not None and self._sync[0] is token:
                self._sync = None
                self._ok()
                self._lose_ok = False
                self._process_queue()

        self._schedule(dwell / self.time_scale, done)

    def _planned_end(self) -> int:
        self._steps_at(time.monotonic())
        return self._moves[-1].target if self._moves else self._steps

    def _dollar(self, s: str) -> None:
        if s == "$X":
            self._alarm = False
            self._send(self._msg("Caution: Unlocked"))
            self._ok()
        elif s == "$$":
            if self._moves or self._held is not None:
                self._error(8)
                return
            for k, v in sorted(self.settings.items()):
                line = f"${k}={v:.3f}" if k >= 100 else f"${k}={int(v)}"
                if self.flavor == "horus":
                    line += {100: " (x, step/mm)", 110: " (x max rate, mm/min)"}.get(k, "")
                self._send(line + "\r\n")
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
