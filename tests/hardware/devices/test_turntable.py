"""The GRBL turntable driver against the emulated controller, through pyserial on a pty.

The emulator behaves like GRBL 1.1h in the cases that matter here (whole motor steps
at $100 = 8.889 steps/deg, WCO in only some status reports, ALARM:3 on a reset in
motion, "Reset to continue" after a limit alarm, feed hold, the $110 rate cap, a lost
``ok``); the tests of the emulator itself talk to it byte by byte.
"""

import time

import numpy as np
import pytest
import serial

from ringscan.hardware.devices.grbl import MIN_POLL_S, GrblTurntable, format_angle, parse_status
from ringscan.hardware.devices.turntable import VirtualTurntable
from ringscan.hardware.emulators.grbl import EmulatedTurntable
from ringscan.hardware.emulators.projector import EmulatedProjector
from ringscan.hardware.errors import (
    TurntableAlarm,
    TurntableCommandError,
    TurntableDisconnected,
    TurntableError,
    TurntableTimeout,
)

FAST = dict(timeout_s=0.5, boot_timeout_s=0.5)
STEP = 1 / 8.889  # the emulator's motor step, degrees


def steps(deg):
    """Where GRBL's steps land for a target: round(deg * $100) / $100, to 0.001 as reported."""
    return round(int(np.floor(abs(deg) * 8.889 + 0.5)) * np.sign(deg) / 8.889, 3) + 0.0


@pytest.fixture
def emu(tmp_path):
    e = EmulatedTurntable(link_path=tmp_path / "tt", time_scale=200.0)
    yield e
    e.close()


def _no_polls(b: bytes) -> bytes:
    return bytes(b).replace(b"?", b"")


class _Raw:
    """A host that talks to the emulator byte by byte (another program, or the firmware's own tests)."""

    def __init__(self, port):
        self.s = serial.Serial(port, 115200, timeout=0.5)
        self.wco = None

    def send(self, data: bytes):
        self.s.write(data)

    def line(self) -> str:
        return self.s.readline().decode().strip()

    def lines_until(self, pred, limit=10):
        out = []
        for _ in range(limit):
            out.append(self.line())
            if pred(out[-1]):
                return out
        raise AssertionError(out)

    def status(self):
        self.s.write(b"?")
        st = parse_status(self.line(), wco=self.wco)
        if st.wco is not None:
            self.wco = st.wco
        return st

    def close(self):
        self.s.close()


# ----------------------------------------------------------------------------- exact bytes


def test_connect_and_move_send_exact_bytes(emu):
    tt = GrblTurntable(emu.port, feed_deg_per_min=600, **FAST)
    assert (tt.firmware, tt.version) == ("Grbl", "1.1h")
    assert tt.steps_per_deg == 8.889 and tt.max_rate_deg_per_min == 3000.0  # read with $$
    tt.move_to(45.0)
    tt.move_to(-30.5)
    tt.close()
    assert emu.received.startswith(b"?\x18")  # the state is asked before the reset
    assert _no_polls(emu.received) == (b"\x18$$\nG90\nG92 X0.000\n"
                                       b"G1 X45.000 F600\nG4 P0\n"
                                       b"G1 X-30.500 F600\nG4 P0\n")
    assert emu.lines == ["$$", "G90", "G92 X0.000", "G1 X45.000 F600", "G4 P0", "G1 X-30.500 F600", "G4 P0"]


def test_homing_lock_is_unlocked_and_horus_gets_motor_enable(tmp_path):
    with EmulatedTurntable(flavor="horus", homing_lock=True, time_scale=200.0) as e:
        tt = GrblTurntable(e.port, feed_deg_per_min=1200, direction=-1, position_deg=10.0, **FAST)
        assert (tt.firmware, tt.version) == ("Horus", "0.2") and tt.position_known
        assert e.motor_enabled and tt.max_rate_deg_per_min == 3000.0  # Horus' "$110=3000.000 (x max rate, ...)"
        tt.move_to(40.0)
        tt.enable_motor(False)
        tt.close()
        assert _no_polls(e.received) == (b"\x18$$\n$X\nG90\nM17\nG92 X-10.000\n"
                                         b"G1 X-40.000 F1200\nG4 P0\nM18\n")
        assert not e.motor_enabled
        # direction -1: the controller turned by -30, i.e. the object by +30 in the scan's sense
        assert e.angle_deg == steps(-30.0)
        assert tt.position_deg == pytest.approx(10.0 - steps(-30.0), abs=1e-9)  # the angle reached


