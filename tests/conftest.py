"""Shared fixtures: the Warp ``device`` fixture and paths to ../shared/data."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest

from ringscan.kernels import init_warp

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("RINGSCAN_SHARED_DATA", REPO.parent / "shared" / "data"))


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


@pytest.fixture(params=_devices())
def device(request) -> str:
    """Every kernel test runs on "cpu", and on "cuda:0" where a GPU is present."""
    return request.param


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (models, procam captures); tests skip with a reason when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (set RINGSCAN_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def model_path(shared_data) -> callable:
    def get(name: str) -> Path:
        p = shared_data / "models" / name
        if not p.is_file():
            pytest.skip(f"model {name} not found in {shared_data / 'models'}")
        return p

    return get
