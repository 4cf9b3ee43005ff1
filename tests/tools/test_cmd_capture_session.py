"""``ringscan capture --poses N`` on the emulated rig: poses captured in a row, reconstructed live, fused into
one mesh; a session stopped between poses resumes (complete poses kept)."""

import io

import numpy as np

from ringscan.hardware.capture.session import pose_state
from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import save_rig
from ringscan.tools.cli import main
from tests.support.hardware_rig import small_patterns, small_rig


def test_session_of_two_poses_on_the_virtual_rig(tmp_path, monkeypatch, capsys):
    save_rig(tmp_path / "rig.json", small_rig())
    spec = small_patterns(bits=5).to_dict()
    atomic_write_json(tmp_path / "patterns.json", {**spec, "pitch": 12.0})  # dense rings: enough points to align
    # Three views a pose (12 frames each): the two poses still overlap enough to align (fitness ~0.17
    # against the 0.1 needed, point-to-plane RMSE ~0.4 mm under --max-pose-rmse 0.6).
    out = tmp_path / "session"
    args = ["capture", "--rig", str(tmp_path / "rig.json"), "--patterns", str(tmp_path / "patterns.json"),
            "--out", str(out), "--no-progress", "--views", "3", "--poses", "2", "--virtual", "terrain",
            "--virtual-poses", "upright,tetra-1",
            "--max-pose-rmse", "0.6", "--seed", "1", "--device", "cpu"]
    # No key before pose 1 (the input ends): pose 0 is captured, the session stops, nothing is fused.
    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "pose 2 of 2: turn the object over" in err and "pose 2: no key pressed" in err
    assert [pose_state(out / f"pose_{i}") for i in range(2)] == ["complete", "new"]
    assert not (out / "mesh").exists()
    before = (out / "pose_0" / "scan.json").stat().st_mtime_ns
    # The rerun resumes: pose 0 kept as it is, one Enter for pose 1, then both fused.
    keys = io.StringIO("\n")
    monkeypatch.setattr("sys.stdin", keys)
    assert main(args) == 0
    err = capsys.readouterr().err
    assert err.count("turn the object over") == 1 and keys.read() == ""  # asked once, key consumed
    assert (out / "pose_0" / "scan.json").stat().st_mtime_ns == before
    assert [pose_state(out / f"pose_{i}") for i in range(2)] == ["complete", "complete"]
    assert read_json(out / "session.json")["labels"] == ["upright", "tetra-1"]
    for i in range(2):
        assert len(read_json(out / "recon" / f"pose_{i}" / "report.json")["views"]) == 3
    rep = read_json(out / "mesh" / "fuse_report.json")
    assert len(rep["sources"]) == 2 and "poses" in rep["fusion"]
    fused = read_ply(out / "mesh" / "fused.ply")
    assert set(np.unique(fused["view"])) == {0, 1}  # both poses in the one cloud


def test_a_trigger_that_is_not_a_serial_port_is_named_before_the_first_pose(tmp_path, capsys):
    from ringscan.tools.cli import main

    out = tmp_path / "session"
    rc = main(["capture", "--out", str(out), "--poses", "2", "--trigger", "/dev/null", "--views", "2",
               "--virtual", "terrain", "--device", "cpu", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.startswith("ringscan capture: error: --trigger /dev/null: cannot open it as a serial port: ")
    assert len(err.splitlines()) == 1 and not out.exists()
