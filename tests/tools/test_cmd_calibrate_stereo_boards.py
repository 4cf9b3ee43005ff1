"""``ringscan calibrate stereo``: ChArUco image pairs of a known two-camera rig, rendered, give back its
pose in OpenCV's sample layout (what ``ringscan import --rig`` reads); unpaired input is a usage error."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.board import Board
from ringscan.pipeline.calibrate.opencv_files import read_stereo_calibration
from ringscan.tools.cli import main
from tests.support.synthetic_captures import render_charuco

BOARD = Board(cols=9, rows=7, square=30.0, charuco="DICT_5X5_100")
K = np.array([[900.0, 0, 319.5], [0, 900.0, 239.5], [0, 0, 1]])
R_TRUE = cv2.Rodrigues(np.array([0.0, -np.radians(10.0), 0.0]))[0]
T_TRUE = np.array([-100.0, 0.0, 10.0])
POSES = [((0.5, -0.2, 0.0), (-130.0, -95.0, 560.0)), ((-0.4, 0.3, 0.1), (-110.0, -90.0, 600.0)),
         ((0.2, 0.5, -0.1), (-120.0, -80.0, 580.0)), ((-0.3, -0.4, 0.0), (-125.0, -100.0, 620.0))]


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    d = tmp_path_factory.mktemp("pairs")
    left, right = [], []
    for i, (rv, tv) in enumerate(POSES):
        r = cv2.Rodrigues(np.array(rv))[0]
        for cam, R, T, out in ((1, np.eye(3), np.zeros(3), left), (2, R_TRUE, T_TRUE, right)):
            img = render_charuco(BOARD, K=K, dist=np.zeros(5), size=(640, 480), rvec=cv2.Rodrigues(R @ r)[0],
                                 tvec=R @ np.array(tv) + T, supersample=2, seed=i + 10 * cam)
            p = d / f"cam{cam}_{i:02d}.png"
            cv2.imwrite(str(p), img)
            out.append(str(p))
    return left, right


def test_stereo_writes_the_pair_that_import_reads(pairs, tmp_path, capsys):
    left, right = pairs
    out = tmp_path / "stereo.yml"
    board = ["--board", "9x7", "--square", "30", "--charuco", "DICT_5X5_100"]
    rc = main(["calibrate", "stereo", "--cam1", *left, "--cam2", *right, *board, "--out", str(out),
               "--report", str(tmp_path / "r.json"), "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "pair: RMS reprojection error" in text and f"wrote {out}" in text
    cal = read_stereo_calibration(out)
    dR = np.degrees(np.linalg.norm(cv2.Rodrigues(np.asarray(cal["R"]) @ R_TRUE.T)[0]))
    # 4 rendered poses, corners to ~0.08 px: the intrinsics to a few tenths of a percent, the rotation
    # to a fraction of a degree; camera 2's offset along the view (T's z) trades against the focal
    # lengths over so few poses, a few percent of the 100 mm baseline (measured 2.4 mm)
    assert dR < 0.5
    assert np.linalg.norm(np.asarray(cal["T"]).ravel() - T_TRUE) < 0.04 * np.linalg.norm(T_TRUE)
    assert np.asarray(cal["cam1_K"])[0, 0] == pytest.approx(900.0, rel=0.01)


def test_unpaired_images_are_a_usage_error(pairs, tmp_path, capsys):
    left, right = pairs
    board = ["--board", "9x7", "--square", "30", "--charuco", "DICT_5X5_100"]
    rc = main(["calibrate", "stereo", "--cam1", *left, "--cam2", *right[:-1], *board, "--out",
               str(tmp_path / "s.yml")])
    err = capsys.readouterr().err
    assert rc == 2 and "give them in pairs" in err and not (tmp_path / "s.yml").exists()
    rc = main(["calibrate", "stereo", "--cam1", *left, "--cam2", *right, *board, "--out", str(tmp_path / "s.json")])
    assert rc == 2 and "needs .yml, .yaml or .xml" in capsys.readouterr().err