def test_grbl_has_no_motor_enable(emu):
    tt = GrblTurntable(emu.port, **FAST)
    tt.enable_motor(True)  # stock GRBL answers error:20 to M17; the driver must not send it
    tt.close()
    assert b"M17" not in emu.received


# ----------------------------------------------------------------------------- motion


def test_move_returns_only_when_idle(tmp_path):
    # 90 deg at 600 deg/min = 9 s real, 0.6 s at time scale 15
    with EmulatedTurntable(time_scale=15.0) as e:
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        n0 = e.received.count(b"?")
        t0 = time.monotonic()
        tt.move_to(90.0)
        dt = time.monotonic() - t0
        assert dt >= 0.6
        assert e.angle_deg == steps(90.0) and not e.moving
        assert tt.position_deg == steps(90.0) and tt.last_status.state == "Idle"
        assert e.received.count(b"?") - n0 >= 3  # polled during the move
        tt.close()


def test_emulator_reports_run_during_a_move_and_idle_after(emu):
    raw = _Raw(emu.port)
    raw.send(b"\x18")
    assert raw.line() == "" and raw.line().startswith("Grbl 1.1h")
    t0 = time.monotonic()
    raw.send(b"G1 X90 F60\n")           # 90 deg at 60 deg/min, 200 times faster: 0.45 s
    assert raw.line() == "ok"
    run = raw.status()
    assert run.state == "Run" and 0 <= run.x < 90
    while True:
        st = raw.status()
        if st.state != "Run" or time.monotonic() - t0 > 5:
            break
        assert 0 <= st.x < 90
    assert st.state == "Idle" and st.x == steps(90.0) and time.monotonic() - t0 >= 0.45
    raw.send(b"G1 X10\n")               # G1 keeps its feed rate (modal)
    assert raw.line() == "ok"
    raw.send(b"G4 P0\n")                # ok only once the move is over
    assert raw.line() == "ok" and not emu.moving and emu.angle_deg == steps(10.0)
    raw.send(b"G7\n")
    assert raw.line() == "error:20"
    raw.close()


def test_emulator_sends_wco_only_now_and_then_as_grbl_does(emu):
    """GRBL 1.1: WCO in the first report after a reset or a G92, then every 10th report
    when idle (every 30th when busy); the override values (Ov) in the report after it."""
    raw = _Raw(emu.port)
    raw.send(b"\x18")
    raw.lines_until(lambda s: s.startswith("Grbl"))
    raw.send(b"G92 X-50\n")
    assert raw.line() == "ok"
    reports = []
    for _ in range(21):
        raw.send(b"?")
        reports.append(raw.line())
    with_wco = [i for i, r in enumerate(reports) if "|WCO:" in r]
    assert with_wco == [0, 10, 20], reports
    assert reports[0] == "<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:50.000,0.000,0.000>"
    assert [i for i, r in enumerate(reports) if "|Ov:" in r] == [1, 11]
    raw.send(b"G92 X0\n")  # a change of the offset: reported in the very next report
    assert raw.line() == "ok"
    raw.send(b"?")
    assert "|WCO:0.000," in raw.line()
    raw.close()


def test_the_last_wco_is_kept_so_the_work_position_is_right(emu):
    # Reports without WCO give only MPos; the work position is MPos - the last WCO seen.
    assert parse_status("<Idle|MPos:60.000,0.000,0.000|FS:0,0>") .x is None
    assert parse_status("<Idle|MPos:60.000,0.000,0.000|FS:0,0>", wco=-50.0).x == 110.0
    tt = GrblTurntable(emu.port, position_deg=50.0, **FAST)  # G92 X50: WCO = -50
    tt.move_to(60.0)
    assert "WCO" not in tt.last_status.raw  # the report after the move had none ...
    assert tt.last_status.mpos == steps(10.0)
    assert tt.last_status.x == pytest.approx(50.0 + steps(10.0))  # ... and the work position is still right
    assert tt.position_deg == pytest.approx(50.0 + steps(10.0))
    tt.close()


def test_status_is_polled_at_most_5_times_a_second(tmp_path):
    with pytest.raises(ValueError, match="at most 5 status queries"):
        GrblTurntable("unused", poll_s=0.05, connect=False)
    # 10 deg at 600 deg/min: 1 s, at real speed; the default polling
    with EmulatedTurntable(time_scale=1.0) as e:
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        n0 = e.received.count(b"?")
        t0 = time.monotonic()
        tt.move_to(10.0)
        dt = time.monotonic() - t0
        polls = e.received.count(b"?") - n0
        tt.close()
    assert dt >= 1.0
    assert tt.poll_s == MIN_POLL_S == 0.2
    assert polls <= dt / MIN_POLL_S + 2  # the polls, plus one status check at the end


