"""The display projector from the command line, on the virtual screen: ``capture
--projector display:0``, ``calibrate latency`` and ``patterns --show``. The camera
spec is replaced by a camera that sees the virtual screen (no real camera here)."""

import json

import numpy as np
import pytest

from ringscan.hardware.capture.latency import read_rig_latency
from ringscan.hardware.capture.sequence import CaptureSettings, capture_scan, read_capture_state
from ringscan.hardware.devices.projector import VirtualProjector
from ringscan.hardware.devices.turntable import VirtualTurntable
from ringscan.hardware.emulators.virtual import VirtualCamera, make_virtual_rig
from ringscan.pipeline.formats.atomic import atomic_write_json
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.rig import save_rig
from ringscan.pipeline.simulate.virtual_rig import RenderSettings
from ringscan.tools import cmd_calibrate_light, cmd_capture, cmd_patterns
from ringscan.tools.cli import main
from tests.support.hardware_rig import pattern_frames, small_patterns, small_rig
from tests.support.virtual_screen import DelayedScreenCamera, ScreenPattern, virtual_screen

SEED = 5


@pytest.fixture(scope="module")
def screen():
    return virtual_screen()


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("rigfiles")
    save_rig(d / "rig.json", small_rig())
    atomic_write_json(d / "patterns.json", small_patterns().to_dict())
    return d


def _post_keys(*names):
    import pygame

    for n in names:
        pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=pygame.key.key_code(n)))


def test_calibrate_latency_writes_the_rig_and_capture_waits_for_it(tmp_path, screen, files, monkeypatch, capsys):
    rig = tmp_path / "rig.json"
    rig.write_bytes((files / "rig.json").read_bytes())
    cams = []

    def screen_camera(spec, **kw):
        assert spec == "cam0"
        cams.append(DelayedScreenCamera(screen, delay_s=2 / 60))
        return cams[-1]

    monkeypatch.setattr(cmd_calibrate_light, "open_camera", screen_camera)
    rc = main(["calibrate", "latency", "--projector", "display:0", "--camera", "cam0", "--rig", str(rig),
               "--trials", "2", "--rest", "0.1", "--max-delay", "0.15", "--report", str(tmp_path / "lat.json")])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "updated light.latency_s" in out and "0.0 ms: old old" in out
    report = json.loads((tmp_path / "lat.json").read_text())
    assert abs(report["measured_s"] - 2 / 60) <= 1 / 60
    assert read_rig_latency(rig) == pytest.approx(report["measured_s"] + 1 / 60, abs=1e-4)

    # the capture takes the rig's latency as the wait after each frame
    # any camera will do here (what is checked is the wait): the cheapest scene, a sharp lens
    virtual_rig = make_virtual_rig(small_rig(), "plane", device="cpu",
                                   settings=RenderSettings(supersample=1, defocus_px=0.0))
    frames = list(pattern_frames(small_patterns()).values())
    monkeypatch.setattr(cmd_capture, "open_camera",
                        lambda spec, **kw: VirtualCamera(virtual_rig, ScreenPattern(screen, frames), None, seed=SEED))
    rc = main(["capture", "--rig", str(rig), "--patterns", str(files / "patterns.json"), "--views", "1",
               "--out", str(tmp_path / "scan"), "--projector", "display:0", "--camera", "cam0", "--no-progress"])
    assert rc == 0
    state = read_capture_state(tmp_path / "scan")
    assert state["settings"]["projector_settle_s"] == read_rig_latency(rig)

    # the same frames as the virtual projector's
    proj = VirtualProjector(frames)
    ref = capture_scan(tmp_path / "ref", camera=VirtualCamera(virtual_rig, proj, None, seed=SEED), projector=proj,
                       turntable=VirtualTurntable(), rig=small_rig(), patterns=small_patterns(), views=1,
                       settings=CaptureSettings(projector_settle_s=0.0, turntable_settle_s=0.0), progress=False)
    for n in frame_names(small_patterns()):
        assert np.array_equal(read_image(tmp_path / "scan" / "view_000" / f"{n}.png"), read_image(ref.frame_path(
            ref.views[0], n))), n


def test_capture_projector_option_errors(tmp_path, files, capsys):
    rc = main(["capture", "--rig", str(files / "rig.json"), "--patterns", str(files / "patterns.json"), "--views",
               "1", "--out", str(tmp_path / "s"), "--projector", "display:", "--camera", "0"])
    assert rc == 2 and "name the display after 'display:'" in capsys.readouterr().err
    rc = main(["capture", "--rig", str(files / "rig.json"), "--patterns", str(files / "patterns.json"), "--views",
               "1", "--out", str(tmp_path / "s"), "--projector", "/dev/null", "--camera", "0", "--centre"])
    assert rc == 2 and "--centre only applies with --projector display" in capsys.readouterr().err


def test_patterns_show_steps_through_the_frames_by_hand(screen, monkeypatch, capsys):
    real = cmd_patterns.run_viewer

    def viewer(proj, **kw):
        _post_keys("right", "right", "left", "q")  # the window is open: the keys reach it
        return real(proj, **kw)

    monkeypatch.setattr(cmd_patterns, "run_viewer", viewer)
    rc = main(["patterns", "--codec", "gray-rings", "--bits", "2", "--sector-bits", "0", "--pitch", "40",
               "--show", "0"])
    out = capsys.readouterr().out
    assert rc == 0
    assert out.splitlines()[1:] == ["  white", "  black", "  gray_0", "  black"]


def test_patterns_show_refuses_a_frame_size_the_display_does_not_have(screen, capsys):
    rc = main(["patterns", "--width", "800", "--height", "600", "--show"])
    err = capsys.readouterr().err
    assert rc == 1 and "frames are 800x600 but the display is 1024x768" in err and len(err.splitlines()) == 1
    assert main(["patterns"]) == 2
    assert "give --out DIR" in capsys.readouterr().err
