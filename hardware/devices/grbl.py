"""A GRBL-compatible turntable controller over serial (:class:`GrblTurntable`).

The open turntable scanners (the Ciclop with Horus, FabScan) drive the table's
stepper from an Arduino running GRBL (or BQ's GRBL fork, "Horus" firmware). The
table is the X axis, with ``$100`` steps per degree, so ``G1 X<deg>`` turns it to
an absolute angle. :class:`GrblTurntable` speaks that protocol:

1. connect: ask ``?`` first; a table that is turning (Run, Jog, Hold) is waited
   for and is never reset while it moves (a reset in motion kills the steps:
   ``ALARM:3``); then soft reset (Ctrl-X, byte 0x18), wait for the banner
   (``Grbl 1.1h ['$' for help]`` or ``Horus 0.2 ['$' for help]``), ``?`` again,
   ``$$`` (``$100`` steps per degree, ``$110`` the highest rate). Only the start-up
   homing lock is unlocked with ``$X`` on its own; any other alarm, an ``ALARM``
   before the banner, or a table found turning makes the table's angle unknown
   (:attr:`GrblTurntable.position_known`) until it is declared with
   :meth:`GrblTurntable.set_position`. Then ``G90`` (absolute), ``G92 X<deg>`` (the
   angle the host knows) and ``M17`` (motor on) on Horus.
2. every line waits for its ``ok``; ``error:N`` becomes
   :class:`TurntableCommandError`, ``ALARM:N`` :class:`TurntableAlarm` (never
   retried: the table's angle is then unknown).
3. a move is ``G1 X<deg> F<deg/min>`` then ``G4 P0``, whose ``ok`` comes only once
   the planner is empty; while waiting, ``?`` is polled (at most 5 times a second, as
   GRBL's interface notes advise) so that a dead line is seen within the reply
   timeout, not after the whole move; the move is finished when a status report says
   ``Idle``, and the angle the steps reached (the report's work position) becomes
   :attr:`GrblTurntable.position_deg`. Only ``error:N`` on the G1 line leaves the
   angle known; a timeout, a lost port or an alarm after the G1 was sent does not
   (GRBL starts a move as soon as the line is queued).

Status reports give the machine position (``MPos``) and only now and then the work
offset (``WCO``); the driver keeps the last WCO it saw, as GRBL's interface notes
describe (WPos = MPos - WCO), and forgets it on a reset or a ``G92``.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass

from ringscan.hardware.devices.serial_link import LineLink
from ringscan.hardware.devices.turntable import TurntableDevice
from ringscan.hardware.errors import (
    GRBL_ALARMS,
    GRBL_ERRORS,
    DeviceError,
    TurntableAlarm,
    TurntableCommandError,
    TurntableDisconnected,
    TurntableError,
    TurntableTimeout,
)

log = logging.getLogger(__name__)

__all__ = ["GrblTurntable", "GrblStatus", "parse_status", "format_angle", "MIN_POLL_S", "TURNING_STATES"]


BANNER_RE = re.compile(r"^(Grbl|Horus)\s+(\d+\.\d+[A-Za-z]?)")


SETTING_RE = re.compile(r"^\$(\d+)=([-+]?\d*\.?\d+)")


SOFT_RESET = b"\x18"


STATUS_QUERY = b"?"


MIN_POLL_S = 0.2
"""Shortest interval between ``?`` polls: GRBL 1.1's interface notes advise at most 5 Hz."""


TURNING_STATES = ("Run", "Jog", "Home", "Hold")


@dataclass(frozen=True)
class GrblStatus:
    """A parsed ``?`` status report (GRBL 1.1 ``<Idle|MPos:..|..>`` or 0.9 ``<Idle,MPos:..,WPos:..>``)."""

    state: str
    """Machine state: Idle, Run, Hold, Jog, Alarm, Door, Check, Home, Sleep."""
    x: float | None
    """Work position of the X axis (the table angle in controller units): WPos when
    the report gives it, else MPos - WCO with the report's WCO or the last one known;
    None when neither is known."""
    raw: str
    """The report as received."""
    mpos: float | None = None
    """Machine position of the X axis, when the report gives it."""
    wco: float | None = None
    """Work coordinate offset of the X axis, when this report carries it."""
    substate: int | None = None
    """The number after the state (``Hold:0`` = hold complete, ``Hold:1`` = stopping)."""


