"""What one ``ringscan capture`` run captures, decided before any device is opened: the turntable angles
checked, and the plan (rig, patterns, views, where the table stands) of a new capture or of the folder being
resumed (docs/hardware.md)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ringscan.hardware.capture.sequence import read_capture_state, resume_angle
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.patterns import PatternSpec
from ringscan.pipeline.formats.scan import load_scan

__all__ = ["MAX_TABLE_DEG", "MAX_STEP_DEG", "check_angles", "CapturePlan", "plan_capture"]

MAX_TABLE_DEG = 3600.0
"""Largest turntable angle accepted from the command line (``--table-at``, ``--start``): ten turns either way."""
MAX_STEP_DEG = 360.0
"""Largest angle between views (``--step``): one turn either way."""


def check_angles(*, table_at: float | None = None, start: float | None = None, step: float | None = None) -> None:
    """``--table-at``, ``--start`` and ``--step`` finite and within range, before anything moves (NaN or 1e300 would
    reach the table's controller as a move, or ``G92 Xnan``).

    Raises:
        ValueError: naming the option, e.g. ``--table-at: expected degrees from -3600 to 3600, got 1e+300``.
    """
    for opt, value, limit in (("--table-at", table_at, MAX_TABLE_DEG), ("--start", start, MAX_TABLE_DEG),
                              ("--step", step, MAX_STEP_DEG)):
        if value is not None and not -limit <= value <= limit:  # NaN fails too
            raise ValueError(f"{opt}: expected degrees from {-limit:g} to {limit:g}, got {value:g}")


@dataclass(frozen=True)
class CapturePlan:
    """What this run captures: the new capture's options, or what the folder being resumed says."""

    rig: object
    """The rig the devices are opened for."""
    patterns: PatternSpec
    """The patterns projected."""
    views: int
    """Number of views in the plan."""
    table_deg: float
    """Where the table stands at the start."""
    table_at: float | None
    """The table angle declared to ``capture_scan`` on a resume (``--table-at``, or the virtual table's)."""


def plan_capture(out: str | os.PathLike, *, rig, patterns: PatternSpec | None, views: int | None,
                 resume: bool = False, table_at: float | None = None, virtual: bool = False) -> CapturePlan:
    """The plan of a new capture into ``out`` (``rig``, ``patterns``, ``views`` as given, the table at 0), or,
    with ``resume``, of the capture in ``out``: its views, the rig and patterns unless given, and the table's
    angle (``table_at``; the emulated rig's, ``virtual``, starts where the capture says the table is).

    Raises:
        FormatError: ``resume`` and no scan.json in ``out``.
    """
    out = Path(out)
    if not resume:
        return CapturePlan(rig, patterns, views, 0.0, None)
    if not (out / "scan.json").is_file():
        raise FormatError(out / "scan.json", "nothing to resume (no scan.json)")
    saved = load_scan(out, check_files=False, allow_incomplete=True)
    n_views = len(read_capture_state(out)["plan"]["angles"])
    if virtual and table_at is None:
        # The virtual world starts afresh with its table where the capture says it
        # is, so the last confirmed angle is always right: declare it.
        table_at = float(read_capture_state(out)["table"]["deg"])
    return CapturePlan(rig or saved.rig, patterns or saved.patterns, n_views, resume_angle(out, table_at), table_at)