def test_the_angle_reached_is_recorded_and_its_remainder_kept(emu):
    # 120 deg at 8.889 steps/deg is 1066.68 steps: the table stops at 1067 steps, 120.036 deg.
    tt = GrblTurntable(emu.port, **FAST)
    tt.move_to(120.0)
    assert tt.position_deg == 120.036 == emu.angle_deg
    tt.recover()  # a reconnection: G92 declares the angle reached, not the one commanded
    assert emu.lines[-1] == "G92 X120.036"
    tt.move_to(240.0)
    # the remainder was kept, so the error stays within half a step (not 240.072)
    assert abs(emu.angle_deg - 240.0) <= STEP / 2
    assert tt.position_deg == emu.angle_deg
    tt.close()


def test_move_timeout_is_computed_at_the_rate_grbl_really_runs(tmp_path):
    # $110 = 60 deg/min caps a G1 at F600: 1 deg takes 1 s, not 0.1 s.
    with EmulatedTurntable(time_scale=1.0, max_rate=60.0) as e:
        tt = GrblTurntable(e.port, feed_deg_per_min=600, motion_timeout_s=0.2, **FAST)
        t0 = time.monotonic()
        tt.move_to(1.0)  # allowed 1.5 * 1 s + 0.2 s; from F it would be 0.35 s
        assert time.monotonic() - t0 >= 1.0 and tt.position_deg == steps(1.0)
        assert tt.max_rate_deg_per_min == 60.0 and tt.rate_deg_per_min == 60.0
        tt.close()


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
    assert emu.angle_deg == steps(45.0)
    tt.close()


def test_horus_text_error_has_no_code():
    with EmulatedTurntable(flavor="horus", time_scale=200.0) as e:
        tt = GrblTurntable(e.port, **FAST)
        e.inject("error", on="G1", code=2)
        with pytest.raises(TurntableCommandError) as ei:
            tt.move_to(10.0)
        assert ei.value.code is None and "Bad number format" in str(ei.value)
        tt.close()


def test_a_lost_ok_after_g1_makes_the_angle_unknown_and_the_table_is_not_reset(tmp_path):
    # GRBL starts a move as soon as the line is queued: a G1 without its ok may be turning.
    with EmulatedTurntable(time_scale=20.0) as e:  # 60 deg: 0.3 s
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        e.inject("lose_ok", on="G1")
        with pytest.raises(TurntableTimeout) as ei:
            tt.move_to(60.0)
        assert not ei.value.position_known and not ei.value.retryable
        assert not tt.position_known and "60" in tt.unknown_reason
        with pytest.raises(TurntableError, match="angle is unknown"):
            tt.move_to(120.0)  # refused until the angle is declared
        assert e.lines.count("G1 X120.000 F600") == 0
        tt.recover()  # reconnect: waits for the move to end, never resets the turning table
        assert e.resets_in_motion == 0 and e.alarms == [] and "$X" not in e.lines
        assert e.angle_deg == steps(60.0) and not tt.position_known
        tt.set_position(60.0)  # the user's word
        tt.move_to(120.0)
        assert tt.position_known and e.angle_deg == pytest.approx(120.0, abs=STEP)
        tt.close()


def test_alarm_mid_move_loses_the_position_and_waits_for_a_reset(tmp_path):
    with EmulatedTurntable(time_scale=20.0) as e:  # 60 deg: 0.3 s
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        e.inject("alarm", on="G1", code=1, at_fraction=0.5)
        with pytest.raises(TurntableAlarm) as ei:
            tt.move_to(60.0)
        assert ei.value.code == 1 and "ALARM:1 (hard limit triggered)" in str(ei.value)
        assert not ei.value.position_known and not ei.value.retryable
        assert 20.0 < e.angle_deg < 40.0  # stopped half way
        tt.close()
        # "[MSG:Reset to continue]": a reconnection finds no answer to '?', resets, and
        # the controller stays locked: not the start-up lock (the table has moved), so no $X.
        tt = GrblTurntable(e.port, position_deg=0.0, **FAST)
        assert "$X" not in e.lines and e.lines[-1] == "$$"
        assert not tt.position_known and "did not see" in tt.unknown_reason
        tt.set_position(30.0)  # declared: unlocked, and the table works again
        assert e.lines[-3:] == ["$X", "G90", "G92 X30.000"]
        tt.move_to(40.0)
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
        assert e.angle_deg == steps(60.0)  # the board finished its move without the host
        # plugged back: a fresh controller; the angle stays unknown (no G92 of a guess)
        e.replug()
        tt.recover()
        assert not tt.position_known and not any(x.startswith("G92") for x in e.lines[-3:])
        tt.set_position(60.0)
        assert e.lines[-1] == "G92 X60.000"
        tt.close()


