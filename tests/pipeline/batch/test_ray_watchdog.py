"""The Ray watchdog on stand-in processes (no Ray needed): at its pipe's end it ends the Ray processes of
the driver's own session, and nothing else."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the watchdog reads /proc (Linux)")

HOLD = "import sys, time; f = open(sys.argv[1], 'a'); time.sleep(120)"  # holds a file open, as Ray's processes do


def _holder(path: Path, *extra, argv0=None):
    path.parent.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen([argv0 or sys.executable, "-c", HOLD, str(path), *extra], executable=sys.executable)


def _wait_open(proc, path, timeout=20.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if any(os.readlink(f"/proc/{proc.pid}/fd/{fd}") == str(path) for fd in os.listdir(f"/proc/{proc.pid}/fd")):
                return
        except OSError:
            pass
        time.sleep(0.05)
    raise AssertionError(f"{proc.pid} never opened {path}")


def test_the_watchdog_ends_the_drivers_session_alone(tmp_path):
    from ringscan.pipeline.batch import ray_watchdog

    me = os.getpid()
    ray_dir = tmp_path / "site-packages" / "ray"
    ours = tmp_path / "ray" / f"session_2026-01-01_00-00-00_1_{me}" / "logs"
    theirs = tmp_path / "ray" / f"session_2026-01-01_00-00-00_1_{me}0" / "logs"  # another driver's pid
    procs = {
        "agent": _holder(ours / "agent.log", argv0="ray::DashboardAgent"),
        "server": _holder(ours / "gcs.out", f"{ray_dir}/core/gcs_server"),
        "other session": _holder(theirs / "agent.log", argv0="ray::DashboardAgent"),
        "not Ray (tail -f)": _holder(ours / "raylet.out"),
    }
    try:
        for name, p in procs.items():
            _wait_open(p, {"agent": ours / "agent.log", "server": ours / "gcs.out",
                           "other session": theirs / "agent.log", "not Ray (tail -f)": ours / "raylet.out"}[name])
        assert sorted(ray_watchdog.session_processes(me, str(ray_dir))) == sorted(
            [procs["agent"].pid, procs["server"].pid])
        dog = subprocess.Popen([sys.executable, "-I", "-S", ray_watchdog.__file__, str(me), str(ray_dir)],
                               stdin=subprocess.PIPE)
        time.sleep(0.5)
        assert all(p.poll() is None for p in procs.values())  # nothing happens while the pipe is open
        dog.stdin.close()  # the driver's end: closed, as when it dies
        assert dog.wait(timeout=30) == 0
        assert procs["agent"].wait(timeout=10) is not None and procs["server"].wait(timeout=10) is not None
        assert procs["other session"].poll() is None and procs["not Ray (tail -f)"].poll() is None
    finally:
        for p in procs.values():
            p.kill()
            p.wait()
