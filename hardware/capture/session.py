"""Capture sessions: several poses of one object in a row (``ringscan capture --poses N``).

A session folder holds one scan folder per pose (``pose_<i>``) and ``session.json``
(the plan and each pose's state, rewritten atomically). Between poses the user turns
the object over and says so: a key (Enter on stdin) or a serial trigger (any line
from a serial port: a foot switch on a small board). A session resumes like a
single capture: complete poses are kept, an interrupted pose is resumed, the rest
captured; what is done with each pose (live reconstruction, fusion) is the caller's.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path

from ringscan.hardware.capture.sequence import read_capture_state
from ringscan.hardware.errors import CaptureError
from ringscan.pipeline.formats.atomic import atomic_write_json, read_json

log = logging.getLogger(__name__)

__all__ = ["SESSION_FORMAT", "pose_folder", "pose_state", "wait_for_key", "wait_for_serial", "run_session"]

SESSION_FORMAT = "ringscan.session/1"


def pose_folder(session: str | os.PathLike, index: int) -> Path:
    """The scan folder of pose ``index`` in a session folder."""
    return Path(session) / f"pose_{index}"


def pose_state(folder: Path) -> str:
    """``new`` (nothing captured), ``partial`` (an interrupted capture) or ``complete``."""
    if not (folder / "capture.json").is_file():
        return "new"
    return "complete" if read_capture_state(folder).get("status") == "complete" else "partial"


def wait_for_key(index: int, total: int, *, stream=None, out=None) -> None:
    """Ask the user to turn the object over for pose ``index`` and wait for Enter."""
    stream = sys.stdin if stream is None else stream
    out = sys.stderr if out is None else out
    print(f"pose {index + 1} of {total}: turn the object over onto another side, then press Enter", file=out,
          flush=True)
    if not stream.readline():
        raise CaptureError(f"pose {index + 1}: no key pressed (the input ended); resume the session to go on")


def wait_for_serial(port: str, *, baudrate: int = 115200, timeout_s: float | None = None) -> Callable[[int, int], None]:
    """A trigger that waits for a line on a serial port (pyserial URL or device) before each pose."""
    import serial

    def open_port():
        try:
            return serial.serial_for_url(port, baudrate=baudrate, timeout=timeout_s)
        except (OSError, ValueError, serial.SerialException) as e:  # e.g. /dev/null: "Inappropriate ioctl"
            raise CaptureError(f"--trigger {port}: cannot open it as a serial port: {e}") from None

    open_port().close()  # checked now, before the first pose is captured

    def wait(index: int, total: int) -> None:
        print(f"pose {index + 1} of {total}: turn the object over, then press the trigger", file=sys.stderr,
              flush=True)
        with open_port() as link:
            try:
                line = link.readline()
            except (OSError, serial.SerialException) as e:
                raise CaptureError(f"--trigger {port}: {e}") from None
            if not line:
                raise CaptureError(f"{port}: no trigger within {timeout_s} s before pose {index + 1}")

    return wait


def run_session(session: str | os.PathLike, poses: int, capture_pose: Callable[[int, Path, bool], None], *,
                wait: Callable[[int, int], None] = wait_for_key, on_pose: Callable[[int, Path], None] | None = None,
                labels: list[str] | None = None) -> list[Path]:
    """Capture ``poses`` poses into ``session``, resuming what an earlier run left.

    Args:
        session: the session folder.
        poses: number of poses.
        capture_pose: ``capture_pose(index, folder, resume)`` captures one pose's scan.
        wait: ``wait(index, total)`` before a new pose other than the first (the user turns the object).
        on_pose: called with each pose's index and folder once it is complete (also for kept ones).
        labels: a name per pose, recorded in session.json.

    Returns:
        The pose folders.
    """
    if not isinstance(poses, int) or poses < 1:
        raise ValueError(f"poses: expected a whole number >= 1, got {poses!r}")
    root = Path(session)
    path = root / "session.json"
    if path.is_file():
        old = read_json(path)
        if old.get("poses") != poses:
            raise ValueError(f"{path}: the session has {old.get('poses')} poses, not {poses}")
    root.mkdir(parents=True, exist_ok=True)
    state = {"format": SESSION_FORMAT, "poses": poses, "labels": labels or [str(i) for i in range(poses)],
             "status": {}}
    folders = [pose_folder(root, i) for i in range(poses)]
    for i, folder in enumerate(folders):
        st = pose_state(folder)
        if st != "complete":
            if st == "new" and i > 0:
                wait(i, poses)
            log.info("pose %d: %s", i, "resuming" if st == "partial" else "capturing")
            state["status"][folder.name] = "capturing"
            atomic_write_json(path, state)
            capture_pose(i, folder, st == "partial")
        state["status"][folder.name] = "complete"
        atomic_write_json(path, state)
        if on_pose is not None:
            on_pose(i, folder)
    return folders