def test_silent_controller_times_out(emu):
    tt = GrblTurntable(emu.port, **FAST)
    emu.inject("silent", on="G1")
    t0 = time.monotonic()
    with pytest.raises(TurntableTimeout) as ei:
        tt.move_to(10.0)
    assert 0.4 < time.monotonic() - t0 < 1.5
    assert "no 'ok'" in str(ei.value) and not ei.value.position_known
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
    with pytest.raises(TurntableDisconnected, match="reset by itself") as ei:
        tt.move_to(10.0)
    assert not ei.value.position_known  # it may have rebooted mid-move
    tt.close()


def test_a_host_stall_during_a_move_is_not_a_silent_controller(tmp_path):
    # The whole host starved for 3x the reply timeout right after a '?' went out: the
    # reply (and the move's ok) came meanwhile and are read, not taken for silence.
    with EmulatedTurntable(time_scale=10.0) as e:  # 90 deg at 600 deg/min: 0.9 s
        tt = GrblTurntable(e.port, **FAST)
        write = tt._link.write
        polls = []

        def stalling_write(data):
            write(data)
            if data == b"?":
                polls.append(time.monotonic())
                if len(polls) == 2:
                    time.sleep(3 * FAST["timeout_s"])

        tt._link.write = stalling_write
        tt.move_to(90.0)
        assert tt.position_known and tt.position_deg == steps(90.0) and e.angle_deg == steps(90.0)
        assert len(polls) >= 2
        tt.close()


def test_the_silence_check_still_fires_after_a_stall(tmp_path):
    # ...and a controller that really stopped answering is still found out.
    with EmulatedTurntable(time_scale=1.0) as e:
        tt = GrblTurntable(e.port, feed_deg_per_min=600, **FAST)
        e.inject("silent", on="?", times=10 ** 6)
        with pytest.raises(TurntableTimeout, match="silent"):
            tt.move_to(360.0)
        tt.close()


def test_reachable_angle_is_the_motor_steps_one(emu):
    tt = GrblTurntable(emu.port, **FAST)
    assert tt.reachable_deg(120.0) == 120.036 == steps(120.0)
    assert tt.reachable_deg(240.0) == 239.96 == steps(240.0)
    tt.move_to(120.0)
    tt.recover()  # reset, G92 X120.036: the work offset now holds the declared angle's remainder
    assert tt.reachable_deg(240.0) == 239.96
    tt.move_to(240.0)
    assert tt.position_deg == 239.96
    tt.close()


def test_a_reset_while_the_table_stands_leaves_the_angle_known(emu):
    # The board reboots by itself while idle; the banner is read before the G1 is sent.
    tt = GrblTurntable(emu.port, **FAST)
    tt.move_to(120.0)
    emu.reboot()
    time.sleep(0.05)
    with pytest.raises(TurntableDisconnected, match="reset by itself") as ei:
        tt.move_to(240.0)
    assert ei.value.position_known and ei.value.retryable  # no move was sent: a retry is safe
    assert tt.position_known and tt.position_deg == steps(120.0)
    assert not any(x.startswith("G1 X240") for x in emu.lines)
    tt.recover()  # what the capture does before its retry
    tt.move_to(240.0)
    assert emu.angle_deg == steps(240.0) and tt.position_deg == steps(240.0)
    tt.close()


def test_emulator_garbles_a_status_report(emu):
    raw = _Raw(emu.port)
    emu.inject("garble", on="?")
    raw.send(b"?")
    line = raw.line()
    assert line.startswith("<Idle|MPos:0.000") and not line.endswith(">") and parse_status(line) is None
    assert raw.status().state == "Idle"  # the next one is whole
    raw.close()


def test_emulator_reboot_sends_the_banner_and_keeps_the_table(emu):
    raw = _Raw(emu.port)
    raw.send(b"G1 X90 F6000\n")
    assert raw.line() == "ok"
    time.sleep(0.1)
    emu.reboot()
    assert raw.lines_until(lambda s: s.startswith("Grbl 1.1h"))[-1] == "Grbl 1.1h ['$' for help]"
    st = raw.status()
    assert st.state == "Idle" and st.mpos == 0.0 and emu.angle_deg == steps(90.0)
    raw.close()


