"""Small simulated scans for the batch tests (320x256 camera, the tiny scan's 256x192 projector of 0.6 mm
pixels and its 3-bit pattern set: an 80 mm scene, about 550 points a view, one view each unless said);
tests/pipeline/batch/conftest.py makes fixtures of them."""

import dataclasses

from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.simulate.scan import simulate_scan
from tests.support.reconstruct_rig import small_rig
from tests.support.shared_renders import shared_render
from tests.support.tiny_scan import TINY_PATTERNS, tiny_rig

SPEC = TINY_PATTERNS
"""The projected patterns: 16 frames; the projector's frames at 256x192 render in a fraction of the time of
the default 1024x768 (the scans are for the batch's bookkeeping, their accuracy is the reconstruction's)."""


def batch_rig():
    """small_rig's 320x256 camera with tiny_rig's 256x192 projector (0.6 mm pixels: 154 mm x 115 mm)."""
    return dataclasses.replace(small_rig(), light=tiny_rig().light)


def simulate_batch_scan(folder, scene="sphere", turntable_deg=(0.0,)):
    """Write the batch scan of ``scene`` into ``folder`` (rendered once per test session for the same
    arguments, tests/support/shared_renders.py: each batch test module's process asks for them)."""
    turntable_deg = tuple(float(a) for a in turntable_deg)

    def render(dst):
        simulate_scan(dst, scene=scene, size_mm=80.0, rig=batch_rig(), patterns=parse_patterns(SPEC),
                      turntable_deg=turntable_deg, progress=False)

    shared_render(folder, "batch", (scene, turntable_deg), render)
