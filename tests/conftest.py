"""Shared fixtures: the Warp ``device`` fixture and paths to ../shared/data."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from ringscan.kernels import init_warp

from tests.support.shared_data import SHARED_DATA, need_shared  # noqa: F401  (SHARED_DATA: for the test modules)

REPO = Path(__file__).resolve().parents[1]


def _devices() -> list:
    import warp as wp

    init_warp()
    devs = ["cpu"]
    cuda = pytest.param("cuda:0", marks=pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device on this machine"))
    return devs + [cuda]


@pytest.fixture(autouse=True)
def _restore_log_levels():
    """A command run in-process (``main([..., "-q"])``) sets the ringscan loggers' levels for the
    process: put them back after every test, so a later test's caplog sees ringscan's warnings
    whatever the test order."""
    names = ("ringscan", "ringscan.progress")
    levels = {n: logging.getLogger(n).level for n in names}
    yield
    for n, lv in levels.items():
        logging.getLogger(n).setLevel(lv)


@pytest.fixture(scope="session", autouse=True)
def _shared_renders(request, tmp_path_factory):
    """The folder where this session's processes share their renders (tests/support/shared_renders.py):
    under pytest-xdist the workers' common base temporary folder (each worker's is a folder in it, made
    afresh for each session), else this process's own."""
    from tests.support.shared_renders import share_renders_in

    base = tmp_path_factory.getbasetemp()
    share_renders_in((base.parent if hasattr(request.config, "workerinput") else base) / "shared_renders")
    yield
    share_renders_in(None)


@pytest.fixture(scope="session", autouse=True)
def _frames_drawn_once():
    """The virtual rig's callers draw each projector frame once per process (tests/support/frame_cache.py)."""
    import ringscan.hardware.emulators.rig as emulated_rig
    import ringscan.pipeline.simulate.scan as simulated_scan
    from tests.support.frame_cache import cached_render_frame

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(simulated_scan, "render_frame", cached_render_frame)
        mp.setattr(emulated_rig, "render_frame", cached_render_frame)
        yield


@pytest.fixture(params=_devices())
def device(request) -> str:
    """Every kernel test runs on "cpu", and on "cuda:0" where a GPU is present."""
    return request.param


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (models, procam captures): fails in CI when absent, skips elsewhere
    (tests/support/shared_data.py)."""
    return need_shared(SHARED_DATA)


@pytest.fixture(scope="session")
def model_path(shared_data) -> callable:
    def get(name: str) -> Path:
        return need_shared(shared_data / "models" / name, f"model {name}")

    return get


# ----------------------------------------------------------------------------- where the suite's time goes

_SUITE = {"start": None, "tests": {}}


def pytest_sessionstart(session):
    import time

    _SUITE["start"] = time.perf_counter()


def pytest_runtest_logreport(report):
    """Setup, call and teardown of each test, added up (on the controller too under pytest-xdist)."""
    _SUITE["tests"][report.nodeid] = _SUITE["tests"].get(report.nodeid, 0.0) + report.duration


def pytest_terminal_summary(terminalreporter):
    """One line at the end: pytest's own time and the five slowest tests, so the next person sees
    where the suite's time goes (the bar: 300 s on a 2-core machine)."""
    import time

    if _SUITE["start"] is None or not _SUITE["tests"]:
        return
    wall = time.perf_counter() - _SUITE["start"]
    slow = sorted(_SUITE["tests"].items(), key=lambda kv: -kv[1])[:5]
    terminalreporter.write_line(f"suite time: pytest {wall:.0f} s, tests {sum(_SUITE['tests'].values()):.0f} s; "
                                "slowest: " + ", ".join(f"{k} {v:.1f} s" for k, v in slow))
