"""The serial pattern projector driver against the emulated projector (pyserial on a pty)."""

import time

import numpy as np
import pytest

import ringscan.hardware.emulators.projector as emulate
from ringscan.hardware.devices.projector import SerialProjector, VirtualProjector
from ringscan.hardware.emulators.projector import EmulatedProjector
from ringscan.hardware.errors import ProjectorCommandError, ProjectorDisconnected, ProjectorError, ProjectorTimeout

NAMES = ["white", "black", "gray_0", "gray_0_inv"]


def _frames(n=4, shape=(6, 8)):
    return {NAMES[i]: np.full(shape, 10 * (i + 1), np.uint8) for i in range(n)}


@pytest.fixture
def emu(tmp_path):
    e = EmulatedProjector(_frames(), link_path=tmp_path / "pj")
    yield e
    e.close()


def test_exact_bytes_and_frames_shown(emu):
    p = SerialProjector(emu.port, expect_names=NAMES, timeout_s=0.5)
    assert (p.frame_count, p.width, p.height, p.names) == (4, 8, 6, NAMES)
    p.show(2)
    assert emu.current_index == 2 and emu.current_frame()[0, 0] == 30
    p.show(0)
    p.blank()
    assert emu.current_index == -1 and emu.current_frame().max() == 0
    p.close()
    assert bytes(emu.received) == b"\nHELLO\nNAME 0\nNAME 1\nNAME 2\nNAME 3\nSHOW 2\nSHOW 0\nBLANK\n"


def test_show_waits_for_the_acknowledgement(tmp_path):
    with EmulatedProjector(_frames(), latency_s=0.1) as e:
        p = SerialProjector(e.port, timeout_s=0.5)
        t0 = time.monotonic()
        p.show(3)
        assert time.monotonic() - t0 >= 0.1 and e.current_index == 3
        p.close()


def test_error_reply(emu):
    p = SerialProjector(emu.port, timeout_s=0.5)
    emu.inject("error", on="SHOW", code=3)
    with pytest.raises(ProjectorCommandError) as ei:
        p.show(1)
    assert ei.value.code == 3 and "display fault" in str(ei.value) and ei.value.retryable
    p.show(1)
    assert emu.current_index == 1
    p.close()


def test_index_out_of_range_is_refused_without_sending(emu):
    p = SerialProjector(emu.port, timeout_s=0.5)
    n = len(emu.received)
    with pytest.raises(ProjectorCommandError) as ei:
        p.show(4)
    assert ei.value.code == 2 and not ei.value.retryable and len(emu.received) == n
    p.close()


def test_frame_count_and_names_are_checked(emu):
    with pytest.raises(ProjectorError, match="holds 4 frames, the pattern set has 3") as ei:
        SerialProjector(emu.port, expect_names=NAMES[:3], timeout_s=0.5)
    assert not ei.value.retryable
    with pytest.raises(ProjectorError, match="frame 2 on the device is 'gray_0', the pattern set expects 'gray_1'"):
        SerialProjector(emu.port, expect_names=["white", "black", "gray_1", "gray_1_inv"], timeout_s=0.5)


def test_device_without_names_checks_the_count_only(tmp_path):
    with EmulatedProjector(_frames(), names_supported=False) as e:
        p = SerialProjector(e.port, expect_names=["a", "b", "c", "d"], timeout_s=0.5)
        assert p.names is None and p.frame_count == 4
        p.close()


def test_timeout_then_resync_drops_the_late_ack(tmp_path):
    with EmulatedProjector(_frames(), latency_s=0.3) as e:
        p = SerialProjector(e.port, timeout_s=0.5)
        p.timeout_s = 0.1
        with pytest.raises(ProjectorTimeout, match="SHOW 1"):
            p.show(1)
        p.timeout_s = 1.0
        p.recover()  # HELLO: everything before its reply (the late OK 1) is dropped
        p.show(2)
        assert e.current_index == 2
        assert e.lines[-3:] == ["SHOW 1", "HELLO", "SHOW 2"]
        p.close()


def test_silent_and_vanished_devices(tmp_path):
    with EmulatedProjector(_frames(), link_path=tmp_path / "pj") as e:
        p = SerialProjector(e.port, timeout_s=0.3)
        e.inject("silent", on="SHOW")
        t0 = time.monotonic()
        with pytest.raises(ProjectorTimeout):
            p.show(0)
        assert 0.25 < time.monotonic() - t0 < 1.0
        e.inject("vanish", on="SHOW")
        with pytest.raises(ProjectorDisconnected, match="connection lost"):
            p.show(0)
        with pytest.raises(ProjectorDisconnected, match="cannot open"):
            p.recover()
        e.replug()
        p.recover()
        p.show(3)
        assert e.current_index == 3
        p.close()


def test_protocol_version_is_checked(emu, monkeypatch):
    monkeypatch.setattr(emulate, "PROTOCOL_VERSION", 2)
    with pytest.raises(ProjectorError, match="protocol version 2") as ei:
        SerialProjector(emu.port, timeout_s=0.5)
    assert not ei.value.retryable


def test_no_device_answers(tmp_path):
    from ringscan.hardware.emulators.grbl import EmulatedTurntable

    with EmulatedTurntable() as t:  # a GRBL board answers HELLO with error:..., never the identify line
        with pytest.raises(ProjectorTimeout, match="HELLO"):
            SerialProjector(t.port, timeout_s=0.3, boot_timeout_s=0.3)


def test_virtual_projector():
    p = VirtualProjector(_frames())
    assert p.frame_count == 4 and p.current_index == -1 and p.current_frame().max() == 0
    p.show(1)
    assert p.current_frame()[0, 0] == 20 and p.shown == [1]
    with pytest.raises(ProjectorCommandError):
        p.show(9)
    p.blank()
    assert p.current_index == -1
    with pytest.raises(ValueError, match="2D uint8"):
        VirtualProjector([np.zeros((4, 4), np.float32)])
    with pytest.raises(ValueError, match="frame 1"):
        VirtualProjector([np.zeros((4, 4), np.uint8), np.zeros((5, 4), np.uint8)])
    with pytest.raises(ValueError, match="at least one"):
        VirtualProjector([])
