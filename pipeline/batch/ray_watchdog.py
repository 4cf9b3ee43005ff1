"""Ends the local Ray cluster a batch started once the batch's process is gone (Linux).

``ray.init()`` starts the cluster's head processes as children of the batch's process
(the driver). Ray ties the GCS server and the raylet to the driver's life, but the
raylet's agents (``ray::DashboardAgent``, ``ray::RuntimeEnvAgent``) outlive a driver
killed with SIGKILL by a minute or more: on the raylet's death they try to report it to
the GCS server, which is dead too, and wait out a 60 s timeout.

:mod:`.ray_backend` runs this file as a script (``python -I -S ray_watchdog.py
DRIVER_PID RAY_PACKAGE_DIR``, in a session of its own, so a Ctrl-C or a hang-up on
the driver's terminal does not reach it) with its standard input a pipe whose only
writer is the driver. The script waits for that pipe's end of file: the driver closed
it (after ``ray.shutdown()``) or died, however it died. It then ends every process of
the driver's own Ray session: a Ray process (its name ``ray::...`` or an argument in
Ray's package folder) holding a file open in a session folder named after the driver
(``session_<date>_<DRIVER_PID>``, the name Ray gives a cluster it starts in that
process). A cluster the driver only joined has another name and is left alone.
SIGTERM first, SIGKILL to what remains after :data:`GRACE_S`.

Only the standard library: the script runs without ringscan's package on its path.
"""

from __future__ import annotations

import os
import re
import signal
import sys
import time

GRACE_S = 1.0
"""Seconds between SIGTERM and SIGKILL."""


def session_processes(driver_pid: int, ray_dir: str) -> list[int]:
    """Pids of the live Ray processes (not the driver's, not this one's) that hold a file open in a
    session folder named after ``driver_pid``."""
    in_session = re.compile(rf"/session_[^/]*_{driver_pid}(/|$)")
    ray_dir_b = os.fsencode(ray_dir.rstrip("/") + "/")
    found = []
    for name in os.listdir("/proc"):
        if not name.isdigit() or int(name) in (driver_pid, os.getpid()):
            continue
        try:
            with open(f"/proc/{name}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
            fds = os.listdir(f"/proc/{name}/fd")  # another user's: PermissionError, skipped
        except OSError:
            continue
        if not (argv[0].startswith(b"ray::") or any(a.startswith(ray_dir_b) for a in argv)):
            continue
        for fd in fds:
            try:
                target = os.readlink(f"/proc/{name}/fd/{fd}")
            except OSError:
                continue
            if in_session.search(target):
                found.append(int(name))
                break
    return found


def end_session(driver_pid: int, ray_dir: str, *, grace_s: float = GRACE_S) -> list[int]:
    """SIGTERM the session's processes, SIGKILL those left after ``grace_s``; returns the pids signalled."""
    pids = session_processes(driver_pid, ray_dir)
    for pid in pids:
        _signal(pid, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while (left := session_processes(driver_pid, ray_dir)) and time.monotonic() < deadline:
        time.sleep(0.05)
    for pid in left:
        _signal(pid, signal.SIGKILL)
    return sorted(set(pids) | set(left))


def _signal(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except OSError:  # gone already
        pass


def main(argv: list[str]) -> int:
    driver_pid, ray_dir = int(argv[0]), argv[1]
    for sig in (signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    while sys.stdin.buffer.read(4096):  # the driver never writes: this returns at its end of file
        pass
    end_session(driver_pid, ray_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
