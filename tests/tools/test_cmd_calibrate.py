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


def test_camera_without_a_board_exits_1_and_writes_nothing(tmp_path, procam, capsys):
    out = tmp_path / "cam.json"
    rc = main(["calibrate", "camera", str(procam / "capture_1" / "graycode_41.png"),
               str(procam / "capture_2" / "graycode_41.png"), "--square", "75", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1 and "no image shows the 9x7 board" in err and "Traceback" not in err
    assert not out.exists()


def test_procam_wrong_layout_exits_1(tmp_path, capsys):
    write_capture(tmp_path / "c1", projector=(128, 96))
    rig = tmp_path / "rig.json"
    rc = main(["calibrate", "procam", str(tmp_path / "c1"), "--square", "75", "--projector", "128x96",
               "--layout", "opencv-graycode-wb-first", "--out", str(rig)])
    assert rc == 1 and "not layout 'opencv-graycode-wb-first'" in capsys.readouterr().err
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


def test_response_with_a_pattern_that_matched_nothing_says_so(tmp_path, capsys):
    from ringscan.pipeline.formats.rig import default_rig, save_rig

    rig = tmp_path / "rig.json"
    save_rig(rig, default_rig())
    before = rig.read_bytes()
    pattern = str(tmp_path / "ramp" / "*.png")  # what the shell passes on when the glob matches nothing
    rc = main(["calibrate", "response", pattern, "--levels", "0", "128", "255", "--rig", str(rig)])
    assert rc == 1
    assert capsys.readouterr().err.strip() == (f"ringscan calibrate response: error: {pattern}: no file matches this "
                                               "pattern (the shell passed it on as it was)")
    assert rig.read_bytes() == before


def test_camera_plot_draws_the_residuals_of_the_fit(tmp_path, procam, capsys):
    import cv2

    from ringscan.pipeline.calibrate.board import Board, detect_board
    from ringscan.pipeline.calibrate.camera import calibrate_camera, reprojection_residuals
    from ringscan.pipeline.formats.images import read_image

    images = [procam / f"capture_{i}" / "graycode_40.png" for i in (1, 2, 3)]  # the white frames
    plot = tmp_path / "res.png"
    assert main(["calibrate", "camera", *map(str, images), "--square", "75", "--out", str(tmp_path / "c.json"),
                 "--plot", str(plot), "--no-progress"]) == 0
    assert f"wrote {plot}" in capsys.readouterr().out
    assert cv2.imread(str(plot)).shape == (560, 1200, 3)
    # The residuals drawn are the fit's: their RMS per view is OpenCV's per-view error.
    board = Board(9, 7, 75.0)
    views = [detect_board(read_image(p), board=board, name=f"v{i}") for i, p in enumerate(images)]
    cal = calibrate_camera(views, board=board, size=(1280, 1024))
    res = reprojection_residuals(views, board, cal)
    assert list(res) == cal.names
    for name, e in zip(cal.names, cal.per_view):
        corners, r = res[name]
        assert len(corners) == 63 and np.sqrt(np.mean(np.sum(r ** 2, axis=1))) == pytest.approx(e, rel=1e-6)