# ----------------------------------------------------------------------------- connecting to a table in any state


def _turning(port, line=b"G1 X90 F600\n"):
    """Another host (or the previous run) set the table turning, then let go of the port."""
    raw = _Raw(port)
    raw.send(line)
    assert raw.line() == "ok"
    raw.close()


def test_a_table_found_turning_is_waited_for_never_reset(tmp_path):
    # The resume that started while the table still turned: wait for Idle, then the
    # angle is unknown until the user says where the table stands.
    with EmulatedTurntable(time_scale=15.0) as e:  # 90 deg: 0.6 s
        _turning(e.port)
        assert e.moving
        tt = GrblTurntable(e.port, position_deg=90.0, **FAST)
        assert not e.moving and e.resets_in_motion == 0 and e.alarms == []
        assert e.angle_deg == steps(90.0)  # the move ran to its end
        assert not tt.position_known and "turning" in tt.unknown_reason
        assert not any(x.startswith("G92") for x in e.lines)  # no angle declared on a guess
        tt.set_position(90.0)  # --table-at 90
        tt.move_to(180.0)
        assert e.angle_deg == pytest.approx(180.0, abs=STEP)
        tt.close()


def test_a_garbled_status_report_while_waiting_for_a_turning_table_is_asked_again(tmp_path):
    # Line noise cuts a report while a resume waits for the table to stop: a new '?',
    # not a failed resume (and never a reset of the turning table).
    with EmulatedTurntable(time_scale=15.0) as e:
        _turning(e.port)
        e.inject("garble", on="?", skip=1)  # the probe's answer is whole, the next one cut
        tt = GrblTurntable(e.port, position_deg=90.0, **FAST)
        assert not e.faults  # the garbled report was sent
        assert not e.moving and e.resets_in_motion == 0 and e.alarms == []
        assert e.angle_deg == steps(90.0) and not tt.position_known
        tt.set_position(90.0)
        tt.move_to(180.0)  # long enough for the status reports the emulator garbles (a short move ends first)
        assert e.angle_deg == pytest.approx(180.0, abs=STEP)
        tt.close()


def test_a_garbled_first_report_does_not_get_a_turning_table_reset(tmp_path):
    with EmulatedTurntable(time_scale=15.0) as e:
        _turning(e.port)
        e.inject("garble", on="?")  # the probe's own answer is cut
        tt = GrblTurntable(e.port, position_deg=90.0, **FAST)
        assert e.resets_in_motion == 0 and e.alarms == [] and not tt.position_known
        tt.close()


def test_an_alarm_before_the_banner_means_the_angle_is_unknown(tmp_path):
    # The '?' asked before the reset goes unanswered, so the driver cannot know the
    # table turns; its reset then stops the move: ALARM:3 before the banner.
    with EmulatedTurntable(time_scale=15.0) as e:
        _turning(e.port)
        e.inject("silent", on="?")
        tt = GrblTurntable(e.port, position_deg=0.0, **FAST)
        assert e.resets_in_motion == 1 and e.alarms == [3]
        assert not tt.position_known and "ALARM:3 (reset while in motion)" in tt.unknown_reason
        assert "$X" not in e.lines  # only the start-up lock is unlocked on its own
        with pytest.raises(TurntableError, match="angle is unknown"):
            tt.move_to(10.0)
        tt.close()


def test_an_alarm_from_before_the_connection_is_not_unlocked(tmp_path):
    with EmulatedTurntable(time_scale=15.0) as e:
        _turning(e.port)
        raw = _Raw(e.port)
        time.sleep(0.2)
        raw.send(b"\x18")  # someone reset the turning table: ALARM:3, then locked
        assert raw.lines_until(lambda s: s.startswith("[MSG:"))[0] == "ALARM:3"
        raw.close()
        tt = GrblTurntable(e.port, position_deg=0.0, **FAST)
        assert "$X" not in e.lines and not any(x.startswith("G92") for x in e.lines)
        assert not tt.position_known and "did not see" in tt.unknown_reason
        tt.close()


