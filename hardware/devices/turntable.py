"""Turntables: a GRBL-compatible controller over serial, and an in-memory one.

The open turntable scanners (the Ciclop with Horus, FabScan) drive the table's
stepper from an Arduino running GRBL (or BQ's GRBL fork, "Horus" firmware). The
table is the X axis, with ``$100`` steps per degree, so ``G1 X<deg>`` turns it to
an absolute angle. :class:`GrblTurntable` speaks that protocol:

1. connect: soft reset (Ctrl-X, byte 0x18), wait for the banner (``Grbl 1.1h
   ['$' for help]`` or ``Horus 0.2 ['$' for help]``), ask ``?`` for the state and
   send ``$X`` when it is ``Alarm``; then ``G90`` (absolute), ``G92 X<deg>`` (the
   table is at the angle the host believes) and ``M17`` (motor on) on Horus.
2. every line waits for its ``ok``; ``error:N`` becomes
   :class:`TurntableCommandError`, ``ALARM:N`` :class:`TurntableAlarm`.
3. a move is ``G1 X<deg> F<deg/min>`` then ``G4 P0``, whose ``ok`` comes only once
   the planner is empty; while waiting, ``?`` is polled so that a dead line is seen
   within the reply timeout, not after the whole move; the move is finished when a
   ``?`` status report says ``Idle``.
"""

from __future__ import annotations

import abc
import logging
import re
import time
from dataclasses import dataclass

from ringscan.hardware.devices.base import Device
from ringscan.hardware.devices.serial_link import LineLink
from ringscan.hardware.errors import (
    GRBL_ALARMS,
    GRBL_ERRORS,
    DeviceError,
    TurntableAlarm,
    TurntableCommandError,
    TurntableDisconnected,
    TurntableTimeout,
)

log = logging.getLogger(__name__)

__all__ = ["TurntableDevice", "GrblTurntable", "VirtualTurntable", "GrblStatus", "parse_status", "format_angle"]

BANNER_RE = re.compile(r"^(Grbl|Horus)\s+(\d+\.\d+[A-Za-z]?)")
SOFT_RESET = b"\x18"
STATUS_QUERY = b"?"


@dataclass(frozen=True)
class GrblStatus:
    """A parsed ``?`` status report (GRBL 1.1 ``<Idle|MPos:..|..>`` or 0.9 ``<Idle,MPos:..,WPos:..>``)."""

    state: str
    """Machine state: Idle, Run, Hold, Jog, Alarm, Door, Check, Home, Sleep."""
    x: float | None
    """Work position of the X axis (the table angle in controller units), when the report gives it."""
    raw: str
    """The report as received."""


def parse_status(line: str) -> GrblStatus | None:
    """Parse a status report line; None when ``line`` is not one."""
    line = line.strip()
    if not (line.startswith("<") and line.endswith(">")):
        return None
    body = line[1:-1]
    fields: dict[str, list[float]] = {}
    if "|" in body:  # GRBL 1.1
        parts = body.split("|")
        state = parts[0]
        for p in parts[1:]:
            key, _, val = p.partition(":")
            try:
                fields[key] = [float(v) for v in val.split(",")]
            except ValueError:
                continue
    else:  # GRBL 0.9 / Horus
        state, _, rest = body.partition(",")
        for key, vals in re.findall(r"(MPos|WPos|WCO):([-+\d.]+(?:,[-+\d.]+)*)", rest):
            fields[key] = [float(v) for v in vals.split(",")]
    state = state.split(":")[0]
    x = None
    if "WPos" in fields:
        x = fields["WPos"][0]
    elif "MPos" in fields:
        x = fields["MPos"][0] - (fields["WCO"][0] if "WCO" in fields else 0.0)
    return GrblStatus(state=state, x=x, raw=line)


def format_angle(deg: float) -> str:
    """An angle as G-code writes it: 3 decimals, never ``-0.000``."""
    s = f"{deg:.3f}"
    return "0.000" if s == "-0.000" else s


