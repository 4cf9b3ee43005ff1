"""``ringscan calibrate`` and ``ringscan import`` end to end (real captures where present)."""

from __future__ import annotations

import numpy as np
import pytest

from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import load_rig
from ringscan.tools.cli import main
from tests.pipeline.calibrate.synthetic import write_capture


@pytest.fixture(scope="module")
def procam(shared_data):
    d = shared_data / "procam"
    if not (d / "capture_1").is_dir():
        pytest.skip(f"procam captures not found in {d}")
    return d


def test_camera_without_a_board_exits_2_and_writes_nothing(tmp_path, procam, capsys):
    out = tmp_path / "cam.json"
    rc = main(["calibrate", "camera", str(procam / "capture_1" / "graycode_41.png"),
               str(procam / "capture_2" / "graycode_41.png"), "--square", "75", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "no image shows the 9x7 board" in err and "Traceback" not in err
    assert not out.exists()


def test_procam_wrong_layout_exits_2(tmp_path, capsys):
    write_capture(tmp_path / "c1", projector=(128, 96))
    rig = tmp_path / "rig.json"
    rc = main(["calibrate", "procam", str(tmp_path / "c1"), "--square", "75", "--projector", "128x96",
               "--layout", "opencv-graycode-wb-first", "--out", str(rig)])
    assert rc == 2 and "not layout 'opencv-graycode-wb-first'" in capsys.readouterr().err
    assert not rig.exists()


@pytest.mark.slow
def test_procam_then_import_then_reconstruct(tmp_path, procam, capsys):
    rig = tmp_path / "rig.json"
    caps = [str(procam / f"capture_{i}") for i in (1, 2, 3)]
    assert main(["calibrate", "procam", *caps, "--square", "75", "--projector", "1024x768", "--out", str(rig)]) == 0
    text = capsys.readouterr().out
    assert "stereo: RMS reprojection error 0.3" in text
    r = load_rig(rig)
    assert r.light.model == "perspective" and r.light.K[1, 2] > 768
    scan = tmp_path / "scan"
    assert main(["import", caps[2], "--rig", str(rig), "--projector", "1024x768", "--out", str(scan)]) == 0
    out = tmp_path / "out"
    assert main(["reconstruct", str(scan), "--out", str(out), "--device", "cpu"]) == 0
    ply = read_ply(out / "capture_3.ply")
    assert len(ply["x"]) > 500_000
    # the board is flat: points in the middle of the board (camera pixels inside its corners) fit a plane
    u, v = ply["u"], ply["v"]
    on = (u > 520) & (u < 900) & (v > 350) & (v < 600)
    P = np.stack([ply["x"][on], ply["y"][on], ply["z"][on]], 1).astype(np.float64)
    c = P.mean(0)
    n = np.linalg.svd(P - c, full_matrices=False)[2][2]
    res = (P - c) @ n
    assert len(P) > 20_000 and np.sqrt(np.mean(res ** 2)) < 1.5


def test_import_opencv_file(tmp_path, procam, capsys):
    scan = tmp_path / "scan"
    assert main(["import", str(procam / "capture_1"), "--rig", str(procam / "calibration_result.xml"),
                 "--projector", "1024x768", "--out", str(scan)]) == 0
    assert (scan / "scan.json").is_file() and (scan / "capture_1" / "proj_u.png").is_file()


# ----------------------------------------------------------------------------- bad input (docs/bad_input.md)


def _err(capsys):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.fixture
def capture_and_rig(tmp_path):
    """A synthetic capture ``caps/c1`` (160x120 camera, 128x96 projector) and a perspective rig for it."""
    from ringscan.pipeline.calibrate.procam import procam_rig
    from ringscan.pipeline.formats.rig import save_rig

    write_capture(tmp_path / "caps" / "c1")
    K = np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]])
    PK = np.array([[160.0, 0, 63.5], [0, 160.0, 47.5], [0, 0, 1]])
    rig = procam_rig(cam_K=K, cam_dist=np.zeros(5), cam_size=(160, 120), proj_K=PK, proj_dist=np.zeros(5),
                     proj_size=(128, 96), R=np.eye(3), T=np.array([-100.0, 0, 0]), z_range=(300.0, 700.0))
    save_rig(tmp_path / "rig.json", rig)
    return tmp_path / "caps" / "c1", tmp_path / "rig.json"


