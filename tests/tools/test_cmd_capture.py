"""``ringscan capture`` and ``ringscan emulate`` end to end: a virtual capture, a capture
killed mid-way and resumed, Ctrl-C, and a capture against a running ``ringscan emulate``."""

import contextlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from ringscan.hardware.capture.sequence import read_capture_state
from ringscan.hardware.emulators.virtual import VirtualCamera
from ringscan.pipeline.formats.atomic import atomic_write_json
from ringscan.pipeline.formats.images import read_image, write_image
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.rig import save_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.tools.cli import main
from tests.support.hardware_rig import small_patterns, small_rig

SEED = "3"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("rigfiles")
    save_rig(d / "rig.json", small_rig())
    atomic_write_json(d / "patterns.json", small_patterns().to_dict())
    return d


def _args(files, out, *extra):
    return ["capture", "--rig", str(files / "rig.json"), "--patterns", str(files / "patterns.json"),
            "--out", str(out), "--no-progress", *extra]


VIRTUAL = ["--virtual", "terrain", "--seed", SEED, "--device", "cpu"]


@pytest.fixture(scope="module")
def reference(files, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "scan"
    assert main(_args(files, out, "--views", "3", *VIRTUAL)) == 0
    return load_scan(out)


def _assert_same(scan, ref):
    names = frame_names(ref.patterns)
    assert [(v.name, v.turntable_deg) for v in scan.views] == [(v.name, v.turntable_deg) for v in ref.views]
    for v, r in zip(scan.views, ref.views):
        assert list(v.frames) == names  # every frame exactly once, in order
        for n in names:
            np.testing.assert_array_equal(read_image(scan.frame_path(v, n)), read_image(ref.frame_path(r, n)))


def test_virtual_capture(reference, capsys):
    scan = reference
    assert [v.turntable_deg for v in scan.views] == [0.0, 120.036, 239.96]  # where the table's steps reached
    state = read_capture_state(scan.folder)
    assert state["status"] == "complete" and state["settings"]["turntable_settle_s"] == 0.0
    white = read_image(scan.frame_path(scan.views[0], "white")).astype(float)
    black = read_image(scan.frame_path(scan.views[0], "black")).astype(float)
    assert white.mean() > black.mean() + 20


def test_killed_capture_resumes_to_the_same_scan(files, reference, tmp_path):
    out = tmp_path / "scan"
    cmd = [sys.executable, "-m", "ringscan.tools.cli"] + _args(files, out, "--views", "3", *VIRTUAL,
                                                                 "--projector-settle", "0.06")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        listed = 0
        while listed < 5:
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "the capture did not start"
            time.sleep(0.02)
            if (out / "scan.json").is_file():
                listed = sum(len(v.frames) for v in load_scan(out, check_files=False, allow_incomplete=True).views)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    part = load_scan(out, allow_incomplete=True)  # still valid after a kill
    listed = sum(len(v.frames) for v in part.views)
    assert 5 <= listed < 18
    assert read_capture_state(out)["status"] == "running"  # it never got to say otherwise
    assert main(["capture", "--out", str(out), "--resume", "--no-progress", *VIRTUAL]) == 0
    scan = load_scan(out)
    _assert_same(scan, reference)
    runs = read_capture_state(out)["runs"]
    assert len(runs) == 2 and runs[1]["result"] == "complete" and runs[1]["frames"] == 18 - listed
    assert runs[0]["result"] == "killed" and runs[0]["frames"] == listed  # the killed run's record, brought up to date
    leftovers = [p for p in out.rglob(".*") if p.is_file()]
    assert not leftovers


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the swallowed interrupt itself
def test_ctrl_c_that_lands_in_a_finalizer_stops_the_capture_with_130(files, tmp_path, monkeypatch, capsys):
    # A KeyboardInterrupt raised in __del__ (a Warp array's finalizer) is only printed by
    # Python; the capture must stop all the same, cleanly, with exit status 130.
    grab = VirtualCamera._read

    def read(self):
        if self.grabs == 2:
            class Buffer:
                def __del__(self):
                    signal.raise_signal(signal.SIGINT)

            Buffer()
        return grab(self)

    monkeypatch.setattr(VirtualCamera, "_read", read)
    out = tmp_path / "scan"
    assert main(_args(files, out, "--views", "3", *VIRTUAL)) == 130
    assert "interrupted" in capsys.readouterr().err
    state = read_capture_state(out)
    assert state["status"] == "interrupted" and state["runs"][0]["frames"] == 3
    assert sum(len(v.frames) for v in load_scan(out, allow_incomplete=True).views) == 3


@contextlib.contextmanager
def _emulator(cmd, **popen):
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, **popen)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()


