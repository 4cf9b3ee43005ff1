"""Camera calibration knows what its views cannot determine: repeated board poses,
too few distinct ones, intrinsics the fit leaves loose (synthetic corners projected
through a known camera)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.board import Board, BoardView, board_points
from ringscan.pipeline.calibrate.camera import CameraSettings, calibrate_camera, distinct_views
from ringscan.pipeline.calibrate.errors import CalibrationError

BOARD = Board(9, 7, 30.0)
SIZE = (1280, 1024)
K = np.array([[1500.0, 0, 640.0], [0, 1500.0, 512.0], [0, 0, 1]])


def tilted(name, ax, ay, z=600.0, shift=(0.0, 0.0), seed=0):
    """The board's corners seen by K: turned by ax, ay degrees about its centre, that centre at (shift, z)."""
    r = cv2.Rodrigues(np.array([np.radians(ax), np.radians(ay), 0.0]))[0]
    pts = board_points(BOARD).astype(np.float64)
    t = np.array([shift[0], shift[1], z]) - r @ pts.mean(0)
    img, _ = cv2.projectPoints(pts, cv2.Rodrigues(r)[0], t, K, np.zeros(5))
    img = img.reshape(-1, 2) + np.random.default_rng(seed).normal(0, 0.05, (pts.shape[0], 2))
    return BoardView(name, True, "", img.astype(np.float32), np.arange(pts.shape[0], dtype=np.int32))


GOOD = [tilted("a", 25, 0), tilted("b", 0, 25, seed=1), tilted("c", -20, -20, z=700, seed=2)]


def test_distinct_views_are_all_calibrated_and_nothing_is_flagged():
    cal = calibrate_camera(GOOD, board=BOARD, size=SIZE)
    assert cal.problems == [] and cal.duplicates == []
    assert abs(cal.K[0, 0] / 1500 - 1) < 0.01 and 0 < cal.std[0] < 0.02 * 1500


def test_one_pose_given_three_times_is_refused():
    # OpenCV fits the same pose three times at a small RMS; only one pose is known.
    same = [tilted("a", 25, 0, seed=s) for s in range(3)]
    keep, notes = distinct_views(same, tol_px=1.0)
    assert keep == [0] and len(notes) == 2 and "a = a" in notes[0]
    with pytest.raises(CalibrationError, match="only 1 distinct board pose"):
        calibrate_camera(same, board=BOARD, size=SIZE)


def test_a_repeated_view_is_left_out_of_the_fit():
    cal = calibrate_camera(GOOD + [tilted("c again", -20, -20, z=700, seed=7)], board=BOARD, size=SIZE)
    ref = calibrate_camera(GOOD, board=BOARD, size=SIZE)
    assert cal.names == ["a", "b", "c"] and len(cal.duplicates) == 1 and cal.duplicates[0].startswith("c again = c (")
    assert np.allclose(cal.K, ref.K)


def test_views_that_leave_the_intrinsics_loose_are_flagged():
    # Three boards facing the camera, only moved sideways: the principal point trades
    # against the board poses (cy comes out ~400 px off), and the fit's own deviations say so.
    flat = [tilted("a", 0, 0, shift=(-60, 0)), tilted("b", 0, 0, shift=(60, 0), seed=1),
            tilted("c", 0, 0, shift=(0, 60), seed=2)]
    cal = calibrate_camera(flat, board=BOARD, size=SIZE)
    assert any("do not determine the principal point" in p for p in cal.problems), cal.problems
    assert abs(cal.K[1, 2] - 512) > 100  # it really is wrong


def test_min_views_below_three_is_refused():
    for n in (-1, 0, 2):
        with pytest.raises(ValueError, match="min-views"):
            CameraSettings(min_views=n)