@pytest.mark.parametrize("extra,message", [
    (["--square", "1e308"], "--board/--square/--marker: board: square size must be a number of mm from 0.01 to 10000, "
                            "got 1e+308"),
    (["--square", "nan"], "square size must be a number of mm from 0.01 to 10000, got nan"),
    (["--square", "5", "--board=--"], "--board: expected WxH (e.g. 9x7), got '--'"),
    (["--square", "5", "--projector=--"], "--projector: expected WxH (e.g. 9x7), got '--'"),
    (["--square", "5", "--projector", "5x" + "9" * 5000], "--projector: expected WxH (e.g. 9x7), got '5x999999999"),
    (["--square", "5", "--window", "100000"], "--window: expected camera px from 1 to 200, got 100000"),
    (["--square", "5", "--max-tilt", "nan"], "--max-tilt: expected degrees from 0 to 90, got nan"),
    (["--square", "5", "--report", "{out}"], "{out}: given to both --out and --report: one would overwrite the other"),
    (["--square", "5", "--out", "{frame}"], "{frame}: writing it would overwrite the input {frame}; choose another "
                                            "output"),
])
def test_procam_bad_options_refused_before_anything(tmp_path, capsys, extra, message):
    frame = tmp_path / "c1" / "graycode_28.png"
    write_capture(tmp_path / "c1")
    before = frame.read_bytes()
    out = tmp_path / "rig.json"
    extra = [a.format(out=out, frame=frame) for a in extra]
    rc = main(["calibrate", "procam", str(tmp_path / "c1"), "--projector", "128x96", "--out", str(out), *extra])
    err = _err(capsys)
    assert rc == 2 and err.startswith("ringscan calibrate: error: ") and message.format(out=out, frame=frame) in err, err
    assert not out.exists() and frame.read_bytes() == before


def test_camera_out_must_not_overwrite_an_image_or_its_rig(tmp_path, capsys, capture_and_rig):
    cap, rig = capture_and_rig
    img = cap / "graycode_28.png"
    before = img.read_bytes()
    assert main(["calibrate", "camera", str(img), "--square", "5", "--out", str(img)]) == 2
    assert _err(capsys) == (f"ringscan calibrate: error: {img}: writing it would overwrite the input {img}; "
                            "choose another output")
    assert main(["calibrate", "camera", str(img), "--square", "5", "--out", str(rig), "--rig", str(rig)]) == 2
    assert _err(capsys).endswith(f"{rig}: given to both --out and --rig: one would overwrite the other")
    assert img.read_bytes() == before


def test_blurred_board_never_quotes_opencvs_placeholder_width(monkeypatch):
    """cv2.estimateChessboardSharpness returns 9999 when it cannot measure an edge: not a width to quote."""
    import cv2

    from ringscan.pipeline.calibrate.board import Board, detect_board

    img = np.zeros((240, 320), np.uint8)
    sq = 20
    for r in range(8):
        for c in range(10):
            if (r + c) % 2:
                img[20 + r * sq:20 + (r + 1) * sq, 40 + c * sq:40 + (c + 1) * sq] = 255
    board = Board(cols=9, rows=7, square=5.0)
    assert detect_board(img, board=board, name="b").found
    monkeypatch.setattr(cv2, "estimateChessboardSharpness", lambda *a, **k: ((9999.0, 0, 0, 0), None))
    v = detect_board(img, board=board, name="b")
    assert not v.found and "9999" not in v.reason and v.reason.startswith("blurred (OpenCV could not measure")


