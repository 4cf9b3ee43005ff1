"""The display projector on a virtual screen (Xvfb), read back by independent code
(mss: XGetImage), byte for byte."""

import subprocess
import sys
import time

import numpy as np
import pytest

from ringscan.hardware.devices.display import (
    DisplayInfo,
    DisplayProjector,
    choose_display,
    list_displays,
    parse_display_spec,
    run_viewer,
)
from ringscan.hardware.errors import ProjectorCommandError, ProjectorError
from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.patterns import CODECS, frame_names, parse_patterns
from tests.support.virtual_screen import SCREEN_H, SCREEN_W, ScreenReader, virtual_screen

CODEC_PARAMS = {
    "rings": {"count": 9, "line_width": 3.0, "pitch": 40.0},
    # every kind of frame (white, black, gray, sector, phase, each inverse) at the fewest bits
    "gray-rings": {"bits": 2, "sector_bits": 1, "pitch": 40.0},
    "phase-rings": {"bits": 1, "sector_bits": 1, "steps": 3, "pitch": 40.0},
}


def _spec(codec, width=SCREEN_W, height=SCREEN_H):
    return parse_patterns({"codec": codec, "width": width, "height": height,
                           "center": [(width - 1) / 2, (height - 1) / 2], "rho0": 8.0, **CODEC_PARAMS[codec]})


@pytest.fixture(scope="module")
def screen():
    """The virtual screen's X display name (one Xvfb for the session)."""
    return virtual_screen()


@pytest.fixture()
def reader(screen):
    r = ScreenReader(screen)
    yield r
    r.close()


def _post(*events):
    import pygame

    for ev in events:
        pygame.event.post(ev)


def _key(name):
    import pygame

    return pygame.event.Event(pygame.KEYDOWN, key=pygame.key.key_code(name))


def test_codec_list_is_covered():
    assert set(CODEC_PARAMS) == set(CODECS)


@pytest.mark.parametrize("codec", CODECS)
def test_every_frame_of_every_codec_is_on_screen_byte_exact(reader, codec):
    spec = _spec(codec)
    names = frame_names(spec)
    frames = [render_frame(spec, n) for n in names]
    # The antialiased frames hold grey levels; make sure some do (not only 0 and 255).
    assert any(len(np.unique(f)) > 2 for f in frames)
    with DisplayProjector(frames, display=0) as proj:
        assert proj.display.index == 0 and (proj.display.width, proj.display.height) == (SCREEN_W, SCREEN_H)
        assert not reader.rgb().any()  # opens black
        for i, name in enumerate(names):
            proj.show(i)
            got = reader.rgb()  # read at once: show() returns only once the frame is on screen
            for c in range(3):
                assert np.array_equal(got[:, :, c], frames[i]), f"{codec} frame {name}, channel {c}"
        proj.blank()
        assert not reader.rgb().any()
        assert proj.shown == list(range(len(names)))


def test_every_grey_level_is_exact(reader):
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (SCREEN_H, SCREEN_W), dtype=np.uint8) for _ in range(3)]
    frames.append(np.broadcast_to(np.arange(256, dtype=np.uint8).repeat(4), (SCREEN_H, SCREEN_W)).copy())
    with DisplayProjector(frames, display="0") as proj:
        for i in (3, 0, 2, 1, 0):
            proj.show(i)
            assert np.array_equal(reader.grey(), frames[i])
            assert np.array_equal(reader.rgb(), np.repeat(frames[i][:, :, None], 3, axis=2))


def test_a_frame_of_another_size_is_refused(screen):
    small = [np.full((600, 800), 200, np.uint8)]
    with pytest.raises(ProjectorError, match=r"frames are 800x600 but the display is 1024x768.*--centre") as e:
        DisplayProjector(small, display=0)
    assert not e.value.retryable and "display 0" in str(e.value)
    big = [np.zeros((800, 1280), np.uint8)]
    with pytest.raises(ProjectorError, match=r"1280x800, larger than the display's 1024x768"):
        DisplayProjector(big, display=0, centre=True)


def test_centre_shows_a_smaller_frame_in_the_middle_on_black(reader):
    rng = np.random.default_rng(5)
    frame = rng.integers(1, 256, (600, 800), dtype=np.uint8)  # no zeros: the border must be the only black
    with DisplayProjector([frame], display=0, centre=True) as proj:
        proj.show(0)
        got = reader.grey()
    y0, x0 = (SCREEN_H - 600) // 2, (SCREEN_W - 800) // 2
    assert np.array_equal(got[y0:y0 + 600, x0:x0 + 800], frame)
    border = got.copy()
    border[y0:y0 + 600, x0:x0 + 800] = 0
    assert not border.any()


