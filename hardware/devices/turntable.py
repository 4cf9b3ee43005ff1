"""Turntables: the device interface (:class:`TurntableDevice`) and an in-memory
table (:class:`VirtualTurntable`). The GRBL/Horus controller over serial is
:class:`ringscan.hardware.devices.grbl.GrblTurntable`."""

from __future__ import annotations

import abc
import logging

from ringscan.hardware.devices.base import Device

log = logging.getLogger(__name__)

__all__ = ["TurntableDevice", "VirtualTurntable"]


class TurntableDevice(Device):
    """A turntable: moves to absolute angles (degrees, docs/design.md §11) and reports where it is."""

    @property
    @abc.abstractmethod
    def position_deg(self) -> float:
        """The angle the table was last confirmed at (degrees): where its last move
        ended (the angle the steps reached), or the angle last declared."""

    @property
    def position_known(self) -> bool:
        """False once something may have turned the table by an unknown angle (a move
        cut short, an alarm, a table found turning); :meth:`set_position` makes it
        known again."""
        return True

    @property
    def unknown_reason(self) -> str | None:
        """Why the angle is unknown (None while it is known)."""
        return None

    @abc.abstractmethod
    def move_to(self, deg: float) -> None:
        """Turn to the absolute angle ``deg``; return when the table has stopped."""

    @abc.abstractmethod
    def set_position(self, deg: float) -> None:
        """Declare that the table now stands at ``deg`` (no motion)."""

    def reachable_deg(self, deg: float) -> float:
        """The angle a move to ``deg`` really ends at (a stepper reaches whole steps
        only); ``deg`` itself where the device does not say."""
        return float(deg)

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


