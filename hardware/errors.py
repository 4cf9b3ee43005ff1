"""Typed device errors: what failed, on which port, and whether a retry may help.

Every driver turns serial exceptions, silence and firmware complaints into one of
these, so the capture sequence can decide what to do (retry after ``recover()``,
or stop with a clear message) without parsing text.

``position_known`` matters for the turntable: once a move has been sent, a lost
line, a timeout or an alarm leaves the table at an unknown angle, and a retry would
silently put the next view at the wrong angle. Such errors are never retried.
"""

from __future__ import annotations

from ringscan.pipeline.formats.errors import RingscanError

__all__ = [
    "DeviceError",
    "DeviceTimeout",
    "DeviceDisconnected",
    "TurntableError",
    "TurntableAlarm",
    "TurntableCommandError",
    "TurntableTimeout",
    "TurntableDisconnected",
    "ProjectorError",
    "ProjectorCommandError",
    "ProjectorTimeout",
    "ProjectorDisconnected",
    "CameraError",
    "CaptureError",
    "GRBL_ERRORS",
    "GRBL_ALARMS",
]

# GRBL 1.1 error and alarm codes (from the GRBL 1.1 interface documentation), used
# to turn "error:N" / "ALARM:N" into a message a user can act on.
GRBL_ERRORS = {
    1: "expected command letter",
    2: "bad number format",
    3: "invalid '$' statement",
    4: "negative value",
    5: "homing not enabled",
    6: "step pulse too short",
    7: "EEPROM read failed",
    8: "'$' command needs Idle",
    9: "G-code locked out during alarm or jog",
    10: "soft limits need homing",
    11: "line overflow",
    12: "step rate above 30 kHz",
    13: "safety door open",
    14: "line too long",
    15: "jog travel exceeded",
    16: "invalid jog command",
    17: "laser mode needs PWM",
    20: "unsupported or invalid G-code command",
    21: "modal group violation",
    22: "undefined feed rate",
    23: "command needs an integer",
    24: "two commands need axis words",
    25: "repeated G-code word",
    26: "no axis words",
    27: "invalid line number",
    28: "missing value word",
    29: "work coordinate system not supported",
    30: "G53 only with G0/G1",
    31: "unused axis words",
    32: "arc needs an in-plane axis word",
    33: "invalid motion target",
    34: "arc radius error",
    35: "arc needs an in-plane offset",
    36: "unused value words",
    37: "tool length offset not assigned",
    38: "tool number too large",
}

GRBL_ALARMS = {
    1: "hard limit triggered",
    2: "soft limit: target outside the travel",
    3: "reset while in motion",
    4: "probe fail (initial state)",
    5: "probe fail (no contact)",
    6: "homing fail (reset during cycle)",
    7: "homing fail (door opened)",
    8: "homing fail (pull-off did not clear the switch)",
    9: "homing fail (switch not found)",
    10: "homing fail (dual axis)",
}


class DeviceError(RingscanError):
    """A device (turntable, projector, camera) failed.

    Args:
        message: what happened, for a user.
        port: the port or source of the device, when there is one.
        retryable: a retry after the device's ``recover()`` may succeed.
        position_known: False when a turntable may have moved by an unknown angle.
    """

    device = "device"

    def __init__(self, message: str, *, port: str | None = None, retryable: bool = True,
                 position_known: bool = True):
        self.port = port
        self.retryable = retryable
        self.position_known = position_known
        self.message = message
        super().__init__(f"{self.device} on {port}: {message}" if port else f"{self.device}: {message}")


class DeviceTimeout(DeviceError):
    """The device did not answer in time."""


class DeviceDisconnected(DeviceError):
    """The port vanished or the line dropped (unplugged cable, board reset, power loss)."""


class TurntableError(DeviceError):
    """A turntable failure."""

    device = "turntable"


class TurntableAlarm(TurntableError):
    """The controller raised an alarm (GRBL ``ALARM:N``).

    Attributes:
        code: the alarm number, or None when the firmware gave text only.
    """

    def __init__(self, message: str, *, code: int | None = None, **kw):
        self.code = code
        super().__init__(message, **kw)


class TurntableCommandError(TurntableError):
    """The controller rejected a line (GRBL ``error:N``); the line was not executed.

    Attributes:
        code: the error number, or None when the firmware gave text only.
        command: the line that was rejected.
    """

    def __init__(self, message: str, *, code: int | None = None, command: str = "", **kw):
        self.code = code
        self.command = command
        super().__init__(message, **kw)


class TurntableTimeout(TurntableError, DeviceTimeout):
    """The turntable controller did not answer in time."""


class TurntableDisconnected(TurntableError, DeviceDisconnected):
    """The turntable's serial port vanished."""


class ProjectorError(DeviceError):
    """A pattern projector failure."""

    device = "projector"


class ProjectorCommandError(ProjectorError):
    """The projector answered ``ERR <code> <text>``.

    Attributes:
        code: the error code of the reply.
    """

    def __init__(self, message: str, *, code: int | None = None, **kw):
        self.code = code
        super().__init__(message, **kw)


class ProjectorTimeout(ProjectorError, DeviceTimeout):
    """The projector did not acknowledge in time."""


class ProjectorDisconnected(ProjectorError, DeviceDisconnected):
    """The projector's serial port vanished."""


class CameraError(DeviceError):
    """A camera failure (no frame, wrong size, unsupported setting)."""

    device = "camera"


class CaptureError(RingscanError):
    """A capture stopped; the scan folder holds a valid partial scan.

    Attributes:
        folder: the scan folder.
        cause: the device error that stopped it, if any.
    """

    def __init__(self, message: str, *, folder=None, cause: BaseException | None = None):
        self.folder = folder
        self.cause = cause
        super().__init__(message)
