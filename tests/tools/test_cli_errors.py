"""Bad input on the command line: one line naming the path, exit status 1, no traceback
(docs/bad_input.md lists every case)."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from ringscan.tools.cli import main
from tests.pipeline.reconstruct.tiny_scan import simulate_tiny_scan

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
