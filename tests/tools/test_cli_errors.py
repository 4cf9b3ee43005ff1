"""Bad input on the command line: one line naming the path, exit status 1, no traceback
(docs/bad_input.md lists every case)."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from ringscan.tools.cli import main
from tests.support.tiny_scan import simulate_tiny_scan

# Each command with its arguments, "{out}" standing for the output path under test.
# Inputs need not exist: the output is checked first, before anything is read or computed.
COMMANDS = {
    "reconstruct": ["reconstruct", "{scan}", "--out", "{out}", "--device", "cpu", "--no-progress"],
    "batch": ["batch", "{scan}", "--out", "{out}", "--device", "cpu", "--no-progress"],
    "simulate": ["simulate", "--scene", "cube", "--out", "{out}", "--device", "cpu", "--no-progress"],
    "mesh": ["mesh", "{tmp}/cloud.ply", "--out", "{out}"],
    "fuse": ["fuse", "{tmp}/recon", "--out", "{out}", "--no-progress"],
    "patterns": ["patterns", "--out", "{out}"],
    "evaluate": ["evaluate", "{tmp}/recon", "--truth", "{scan}", "--json", "{out}"],
    "demo": ["demo", "--out", "{out}", "--device", "cpu"],
    "sweep": ["sweep", "--scene", "sphere", "--out", "{out}", "--device", "cpu", "--no-progress"],
}


@pytest.fixture
def tiny_scan(tmp_path):
    """A valid scan folder (one view) for the commands that read one before writing."""
    return simulate_tiny_scan(tmp_path / "scan").folder


def _run(argv, capsys):
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.err.strip()


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("where", ["a file", "under a file", "/dev/null"])
def test_out_that_cannot_be_written(tmp_path, capsys, tiny_scan, command, where):
    afile = tmp_path / "afile.ply"
    afile.write_text("I am a file")
    out = {"a file": afile, "under a file": afile / "sub" / "x.ply", "/dev/null": "/dev/null"}[where]
    if command == "mesh" and where == "a file":
        out = tmp_path  # mesh writes a file: a folder is what it cannot write
    argv = [a.format(scan=tiny_scan, tmp=tmp_path, out=out) for a in COMMANDS[command]]
    if command == "evaluate" and where == "a file":
        out = tmp_path
        argv[-1] = str(out)
    rc, err = _run(argv, capsys)
    assert rc == 1, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"ringscan {command}: error: {out}: "), err
    assert afile.read_text() == "I am a file"


def test_a_folder_where_a_file_goes(tmp_path, capsys, tiny_scan):
    for name in ("report.json", "view_000.ply"):
        out = tmp_path / f"out_{name}"
        (out / name).mkdir(parents=True)
        rc, err = _run(["reconstruct", str(tiny_scan), "--out", str(out), "--device", "cpu", "--no-progress"], capsys)
        assert rc == 1 and err.startswith(f"ringscan reconstruct: error: {out / name}: ") and "a folder" in err, err
        assert sorted(p.name for p in out.iterdir()) == [name]  # refused before writing anything


def test_view_out_a_folder_or_another_extension(tmp_path, capsys):
    cloud = tmp_path / "c.ply"
    o3d.io.write_point_cloud(str(cloud), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.eye(3))))
    rc, err = _run(["view", str(cloud), "--out", str(tmp_path)], capsys)
    assert rc == 1 and err == f"ringscan view: error: {tmp_path}: cannot be the picture (--out): it is a folder"
    rc, err = _run(["view", str(cloud), "--out", str(tmp_path / "x.gif")], capsys)
    assert rc == 1 and "x.gif: cannot be the picture (--out): the extension must be .png, not '.gif'" in err


def test_binary_scan_json_and_a_nul_in_a_path(tmp_path, capsys, tiny_scan):
    d = json.loads((tiny_scan / "scan.json").read_text())
    d["views"][0]["frames"]["white"] = "view_000/wh\u0000ite.png"
    (tiny_scan / "scan.json").write_text(json.dumps(d))
    rc, err = _run(["reconstruct", str(tiny_scan), "--out", str(tmp_path / "o"), "--device", "cpu"], capsys)
    assert rc == 1 and err == (f"ringscan reconstruct: error: {tiny_scan / 'scan.json'}: views[0].frames.white: path "
                               "'view_000/wh\\x00ite.png' contains a control character (a NUL, a newline...)")
    (tiny_scan / "scan.json").write_bytes(b"\x00\x01\xff\xfe" * 10)
    rc, err = _run(["reconstruct", str(tiny_scan), "--out", str(tmp_path / "o"), "--device", "cpu"], capsys)
    assert rc == 1 and err.startswith(f"ringscan reconstruct: error: {tiny_scan / 'scan.json'}: not a text file")


def test_simulate_does_not_overwrite_its_own_input(tmp_path, capsys, tiny_scan):
    scene = tiny_scan / "truth" / "object.ply"
    before = scene.read_bytes()
    rc, err = _run(["simulate", "--scene", str(scene), "--out", str(tiny_scan), "--device", "cpu", "--no-progress"],
                   capsys)
    assert rc == 1 and "would overwrite the input" in err and str(scene) in err
    assert scene.read_bytes() == before


def test_fuse_voxel_must_be_a_positive_number(tmp_path, capsys):
    for v in ("0", "nan", "-1", "inf", "abc"):
        rc, err = _run(["fuse", str(tmp_path), "--out", str(tmp_path / "o"), "--voxel", v], capsys)
        assert rc == 2 and "--voxel: expected a finite number of mm > 0 (or 'none' to keep every point)" in err, v


def test_settings_file_errors_name_the_file(tmp_path, capsys, tiny_scan):
    s = tmp_path / "s.json"
    s.write_text(json.dumps({"min_confidnce": 0.5}))
    rc, err = _run(["reconstruct", str(tiny_scan), "--out", str(tmp_path / "o"), "--settings", str(s)], capsys)
    assert rc == 1
    assert err.startswith(f"ringscan reconstruct: error: {s}: min_confidnce: unknown setting of ReconstructSettings")
    s.write_text('{"min_confidence": NaN}')
    rc, err = _run(["reconstruct", str(tiny_scan), "--out", str(tmp_path / "o"), "--settings", str(s)], capsys)
    assert rc == 1 and "min_confidence must be a finite number" in err and str(s) in err


def _in_thread(fn, timeout=60.0):
    """fn() in a thread, so that a read that blocks (a FIFO) fails the test instead of hanging it."""
    import threading

    box = {}
    t = threading.Thread(target=lambda: box.setdefault("rc", fn()), daemon=True)
    t.start()
    t.join(timeout)
    return box.get("rc", "hung")


def test_fifo_and_device_inputs_are_refused_without_blocking(tmp_path, capsys, tiny_scan):
    """A rig or settings file that is a FIFO (read: blocks forever) or /dev/zero (never ends): one line, exit 1."""
    import os

    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    out = tmp_path / "o"
    cases = [["batch", str(tiny_scan), "--out", str(out), "--settings", str(fifo), "--dry-run"],
             ["batch", str(tiny_scan), "--out", str(out), "--settings", str(fifo), "--workers", "0"],
             ["reconstruct", str(tiny_scan), "--out", str(out), "--settings", "/dev/zero"],
             ["patterns", "--rig", str(fifo), "--out", str(out)]]
    for argv in cases:
        rc = _in_thread(lambda: main(argv))
        if rc == "hung":
            with open(fifo, "wb") as f:  # let the blocked reader go
                f.write(b"{}")
        err = capsys.readouterr().err.strip()
        assert rc == 1, (argv, rc, err)
        assert len(err.splitlines()) == 1 and "not a regular file: ringscan reads regular files only" in err, err
        assert not out.exists()
    # a scan whose rig file is a FIFO
    d = json.loads((tiny_scan / "scan.json").read_text())
    os.mkfifo(tiny_scan / "rig.json")
    d["rig"] = "rig.json"
    (tiny_scan / "scan.json").write_text(json.dumps(d))
    rc = _in_thread(lambda: main(["reconstruct", str(tiny_scan), "--out", str(out), "--device", "cpu"]))
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err == (f"ringscan reconstruct: error: {tiny_scan / 'rig.json'}: is a pipe (FIFO), not a "
                               "regular file: ringscan reads regular files only"), err


def test_a_5000_digit_number_in_a_rig_names_the_file(tmp_path, capsys, tiny_scan):
    d = json.loads((tiny_scan / "scan.json").read_text())
    text = json.dumps(d).replace('"width": 160', '"width": ' + "9" * 5000, 1)
    assert text != json.dumps(d)
    (tiny_scan / "scan.json").write_text(text)
    rc, err = _run(["reconstruct", str(tiny_scan), "--out", str(tmp_path / "o"), "--device", "cpu"], capsys)
    assert rc == 1 and err.startswith(f"ringscan reconstruct: error: {tiny_scan / 'scan.json'}: not valid JSON "
                                      "(Exceeds the limit (4300 digits) for integer string conversion")


@pytest.mark.parametrize("mesh", ["../outside.ply", "/etc/passwd", 5, None])
def test_evaluate_truth_mesh_outside_the_scan_or_not_a_path(tmp_path, capsys, tiny_scan, mesh):
    recon = tmp_path / "recon"
    assert main(["reconstruct", str(tiny_scan), "--out", str(recon), "--device", "cpu", "--no-progress"]) == 0
    capsys.readouterr()
    (tmp_path / "outside.ply").write_text("ply\n")
    d = json.loads((tiny_scan / "scan.json").read_text())
    d["truth"]["mesh"] = mesh
    (tiny_scan / "scan.json").write_text(json.dumps(d))
    rc, err = _run(["evaluate", str(recon), "--truth", str(tiny_scan)], capsys)
    want = (f"path {mesh!r} leaves the scan folder" if isinstance(mesh, str) else
            f"expected a relative path, got {mesh!r}")
    assert rc == 1 and err == f"ringscan evaluate: error: {tiny_scan / 'scan.json'}: truth.mesh: {want}", err


@pytest.mark.parametrize("what", ["light", "turntable"])
def test_calibrate_out_must_not_overwrite_a_scan_json(tmp_path, capsys, tiny_scan, what):
    target = tiny_scan / "scan.json"
    before = target.read_bytes()
    extra = ["--heights", "0"] if what == "light" else ["--square", "5"]
    rc, err = _run(["calibrate", what, str(tiny_scan), *extra, "--out", str(target)], capsys)
    assert rc == 1 and err == (f"ringscan calibrate {what}: error: {target}: writing it would overwrite the input {target}; "
                               "choose another output"), err
    rc, err = _run(["calibrate", what, str(tiny_scan), *extra, "--out", str(tmp_path / "r.json"),
                    "--report", str(tmp_path / "r.json")], capsys)
    assert rc == 1 and err.endswith("r.json: given to both --out and --report: one would overwrite the other"), err
    assert target.read_bytes() == before and not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("w,bits", [(60000, 8), (30000, 16)])
def test_a_huge_image_is_one_line_before_decoding(tmp_path, capsys, tiny_scan, w, bits):
    """A PNG of a few bytes whose header says 60000x60000 (before: a cv2.error traceback) or 30000x30000 16-bit
    (before: 20 GB in `calibrate camera`, then the OOM killer): refused from its header."""
    from tests.support.header_only import png_header_only

    frame = tiny_scan / "view_000" / "gray_1.png"
    png_header_only(frame, w, w, bits)
    want = f"{frame}: image is {w}x{w} ({w * w / 1e6:.0f} megapixels): larger than ringscan reads"
    rc, err = _run(["reconstruct", str(tiny_scan), "--out", str(tmp_path / "o"), "--device", "cpu", "--no-progress"],
                   capsys)
    assert rc == 1 and err.startswith(f"ringscan reconstruct: error: {want}"), err
    assert not (tmp_path / "o").exists()  # every frame's header checked before anything is written
    rc, err = _run(["calibrate", "camera", str(frame), "--square", "5", "--out", str(tmp_path / "cam.json")], capsys)
    assert rc == 1 and err.startswith(f"ringscan calibrate camera: error: {want}"), err
    assert not (tmp_path / "cam.json").exists()


@pytest.mark.parametrize("command", ["reconstruct", "batch"])
def test_a_lock_file_linked_to_another_file_is_refused_and_that_file_left_alone(tmp_path, capsys, tiny_scan,
                                                                               command):
    """OUT/.ringscan.lock a symbolic link to another file: before, the run truncated that file and wrote its
    process id into it."""
    out = tmp_path / "out"
    out.mkdir()
    other = tmp_path / "notes.txt"
    other.write_text("keep me\n")
    (out / ".ringscan.lock").symlink_to(other)
    argv = [a.format(scan=tiny_scan, tmp=tmp_path, out=out) for a in COMMANDS[command]]
    rc, err = _run(argv + (["--workers", "0"] if command == "batch" else []), capsys)
    assert rc == 1 and err == (f"ringscan {command}: error: {out / '.ringscan.lock'}: is a symbolic link (to "
                               f"{other}), not a plain file: it is ringscan's own lock file, a plain file: remove it "
                               "(no ringscan run uses it then)"), err
    assert other.read_text() == "keep me\n" and sorted(p.name for p in out.iterdir()) == [".ringscan.lock"]


def test_import_refuses_a_projector_its_maps_cannot_hold(tmp_path, capsys):
    """A projector side of 65535 px or more: the scan's 16-bit maps cannot hold its coordinates (65534 at one
    step a px); one line naming the option, exit 2, before anything is read or written."""
    out = tmp_path / "scan"
    assert main(["import", str(tmp_path / "nowhere"), "--rig", str(tmp_path / "rig.json"), "--projector", "65535x384",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--projector 65535x384" in err[0] and "65534" in err[0]
    assert not out.exists()
