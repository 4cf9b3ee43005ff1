"""The capture sequence: complete scans, retries, faults, partial scans and resume.

The emulated table moves in whole motor steps (8.889 steps/deg), so the views of a
3-view capture are recorded at the angles the steps reached: 0, 120.036, 239.96.
"""

import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ringscan.hardware.capture.sequence import (
    CaptureSettings,
    capture_scan,
    plan_angles,
    read_capture_state,
    resume_angle,
)
from ringscan.hardware.devices.grbl import GrblTurntable
from ringscan.hardware.devices.projector import SerialProjector, VirtualProjector
from ringscan.hardware.devices.turntable import VirtualTurntable
from ringscan.hardware.emulators.rig import EmulatedRig
from ringscan.hardware.errors import CameraError, CaptureError, ProjectorError
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.scan import load_scan
from tests.support.hardware_rig import ProbeCamera, pattern_frames, small_patterns, small_rig

FAST = CaptureSettings(turntable_settle_s=0.0, projector_settle_s=0.0, retries=2, retry_delay_s=0.0,
                       command_timeout_s=0.3)
SEED = 11
REACHED = [0.0, 120.036, 239.96]  # round(k * 120 * 8.889) / 8.889, as GRBL reports them
STEP = 1 / 8.889
REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def virtual_rig(rig):
    """The real virtual rig renderer on the CPU, as in tests/hardware/conftest.py, but with a
    sharp projector lens (defocus_px=0): the emitted light is then the projector's own
    1024x768 pixels, not a blurred image 4x finer, which makes each frame several times
    cheaper to render. These tests check what the capture does with the frames (which
    frame at which angle, byte-exact against the renderer), not the lens blur."""
    from ringscan.hardware.emulators.virtual import make_virtual_rig
    from ringscan.pipeline.simulate.virtual_rig import RenderSettings

    return make_virtual_rig(rig, "terrain", device="cpu", settings=RenderSettings(supersample=1, defocus_px=0.0))


