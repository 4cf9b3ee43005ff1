"""Two cameras from board pairs (pipeline/calibrate/stereo_boards.py): synthetic corners seen by a
known pair recover its pose; pairs out of order and too few pairs are said."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.board import Board, BoardView, board_points
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.stereo_boards import MAX_PAIR_RMS_PX, calibrate_stereo_boards

BOARD = Board(9, 7, 30.0)
SIZE = (1280, 1024)
K1 = np.array([[1500.0, 0, 640.0], [0, 1500.0, 512.0], [0, 0, 1]])
K2 = np.array([[1450.0, 0, 630.0], [0, 1450.0, 520.0], [0, 0, 1]])
R_TRUE = cv2.Rodrigues(np.array([0.01, -np.radians(8.0), 0.02]))[0]
T_TRUE = np.array([-120.0, 2.0, 8.0])  # mm: camera 2 about 120 mm to the right of camera 1
POSES = [(25, 0, 600), (0, 25, 650), (-20, -20, 700), (15, -25, 620), (-25, 10, 680), (10, 30, 640)]


def pair(i, ax, ay, z, noise=0.05):
    """Camera 1's and camera 2's view of the board turned by ax, ay degrees, its centre z mm in front."""
    r = cv2.Rodrigues(np.array([np.radians(ax), np.radians(ay), 0.0]))[0]
    pts = board_points(BOARD).astype(np.float64)
    t = np.array([0.0, 0.0, z]) - r @ pts.mean(0)
    rng = np.random.default_rng(i)
    out = []
    for K, R, T in ((K1, np.eye(3), np.zeros(3)), (K2, R_TRUE, T_TRUE)):
        img, _ = cv2.projectPoints(pts, cv2.Rodrigues(R @ r)[0], R @ t + T, K, np.zeros(5))
        img = img.reshape(-1, 2) + rng.normal(0, noise, (pts.shape[0], 2))
        out.append(BoardView(f"v{i}", True, "", img.astype(np.float32), np.arange(pts.shape[0], dtype=np.int32)))
    return out


def views():
    ps = [pair(i, *p) for i, p in enumerate(POSES)]
    return [a for a, _ in ps], [b for _, b in ps]


def test_pairs_recover_the_pose():
    v1, v2 = views()
    cal = calibrate_stereo_boards(v1, v2, board=BOARD, size1=SIZE, size2=SIZE)
    dR = cv2.Rodrigues(cal.R @ R_TRUE.T)[0]
    # the pose holds each camera's intrinsics, fitted from 6 views: their principal points are known to
    # ~0.7 px (the fit's own standard deviation), which turns a camera by up to 3 x 0.7 / 1500 rad, 0.08 deg;
    # the baseline's 120 mm come out within a fraction of a millimetre
    assert np.degrees(np.linalg.norm(dR)) < 3 * np.degrees(max(cal.camera1.std[2], cal.camera2.std[2]) / 1450)
    assert np.linalg.norm(cal.T - T_TRUE) < 0.5
    assert cal.rms < 0.1 and cal.problems == [] and len(cal.pairs) == len(POSES)
    c1, c2 = cal.cameras()
    assert np.allclose(c1.R, np.eye(3)) and np.allclose(c2.t, cal.T)
    assert cal.report()["baseline"] == pytest.approx(np.linalg.norm(T_TRUE), abs=0.2)


def test_pairs_out_of_order_are_said():
    v1, v2 = views()
    v2 = [v2[1], v2[0], *v2[2:]]  # the first two of camera 2 swapped
    cal = calibrate_stereo_boards(v1, v2, board=BOARD, size1=SIZE, size2=SIZE)
    assert any("out of order" in p for p in cal.problems)
    assert max(cal.per_pair) > MAX_PAIR_RMS_PX


def test_unequal_lists_and_too_few_pairs_are_refused():
    v1, v2 = views()
    with pytest.raises(CalibrationError, match="in pairs"):
        calibrate_stereo_boards(v1, v2[:-1], board=BOARD, size1=SIZE, size2=SIZE)
    lost = [BoardView(v.name, False, "not found", None, None) if i >= 2 else v for i, v in enumerate(v2)]
    # camera 2 then has too few views of its own: the camera fit refuses first
    with pytest.raises(CalibrationError):
        calibrate_stereo_boards(v1, lost, board=BOARD, size1=SIZE, size2=SIZE)
