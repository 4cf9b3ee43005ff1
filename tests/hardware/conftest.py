"""Fixtures of the hardware tests: the small rig and pattern set of tests/support/hardware_rig.py (kept
fast: 320x256 camera, 6-frame pattern sets, emulated moves of milliseconds) and the virtual rig."""

from __future__ import annotations

import pytest

from tests.support.hardware_rig import small_patterns, small_rig


@pytest.fixture(scope="session")
def rig():
    return small_rig()


@pytest.fixture(scope="session")
def patterns():
    return small_patterns()


@pytest.fixture(scope="session")
def virtual_rig(rig):
    """The real virtual rig renderer (pipeline.simulate) on the CPU, one ray per pixel;
    terrain scene (not symmetric about the turntable axis)."""
    from ringscan.hardware.emulators.virtual import make_virtual_rig
    from ringscan.pipeline.simulate.virtual_rig import RenderSettings

    return make_virtual_rig(rig, "terrain", device="cpu", settings=RenderSettings(supersample=1))