def _files(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def _listed(scan):
    return sorted([rel for v in scan.views for rel in v.frames.values()] + ["capture.json", "scan.json"])


def _virtual(patterns, views=3, **kw):
    proj = VirtualProjector(pattern_frames(patterns))
    table = VirtualTurntable()
    return proj, table, ProbeCamera(proj, table)


class _Emulated:
    """An emulated rig (real renderer) plus the real serial drivers connected to it."""

    def __init__(self, rig, patterns, virtual_rig, start_deg=0.0, time_scale=1000.0, **kw):
        self.emu = EmulatedRig(rig, patterns, virtual_rig=virtual_rig, time_scale=time_scale, seed=SEED,
                               start_deg=start_deg, **kw)
        self.names = frame_names(patterns)
        self.connect(start_deg)

    def connect(self, position_deg):
        self.turntable = GrblTurntable(self.emu.turntable_port, timeout_s=0.3, boot_timeout_s=0.5,
                                       position_deg=position_deg)
        self.projector = SerialProjector(self.emu.projector_port, timeout_s=0.3, expect_names=self.names)

    def devices(self):
        return dict(camera=self.emu.camera, projector=self.projector, turntable=self.turntable)

    def close(self):
        self.turntable.close()
        self.projector.close()
        self.emu.close()


@pytest.fixture(scope="module")
def reference(tmp_path_factory, rig, patterns, virtual_rig):
    """An uninterrupted emulated capture: 3 views x 6 frames."""
    out = tmp_path_factory.mktemp("ref") / "scan"
    e = _Emulated(rig, patterns, virtual_rig)
    try:
        scan = capture_scan(out, rig=rig, patterns=patterns, views=3, settings=FAST, progress=False, **e.devices())
        sent = bytes(e.emu.turntable.received).replace(b"?", b"")
        shown = list(e.emu.projector.lines)
    finally:
        e.close()
    return scan, sent, shown


def _same_images(a, b, angle_tol=0.0):
    assert [v.name for v in a.views] == [v.name for v in b.views]
    for va, vb in zip(a.views, b.views):
        assert abs(va.turntable_deg - vb.turntable_deg) <= angle_tol and sorted(va.frames) == sorted(vb.frames)
        for n in va.frames:
            np.testing.assert_array_equal(read_image(a.frame_path(va, n)), read_image(b.frame_path(vb, n)),
                                          err_msg=f"{va.name}/{n}")


# ----------------------------------------------------------------------------- complete captures


def test_sequence_turns_shows_and_grabs_in_order(tmp_path, rig, patterns):
    proj, table, cam = _virtual(patterns)
    done = []
    scan = capture_scan(tmp_path / "s", camera=cam, projector=proj, turntable=table, rig=rig, patterns=patterns,
                        views=3, settings=FAST, progress=False, on_view=lambda s, v: done.append(v.name))
    names = frame_names(patterns)
    assert [v.turntable_deg for v in scan.views] == [0.0, 120.0, 240.0] and table.moves == [120.0, 240.0]
    assert done == ["view_000", "view_001", "view_002"]
    for v in scan.views:
        assert list(v.frames) == names
        for j, n in enumerate(names):
            img = read_image(scan.frame_path(v, n))
            assert img[0, 0] == j + 1 and img[0, 1] == round(v.turntable_deg / 5)  # frame j at the view's angle
    assert proj.current_index == -1  # blanked at the end
    assert _files(scan.folder) == _listed(scan)
    state = read_capture_state(scan.folder)
    assert state["status"] == "complete" and state["plan"]["angles"] == [0.0, 120.0, 240.0]
    assert state["table"] == {"deg": 240.0, "moving_to": None, "known": True}
    assert CaptureSettings.from_dict(state["settings"]) == FAST
    assert state["runs"][0]["frames"] == 18 and state["runs"][0]["result"] == "complete"


def test_emulated_rig_capture_is_complete_and_rendered_in_state(reference, rig, patterns, virtual_rig):
    scan, sent, shown = reference
    scan = load_scan(scan.folder)  # complete: strict load passes
    names = frame_names(patterns)
    assert [v.turntable_deg for v in scan.views] == REACHED  # the angles the steps reached
    assert all(list(v.frames) == names for v in scan.views)
    assert _files(scan.folder) == _listed(scan)
    # the exact lines the drivers sent through the pty
    assert sent == (b"\x18$$\nG90\nG92 X0.000\nG92 X0.000\n"
                    b"G1 X120.000 F600\nG4 P0\nG1 X240.000 F600\nG4 P0\n")
    assert shown[:2 + len(names)] == ["HELLO"] + [f"NAME {i}" for i in range(len(names))] + ["SHOW 0"]
    assert shown.count("SHOW 3") == 3 and shown[-1] == "BLANK"
    # each frame is what the virtual rig renders with that frame shown at the recorded angle
    cam = scan.views[1]
    virtual_rig.set_turntable(cam.turntable_deg)
    from ringscan.hardware.emulators.virtual import VirtualCamera

    probe = VirtualCamera(virtual_rig, None, None, seed=SEED)
    for j in (0, 4):
        want = virtual_rig.render(pattern_frames(patterns)[names[j]], seed=probe._state_seed(j, cam.turntable_deg))
        np.testing.assert_array_equal(read_image(scan.frame_path(cam, names[j])), want)


# ----------------------------------------------------------------------------- faults and retries


def test_projector_faults_are_retried(tmp_path, rig, patterns, caplog):
    names = frame_names(patterns)
    from ringscan.hardware.emulators.projector import EmulatedProjector

    with EmulatedProjector(pattern_frames(patterns), link_path=tmp_path / "pj") as emu:
        proj = SerialProjector(emu.port, timeout_s=0.3, expect_names=names)
        table = VirtualTurntable()
        emu.inject("error", on="SHOW 2")
        emu.inject("silent", on="SHOW 4")
        with caplog.at_level(logging.WARNING, logger="ringscan.hardware.capture"):
            scan = capture_scan(tmp_path / "s", camera=ProbeCamera(emu, table), projector=proj, turntable=table,
                                rig=rig, patterns=patterns, views=2, settings=FAST, progress=False)
        proj.close()
    assert "retry 1 of 2" in caplog.text and "display fault" in caplog.text
    for v in scan.views:
        for j, n in enumerate(names):
            assert read_image(scan.frame_path(v, n))[0, 0] == j + 1


def test_turntable_error_is_retried(tmp_path, rig, patterns, virtual_rig, reference):
    e = _Emulated(rig, patterns, virtual_rig)
    try:
        e.emu.turntable.inject("error", on="G1", code=20)
        scan = capture_scan(tmp_path / "s", rig=rig, patterns=patterns, views=3, settings=FAST, progress=False,
                            **e.devices())
        assert e.emu.turntable.resets == 2  # connect, then the recovery before the retry
        assert e.emu.turntable.lines.count("G1 X120.000 F600") == 2
    finally:
        e.close()
    _same_images(scan, reference[0])


def test_faults_outside_a_move_are_retried(tmp_path, rig, patterns):
    # A camera without a frame (a live camera, the emulator's socket) and a turntable
    # that does not answer a line while it stands: reconnected and retried.
    from ringscan.hardware.emulators.grbl import EmulatedTurntable

    class Flaky(ProbeCamera):
        def _read(self):
            if self.grabs == 4 and not getattr(self, "failed", False):
                self.failed = True
                raise CameraError("camera gave no frame (unplugged or busy?)", port="probe")
            return super()._read()

    with EmulatedTurntable(time_scale=1000.0) as emu:
        proj = VirtualProjector(pattern_frames(patterns))
        table = GrblTurntable(emu.port, timeout_s=0.3)
        emu.inject("silent", on="G92")  # the capture's own G92
        cam = Flaky(proj, emu)
        scan = capture_scan(tmp_path / "s", rig=rig, patterns=patterns, views=2, camera=cam, projector=proj,
                            turntable=table, settings=FAST, progress=False)
        table.close()
        # G92: the connection's, the silent one, the reconnection's, the retry's
        assert emu.resets == 2 and emu.lines.count("G92 X0.000") == 4
    assert cam.failed and [len(v.frames) for v in scan.views] == [6, 6]
    for v in scan.views:
        for j, n in enumerate(frame_names(patterns)):
            assert read_image(scan.frame_path(v, n))[0, 0] == j + 1


def test_persistent_fault_stops_with_a_valid_partial_scan_and_resume_completes_it(tmp_path, rig, patterns,
                                                                                  virtual_rig, reference):
    out = tmp_path / "s"
    e = _Emulated(rig, patterns, virtual_rig)
    try:
        e.emu.projector.inject("error", on="SHOW", skip=8, times=100)  # 8 frames, then a dead display
        with pytest.raises(CaptureError, match="after 2 retries.*display fault.*--resume") as ei:
            capture_scan(out, rig=rig, patterns=patterns, views=3, settings=FAST, progress=False, **e.devices())
        assert ei.value.cause is not None
    finally:
        e.close()
    with pytest.raises(FormatError, match="missing frame"):
        load_scan(out)  # incomplete, so a strict load refuses it ...
    part = load_scan(out, allow_incomplete=True)  # ... but it is valid, and every listed frame is there
    assert [len(v.frames) for v in part.views] == [6, 2]
    assert _files(out) == _listed(part)  # nothing written half, nothing unlisted
    state = read_capture_state(out)
    assert state["status"] == "stopped" and "display fault" in state["error"]
    assert state["table"] == {"deg": 120.036, "moving_to": None, "known": True}
    # leftovers of a killed writer: a temporary file and a frame written but not yet listed
    (out / "view_001" / ".gray_1.x1y2.tmp.png").write_bytes(b"\x89PNG half")
    (out / "view_001" / "gray_1.png").write_bytes(b"junk")

    e = _Emulated(rig, patterns, virtual_rig, start_deg=resume_angle(out))  # the table stayed at 120.036
    try:
        scan = capture_scan(out, rig=rig, patterns=patterns, settings=FAST, resume=True, progress=False,
                            **e.devices())
    finally:
        e.close()
    assert _files(out) == _listed(scan)
    state = read_capture_state(out)
    assert state["status"] == "complete" and [r["frames"] for r in state["runs"]] == [8, 10]
    _same_images(scan, reference[0])


def test_turntable_lost_mid_move_needs_table_at_and_resumes_exactly(tmp_path, rig, patterns, virtual_rig,
                                                                    reference):
    out = tmp_path / "s"
    e = _Emulated(rig, patterns, virtual_rig, folder=tmp_path / "emu")
    try:
        e.emu.turntable.inject("vanish", on="G1", skip=1, at_fraction=0.5)  # the move to 240
        with pytest.raises(CaptureError, match="part way to 240 deg.*--resume --table-at"):
            capture_scan(out, rig=rig, patterns=patterns, views=3, settings=FAST, progress=False, **e.devices())
        assert e.emu.turntable.resets == 1  # never retried: the table's angle is unknown
        state = read_capture_state(out)
        # the move's end is recorded as the motor's whole steps reach it (239.96, not 240)
        assert state["table"] == {"deg": 120.036, "moving_to": 240.0, "known": False, "reaches": 239.96}
        assert state["status"] == "stopped"
        assert [len(v.frames) for v in load_scan(out, allow_incomplete=True).views] == [6, 6]
        with pytest.raises(CaptureError, match="angle is unknown.*--table-at 239.96 if the move finished"):
            resume_angle(out)
        with pytest.raises(CaptureError, match="--table-at"):
            capture_scan(out, settings=FAST, resume=True, progress=False, **e.devices())
        # the board finishes the move on its own; the user plugs it back and says so
        deadline = time.monotonic() + 5.0
        while e.emu.turntable.moving and time.monotonic() < deadline:
            time.sleep(0.005)
        e.emu.turntable.replug()
        assert e.emu.turntable.angle_deg == REACHED[2]
        e.turntable.close()
        e.projector.close()
        e.connect(240.0)
        scan = capture_scan(out, settings=FAST, resume=True, table_at=240.0, progress=False, **e.devices())
    finally:
        e.close()
    _same_images(scan, reference[0], angle_tol=STEP / 2)  # the user said 240; the steps reached 239.96
    assert read_capture_state(out)["table"] == {"deg": 240.0, "moving_to": None, "known": True}


def test_turntable_alarm_mid_move_stops_clearly(tmp_path, rig, patterns, virtual_rig):
    e = _Emulated(rig, patterns, virtual_rig)
    try:
        e.emu.turntable.inject("alarm", on="G1", code=1)
        with pytest.raises(CaptureError, match="ALARM:1 \\(hard limit triggered\\).*part way to 120"):
            capture_scan(tmp_path / "s", rig=rig, patterns=patterns, views=3, settings=FAST, progress=False,
                         **e.devices())
        assert e.emu.turntable.resets == 1 and "$X" not in e.emu.turntable.lines  # not retried, not unlocked
    finally:
        e.close()
    part = load_scan(tmp_path / "s", allow_incomplete=True)
    assert [len(v.frames) for v in part.views] == [6]
    with pytest.raises(CaptureError, match="--table-at"):
        resume_angle(tmp_path / "s")


def test_an_alarm_while_the_table_stands_stops_the_capture_at_once(tmp_path, rig, patterns):
    # docs/hardware.md: an alarm stops the capture, with its meaning; no reset, no $X, no retry.
    from ringscan.hardware.emulators.grbl import EmulatedTurntable

    with EmulatedTurntable(time_scale=1000.0) as emu:
        proj = VirtualProjector(pattern_frames(patterns))
        table = GrblTurntable(emu.port, timeout_s=0.3)
        emu.inject("alarm", on="G92", code=1)  # the capture's own G92 (the connection's came before)
        t0 = time.monotonic()
        with pytest.raises(CaptureError, match="ALARM:1 \\(hard limit triggered\\).*angle is unknown.*--table-at"):
            capture_scan(tmp_path / "s", rig=rig, patterns=patterns, views=3, camera=ProbeCamera(proj, emu),
                         projector=proj, turntable=table, settings=FAST, progress=False)
        assert time.monotonic() - t0 < 1.0
        assert emu.resets == 1 and "$X" not in emu.lines and emu.lines.count("G92 X0.000") == 2
        table.close()
    state = read_capture_state(tmp_path / "s")
    assert state["status"] == "stopped" and state["table"]["known"] is False
    with pytest.raises(CaptureError, match="angle became unknown.*--table-at"):
        resume_angle(tmp_path / "s")


def test_a_lost_ok_stops_the_capture_and_a_quick_resume_waits_for_the_table(tmp_path, rig, patterns, virtual_rig,
                                                                          reference):
    # Issue: an ok lost after the first G1; the retry reset the moving table, the
    # reconnect dropped the ALARM:3, unlocked it and declared 120: exit 0, views at
    # wrong angles. Now the capture stops, and a resume started while the table still
    # turns waits for it to stop instead of resetting it.
    out = tmp_path / "s"
    e = _Emulated(rig, patterns, virtual_rig, time_scale=20.0)  # 120 deg: 0.6 s
    try:
        tt = e.emu.turntable
        tt.inject("lose_ok", on="G1")
        with pytest.raises(CaptureError, match="part way to 120 deg.*--resume --table-at"):
            capture_scan(out, rig=rig, patterns=patterns, views=3, settings=FAST, progress=False, **e.devices())
        assert tt.resets == 1 and tt.resets_in_motion == 0 and "$X" not in tt.lines
        assert read_capture_state(out)["table"] == {"deg": 0.0, "moving_to": 120.0, "known": False, "reaches": 120.036}
        with pytest.raises(CaptureError, match="--table-at 120.036 if the move finished"):  # reachable, not 120
            resume_angle(out)
        assert tt.moving  # still turning
        e.turntable.close()
        e.projector.close()
        e.connect(120.0)  # resume --table-at 120 at once
        assert tt.resets_in_motion == 0 and tt.alarms == [] and tt.angle_deg == REACHED[1]
        scan = capture_scan(out, settings=FAST, resume=True, table_at=120.0, progress=False, **e.devices())
    finally:
        e.close()
    assert [v.turntable_deg for v in scan.views] == pytest.approx([0.0, 120.0, 240.0], abs=STEP)
    # view 1 was taken where the table really stood, as in the uninterrupted capture
    _same_images(dataclasses.replace(scan, views=scan.views[:2]),
                 dataclasses.replace(reference[0], views=reference[0].views[:2]), angle_tol=STEP / 2)


def test_resume_refuses_the_last_angle_when_the_table_was_found_locked(tmp_path, rig, patterns):
    from ringscan.hardware.emulators.grbl import EmulatedTurntable

    out = tmp_path / "s"
    with EmulatedTurntable(time_scale=20.0) as emu:
        proj = VirtualProjector(pattern_frames(patterns))
        kw = dict(camera=ProbeCamera(proj, emu), projector=proj, settings=FAST, progress=False)
        table = GrblTurntable(emu.port, timeout_s=0.3)
        proj_fault = {"n": 0}

        def show(i, _show=proj.show):
            proj_fault["n"] += 1
            if proj_fault["n"] > 8:
                raise ProjectorError("display fault", retryable=False)
            _show(i)

        proj.show = show
        with pytest.raises(CaptureError, match="display fault"):
            capture_scan(out, rig=rig, patterns=patterns, views=3, turntable=table, **kw)
        table.close()
        assert read_capture_state(out)["table"] == {"deg": 120.036, "moving_to": None, "known": True}
        # meanwhile someone turned the table and reset it in motion: ALARM:3, locked
        import serial

        with serial.Serial(emu.port, 115200, timeout=0.5) as s:
            s.write(b"G1 X200 F600\n")
            assert s.readline() == b"ok\r\n"
            time.sleep(0.1)
            s.write(b"\x18")
            assert s.readline() == b"ALARM:3\r\n"
        del proj.show  # the display works again
        table = GrblTurntable(emu.port, timeout_s=0.3, position_deg=resume_angle(out))
        assert "$X" not in emu.lines
        with pytest.raises(CaptureError, match="did not see.*120.036 deg.*cannot be trusted.*--table-at"):
            capture_scan(out, resume=True, turntable=table, **kw)
        assert read_capture_state(out)["table"]["known"] is False
        here = emu.angle_deg
        scan = capture_scan(out, resume=True, turntable=table, table_at=here, **kw)  # the user's word
        table.close()
    assert scan.views[1].turntable_deg == 120.036 and len(scan.views) == 3
    # every frame at the angle its view records
    for v in scan.views:
        assert all(read_image(scan.frame_path(v, n))[0, 1] == round(v.turntable_deg / 5) for n in v.frames)


class _FinalizerCtrlC(ProbeCamera):
    """A grab during which Ctrl-C lands in a finalizer (as in a Warp array's __del__):
    Python only prints "Exception ignored in ..." for the KeyboardInterrupt."""

    def __init__(self, *a, at=3, **kw):
        super().__init__(*a, **kw)
        self.at = at

    def _read(self):
        if self.grabs + 1 == self.at:
            class Buffer:
                def __del__(self):
                    signal.raise_signal(signal.SIGINT)

            Buffer()  # freed at once: the signal handler runs inside __del__
        return super()._read()


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the swallowed interrupt itself
def test_ctrl_c_in_a_finalizer_still_stops_the_capture(tmp_path, rig, patterns):
    proj, table, _ = _virtual(patterns)
    before = signal.getsignal(signal.SIGINT)
    kw = dict(projector=proj, turntable=table, settings=FAST, progress=False)
    with pytest.raises(KeyboardInterrupt):
        capture_scan(tmp_path / "s", camera=_FinalizerCtrlC(proj, table, at=3), rig=rig, patterns=patterns,
                     views=2, **kw)
    assert signal.getsignal(signal.SIGINT) is before  # the handler is put back
    state = read_capture_state(tmp_path / "s")
    assert state["status"] == "interrupted" and state["runs"][0]["frames"] == 3
    part = load_scan(tmp_path / "s", allow_incomplete=True)
    assert [len(v.frames) for v in part.views] == [3]
    scan = capture_scan(tmp_path / "s", camera=ProbeCamera(proj, table), resume=True, **kw)
    assert [len(v.frames) for v in scan.views] == [6, 6]


_KILLED = """
import os, sys
from ringscan.hardware.capture.sequence import CaptureSettings, capture_scan
from ringscan.hardware.devices.projector import VirtualProjector
from ringscan.hardware.devices.turntable import VirtualTurntable
from tests.support.hardware_rig import ProbeCamera, pattern_frames, small_patterns, small_rig

class Killed(ProbeCamera):
    def _read(self):
        if self.grabs == int(sys.argv[2]):
            os._exit(9)  # like SIGKILL: no finally, no word in capture.json
        return super()._read()

patterns = small_patterns()
proj, table = VirtualProjector(pattern_frames(patterns)), VirtualTurntable()
capture_scan(sys.argv[1], camera=Killed(proj, table), projector=proj, turntable=table, rig=small_rig(),
             patterns=patterns, views=3, progress=False,
             settings=CaptureSettings(turntable_settle_s=0.0, projector_settle_s=0.0))
"""


def test_the_record_of_a_killed_run_is_brought_up_to_date_on_resume(tmp_path, rig, patterns):
    out = tmp_path / "s"
    r = subprocess.run([sys.executable, "-c", _KILLED, str(out), "8"], cwd=REPO, capture_output=True, text=True,
                       timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert r.returncode == 9, r.stderr
    state = read_capture_state(out)
    assert state["status"] == "running" and state["runs"][0]["frames"] == 6  # out of date: 8 frames listed
    assert sum(len(v.frames) for v in load_scan(out, allow_incomplete=True).views) == 8
    proj = VirtualProjector(pattern_frames(patterns))
    table = VirtualTurntable(resume_angle(out))
    capture_scan(out, camera=ProbeCamera(proj, table), projector=proj, turntable=table, resume=True,
                 settings=FAST, progress=False)
    runs = read_capture_state(out)["runs"]
    assert [r["result"] for r in runs] == ["killed", "complete"]
    assert [r["frames"] for r in runs] == [8, 10] and runs[0]["ended"] is not None


def test_a_controller_reset_while_the_table_stands_is_no_cut_short_move(tmp_path, rig, patterns):
    # The board reboots by itself (power, USB) while the table stands at 120.036: its
    # banner is read before the G1 to 240 is sent. No move was cut short: the angle is
    # known, the table is reconnected, the angle declared again and the capture goes on.
    from ringscan.hardware.emulators.grbl import EmulatedTurntable

    with EmulatedTurntable(time_scale=1000.0) as emu:
        proj = VirtualProjector(pattern_frames(patterns))
        table = GrblTurntable(emu.port, timeout_s=0.3)

        def reboot_after_view_1(scan, view):
            if view.name == "view_001":
                emu.reboot()
                time.sleep(0.05)  # the banner arrives while the table stands

        scan = capture_scan(tmp_path / "s", rig=rig, patterns=patterns, views=3, camera=ProbeCamera(proj, emu),
                            projector=proj, turntable=table, settings=FAST, progress=False,
                            on_view=reboot_after_view_1)
        table.close()
        assert emu.lines.count("G1 X240.000 F600") == 1 and emu.resets_in_motion == 0
        assert "G92 X120.036" in emu.lines  # the angle the table stood at, declared after the reboot
    assert [v.turntable_deg for v in scan.views] == REACHED
    assert all(read_image(scan.frame_path(v, "white"))[0, 1] == round(v.turntable_deg / 5) for v in scan.views)
    assert read_capture_state(tmp_path / "s")["status"] == "complete"


def test_refused_move_keeps_the_angle_known(tmp_path, rig, patterns):
    from ringscan.hardware.emulators.grbl import EmulatedTurntable

    with EmulatedTurntable(time_scale=1000.0) as emu:
        proj = VirtualProjector(pattern_frames(patterns))
        table = GrblTurntable(emu.port, timeout_s=0.3)
        kw = dict(camera=ProbeCamera(proj, emu), projector=proj, turntable=table, settings=FAST, progress=False)
        emu.inject("error", on="G1 X240", code=33, times=100)
        with pytest.raises(CaptureError, match="stopped after 2 retries.*error:33 \\(invalid motion target\\)"):
            capture_scan(tmp_path / "s", rig=rig, patterns=patterns, views=3, **kw)
        assert emu.lines.count("G1 X240.000 F600") == 3 and emu.resets == 3
        assert read_capture_state(tmp_path / "s")["table"] == {"deg": 120.036, "moving_to": None, "known": True}
        assert resume_angle(tmp_path / "s") == 120.036  # the table did not move: no --table-at needed
        emu.faults.clear()
        scan = capture_scan(tmp_path / "s", resume=True, **kw)
        table.close()
    assert [v.turntable_deg for v in scan.views] == REACHED
    assert all(read_image(scan.frame_path(v, "white"))[0, 1] == round(v.turntable_deg / 5) for v in scan.views)


# ----------------------------------------------------------------------------- bad input


def test_bad_input(tmp_path, rig, patterns):
    proj, table, cam = _virtual(patterns)
    kw = dict(camera=cam, projector=proj, turntable=table, settings=FAST, progress=False)
    with pytest.raises(ValueError, match="needs the rig"):
        capture_scan(tmp_path / "a", rig=rig, patterns=patterns, **kw)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "x.txt").write_text("x")
    with pytest.raises(CaptureError, match="not an empty folder"):
        capture_scan(tmp_path / "b", rig=rig, patterns=patterns, views=2, **kw)
    with pytest.raises(CaptureError, match="nothing to resume"):
        capture_scan(tmp_path / "c", resume=True, **kw)
    other = small_patterns(bits=3)
    with pytest.raises(ValueError, match="projector"):
        capture_scan(tmp_path / "d", rig=rig, patterns=dataclasses.replace(patterns, width=800), views=2, **kw)
    assert not (tmp_path / "d").exists()  # nothing written for bad input
    with pytest.raises(CaptureError, match="holds 6 frames, the gray-rings codec needs 8"):
        capture_scan(tmp_path / "e", rig=rig, patterns=other, views=2, **kw)

    scan = capture_scan(tmp_path / "f", rig=rig, patterns=patterns, views=2, **kw)
    with pytest.raises(CaptureError, match="already holds a scan"):
        capture_scan(tmp_path / "f", rig=rig, patterns=patterns, views=2, **kw)
    with pytest.raises(CaptureError, match="rig given differs"):
        capture_scan(tmp_path / "f", rig=small_rig(160, 128), resume=True, **kw)
    with pytest.raises(CaptureError, match="2 views at .* ask for"):
        capture_scan(tmp_path / "f", views=4, resume=True, **kw)
    assert capture_scan(tmp_path / "f", resume=True, **kw).views == scan.views  # complete: nothing to do

    bad = dict(kw, camera=ProbeCamera(proj, table, width=64, height=48))
    with pytest.raises(CaptureError, match="camera delivers 64x48 frames, the rig's camera is 320x256"):
        capture_scan(tmp_path / "g", rig=rig, patterns=patterns, views=2, **bad)
    assert bad["camera"].grabs == 1  # not retried

    (tmp_path / "h").mkdir()
    (tmp_path / "h" / "scan.json").write_text(json.dumps({"format": "ringscan.scan/1"}))
    with pytest.raises(CaptureError, match="no capture.json"):
        capture_scan(tmp_path / "h", resume=True, **kw)


def test_settings_and_plan():
    s = CaptureSettings(retries=5, image_format="tiff")
    assert CaptureSettings.from_dict(s.to_dict()) == s
    with pytest.raises(FormatError, match="unknown key.*settle"):
        CaptureSettings.from_dict({"settle": 1})
    with pytest.raises(FormatError, match="retries"):
        CaptureSettings.from_dict({"retries": -1})
    with pytest.raises(ValueError, match="image_format"):
        CaptureSettings(image_format="jpg")
    with pytest.raises(ValueError, match="turntable_settle_s"):
        CaptureSettings(turntable_settle_s=float("nan"))
    assert plan_angles(8) == [0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0]
    assert plan_angles(7)[1] == 51.429 and plan_angles(3, 10.0, 5.0) == [5.0, 15.0, 25.0]
    with pytest.raises(ValueError):
        plan_angles(0)


def test_tiff_frames(tmp_path, rig, patterns):
    proj, table, cam = _virtual(patterns)
    scan = capture_scan(tmp_path / "s", camera=cam, projector=proj, turntable=table, rig=rig, patterns=patterns,
                        views=1, settings=dataclasses.replace(FAST, image_format="tiff"), progress=False)
    assert all(p.endswith(".tiff") for p in scan.views[0].frames.values())
    assert read_image(scan.frame_path(scan.views[0], "black"))[0, 0] == 2


class _Dies(ProbeCamera):
    """Stops the capture at grab ``at`` as a kill would (no word in capture.json)."""

    def __init__(self, *a, at, **kw):
        super().__init__(*a, **kw)
        self.at = at

    def _read(self):
        if self.grabs == self.at:
            raise SystemExit(9)
        return super()._read()


def test_packed_frames_are_appended_and_a_killed_capture_resumes(tmp_path, rig, patterns):
    from ringscan.pipeline.formats.frame_store import missing_frames, open_store
    from ringscan.pipeline.formats.scan import read_view_frames

    out = tmp_path / "s"
    proj, table, _ = _virtual(patterns)
    kw = dict(projector=proj, turntable=table, settings=dataclasses.replace(FAST, image_format="packed"),
              progress=False)
    with pytest.raises(SystemExit):
        capture_scan(out, camera=_Dies(proj, table, at=8), rig=rig, patterns=patterns, views=3, **kw)
    part = load_scan(out, allow_incomplete=True)
    assert [v.packed for v in part.views] == ["view_000/frames.zarr", "view_001/frames.zarr"]
    assert [len(v.frames) for v in part.views] == [6, 2]
    store = open_store(out / "view_001" / "frames.zarr")
    assert missing_frames(store) == frame_names(patterns)[2:]  # the frames so far, whole
    assert read_view_frames(part, part.views[1], list(part.views[1].frames))[:, 0, 0].tolist() == [1, 2]
    # a chunk written by a killed run but not listed is captured again; a killed writer's temporary goes
    (store.chunk_path(2)).parent.mkdir(parents=True)
    store.chunk_path(2).write_bytes(b"junk")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = store.chunk_path(2).parent / f".0.{int(dead.stdout)}-0123abcd.tmp"
    stale.write_bytes(b"half a chunk")
    scan = capture_scan(out, camera=ProbeCamera(proj, table), resume=True, **kw)
    assert json.loads((out / "scan.json").read_text())["format"] == "ringscan.scan/2"
    assert [len(v.frames) for v in scan.views] == [6, 6, 6] and all(v.packed for v in scan.views)
    for v in scan.views:
        frames = read_view_frames(scan, v)
        assert frames[:, 0, 0].tolist() == [j + 1 for j in range(6)]
        assert len(set(frames[:, 0, 1].tolist())) == 1  # every frame of a view at one table angle
    assert read_capture_state(out)["status"] == "complete"
    assert not stale.exists()


class _DeepProbe(ProbeCamera):
    """The probe as a 12-bit camera delivers it: 16-bit frames, values LSB-aligned
    (frame j's pixel (0, 0) = 60 (j + 1)), one pixel at ``peak``."""

    def __init__(self, projector, turntable, peak=4095, dtype=np.uint16):
        super().__init__(projector, turntable)
        self.peak, self.dtype = peak, dtype

    def _read(self):
        img = super()._read().astype(np.uint16) * 60
        img[5, 5] = self.peak
        return img.astype(self.dtype)


def test_frame_bits_is_written_to_scan_json_and_every_frame_checked_against_it(tmp_path, rig, patterns):
    from ringscan.pipeline.formats.scan import read_view_frame

    proj, table, _ = _virtual(patterns)
    kw = dict(projector=proj, turntable=table, settings=FAST, progress=False, rig=rig, patterns=patterns, views=2)
    scan = capture_scan(tmp_path / "a", camera=_DeepProbe(proj, table), frame_bits=12, **kw)
    assert scan.frame_bits == 12 and json.loads(scan.path.read_text())["frame_bits"] == 12
    v = scan.views[1]
    raw = read_image(scan.frame_path(v, "black"))  # stored as the camera gave it
    assert raw.dtype == np.uint16 and raw[0, 0] == 120 and raw[5, 5] == 4095
    scaled = read_view_frame(scan, v, "black")  # read scaled: 120 -> 120 << 4 | 120 >> 8
    assert scaled[0, 0] == (120 << 4 | 120 >> 8) and scaled[5, 5] == 65535
    # a resumed capture keeps it; another value is refused before anything moves
    assert capture_scan(tmp_path / "a", camera=_DeepProbe(proj, table), resume=True, frame_bits=12,
                        **{k: kw[k] for k in ("projector", "turntable", "settings", "progress")}).frame_bits == 12
    with pytest.raises(CaptureError, match="the capture being resumed has frame_bits 12, not 10"):
        capture_scan(tmp_path / "a", camera=_DeepProbe(proj, table), resume=True, frame_bits=10,
                     **{k: kw[k] for k in ("projector", "turntable", "settings", "progress")})
    # a frame above the range, or of the other depth, stops the capture at the first grab (not retried)
    cam = _DeepProbe(proj, table, peak=4096)
    with pytest.raises(CaptureError, match=r"camera delivers 16-bit frames holding 4096, but frame_bits "
                                           r"\(--frame-bits\) says 12 bits \(at most 4095\)"):
        capture_scan(tmp_path / "b", camera=cam, frame_bits=12, **kw)
    assert cam.grabs == 1
    cam = _DeepProbe(proj, table, peak=200, dtype=np.uint8)
    with pytest.raises(CaptureError, match=r"camera delivers 8-bit frames, but frame_bits \(--frame-bits\) says 12"):
        capture_scan(tmp_path / "c", camera=cam, frame_bits=12, **kw)
    with pytest.raises(CaptureError, match=r"camera delivers 16-bit frames, but frame_bits \(--frame-bits\) says 8"):
        capture_scan(tmp_path / "d", camera=_DeepProbe(proj, table), frame_bits=8, **kw)
    for bad in (7, 17, "12"):
        with pytest.raises(FormatError, match="frame_bits: expected a whole number"):
            capture_scan(tmp_path / "e", camera=_DeepProbe(proj, table), frame_bits=bad, **kw)
    assert not (tmp_path / "e").exists()