def test_import_view_names_checked_before_anything_is_written(tmp_path, capsys, capture_and_rig):
    """`import .` names the view by the folder's real name (before: '' wrote proj_u.png into /); a name that is not
    folder-safe, or two captures of one name, are refused before anything is written."""
    import os
    import shutil

    cap, rig = capture_and_rig
    out = tmp_path / "scan"
    cwd = os.getcwd()
    try:
        os.chdir(cap)
        assert main(["import", ".", "--rig", str(rig), "--projector", "128x96", "--out", str(out)]) == 0
    finally:
        os.chdir(cwd)
    capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == ["c1", "scan.json"]
    (cap / "sub").mkdir()
    out2 = tmp_path / "o" / "scan2"
    assert main(["import", f"{cap}/sub/..", "--rig", str(rig), "--projector", "128x96", "--out", str(out2)]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["scan2"]  # nothing beside --out
    assert (out2 / "c1" / "proj_u.png").is_file()
    for bad, why in (("bad:name", "contains ':'"), ("new\nline", "contains '\\n'"), (".hidden", "starts with a dot")):
        folder = tmp_path / "caps" / bad
        shutil.copytree(cap, folder)
        out = tmp_path / f"out_{len(why)}"
        rc = main(["import", str(folder), "--rig", str(rig), "--projector", "128x96", "--out", str(out)])
        err = _err(capsys)
        assert rc == 2 and f"is not a folder-safe name ({why})" in err, err
        assert not out.exists()
    other = tmp_path / "x" / "c1"
    shutil.copytree(cap, other)
    out = tmp_path / "two"
    rc = main(["import", str(cap), str(other), "--rig", str(rig), "--projector", "128x96", "--out", str(out)])
    assert rc == 2 and _err(capsys) == (f"ringscan import: error: {other}: has the name 'c1' of the capture {cap}: two "
                                        "views of one name (give capture folders of different names)")
    assert not out.exists()


def test_import_into_an_existing_scan_is_refused(tmp_path, capsys, capture_and_rig):
    cap, rig = capture_and_rig
    out = tmp_path / "scan"
    assert main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(out)]) == 0
    capsys.readouterr()
    before = (out / "scan.json").read_bytes()
    rc = main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(out)])
    assert rc == 2 and _err(capsys) == (f"ringscan import: error: {out}: already holds a scan (scan.json); choose "
                                        "another folder (import writes a new scan)")
    assert (out / "scan.json").read_bytes() == before


def test_import_rig_that_is_a_fifo_or_a_device(tmp_path, capsys, capture_and_rig):
    import os

    cap, _ = capture_and_rig
    fifo = tmp_path / "rig.json.fifo"
    os.mkfifo(fifo)
    for rig in (fifo, "/dev/zero", tmp_path / "calib.xml"):
        if str(rig).endswith(".xml"):
            os.mkfifo(rig)
        rc = main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(tmp_path / "s")])
        err = _err(capsys)
        assert rc == 2 and err.startswith(f"ringscan import: error: {rig}: is a ") and "not a regular file" in err, err
    assert not (tmp_path / "s").exists()


def test_import_into_a_folder_another_run_holds_is_refused(tmp_path, capsys, capture_and_rig):
    import os

    from ringscan.pipeline.formats.atomic import LOCK_NAME, lock_folder

    cap, rig = capture_and_rig
    out = tmp_path / "scan"
    out.mkdir()
    with lock_folder(out, what="reconstruct"):  # flock: a second open of the file conflicts, even in one process
        rc = main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(out)])
        assert rc == 2 and _err(capsys) == (f"ringscan import: error: {out}: in use by another ringscan run "
                                            f"(reconstruct, process {os.getpid()}); wait for it to end or choose "
                                            f"another output folder (lock file {LOCK_NAME})")
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    assert main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["c1", "scan.json"]