def _assert_stops_cleanly(proc, sig, emu_dir):
    proc.send_signal(sig)
    rest = proc.communicate(timeout=30)[0]  # not the --seconds 120 running out
    assert proc.returncode == 0 and "emulator stopped" in rest
    assert not (emu_dir / "turntable").exists() and not (emu_dir / "camera.sock").exists()


def test_capture_against_ringscan_emulate(files, reference, tmp_path):
    emu_dir = tmp_path / "emu"
    cmd = [sys.executable, "-m", "ringscan.tools.cli", "emulate", "--rig", str(files / "rig.json"), "--patterns",
           str(files / "patterns.json"), "--scene", "terrain", "--folder", str(emu_dir), "--time-scale", "500",
           "--seed", SEED, "--seconds", "120", "--device", "cpu"]
    # Started as a shell starts a background job (SIGINT ignored): Ctrl-C must stop it all the same.
    with _emulator(cmd, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) as proc:
        ports = {}
        for line in proc.stdout:
            key, _, rest = line.partition(":")
            if key in ("turntable", "projector", "camera"):
                ports[key] = rest.split()[0]
            if line.startswith("running"):
                break
        assert set(ports) == {"turntable", "projector", "camera"}, ports
        assert ports["camera"] == f"unix:{emu_dir / 'camera.sock'}"
        out = tmp_path / "scan"
        assert main(_args(files, out, "--views", "3", "--turntable", ports["turntable"], "--projector",
                          ports["projector"], "--camera", ports["camera"], "--turntable-settle", "0",
                          "--projector-settle", "0", "--timeout", "1")) == 0
        _assert_same(load_scan(out), reference)
        _assert_stops_cleanly(proc, signal.SIGINT, emu_dir)


def test_emulate_stops_cleanly_on_sigterm(tmp_path):
    emu_dir = tmp_path / "emu"
    cmd = [sys.executable, "-m", "ringscan.tools.cli", "emulate", "--folder", str(emu_dir), "--seconds", "120",
           "--device", "cpu"]
    with _emulator(cmd) as proc:
        for line in proc.stdout:
            if line.startswith("running"):
                break
        assert (emu_dir / "camera.sock").exists()
        _assert_stops_cleanly(proc, signal.SIGTERM, emu_dir)  # what a service manager sends


def test_cli_errors(files, tmp_path, capsys):
    assert main(["capture", "--out", str(tmp_path / "a")]) == 2
    assert "needs --rig, --patterns and --views" in capsys.readouterr().err
    assert main(_args(files, tmp_path / "b", "--views", "2", "--camera", "0")) == 2
    assert "missing --turntable, --projector" in capsys.readouterr().err
    assert main(_args(files, tmp_path / "c", "--views", "2", "--table-at", "5", *VIRTUAL)) == 2
    assert "--table-at only applies with --resume" in capsys.readouterr().err
    assert main(["capture", "--out", str(tmp_path / "d"), "--resume"]) == 1
    assert "nothing to resume" in capsys.readouterr().err
    for n in ("1000000000", "0", "-3"):  # before: 10^9 views planned in memory, 85 MB/s and no output
        assert main(_args(files, tmp_path / "v", "--views", n, *VIRTUAL)) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"ringscan capture: error: --views: expected 1 to 10000 views (a view every 0.036 "
                              f"degrees), got {n}"), err
        assert not (tmp_path / "v").exists()
    assert main(_args(files, tmp_path / "c2", "--views", "2", "--allow-auto-exposure", *VIRTUAL)) == 2
    assert "--allow-auto-exposure only applies with --exposure" in capsys.readouterr().err
    port = str(tmp_path / "no_such_port")
    (tmp_path / "cam").mkdir()
    write_image(tmp_path / "cam" / "0.png", np.zeros((256, 320), np.uint8))
    assert main(_args(files, tmp_path / "e", "--views", "2", "--turntable", port, "--projector", port,
                      "--camera", str(tmp_path / "cam"))) == 1
    err = capsys.readouterr().err
    assert "no_such_port" in err and "cannot open" in err
    assert not (tmp_path / "e").exists()
    bad = tmp_path / "settings.json"
    atomic_write_json(bad, {"retries": "x"})
    assert main(_args(files, tmp_path / "f", "--views", "2", "--settings", str(bad), *VIRTUAL)) == 1
    assert "settings.json: settings: retries" in capsys.readouterr().err