def parse_status(line: str, *, wco: float | None = None) -> GrblStatus | None:
    """Parse a status report line; None when ``line`` is not one.

    Args:
        line: the line received.
        wco: the last work coordinate offset (X) seen in an earlier report: GRBL 1.1
            sends ``WCO`` only every 10 to 30 reports, and WPos = MPos - WCO.
    """
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
    state, _, sub = state.partition(":")
    mpos = fields["MPos"][0] if "MPos" in fields else None
    here = fields["WCO"][0] if "WCO" in fields else None
    known = here if here is not None else wco
    x = None
    if "WPos" in fields:
        x = fields["WPos"][0]
    elif mpos is not None and known is not None:
        x = round(mpos - known, 3) + 0.0
    return GrblStatus(state=state, x=x, raw=line, mpos=mpos, wco=here,
                      substate=int(sub) if sub.isdigit() else None)


def _garbled_status(line: str) -> bool:
    """A status report cut or corrupted on the line (``<Run|MPos:...`` with no closing
    ``>``): not a message; the report is asked for again."""
    s = line.strip()
    return s.startswith("<") and parse_status(s) is None


def _lround(x: float) -> int:
    """C's lround (half away from zero), as GRBL's planner rounds a target to whole steps."""
    return int(abs(x) + 0.5) * (1 if x >= 0 else -1)


def format_angle(deg: float) -> str:
    """An angle as G-code writes it: 3 decimals, never ``-0.000``."""
    s = f"{deg:.3f}"
    return "0.000" if s == "-0.000" else s


def _alarm_message(line: str) -> tuple[int | None, str]:
    """``ALARM:3`` -> (3, "ALARM:3 (reset while in motion)")."""
    code, text = _parse_code(line)
    what = GRBL_ALARMS.get(code, text) if code is not None else text
    return code, f"ALARM{':' + str(code) if code is not None else ''} ({what or 'alarm'})"