def test_a_table_in_feed_hold_is_not_reset_mid_move(tmp_path):
    with EmulatedTurntable(time_scale=15.0) as e:
        _turning(e.port)
        raw = _Raw(e.port)
        time.sleep(0.2)
        raw.send(b"!")  # feed hold part way
        assert raw.status().state == "Hold"
        raw.close()
        held = e.angle_deg
        assert 5 < held < 85
        tt = GrblTurntable(e.port, position_deg=90.0, **FAST)
        assert e.alarms == [] and e.angle_deg == held  # reset in a complete hold: no alarm, no motion
        assert not any(x.startswith("G92") for x in e.lines)  # 90 would be a guess
        assert not tt.position_known and "Hold" in tt.unknown_reason
        tt.close()


def test_emulator_reset_in_an_alarm_and_the_reset_to_continue_lock(emu):
    raw = _Raw(emu.port)
    raw.send(b"\x18")
    raw.lines_until(lambda s: s.startswith("Grbl"))
    emu.inject("alarm", on="G1", code=2, at_fraction=0.0)
    raw.send(b"G1 X30 F600\n")
    assert raw.lines_until(lambda s: s.startswith("[MSG:")) == ["ok", "ALARM:2", "[MSG:Reset to continue]"]
    raw.send(b"?")
    raw.send(b"$X\n")
    assert raw.line() == ""  # nothing is answered but a reset
    raw.send(b"\x18")
    assert raw.lines_until(lambda s: s.startswith("[MSG:")) == ["", "Grbl 1.1h ['$' for help]",
                                                                 "[MSG:'$H'|'$X' to unlock]"]
    assert raw.status().state == "Alarm"
    raw.send(b"\x18")  # a reset keeps the Alarm state
    assert raw.lines_until(lambda s: s.startswith("[MSG:"))[-1] == "[MSG:'$H'|'$X' to unlock]"
    raw.send(b"G1 X10\n")
    assert raw.line() == "error:9"
    raw.send(b"$X\n")
    assert raw.lines_until(lambda s: s == "ok") == ["[MSG:Caution: Unlocked]", "ok"]
    assert raw.status().state == "Idle"
    raw.close()


def test_emulator_can_lose_an_ok(emu):
    raw = _Raw(emu.port)
    raw.send(b"\x18")
    raw.lines_until(lambda s: s.startswith("Grbl"))
    emu.inject("lose_ok", on="G1")
    # a move long enough (90 degrees at 60 deg/min: ~0.45 s at the emulator's time scale) that the status asked
    # right after it finds it running on a loaded machine too (10 degrees at 600 deg/min took 5 ms: seen Idle)
    raw.send(b"G1 X90 F60\n")
    assert raw.status().state == "Run"  # executed, but no ok came before the report
    raw.send(b"G4 P0\n")
    assert raw.line() == "ok" and emu.angle_deg == steps(90.0)
    raw.close()


# ----------------------------------------------------------------------------- other


def test_wrong_device_gives_no_banner(tmp_path):
    with EmulatedProjector([np.zeros((4, 4), np.uint8)]) as p:
        with pytest.raises(TurntableTimeout, match="banner"):
            GrblTurntable(p.port, timeout_s=0.2, boot_timeout_s=0.2)  # it never sends one: no need to wait long


def test_missing_port(tmp_path):
    with pytest.raises(TurntableDisconnected, match="cannot open"):
        GrblTurntable(str(tmp_path / "nope"), **FAST)


def test_bad_arguments():
    for kw in (dict(feed_deg_per_min=0), dict(direction=2), dict(motor_enable="x"), dict(timeout_s=0),
               dict(poll_s=0.1), dict(motion_timeout_s=-1)):
        with pytest.raises(ValueError):
            GrblTurntable("unused", connect=False, **kw)


# ----------------------------------------------------------------------------- parsing


def test_parse_status_both_dialects():
    s = parse_status("<Run|MPos:12.500,0.000,0.000|FS:600,0|WCO:2.500,0.000,0.000>")
    assert (s.state, s.x, s.mpos, s.wco) == ("Run", 10.0, 12.5, 2.5)
    s = parse_status("<Idle|WPos:7.000,0.000,0.000|FS:0,0>")
    assert (s.state, s.x) == ("Idle", 7.0)
    s = parse_status("<Hold:0|MPos:1.000,0.000,0.000|FS:0,0>", wco=0.25)
    assert (s.state, s.substate, s.x, s.wco) == ("Hold", 0, 0.75, None)
    assert parse_status("<Hold:1|MPos:1.000,0.000,0.000|FS:0,0>").x is None  # no WCO known: no work position
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
    assert t.moves == [90.0, 45.0] and t.angle_deg == t.position_deg == 45.0 and t.position_known