class TurntableDevice(Device):
    """A turntable: moves to absolute angles (degrees, DESIGN §6) and reports where it is."""

    @property
    @abc.abstractmethod
    def position_deg(self) -> float:
        """The angle the table was last confirmed at (degrees)."""

    @abc.abstractmethod
    def move_to(self, deg: float) -> None:
        """Turn to the absolute angle ``deg``; return when the table has stopped."""

    @abc.abstractmethod
    def set_position(self, deg: float) -> None:
        """Declare that the table now stands at ``deg`` (no motion)."""

    def enable_motor(self, on: bool = True) -> None:
        """Energise (or release) the stepper where the controller can; else nothing."""

    def recover(self) -> None:
        """Bring the device back after a fault whose position is known (reconnect)."""



class VirtualTurntable(TurntableDevice):
    """A turntable in memory: moves at once. Its ``angle_deg`` feeds a VirtualCamera.

    Args:
        start_deg: the angle it stands at.
    """

    def __init__(self, start_deg: float = 0.0):
        self._deg = float(start_deg)
        self.moves: list[float] = []
        """Every angle moved to, in order."""

    @property
    def position_deg(self) -> float:
        return self._deg

    @property
    def angle_deg(self) -> float:
        """The physical angle of the table (for a virtual camera)."""
        return self._deg

    def move_to(self, deg: float) -> None:
        self._deg = float(deg)
        self.moves.append(self._deg)

    def set_position(self, deg: float) -> None:
        self._deg = float(deg)