def test_displays_are_listed_and_chosen_by_index_or_name(screen, reader):
    displays = list_displays()
    assert len(displays) == 1
    d = displays[0]
    assert (d.index, d.x, d.y, d.width, d.height) == (0, 0, 0, SCREEN_W, SCREEN_H)
    assert d.name  # SDL's name for it
    frame = np.full((SCREEN_H, SCREEN_W), 77, np.uint8)
    with DisplayProjector([frame], display=d.name.upper()) as proj:
        proj.show(0)
        assert proj.display == d
        assert (reader.grey() == 77).all()
    with pytest.raises(ProjectorError, match=r"there is no display 1; the displays are: 0: "):
        DisplayProjector([frame], display=1)


def test_choose_display_by_index_name_or_part_of_a_name():
    ds = [DisplayInfo(0, "DELL U2720Q", 0, 0, 3840, 2160, 60.0), DisplayInfo(1, "EPSON PJ", 3840, 0, 1920, 1080, 60.0),
          DisplayInfo(2, "EPSON PJ 2", 5760, 0, 1024, 768, 0.0)]
    assert choose_display(ds, 1) is ds[1]
    assert choose_display(ds, " 2 ") is ds[2]
    assert choose_display(ds, "epson pj") is ds[1]  # the whole name wins over a part of another
    assert choose_display(ds, "dell") is ds[0]
    with pytest.raises(ProjectorError, match=r"several displays match 'EPSON'.*1: 'EPSON PJ' 1920x1080 at \(3840, 0\)"):
        choose_display(ds, "EPSON")
    with pytest.raises(ProjectorError, match=r"no display is called 'HDMI-1'; the displays are: 0: 'DELL U2720Q'"):
        choose_display(ds, "HDMI-1")
    with pytest.raises(ProjectorError, match="there is no display 3"):
        choose_display(ds, 3)
    with pytest.raises(ValueError):
        choose_display(ds, True)


def test_projector_option_values():
    assert parse_display_spec("display") == 0
    assert parse_display_spec("display:1") == 1
    assert parse_display_spec("display:HDMI-1") == "HDMI-1"
    assert parse_display_spec("/dev/ttyACM0") is None and parse_display_spec("displayport") is None
    with pytest.raises(ValueError, match="name the display"):
        parse_display_spec("display:")


def test_show_waits_for_the_latency_and_refuses_a_bad_index(screen):
    frames = [np.zeros((SCREEN_H, SCREEN_W), np.uint8), np.full((SCREEN_H, SCREEN_W), 255, np.uint8)]
    with DisplayProjector(frames, display=0, latency_s=0.12) as proj:
        t0 = time.monotonic()
        proj.show(1)
        t1 = time.monotonic()
        assert t1 - proj.last_swap_s >= 0.12 and proj.last_swap_s >= t0
        with pytest.raises(ProjectorCommandError, match=r"frame index 2 out of range \(0..1\)") as e:
            proj.show(2)
        assert e.value.code == 2 and not e.value.retryable
    with pytest.raises(ValueError, match="latency_s"):
        DisplayProjector(frames, latency_s=-1.0, open=False)


def test_keys_are_handled_between_frames_and_drive_the_viewer(screen, reader):
    frames = [np.full((SCREEN_H, SCREEN_W), 10 * (i + 1), np.uint8) for i in range(4)]
    with DisplayProjector(frames, display=0) as proj:
        proj.show(0)
        proj.poll_keys()
        _post(_key("x"))
        time.sleep(0.3)  # no call into the projector: its SDL thread handles the events
        assert proj.poll_keys() == ["x"]

        seen_on_screen = []
        _post(*[_key(k) for k in ("right", "right", "left", "b", "space", "end", "right", "home", "escape")])
        shown = run_viewer(proj, start=0, on_show=lambda i: seen_on_screen.append(int(reader.grey()[0, 0])))
    assert shown == [0, 1, 2, 1, -1, 1, 3, 0]
    assert seen_on_screen == [0 if i < 0 else 10 * (i + 1) for i in shown]


def test_a_closed_window_is_an_error_that_recover_cures(screen, reader):
    import pygame

    frames = [np.full((SCREEN_H, SCREEN_W), 99, np.uint8)]
    with DisplayProjector(frames, display=0) as proj:
        _post(pygame.event.Event(pygame.QUIT))
        time.sleep(0.3)
        assert proj.window_closed
        with pytest.raises(ProjectorError, match="window was closed") as e:
            proj.show(0)
        assert e.value.retryable
        proj.recover()
        proj.show(0)
        assert (reader.grey() == 99).all()
    assert not proj.is_open


def test_importing_ringscan_hardware_does_not_load_pygame():
    code = ("import sys, ringscan.hardware, ringscan.hardware.devices.display; "
            "assert 'pygame' not in sys.modules, 'pygame loaded'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_without_pygame_the_error_says_how_to_install_it():
    code = ("import sys; sys.modules['pygame'] = None\n"
            "from ringscan.hardware.devices.display import list_displays\n"
            "from ringscan.hardware.errors import ProjectorError\n"
            "try:\n    list_displays()\nexcept ProjectorError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True, timeout=120).stdout
    assert "pip install pygame-ce (or '.[display]' in ringscan's source tree)" in out
