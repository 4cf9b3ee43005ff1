"""The capture sequence with the display projector: the camera renders what the
virtual screen shows at the moment it grabs (read back from the X server), so a frame
that is not on screen yet when show() returns gives a different scan."""

import json

import numpy as np
import pytest

from ringscan.hardware.capture.sequence import CaptureSettings, capture_scan
from ringscan.hardware.devices.display import DisplayProjector
from ringscan.hardware.devices.projector import VirtualProjector
from ringscan.hardware.devices.turntable import VirtualTurntable
from ringscan.hardware.emulators.virtual import VirtualCamera
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import frame_names
from tests.support.hardware_rig import pattern_frames
from tests.support.virtual_screen import SCREEN_H, SCREEN_W, ScreenPattern, virtual_screen

FAST = CaptureSettings(turntable_settle_s=0.0, projector_settle_s=0.0, retries=0)
SEED = 7


@pytest.fixture(scope="module")
def screen():
    return virtual_screen()


def _capture(out, rig, patterns, virtual_rig, projector, pattern_source, views):
    table = VirtualTurntable()
    camera = VirtualCamera(virtual_rig, pattern_source, table, seed=SEED)
    return capture_scan(out, camera=camera, projector=projector, turntable=table, rig=rig, patterns=patterns,
                        views=views, settings=FAST, progress=False)


def _frames_equal(a, b) -> list[str]:
    """The frames (view/name) whose images differ."""
    diff = []
    for va, vb in zip(a.views, b.views):
        for n in va.frames:
            if not np.array_equal(read_image(a.frame_path(va, n)), read_image(b.frame_path(vb, n))):
                diff.append(f"{va.name}/{n}")
    return diff


class _IndexLog:
    """The screen as the camera sees it, logging which frame it matched at each grab."""

    def __init__(self, screen, frames):
        self.inner = ScreenPattern(screen, frames)
        self.seen = []

    def current_frame(self):
        return self.inner.current_frame()

    @property
    def current_index(self):
        i = self.inner.current_index
        self.seen.append(i)
        return i


def test_capture_with_the_display_projector_gives_the_virtual_projectors_scan(tmp_path, screen, rig, patterns,
                                                                               virtual_rig):
    assert (patterns.width, patterns.height) == (SCREEN_W, SCREEN_H)
    frames = list(pattern_frames(patterns).values())
    ref_proj = VirtualProjector(frames)
    ref = _capture(tmp_path / "virtual", rig, patterns, virtual_rig, ref_proj, ref_proj, views=2)

    with DisplayProjector(frames, display=0) as proj:
        log = _IndexLog(screen, frames)
        got = _capture(tmp_path / "display", rig, patterns, virtual_rig, proj, log, views=2)
        assert proj.shown == ref_proj.shown
    n = len(frame_names(patterns))
    assert log.seen == list(range(n)) * 2  # at every grab the screen showed exactly the frame asked for
    assert json.loads((got.folder / "scan.json").read_text()) == json.loads((ref.folder / "scan.json").read_text())
    assert _frames_equal(ref, got) == []


class _LateDisplayProjector(DisplayProjector):
    """A broken driver: show() returns before the new frame is on screen (the screen
    still shows the previous one when the camera grabs)."""

    def show(self, index):
        prev = self.current_index
        if prev >= 0:
            self._present(self.images[prev])
        else:
            self._present(None)
        self.current_index = int(index)
        self.shown.append(int(index))


def test_a_frame_shown_late_is_caught(tmp_path, screen, rig, patterns, virtual_rig):
    frames = list(pattern_frames(patterns).values())
    ref_proj = VirtualProjector(frames)
    ref = _capture(tmp_path / "virtual", rig, patterns, virtual_rig, ref_proj, ref_proj, views=1)
    with _LateDisplayProjector(frames, display=0) as proj:
        got = _capture(tmp_path / "late", rig, patterns, virtual_rig, proj, ScreenPattern(screen, frames), views=1)
    assert len(_frames_equal(ref, got)) == len(frame_names(patterns))  # every frame is the wrong one
