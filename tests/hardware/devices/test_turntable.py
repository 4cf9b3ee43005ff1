"""The GRBL turntable driver against the emulated controller, through pyserial on a pty."""

import time

import numpy as np
import pytest
import serial

from ringscan.hardware.devices.turntable import GrblTurntable, VirtualTurntable, format_angle, parse_status
from ringscan.hardware.emulators.grbl import EmulatedTurntable
from ringscan.hardware.emulators.projector import EmulatedProjector
from ringscan.hardware.errors import TurntableAlarm, TurntableCommandError, TurntableDisconnected, TurntableTimeout

FAST = dict(timeout_s=0.5, poll_s=0.005, boot_timeout_s=0.5)


@pytest.fixture
def emu(tmp_path):
    e = EmulatedTurntable(link_path=tmp_path / "tt", time_scale=200.0)
    yield e
    e.close()


def _no_polls(b: bytes) -> bytes:
    return bytes(b).replace(b"?", b"")


# ----------------------------------------------------------------------------- exact bytes


def test_connect_and_move_send_exact_bytes(emu):
    tt = GrblTurntable(emu.port, feed_deg_per_min=600, **FAST)
    assert (tt.firmware, tt.version) == ("Grbl", "1.1h")
    tt.move_to(45.0)
    tt.move_to(-30.5)
    tt.close()
    assert _no_polls(emu.received) == (b"\x18G90\nG92 X0.000\n"
                                       b"G1 X45.000 F600\nG4 P0\n"
                                       b"G1 X-30.500 F600\nG4 P0\n")
    # status queries: one at connect, polls during each move, one Idle check after each
    assert emu.received.count(b"?") >= 3
    assert emu.lines == ["G90", "G92 X0.000", "G1 X45.000 F600", "G4 P0", "G1 X-30.500 F600", "G4 P0"]


def test_alarm_on_reset_is_unlocked_and_horus_gets_motor_enable(tmp_path):
    with EmulatedTurntable(flavor="horus", alarm_on_reset=True, time_scale=200.0) as e:
        tt = GrblTurntable(e.port, feed_deg_per_min=1200, direction=-1, position_deg=10.0, **FAST)
        assert (tt.firmware, tt.version) == ("Horus", "0.2")
        assert e.motor_enabled
        tt.move_to(40.0)
        tt.enable_motor(False)
        tt.close()
        assert _no_polls(e.received) == (b"\x18$X\nG90\nG92 X-10.000\nM17\n"
                                         b"G1 X-40.000 F1200\nG4 P0\nM18\n")
        assert not e.motor_enabled
        # direction -1: the controller turned by -30, i.e. the object by +30 in the scan's sense
        assert e.angle_deg == pytest.approx(-30.0)


def test_grbl_has_no_motor_enable(emu):
    tt = GrblTurntable(emu.port, **FAST)
    tt.enable_motor(True)  # stock GRBL answers error:20 to M17; the driver must not send it
    tt.close()
    assert b"M17" not in emu.received


# ----------------------------------------------------------------------------- motion


def test_move_returns_only_when_idle(tmp_path):
    # 90 deg at 600 deg/min = 9 s real, 0.15 s at time scale 60
    with EmulatedTurntable(time_scale=60.0) as e:
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        t0 = time.monotonic()
        tt.move_to(90.0)
        dt = time.monotonic() - t0
        assert dt >= 0.15
        assert e.angle_deg == 90.0 and not e.moving
        assert tt.position_deg == 90.0 and tt.last_status.state == "Idle"
        assert tt.last_status.x == pytest.approx(90.0)
        assert e.received.count(b"?") >= 5  # polled during the move
        tt.close()


def test_emulator_reports_run_during_a_move_and_idle_after(emu):
    with serial.Serial(emu.port, 115200, timeout=0.5) as s:
        s.write(b"\x18")
        assert s.readline() == b"\r\n" and s.readline().startswith(b"Grbl 1.1h")
        t0 = time.monotonic()
        s.write(b"G1 X90 F60\n")           # 90 deg at 60 deg/min, 200 times faster: 0.45 s
        assert s.readline() == b"ok\r\n"
        s.write(b"?")
        run = parse_status(s.readline().decode())
        assert run.state == "Run" and 0 <= run.x < 90
        while True:
            s.write(b"?")
            st = parse_status(s.readline().decode())
            if st.state != "Run" or time.monotonic() - t0 > 5:
                break
            assert 0 <= st.x < 90
        assert st.state == "Idle" and st.x == 90.0 and time.monotonic() - t0 >= 0.45
        s.write(b"G1 X10\n")               # G1 keeps its feed rate (modal)
        assert s.readline() == b"ok\r\n"
        s.write(b"G4 P0\n")                # ok only once the move is over
        assert s.readline() == b"ok\r\n" and not emu.moving and emu.angle_deg == 10.0
        s.write(b"G7\n")
        assert s.readline() == b"error:20\r\n"


# ----------------------------------------------------------------------------- faults


def test_error_reply_is_a_command_error_with_the_code(emu):
    tt = GrblTurntable(emu.port, **FAST)
    emu.inject("error", on="G1", code=33)
    with pytest.raises(TurntableCommandError) as ei:
        tt.move_to(45.0)
    e = ei.value
    assert e.code == 33 and "invalid motion target" in str(e) and emu.port in str(e)
    assert e.position_known and e.retryable and tt.position_deg == 0.0 and emu.angle_deg == 0.0
    tt.move_to(45.0)  # the next try goes through
    assert emu.angle_deg == 45.0
    tt.close()