def test_capture_reconstructs_while_capturing(files, reference, tmp_path, capsys):
    from ringscan.pipeline.formats.atomic import read_json
    from ringscan.pipeline.formats.ply import read_ply
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan

    out, rec = tmp_path / "scan", tmp_path / "rec"
    assert main(_args(files, out, "--views", "3", *VIRTUAL, "--reconstruct", str(rec))) == 0
    assert "reconstructed 3 view(s)" in capsys.readouterr().out
    _assert_same(load_scan(out), reference)
    live = read_json(rec / "report.json")
    again = reconstruct_scan(out, tmp_path / "again", device="cpu", progress=False)
    assert [v["name"] for v in live["views"]] == [v.name for v in reference.views]
    assert live["totals"]["points"] == again["totals"]["points"] > 100
    for v in reference.views:  # the same points as a reconstruction after the capture
        a, b = read_ply(rec / f"{v.name}.ply"), read_ply(tmp_path / "again" / f"{v.name}.ply")
        for key in ("x", "y", "z", "ring", "view"):
            np.testing.assert_array_equal(a[key], b[key])
    assert main(_args(files, tmp_path / "x", "--views", "2", *VIRTUAL, "--reconstruct-settings", "s.json")) == 2
    assert "--reconstruct-settings only applies with --reconstruct" in capsys.readouterr().err
    (tmp_path / "afile").write_text("")
    assert main(_args(files, tmp_path / "y", "--views", "2", *VIRTUAL, "--reconstruct", str(tmp_path / "afile"))) == 1
    assert "afile: exists and is not a folder" in capsys.readouterr().err
    assert not (tmp_path / "y").exists()  # refused before anything was captured


def test_live_reconstructor_partial_scan_resume_and_failure(reference, tmp_path):
    import dataclasses
    import shutil

    from ringscan.pipeline.formats.atomic import read_json
    from ringscan.pipeline.formats.scan import View
    from ringscan.pipeline.reconstruct.live import LiveReconstructor

    v0, v1, v2 = reference.views
    half = View(name=v2.name, turntable_deg=v2.turntable_deg, frames=dict(list(v2.frames.items())[:3]))
    partial = dataclasses.replace(reference, views=(v0, v1, half))  # a capture that stopped in view 2
    live = LiveReconstructor(tmp_path / "rec", device="cpu")
    live(partial, v0)
    rep = live.finish(partial)
    assert [v["name"] for v in rep["views"]] == [v0.name, v1.name] and live.error is None
    first = read_json(tmp_path / "rec" / "report.json")["views"]
    # Resumed and finished: only the new view is reconstructed, the others are kept.
    rep = LiveReconstructor(tmp_path / "rec", device="cpu").finish(reference)
    assert [v["name"] for v in rep["views"]] == [v0.name, v1.name, v2.name]
    assert rep["views"][:2] == first
    # A frame that cannot be read: logged and kept, never raised into the capture.
    bad = tmp_path / "bad"
    shutil.copytree(reference.folder, bad)
    (bad / v1.frames["white"]).write_bytes(b"not a png")
    live = LiveReconstructor(tmp_path / "rec_bad", device="cpu")
    scan = load_scan(bad, check_files=False)
    live(scan, scan.views[1])
    assert live.finish() is None
    assert "white.png" in live.error and "failed" in live.error and str(bad) in live.error


@pytest.mark.parametrize("extra,message", [
    (["--resume", "--table-at", "1e300"], "--table-at: expected degrees from -3600 to 3600, got 1e+300"),
    (["--resume", "--table-at=-1e300"], "--table-at: expected degrees from -3600 to 3600, got -1e+300"),
    (["--resume", "--table-at", "1e15"], "--table-at: expected degrees from -3600 to 3600, got 1e+15"),
    (["--resume", "--table-at", "nan"], "--table-at: expected degrees from -3600 to 3600, got nan"),
    (["--resume", "--table-at", "inf"], "--table-at: expected degrees from -3600 to 3600, got inf"),
    (["--views", "2", "--step", "1e300"], "--step: expected degrees from -360 to 360, got 1e+300"),
    (["--views", "2", "--start", "nan"], "--start: expected degrees from -3600 to 3600, got nan"),
])
def test_table_angles_checked_before_anything_moves(files, reference, tmp_path, capsys, extra, message):
    import shutil

    out = tmp_path / "scan"
    if "--resume" in extra:
        shutil.copytree(reference.folder, out)
        before = (out / "capture.json").read_bytes()
    rc = main(_args(files, out, *extra, *VIRTUAL))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err == f"ringscan capture: error: {message}", err
    if "--resume" in extra:
        assert (out / "capture.json").read_bytes() == before  # no angle recorded
    else:
        assert not out.exists()


def test_frame_bits_option(files, tmp_path, capsys):
    assert main(_args(files, tmp_path / "a", "--views", "2", "--frame-bits", "7", *VIRTUAL)) == 2
    assert "--frame-bits: expected a whole number, 8 for 8-bit frames or 9..16" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    # the virtual camera's frames are 8-bit: a 12-bit setting stops the capture at its first frame
    assert main(_args(files, tmp_path / "b", "--views", "2", "--frame-bits", "12", *VIRTUAL)) == 1
    err = capsys.readouterr().err
    assert "camera delivers 8-bit frames, but frame_bits (--frame-bits) says 12" in err
    assert load_scan(tmp_path / "b", check_files=False, allow_incomplete=True).frame_bits == 12