class GrblTurntable(TurntableDevice):
    """A GRBL (or Horus) controlled turntable on a serial port.

    Args:
        port: serial port or pyserial URL.
        baudrate: 115200 for GRBL 1.1 and Horus.
        feed_deg_per_min: table speed, the ``F`` word of every move (deg/min).
        direction: +1, or -1 to flip the sign of every angle sent (when the motor
            turns the object clockwise seen from above for positive X).
        timeout_s: longest wait for the reply to one line or status query.
        motion_timeout_s: time allowed for a move on top of its length at the feed rate.
        boot_timeout_s: longest wait for the banner after a reset.
        poll_s: interval of ``?`` polls during a move.
        motor_enable: "auto" (M17/M18 on Horus firmware only), "always" or "never".
        position_deg: the angle the table stands at when connecting.
        connect: connect now (else call :meth:`connect`).

    Raises:
        TurntableError: subclasses naming the port and the reason.
    """

    def __init__(self, port: str, *, baudrate: int = 115200, feed_deg_per_min: float = 600.0, direction: int = 1,
                 timeout_s: float = 2.0, motion_timeout_s: float = 30.0, boot_timeout_s: float = 3.0,
                 poll_s: float = 0.05, motor_enable: str = "auto", position_deg: float = 0.0, connect: bool = True):
        if not feed_deg_per_min > 0:
            raise ValueError(f"feed_deg_per_min must be > 0, got {feed_deg_per_min}")
        if direction not in (1, -1):
            raise ValueError(f"direction must be 1 or -1, got {direction}")
        if motor_enable not in ("auto", "always", "never"):
            raise ValueError(f"motor_enable must be 'auto', 'always' or 'never', got {motor_enable!r}")
        for name, v in (("timeout_s", timeout_s), ("boot_timeout_s", boot_timeout_s), ("poll_s", poll_s)):
            if not v > 0:
                raise ValueError(f"{name} must be > 0, got {v}")
        self.port = str(port)
        self.feed_deg_per_min = float(feed_deg_per_min)
        self.direction = direction
        self.timeout_s = float(timeout_s)
        self.motion_timeout_s = float(motion_timeout_s)
        self.boot_timeout_s = float(boot_timeout_s)
        self.poll_s = float(poll_s)
        self.motor_enable = motor_enable
        self.firmware: str | None = None
        """"Grbl" or "Horus", from the banner."""
        self.version: str | None = None
        """Firmware version from the banner, e.g. "1.1h"."""
        self.last_status: GrblStatus | None = None
        self._position = float(position_deg)
        self._link = LineLink(self.port, baudrate=baudrate, name="turntable", timeout_error=TurntableTimeout,
                              disconnected_error=TurntableDisconnected)
        if connect:
            self.connect(position_deg=self._position)

    # ------------------------------------------------------------------ connection

    @property
    def position_deg(self) -> float:
        return self._position

    @property
    def has_motor_enable(self) -> bool:
        """Whether M17/M18 are sent (Horus firmware has them, stock GRBL answers error:20)."""
        if self.motor_enable == "auto":
            return self.firmware == "Horus"
        return self.motor_enable == "always"

    def connect(self, *, position_deg: float | None = None) -> None:
        """Open the port, reset the controller, unlock it and declare the table's angle."""
        if position_deg is not None:
            self._position = float(position_deg)
        self._link.open()
        try:
            self._reset()
            st = self.status()
            if st.state == "Alarm":
                log.info("turntable: controller in alarm after reset; unlocking with $X")
                self.command("$X")
            self.command("G90")
            self.set_position(self._position)
            if self.has_motor_enable:
                self.command("M17")
        except BaseException:
            self._link.close()
            raise

    def _reset(self) -> None:
        self._link.discard_input()
        for attempt in range(2):
            self._link.write(SOFT_RESET)
            deadline = time.monotonic() + self.boot_timeout_s
            while (remaining := deadline - time.monotonic()) > 0:
                line = self._link.read_line(remaining)
                if line is None:
                    break
                m = BANNER_RE.match(line.strip())
                if m:
                    self.firmware, self.version = m.group(1), m.group(2)
                    log.info("turntable: %s %s on %s", self.firmware, self.version, self.port)
                    return
                if line.strip():
                    log.debug("turntable: before banner: %r", line)
            log.debug("turntable: no banner after reset attempt %d", attempt + 1)
        raise TurntableTimeout(f"no GRBL/Horus banner within {self.boot_timeout_s:g} s of a soft reset (Ctrl-X); "
                               f"is a GRBL board on this port, at this baud rate?", port=self.port)

    def recover(self) -> None:
        """Reconnect (reset, unlock, declare the last confirmed angle)."""
        self._link.close()
        self.connect(position_deg=self._position)

    def close(self) -> None:
        self._link.close()

    # ------------------------------------------------------------------ lines

    def _handle_async(self, line: str) -> None:
        """Status reports, messages, alarms and unexpected banners between replies."""
        s = line.strip()
        if not s:
            return
        st = parse_status(s)
        if st is not None:
            self.last_status = st
            if st.state == "Alarm":
                raise TurntableAlarm("controller is in the Alarm state", port=self.port)
            return
        if s.upper().startswith("ALARM"):
            code, text = _parse_code(s)
            what = GRBL_ALARMS.get(code, text) if code is not None else text
            raise TurntableAlarm(f"ALARM{':' + str(code) if code is not None else ''} ({what or 'alarm'})",
                                 code=code, port=self.port)
        if BANNER_RE.match(s):
            raise TurntableDisconnected("the controller reset by itself (banner seen mid-session); "
                                        "power or USB glitch?", port=self.port)
        log.debug("turntable: message %r", s)

    def _drain(self) -> None:
        for line in self._link.pending_lines():
            self._handle_async(line)

    def command(self, line: str, *, timeout_s: float | None = None, poll: bool = False) -> None:
        """Send one line and wait for its ``ok``.

        Args:
            line: the G-code or ``$`` line, without terminator.
            timeout_s: longest wait for the ``ok`` (default: the reply timeout).
            poll: send ``?`` every ``poll_s`` while waiting; then silence longer than
                the reply timeout is an error even when ``timeout_s`` is longer.

        Raises:
            TurntableCommandError: ``error:N``.
            TurntableAlarm: an alarm while waiting.
            TurntableTimeout: no ``ok`` in time.
        """
        self._drain()
        self._link.send_line(line)
        total = self.timeout_s if timeout_s is None else timeout_s
        start = time.monotonic()
        deadline = start + total
        heard = start
        next_poll = start + self.poll_s
        if poll:
            self._link.write(STATUS_QUERY)
        while True:
            now = time.monotonic()
            if now >= deadline:
                raise TurntableTimeout(f"no 'ok' for {line!r} within {total:g} s", port=self.port)
            if poll and now - heard > self.timeout_s:
                raise TurntableTimeout(f"controller silent for {self.timeout_s:g} s while waiting for {line!r} "
                                       f"(no status replies)", port=self.port)
            wait = deadline - now
            if poll:
                wait = min(wait, max(next_poll - now, 0.0))
            reply = self._link.read_line(wait)
            if reply is None:
                if poll and time.monotonic() >= next_poll:
                    self._link.write(STATUS_QUERY)
                    next_poll = time.monotonic() + self.poll_s
                continue
            heard = time.monotonic()
            s = reply.strip()
            if s == "ok":
                return
            if s.lower().startswith("error"):
                code, text = _parse_code(s)
                what = GRBL_ERRORS.get(code, text) if code is not None else text
                raise TurntableCommandError(f"{line!r} rejected: {s} ({what or 'error'})", code=code, command=line,
                                            port=self.port)
            self._handle_async(s)

    def status(self, *, timeout_s: float | None = None) -> GrblStatus:
        """Send ``?`` and return the next status report (an Alarm state is returned, not raised)."""
        self._drain_quietly()
        self._link.write(STATUS_QUERY)
        total = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + total
        while (remaining := deadline - time.monotonic()) > 0:
            reply = self._link.read_line(remaining)
            if reply is None:
                break
            st = parse_status(reply)
            if st is not None:
                self.last_status = st
                return st
            if reply.strip().upper().startswith("ALARM"):
                continue  # the status report that follows says Alarm
            if BANNER_RE.match(reply.strip()):
                raise TurntableDisconnected("the controller reset by itself (banner seen mid-session)", port=self.port)
            log.debug("turntable: message %r", reply)
        raise TurntableTimeout(f"no reply to a '?' status query within {total:g} s", port=self.port)

    def _drain_quietly(self) -> None:
        for line in self._link.pending_lines():
            st = parse_status(line)
            if st is not None:
                self.last_status = st

    # ------------------------------------------------------------------ motion

    def set_position(self, deg: float) -> None:
        """``G92 X<deg>``: the table's current angle is ``deg`` from now on."""
        self.command(f"G92 X{format_angle(self.direction * float(deg))}")
        self._position = float(deg)

    def enable_motor(self, on: bool = True) -> None:
        """``M17`` / ``M18`` where the firmware has them (Horus); else nothing."""
        if self.has_motor_enable:
            self.command("M17" if on else "M18")
        else:
            log.debug("turntable: %s has no motor enable command; skipped", self.firmware)

    def move_to(self, deg: float) -> None:
        """Turn to ``deg`` (absolute) and return once a status report says Idle.

        Raises:
            TurntableCommandError: the move was rejected (the table did not move).
            TurntableAlarm, TurntableTimeout, TurntableDisconnected: the table may
                have moved partly; ``position_known`` is False on these.
        """
        deg = float(deg)
        x = format_angle(self.direction * deg)
        feed = f"{self.feed_deg_per_min:g}"
        self.command(f"G1 X{x} F{feed}")
        expected = abs(deg - self._position) / self.feed_deg_per_min * 60.0
        try:
            self.command("G4 P0", timeout_s=1.5 * expected + self.motion_timeout_s, poll=True)
            self._wait_idle()
        except DeviceError as e:
            e.position_known = False
            e.retryable = False
            raise
        self._position = deg

    def _wait_idle(self) -> None:
        deadline = time.monotonic() + self.timeout_s
        while True:
            st = self.status()
            if st.state == "Idle":
                return
            if st.state == "Alarm":
                raise TurntableAlarm("controller in Alarm after a move", port=self.port)
            if time.monotonic() > deadline:
                raise TurntableTimeout(f"status still {st.state!r} {self.timeout_s:g} s after the move's end",
                                       port=self.port)
            time.sleep(self.poll_s)


def _parse_code(line: str) -> tuple[int | None, str]:
    """``error:20`` -> (20, ""); ``error: Bad number format`` -> (None, "Bad number format")."""
    _, _, rest = line.partition(":")
    rest = rest.strip()
    if rest.isdigit():
        return int(rest), ""
    return None, rest
