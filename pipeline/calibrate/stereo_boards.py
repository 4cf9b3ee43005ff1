"""Two cameras from board pairs (``ringscan calibrate stereo``, docs/calibration.md §8).

Each camera is calibrated from its own board views (``calibrate_camera``: the same
checks as ``calibrate camera``), then the pair's pose from the views in which both
cameras found the board (``cv2.stereoCalibrate`` with the intrinsics held, on the
board corners both saw): X_cam2 = R X_cam1 + T, in the board's units (mm). The result
is what OpenCV's structured-light sample reads (``write_opencv_stereo_cameras``) and
what ``ringscan import --rig`` takes.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ringscan.pipeline.calibrate.board import Board, BoardView, board_points
from ringscan.pipeline.calibrate.camera import CameraCalibration, CameraSettings, calibrate_camera
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.formats.rig import Camera

log = logging.getLogger(__name__)

__all__ = ["StereoBoardCalibration", "calibrate_stereo_boards", "MIN_PAIRS", "MAX_PAIR_RMS_PX"]

MIN_PAIRS = 3
"""Fewest board poses both cameras must see for the pair's pose."""
MAX_PAIR_RMS_PX = 1.0
"""A pair's RMS reprojection error above this (px) is a problem: the two images were not
taken at one board pose (pairs out of order), or a camera moved."""
MIN_PAIR_CORNERS = 6
"""Fewest corners both cameras must see in a pair for it to count."""


@dataclass
class StereoBoardCalibration:
    """Two cameras and their relative pose."""

    camera1: CameraCalibration
    """Camera 1's own calibration."""
    camera2: CameraCalibration
    """Camera 2's own calibration."""
    R: np.ndarray
    """3x3 rotation camera 1 -> camera 2."""
    T: np.ndarray
    """(3,) translation (board units, mm): X_cam2 = R X_cam1 + T."""
    rms: float
    """RMS reprojection error of the pairs under the pose (px, both cameras)."""
    pairs: list[str]
    """Names (camera 1's image) of the pairs used."""
    per_pair: np.ndarray
    """(n_pairs,) RMS reprojection error of each pair (px)."""
    problems: list[str] = field(default_factory=list)
    """What the pairs do not determine (empty: a calibration to stand behind)."""

    @property
    def baseline(self) -> float:
        """Distance between the camera centres (board units)."""
        return float(np.linalg.norm(self.T))

    def cameras(self) -> tuple[Camera, Camera]:
        """The two cameras with camera 1's frame as the world frame."""
        c1, c2 = self.camera1, self.camera2
        return (Camera(width=c1.size[0], height=c1.size[1], K=c1.K, dist=c1.dist, R=np.eye(3), t=np.zeros(3)),
                Camera(width=c2.size[0], height=c2.size[1], K=c2.K, dist=c2.dist, R=self.R, t=self.T))

    def report(self) -> dict:
        """A JSON-able summary."""
        return {"R": self.R.tolist(), "T": self.T.tolist(), "baseline": self.baseline, "rms_px": self.rms,
                "pairs": list(self.pairs), "per_pair_px": [float(x) for x in self.per_pair],
                "camera1_rms_px": self.camera1.rms, "camera2_rms_px": self.camera2.rms,
                "problems": list(self.problems)}


def _pose(cal: CameraCalibration, name: str):
    i = cal.names.index(name)
    return cv2.Rodrigues(np.asarray(cal.rvecs[i], float))[0], np.asarray(cal.tvecs[i], float).reshape(3)


def calibrate_stereo_boards(views1: list[BoardView], views2: list[BoardView], *, board: Board,
                            size1: tuple[int, int], size2: tuple[int, int],
                            settings: CameraSettings = CameraSettings()) -> StereoBoardCalibration:
    """Both cameras' intrinsics and their relative pose from board views taken in pairs.

    Args:
        views1, views2: detections of the same board poses, pair by pair (equal length, in order).
        board: the board.
        size1, size2: each camera's image (width, height).
        settings: the camera fits' flags and limits (both cameras).

    Raises:
        CalibrationError: the lists differ in length, a camera cannot be calibrated, or fewer
            than ``MIN_PAIRS`` pairs show the board to both cameras.
    """
    if len(views1) != len(views2):
        raise CalibrationError(None, f"stereo calibration: {len(views1)} images of camera 1 but {len(views2)} of "
                                     "camera 2; give them in pairs (the same board pose, in the same order)")
    cal1 = calibrate_camera(views1, board=board, size=size1, settings=settings, what="camera 1")
    cal2 = calibrate_camera(views2, board=board, size=size2, settings=settings, what="camera 2")
    pts = board_points(board)
    obj, img1, img2, names = [], [], [], []
    for a, b in zip(views1, views2):
        if not (a.found and b.found and a.name in cal1.names and b.name in cal2.names):
            continue
        common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
        if common.size < MIN_PAIR_CORNERS:
            continue
        obj.append(pts[common].reshape(-1, 1, 3).astype(np.float32))
        img1.append(a.corners[ia].reshape(-1, 1, 2).astype(np.float32))
        img2.append(b.corners[ib].reshape(-1, 1, 2).astype(np.float32))
        names.append(a.name)
    if len(names) < MIN_PAIRS:
        raise CalibrationError(None, f"stereo calibration: both cameras see the board in only {len(names)} pair(s) "
                                     f"({', '.join(names) or 'none'}); need at least {MIN_PAIRS}")
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(obj, img1, img2, cal1.K, cal1.dist, cal2.K, cal2.dist, tuple(size1),
                                              flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    R = np.asarray(R, float)
    T = np.asarray(T, float).reshape(3)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(T)) and np.linalg.norm(T) > 0):
        raise CalibrationError(None, "stereo calibration diverged (no finite pose with a baseline)")
    rv = cv2.Rodrigues(R)[0]
    per = []
    for o, p1, p2 in zip(obj, img1, img2):
        _, r1, t1 = cv2.solvePnP(o, p1, cal1.K, cal1.dist)
        R1 = cv2.Rodrigues(r1)[0]
        q1, _ = cv2.projectPoints(o, r1, t1, cal1.K, cal1.dist)
        q2, _ = cv2.projectPoints(o, cv2.Rodrigues(R @ R1)[0], R @ t1.reshape(3) + T, cal2.K, cal2.dist)
        e = np.r_[(q1 - p1).reshape(-1, 2), (q2 - p2).reshape(-1, 2)]
        per.append(math.sqrt(float(np.mean(np.sum(e * e, axis=1)))))
    per = np.asarray(per)
    problems = [f"camera 1: {p}" for p in cal1.problems] + [f"camera 2: {p}" for p in cal2.problems]
    bad = [n for n, e in zip(names, per) if e > MAX_PAIR_RMS_PX]
    if bad:
        problems.append(f"{len(bad)} pair(s) reproject worse than {MAX_PAIR_RMS_PX:g} px under the pose "
                        f"({', '.join(bad[:5])}{', ...' if len(bad) > 5 else ''}): images out of order, or a "
                        "camera moved between them")
    log.info("stereo: RMS %.3f px over %d pairs, baseline %.2f, rotation %.3f deg", rms, len(names),
             float(np.linalg.norm(T)), math.degrees(float(np.linalg.norm(rv))))
    return StereoBoardCalibration(camera1=cal1, camera2=cal2, R=R, T=T, rms=float(rms), pairs=names, per_pair=per,
                                  problems=problems)