def test_horus_text_error_has_no_code():
    with EmulatedTurntable(flavor="horus", time_scale=200.0) as e:
        tt = GrblTurntable(e.port, **FAST)
        e.inject("error", on="G1", code=2)
        with pytest.raises(TurntableCommandError) as ei:
            tt.move_to(10.0)
        assert ei.value.code is None and "Bad number format" in str(ei.value)
        tt.close()


def test_alarm_mid_move_loses_the_position(tmp_path):
    with EmulatedTurntable(time_scale=20.0) as e:  # 60 deg: 0.3 s
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        e.inject("alarm", on="G1", code=1, at_fraction=0.5)
        with pytest.raises(TurntableAlarm) as ei:
            tt.move_to(60.0)
        assert ei.value.code == 1 and "hard limit" in str(ei.value)
        assert not ei.value.position_known and not ei.value.retryable
        assert 20.0 < e.angle_deg < 40.0  # stopped half way
        tt.close()


def test_vanished_port_mid_move_is_disconnected_fast(tmp_path):
    with EmulatedTurntable(link_path=tmp_path / "tt", time_scale=20.0) as e:
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        e.inject("vanish", on="G1", at_fraction=0.3)
        t0 = time.monotonic()
        with pytest.raises(TurntableDisconnected) as ei:
            tt.move_to(60.0)
        assert time.monotonic() - t0 < 0.5  # seen at once, not after a timeout
        assert not ei.value.position_known and "connection lost" in str(ei.value)
        assert not (tmp_path / "tt").exists()
        time.sleep(0.3)
        assert e.angle_deg == 60.0  # the board finished its move without the host
        # plugged back: a fresh controller; recover() declares the last confirmed angle
        e.replug()
        tt.recover()
        assert e.lines[-1] == "G92 X0.000"
        tt.close()


def test_silent_controller_times_out(emu):
    tt = GrblTurntable(emu.port, **FAST)
    emu.inject("silent", on="G1")
    t0 = time.monotonic()
    with pytest.raises(TurntableTimeout) as ei:
        tt.move_to(10.0)
    assert 0.4 < time.monotonic() - t0 < 1.5
    assert "no 'ok'" in str(ei.value)
    tt.close()


def test_silence_during_a_move_is_seen_within_the_reply_timeout(tmp_path):
    with EmulatedTurntable(time_scale=1.0) as e:  # a real-speed 360 deg move: 36 s
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        e.inject("silent", on="?", times=10 ** 6, skip=0)
        t0 = time.monotonic()
        with pytest.raises(TurntableTimeout) as ei:
            tt.move_to(360.0)
        assert time.monotonic() - t0 < 1.5
        assert "silent" in str(ei.value) and not ei.value.position_known
        tt.close()


def test_controller_resetting_by_itself_is_reported(emu):
    tt = GrblTurntable(emu.port, **FAST)
    emu.inject("reset", on="G1")
    with pytest.raises(TurntableDisconnected, match="reset by itself"):
        tt.move_to(10.0)
    tt.close()


def test_wrong_device_gives_no_banner(tmp_path):
    with EmulatedProjector([np.zeros((4, 4), np.uint8)]) as p:
        with pytest.raises(TurntableTimeout, match="banner"):
            GrblTurntable(p.port, **FAST)


def test_missing_port(tmp_path):
    with pytest.raises(TurntableDisconnected, match="cannot open"):
        GrblTurntable(str(tmp_path / "nope"), **FAST)


def test_bad_arguments():
    for kw in (dict(feed_deg_per_min=0), dict(direction=2), dict(motor_enable="x"), dict(timeout_s=0)):
        with pytest.raises(ValueError):
            GrblTurntable("unused", connect=False, **kw)


# ----------------------------------------------------------------------------- parsing


def test_parse_status_both_dialects():
    s = parse_status("<Run|MPos:12.500,0.000,0.000|FS:600,0|WCO:2.500,0.000,0.000>")
    assert (s.state, s.x) == ("Run", 10.0)
    s = parse_status("<Idle|WPos:7.000,0.000,0.000|FS:0,0>")
    assert (s.state, s.x) == ("Idle", 7.0)
    s = parse_status("<Hold:0|MPos:1.000,0.000,0.000|FS:0,0>")
    assert (s.state, s.x) == ("Hold", 1.0)
    s = parse_status("<Idle,MPos:5.000,0.000,0.000,WPos:3.000,0.000,0.000>")
    assert (s.state, s.x) == ("Idle", 3.0)
    assert parse_status("<Alarm>").state == "Alarm" and parse_status("<Alarm>").x is None
    assert parse_status("ok") is None and parse_status("[MSG:x]") is None


def test_format_angle():
    assert format_angle(-0.0001) == "0.000" and format_angle(45) == "45.000" and format_angle(-1.23456) == "-1.235"


def test_virtual_turntable():
    t = VirtualTurntable(5.0)
    t.move_to(90.0)
    t.set_position(0.0)
    t.move_to(45.0)
    assert t.moves == [90.0, 45.0] and t.angle_deg == t.position_deg == 45.0