class GrblTurntable(TurntableDevice):
    """A GRBL (or Horus) controlled turntable on a serial port.

    Args:
        port: serial port or pyserial URL.
        baudrate: 115200 for GRBL 1.1 and Horus.
        feed_deg_per_min: table speed, the ``F`` word of every move (deg/min); GRBL
            caps it at ``$110``, which is read at connect.
        direction: +1, or -1 to flip the sign of every angle sent (when the motor
            turns the object clockwise seen from above for positive X).
        timeout_s: longest wait for the reply to one line or status query.
        motion_timeout_s: time allowed for a move on top of its length at the rate
            the controller really runs (the lower of the feed and ``$110``); also the
            longest wait for a table found turning at connect, on top of a full turn.
        boot_timeout_s: longest wait for the banner after a reset.
        poll_s: interval of ``?`` polls during a move; at least 0.2 s (GRBL's
            interface notes advise at most 5 status queries a second).
        motor_enable: "auto" (M17/M18 on Horus firmware only), "always" or "never".
        position_deg: the angle the table stands at when connecting (what the host
            knows; a table found turning or in an alarm makes it unknown).
        connect: connect now (else call :meth:`connect`).

    Raises:
        TurntableError: subclasses naming the port and the reason.
    """

    def __init__(self, port: str, *, baudrate: int = 115200, feed_deg_per_min: float = 600.0, direction: int = 1,
                 timeout_s: float = 2.0, motion_timeout_s: float = 30.0, boot_timeout_s: float = 3.0,
                 poll_s: float = MIN_POLL_S, motor_enable: str = "auto", position_deg: float = 0.0,
                 connect: bool = True):
        """Check the options, keep them and connect (see the class docstring for the arguments).

        Size: its keyword-only arguments are the class's documented options, one per setting of the controller's
        link and moves.
        """
        if not feed_deg_per_min > 0:
            raise ValueError(f"feed_deg_per_min must be > 0, got {feed_deg_per_min}")
        if direction not in (1, -1):
            raise ValueError(f"direction must be 1 or -1, got {direction}")
        if motor_enable not in ("auto", "always", "never"):
            raise ValueError(f"motor_enable must be 'auto', 'always' or 'never', got {motor_enable!r}")
        for name, v in (("timeout_s", timeout_s), ("boot_timeout_s", boot_timeout_s)):
            if not v > 0:
                raise ValueError(f"{name} must be > 0, got {v}")
        if not motion_timeout_s >= 0:
            raise ValueError(f"motion_timeout_s must be >= 0, got {motion_timeout_s}")
        if not poll_s >= MIN_POLL_S:
            raise ValueError(f"poll_s must be >= {MIN_POLL_S} s (GRBL's interface notes advise at most 5 status "
                             f"queries a second), got {poll_s}")
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
        self.settings: dict[int, float] = {}
        """The controller's ``$$`` settings read at connect."""
        self.last_status: GrblStatus | None = None
        self._position = float(position_deg)
        self._unknown: str | None = None  # why the angle is unknown; None: known
        self._locked = False  # Alarm state: G-code refused until $X
        self._critical = False  # "[MSG:Reset to continue]": nothing answered until a reset
        self._wco: float | None = None  # the last work offset (X) a status report gave
        self._last_alarm: str | None = None
        self._setup_done = False
        self._link = LineLink(self.port, baudrate=baudrate, name="turntable", timeout_error=TurntableTimeout,
                              disconnected_error=TurntableDisconnected)
        if connect:
            self.connect(position_deg=self._position)

    # ------------------------------------------------------------------ state

    @property
    def position_deg(self) -> float:
        return self._position

    @property
    def position_known(self) -> bool:
        return self._unknown is None

    @property
    def unknown_reason(self) -> str | None:
        return self._unknown

    @property
    def steps_per_deg(self) -> float | None:
        """``$100`` as read at connect (None if the controller did not say)."""
        return self.settings.get(100)

    @property
    def max_rate_deg_per_min(self) -> float | None:
        """``$110`` as read at connect: GRBL runs no move faster (None if not read)."""
        return self.settings.get(110)

    @property
    def rate_deg_per_min(self) -> float:
        """The rate moves really run at: the feed, capped at ``$110``."""
        cap = self.max_rate_deg_per_min
        return min(self.feed_deg_per_min, cap) if cap and cap > 0 else self.feed_deg_per_min

    def _lose_position(self, why: str) -> None:
        if self._unknown is None:
            log.warning("turntable on %s: the table's angle is unknown from now on: %s", self.port, why)
            self._unknown = why

    @property
    def has_motor_enable(self) -> bool:
        """Whether M17/M18 are sent (Horus firmware has them, stock GRBL answers error:20)."""
        if self.motor_enable == "auto":
            return self.firmware == "Horus"
        return self.motor_enable == "always"

    # ------------------------------------------------------------------ connection

    def connect(self, *, position_deg: float | None = None) -> None:
        """Open the port, let a turning table stop, reset the controller, read its
        settings, unlock the start-up homing lock and declare the table's angle.

        Args:
            position_deg: the angle the table stands at (what the host knows); None
                keeps the last one, known or not (a reconnection).
        """
        if position_deg is not None:
            self._position = float(position_deg)
            self._unknown = None
        self._link.open()
        self._setup_done = False
        try:
            self._last_alarm = None
            before = self._probe()
            if before is not None and before.state in TURNING_STATES:
                found = before.raw
                before = self._wait_stopped(before)
                self._lose_position(f"the table was turning ({found}) when ringscan connected, "
                                    f"so it was not where ringscan had left it")
            if self._last_alarm is not None:
                self._lose_position(f"the controller reported {self._last_alarm} before ringscan connected")
            self._reset()
            st = self.status()
            self._locked = st.state == "Alarm"
            self._read_settings()
            if self._locked:
                startup_lock = (self._last_alarm is None and st.mpos is not None and abs(st.mpos) < 5e-4
                                and before is not None and before.state in ("Idle", "Alarm"))
                if startup_lock:
                    # GRBL locks all motion in Alarm, so at machine position 0 the table
                    # has not moved since the board powered up: the homing lock. (A board
                    # that did not answer '?' may wait in "Reset to continue" after a
                    # limit alarm: not a start-up lock.)
                    log.info("turntable: the start-up homing lock is on; unlocking with $X")
                    self._unlock()
                elif self._last_alarm is not None:
                    self._lose_position(f"the controller is locked after {self._last_alarm}")
                else:
                    self._lose_position("the controller is locked in an alarm whose cause ringscan did not see "
                                        f"(it came before this connection; machine position {st.mpos})")
            if not self._locked:
                self._setup()
                if self._unknown is None:
                    self.set_position(self._position)
        except BaseException:
            self._link.close()
            raise

    def _probe(self) -> GrblStatus | None:
        """``?`` before any reset: the state the controller is in (None: no answer,
        as in "Reset to continue" or while an Arduino boots)."""
        self._link.discard_input()
        self._link.write(STATUS_QUERY)
        deadline = time.monotonic() + self.timeout_s
        garbled = 0
        while (remaining := deadline - time.monotonic()) > 0:
            line = self._link.read_line(remaining)
            if line is None:
                break
            s = line.strip()
            st = self._parse(s)
            if st is not None:
                return st
            if _garbled_status(s):  # not "no answer": that would reset a table that may be turning
                garbled += 1
                if garbled > 3:
                    raise TurntableError(f"{garbled} garbled status reports in a row (the last {s!r}); check the "
                                         f"cable and the baud rate", port=self.port)
                log.warning("turntable: garbled status report %r; asking again", s)
                self._link.write(STATUS_QUERY)
                deadline = time.monotonic() + self.timeout_s
            elif s.upper().startswith("ALARM"):
                self._last_alarm = _alarm_message(s)[1]
            elif BANNER_RE.match(s):  # the board just booted (an Arduino resets when its port opens)
                log.info("turntable: %s booted as the port opened", s)
                self._link.write(STATUS_QUERY)
            elif s:
                log.debug("turntable: before reset: %r", s)
        return None

    def _wait_stopped(self, st: GrblStatus) -> GrblStatus:
        """Poll ``?`` until a table found turning stops (Idle, Alarm, or a complete
        hold), never resetting it while it moves."""
        limit = self.motion_timeout_s + 1.5 * 360.0 / self.rate_deg_per_min * 60.0
        deadline = time.monotonic() + limit
        log.warning("turntable: the table is turning (%s); waiting for it to stop before resetting", st.raw)
        while st.state in ("Run", "Jog", "Home") or (st.state == "Hold" and st.substate != 0):
            if time.monotonic() > deadline:
                self._lose_position(f"the table was still turning {limit:.0f} s after ringscan connected")
                raise TurntableTimeout(f"the table is still turning ({st.raw}) {limit:.0f} s after ringscan "
                                       f"connected; stop it, check where it stands and declare that angle "
                                       f"(--table-at)", port=self.port, retryable=False, position_known=False)
            time.sleep(self.poll_s)
            st = self.status()
        return st

    def _reset(self) -> None:
        """Ctrl-X and the banner. An ``ALARM`` before the banner (a reset that stopped
        a move) is remembered: the table's angle is then unknown."""
        self._link.discard_input()
        for attempt in range(2):
            self._link.write(SOFT_RESET)
            deadline = time.monotonic() + self.boot_timeout_s
            while (remaining := deadline - time.monotonic()) > 0:
                line = self._link.read_line(remaining)
                if line is None:
                    break
                s = line.strip()
                m = BANNER_RE.match(s)
                if m:
                    self.firmware, self.version = m.group(1), m.group(2)
                    self._wco = None  # GRBL clears the G92 offset on a reset
                    self._critical = False
                    log.info("turntable: %s %s on %s", self.firmware, self.version, self.port)
                    return
                if s.upper().startswith("ALARM"):
                    self._last_alarm = _alarm_message(s)[1]
                    self._lose_position(f"the reset stopped a move: {self._last_alarm}")
                elif s:
                    log.debug("turntable: before banner: %r", s)
            log.debug("turntable: no banner after reset attempt %d", attempt + 1)
        raise TurntableTimeout(f"no GRBL/Horus banner within {self.boot_timeout_s:g} s of a soft reset (Ctrl-X); "
                               f"is a GRBL board on this port, at this baud rate?", port=self.port)

    def _read_settings(self) -> None:
        """``$$``: keep ``$100`` (steps/deg) and ``$110`` (the highest rate)."""
        lines: list[str] = []
        try:
            self._command("$$", collect=lines)
        except TurntableCommandError as e:
            log.warning("turntable: could not read the settings ($$): %s", e)
            return
        for line in lines:
            m = SETTING_RE.match(line.strip())
            if m:
                self.settings[int(m.group(1))] = float(m.group(2))
        cap = self.max_rate_deg_per_min
        if cap and self.feed_deg_per_min > cap:
            log.warning("turntable: feed %g deg/min is above the controller's $110=%g; GRBL moves the table at "
                        "%g deg/min", self.feed_deg_per_min, cap, cap)

    def _setup(self) -> None:
        self.command("G90")
        if self.has_motor_enable:
            self.command("M17")
        self._setup_done = True

    def _unlock(self) -> None:
        self.command("$X")
        self._locked = False

    def recover(self) -> None:
        """Reconnect (let a turning table stop, reset, unlock the start-up lock,
        declare the last confirmed angle if it is still known)."""
        self._link.close()
        self.connect()

    def close(self) -> None:
        self._link.close()

    # ------------------------------------------------------------------ lines

    def _parse(self, line: str) -> GrblStatus | None:
        st = parse_status(line, wco=self._wco)
        if st is not None:
            if st.wco is not None:
                self._wco = st.wco
            self.last_status = st
            if st.state == "Alarm":
                self._locked = True
        return st

    def _alarm(self, text: str, code: int | None = None) -> TurntableAlarm:
        self._locked = True
        self._lose_position(text)
        return TurntableAlarm(text, code=code, port=self.port, retryable=False, position_known=False)

    def _alarm_line(self, line: str) -> TurntableAlarm:
        """An ``ALARM:N`` message: the error to raise, with the code's meaning."""
        code, self._last_alarm = _alarm_message(line)
        if code in (1, 2) or code is None:
            self._critical = True  # GRBL now waits for a reset ("[MSG:Reset to continue]")
        return self._alarm(self._last_alarm, code)

    def _handle_async(self, line: str) -> None:
        """Status reports, messages, alarms and unexpected banners between replies."""
        s = line.strip()
        if not s:
            return
        st = self._parse(s)
        if st is not None:
            if st.state == "Alarm":
                raise self._alarm(self._last_alarm or "the controller is in the Alarm state")
            return
        if s.upper().startswith("ALARM"):
            raise self._alarm_line(s)
        if BANNER_RE.match(s):
            self._wco = None
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
        self._command(line, timeout_s=timeout_s, poll=poll)

    def _command(self, line: str, *, timeout_s: float | None = None, poll: bool = False,
                 collect: list[str] | None = None) -> None:
        self._drain()
        self._link.send_line(line)
        total = self.timeout_s if timeout_s is None else timeout_s
        start = time.monotonic()
        deadline = start + total
        asked = None  # when the oldest '?' that no line has followed was sent
        next_poll = start + self.poll_s
        if poll:
            self._link.write(STATUS_QUERY)
            asked = time.monotonic()
        while True:
            now = time.monotonic()
            wait = max(deadline - now, 0.0)
            if poll:
                wait = min(wait, max(next_poll - now, 0.0))
            reply = self._link.read_line(wait)
            if reply is None:
                # Silence is judged only after a read found nothing: a host that was not
                # running for a while (a starved machine) finds the replies that came
                # meanwhile waiting, and must not take the stall for a silent controller.
                now = time.monotonic()
                if now >= deadline:
                    raise TurntableTimeout(f"no 'ok' for {line!r} within {total:g} s", port=self.port)
                if poll and asked is not None and now - asked > self.timeout_s:
                    raise TurntableTimeout(f"controller silent for {self.timeout_s:g} s while waiting for {line!r} "
                                           f"(no status replies)", port=self.port)
                if poll and now >= next_poll:
                    self._link.write(STATUS_QUERY)
                    next_poll = time.monotonic() + self.poll_s
                    if asked is None:
                        asked = time.monotonic()
                continue
            asked = None
            s = reply.strip()
            if s == "ok":
                return
            if s.lower().startswith("error"):
                code, text = _parse_code(s)
                what = GRBL_ERRORS.get(code, text) if code is not None else text
                raise TurntableCommandError(f"{line!r} rejected: {s} ({what or 'error'})", code=code, command=line,
                                            port=self.port)
            if collect is not None and s.startswith("$"):
                collect.append(s)
                continue
            self._handle_async(s)

    def status(self, *, timeout_s: float | None = None) -> GrblStatus:
        """Send ``?`` and return the next status report.

        An Alarm *state* is returned, not raised; an ``ALARM:N`` message (an alarm
        happening now) raises :class:`TurntableAlarm`.
        """
        self._drain_quietly()
        self._link.write(STATUS_QUERY)
        total = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + total
        garbled = 0
        while True:
            reply = self._link.read_line(max(deadline - time.monotonic(), 0.0))  # reads at least once
            if reply is None:
                break
            s = reply.strip()
            st = self._parse(s)
            if st is not None:
                return st
            if _garbled_status(s) and garbled < 3:
                # line noise cut the report: its answer will not come again, so ask again
                garbled += 1
                log.warning("turntable: garbled status report %r; asking again", s)
                self._link.write(STATUS_QUERY)
                deadline = time.monotonic() + total
                continue
            if s.upper().startswith("ALARM"):
                raise self._alarm_line(s)
            if BANNER_RE.match(s):
                self._wco = None
                raise TurntableDisconnected("the controller reset by itself (banner seen mid-session)", port=self.port)
            log.debug("turntable: message %r", s)
        raise TurntableTimeout(f"no reply to a '?' status query within {total:g} s", port=self.port)

    def _drain_quietly(self) -> None:
        """Read what is pending: status reports are kept, an alarm raises."""
        for line in self._link.pending_lines():
            s = line.strip()
            if self._parse(s) is None and s.upper().startswith("ALARM"):
                raise self._alarm_line(s)

    # ------------------------------------------------------------------ motion

    def set_position(self, deg: float) -> None:
        """``G92 X<deg>``: the table's current angle is ``deg`` from now on.

        This is the host's word on where the table stands, so it also ends an
        unknown angle: a controller locked in an alarm is reset if it waits for one
        and unlocked (``$X``) first.
        """
        deg = float(deg)
        if self._critical:
            self._reset()
        if self._locked:
            log.warning("turntable: unlocking the controller ($X)%s: the table's angle is declared as %g deg",
                        f" after {self._last_alarm}" if self._last_alarm else "", deg)
            self._unlock()
        if not self._setup_done:
            self._setup()
        self.command(f"G92 X{format_angle(self.direction * deg)}")
        self._wco = None  # changed; GRBL sends the new WCO in its next report
        self._position = deg
        self._unknown = None
        st = self.status()
        if st.x is not None and abs(self.direction * st.x - deg) > 0.0015:
            log.warning("turntable: declared %g deg, the controller reports %g", deg, self.direction * st.x)

    def enable_motor(self, on: bool = True) -> None:
        """``M17`` / ``M18`` where the firmware has them (Horus); else nothing."""
        if self.has_motor_enable:
            self.command("M17" if on else "M18")
        else:
            log.debug("turntable: %s has no motor enable command; skipped", self.firmware)

    def move_to(self, deg: float) -> None:
        """Turn to ``deg`` (absolute) and return once a status report says Idle;
        :attr:`position_deg` is then the angle the steps reached.

        Raises:
            TurntableCommandError: the G1 line was refused (``error:N``: the table did
                not move; ``position_known`` stays True, a retry is safe).
            TurntableAlarm, TurntableTimeout, TurntableDisconnected: the table may
                have moved partly; ``position_known`` is False on these.
            TurntableError: the angle is unknown (declare it with :meth:`set_position`),
                or the table stopped away from the target.
        """
        deg = float(deg)
        if self._unknown is not None:
            raise TurntableError(f"the table's angle is unknown ({self._unknown}); check where it stands and "
                                 f"declare it (--table-at DEG, or set_position())", port=self.port,
                                 retryable=False, position_known=False)
        line = f"G1 X{format_angle(self.direction * deg)} F{self.feed_deg_per_min:g}"
        start = self._position
        # What came while the table stood (a reset's banner, an alarm) is read before the
        # G1 is sent: a reset then stopped no move, and the angle stays known.
        self._drain()
        try:
            self.command(line)
        except TurntableCommandError as e:
            if e.command == line:  # error:N on the G1 itself: not queued, the table did not move
                raise
            self._moved_unknown(e, deg)
            raise
        except DeviceError as e:  # the line may have been queued: GRBL starts the move at once
            self._moved_unknown(e, deg)
            raise
        expected = abs(deg - start) / self.rate_deg_per_min * 60.0
        try:
            self.command("G4 P0", timeout_s=1.5 * expected + self.motion_timeout_s, poll=True)
            st = self._wait_idle()
        except DeviceError as e:
            self._moved_unknown(e, deg)
            raise
        self._position = self._reached(st, deg)

    def reachable_deg(self, deg: float) -> float:
        """The angle a move to ``deg`` really ends at: GRBL rounds the target to whole
        motor steps (``$100``), in machine coordinates (work angle + WCO); to 0.001 as
        a status report gives it."""
        spd = self.steps_per_deg
        if not spd or spd <= 0:
            return float(deg)
        wco = self._wco or 0.0
        m = _lround((self.direction * float(deg) + wco) * spd) / spd - wco
        return round(self.direction * m, 3) + 0.0

    def _moved_unknown(self, e: DeviceError, target: float) -> None:
        e.position_known = False
        e.retryable = False
        self._lose_position(f"a move to {target:g} deg was cut short or not confirmed ({e.message})")

    def _reached(self, st: GrblStatus, target: float) -> float:
        """The angle the steps reached (the report's work position)."""
        if st.x is None:
            log.warning("turntable: the status report gives no work position (%s); recording the commanded "
                        "angle %g", st.raw, target)
            return target
        reached = round(self.direction * st.x, 3) + 0.0
        step = 1.0 / self.steps_per_deg if self.steps_per_deg else 0.5
        if abs(reached - target) > step + 0.002:
            self._position = reached
            raise TurntableError(f"the table stopped at {reached:.3f} deg, not at the {target:.3f} deg it was sent "
                                 f"to (a soft limit, or $100 / the direction set wrong?)", port=self.port,
                                 retryable=False)
        return reached

    def _wait_idle(self) -> GrblStatus:
        deadline = time.monotonic() + self.timeout_s
        while True:
            st = self.status()
            if st.state == "Idle":
                return st
            if st.state == "Alarm":
                raise self._alarm(self._last_alarm or "the controller is in the Alarm state after a move")
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
