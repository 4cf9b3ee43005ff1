"""Projector frames drawn once per test process for the virtual rig.

``simulate_scan`` and the virtual capture (``hardware.emulators.rig``) draw every frame of their pattern set
each time (1024x768 frames: as long as the render that uses them); the suite simulates the same pattern sets
over and over (two plates for the light, three batch scans, captures view after view). A frame of the
built-in kinds (``pipeline.codecs.drawing.FRAME_KINDS``) is a function of the pattern set and its name alone,
so tests/conftest.py hands those two callers :func:`cached_render_frame`: the first call draws it, later ones
get a copy of the same bytes. Frames of codecs registered by a test (another ``render_frame``) are drawn
every time. tests/pipeline/codecs/test_render.py and the codecs' tests call the drawing itself.
"""

from __future__ import annotations

import pickle
from collections import OrderedDict

from ringscan.pipeline.codecs.drawing import FRAME_KINDS
from ringscan.pipeline.codecs.render import render_frame

MAX_FRAMES = 160
"""Frames kept (least recently used dropped first): ~125 MB of 1024x768 frames a process."""

_frames: OrderedDict = OrderedDict()


def cached_render_frame(spec, name: str):
    """:func:`ringscan.pipeline.codecs.render.render_frame`, drawn once per (pattern set, name)."""
    if name.split("_")[0] not in FRAME_KINDS:
        return render_frame(spec, name)
    key = (pickle.dumps(spec, protocol=4), name)
    img = _frames.get(key)
    if img is None:
        img = render_frame(spec, name)
        _frames[key] = img
        while len(_frames) > MAX_FRAMES:
            _frames.popitem(last=False)
    else:
        _frames.move_to_end(key)
    return img.copy()
