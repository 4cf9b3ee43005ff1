"""Scans rendered once per test session and copied to every test that asks for the same one.

Several test modules ask for the same virtual-rig scan (the two-camera scan of
tests/support/two_camera_scan.py, the batch tests' scans, the tiny scan). The renders
are deterministic (seeded noise: a render into another folder writes the same bytes), so the
first process of a session to ask for one renders it into a folder every process of the session
shares (under pytest-xdist the workers' common base temporary folder), under a file lock; every
caller, that one included, gets its own copy (tests change their scan's files).

Outside a pytest session (a benchmark importing a helper) nothing is shared: each call renders.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import pickle
import shutil
from collections.abc import Callable
from pathlib import Path

_ROOT: Path | None = None
"""The session's shared folder (tests/conftest.py sets it at the session's start); None: no sharing."""


def share_renders_in(folder: Path | None) -> None:
    global _ROOT
    _ROOT = None if folder is None else Path(folder)


def shared_render(folder: Path, what: str, params, render: Callable[[Path], object]) -> None:
    """Write into ``folder`` what ``render(folder)`` writes there.

    ``what`` names the kind of render and ``params`` (picklable) is everything its output depends on:
    equal (``what``, ``params``) must mean equal bytes. The first call of the session with them
    renders into the shared folder; every call copies that render into ``folder``.
    """
    folder = Path(folder)
    if _ROOT is None:
        render(folder)
        return
    digest = hashlib.sha1(pickle.dumps((what, params), protocol=4)).hexdigest()[:16]
    master = _ROOT / f"{what}-{digest}"
    if not master.is_dir():
        _ROOT.mkdir(parents=True, exist_ok=True)
        with open(_ROOT / f"{what}-{digest}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # another process rendering the same: wait for it, then copy
            if not master.is_dir():
                partial = _ROOT / f"{what}-{digest}.partial-{os.getpid()}"
                shutil.rmtree(partial, ignore_errors=True)
                render(partial / "scan")
                os.rename(partial, master)  # whole or not at all: a render that failed is not shared
    shutil.copytree(master / "scan", folder, dirs_exist_ok=True)
