"""Camera intrinsics from board views (OpenCV's ``calibrateCamera``).

With few views OpenCV's full model (k1, k2, p1, p2, k3) is not determined: with
three views of a board k3 runs away (to ~950 with k2 ~ -36 on the procam captures)
while the reprojection error hardly moves. :class:`CameraSettings` therefore fixes
k3 (and, with very few views, the tangential terms) unless enough views are given;
the choice is reported (``CameraCalibration.fixed``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from ringscan.pipeline.calibrate.board import Board, BoardView, board_points
from ringscan.pipeline.calibrate.errors import CalibrationError

__all__ = ["CameraSettings", "CameraCalibration", "calibrate_camera", "calibration_flags", "view_errors",
           "reprojection_residuals", "camera_block",
           "calibration_report"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraSettings:
    """Camera (and projector) calibration settings."""

    min_views: int = 3
    """Fewest usable views; fewer is an error."""
    k3_min_views: int = 8
    """k3 is estimated only from this many views up (fixed to 0 below)."""
    tangential_min_views: int = 3
    """p1, p2 are estimated only from this many views up (fixed to 0 below)."""
    fix_k3: bool | None = None
    """Force k3 fixed (True) or free (False); None: by ``k3_min_views``."""
    fix_tangential: bool | None = None
    """Force p1, p2 fixed (True) or free (False); None: by ``tangential_min_views``."""
    outlier_factor: float = 2.0
    """A view whose RMS error exceeds this many times the median view's (and 0.5 px)
    is named as spoiling the fit."""


@dataclass
class CameraCalibration:
    """The result of a calibration."""

    K: np.ndarray
    """3x3 intrinsics."""
    dist: np.ndarray
    """(5,) distortion k1, k2, p1, p2, k3."""
    rms: float
    """Overall RMS reprojection error (px)."""
    size: tuple[int, int]
    """Image (width, height)."""
    names: list[str]
    """Names of the views used."""
    per_view: np.ndarray
    """(n_views,) RMS reprojection error per view (px)."""
    rvecs: list[np.ndarray]
    """Board -> camera rotations (Rodrigues) per view."""
    tvecs: list[np.ndarray]
    """Board -> camera translations per view."""
    fixed: list[str] = field(default_factory=list)
    """Parameters held fixed (e.g. ['k3'])."""
    outliers: list[str] = field(default_factory=list)
    """Names of views that spoil the fit."""


def calibration_flags(n_views: int, settings: CameraSettings) -> tuple[int, list[str]]:
    """OpenCV flags for ``n_views`` views, and the names of what they hold fixed."""
    flags, fixed = 0, []
    fix_k3 = settings.fix_k3 if settings.fix_k3 is not None else n_views < settings.k3_min_views
    fix_tan = settings.fix_tangential if settings.fix_tangential is not None else n_views < settings.tangential_min_views
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
        fixed.append("k3")
    if fix_tan:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
        fixed += ["p1", "p2"]
    return flags, fixed


def view_errors(obj: list[np.ndarray], img: list[np.ndarray], K, dist, rvecs, tvecs) -> np.ndarray:
    """RMS reprojection error (px) of each view."""
    out = []
    for o, p, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o.astype(np.float64), r, t, K, dist)
        out.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - p.reshape(-1, 2)) ** 2, 1)))))
    return np.asarray(out)


def reprojection_residuals(views: list[BoardView], board: Board, cal: CameraCalibration) -> dict:
    """Each calibrated view's corners and their reprojection residuals.

    Returns:
        {view name: (corners (N, 2) px, residuals (N, 2) px: projected - detected)},
        in ``cal.names`` order.
    """
    by_name = {v.name: v for v in views if v.found}
    pts = board_points(board)
    out = {}
    for name, r, t in zip(cal.names, cal.rvecs, cal.tvecs):
        v = by_name.get(name)
        if v is None:
            continue
        proj, _ = cv2.projectPoints(pts[v.ids].reshape(-1, 1, 3).astype(np.float64), r, t, cal.K, cal.dist)
        c = v.corners.reshape(-1, 2).astype(np.float64)
        out[name] = (c, proj.reshape(-1, 2) - c)
    return out


def outlier_views(names: list[str], per_view: np.ndarray, settings: CameraSettings) -> list[str]:
    med = float(np.median(per_view))
    lim = max(settings.outlier_factor * med, 0.5)
    return [n for n, e in zip(names, per_view) if e > lim]


def calibrate_camera(
    views: list[BoardView],
    *,
    board: Board,
    size: tuple[int, int],
    settings: CameraSettings = CameraSettings(),
    what: str = "camera",
) -> CameraCalibration:
    """Intrinsics from the usable views of a board.

    Args:
        views: detections (rejected ones are skipped).
        board: the board (for its corner positions).
        size: image (width, height).
        settings: flags and limits.
        what: "camera" or "projector", for messages.

    Raises:
        CalibrationError: no view shows the board, or fewer than ``settings.min_views`` do.
    """
    if len(size) != 2 or min(size) <= 0:
        raise ValueError(f"calibrate_camera: size must be (width, height) > 0, got {size}")
    used = [v for v in views if v.found]
    if not used:
        why = "; ".join(f"{v.name}: {v.reason}" for v in views[:8]) or "no images given"
        raise CalibrationError(None, f"{what} calibration: no image shows the {board.cols}x{board.rows} board ({why})")
    if len(used) < settings.min_views:
        raise CalibrationError(None, f"{what} calibration: only {len(used)} usable view(s) "
                                     f"({', '.join(v.name for v in used)}); need at least {settings.min_views}")
    pts = board_points(board)
    obj = [pts[v.ids].reshape(-1, 1, 3) for v in used]
    img = [v.corners.reshape(-1, 1, 2).astype(np.float32) for v in used]
    flags, fixed = calibration_flags(len(used), settings)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(size), None, None, flags=flags, criteria=crit)
    dist = np.asarray(dist, float).ravel()[:5]
    dist = np.concatenate([dist, np.zeros(5 - dist.size)])
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(None, f"{what} calibration diverged (K = {K.tolist()})")
    per = view_errors(obj, img, K, dist, rvecs, tvecs)
    names = [v.name for v in used]
    out = outlier_views(names, per, settings)
    log.info("%s: RMS %.3f px over %d views, fx %.1f fy %.1f, fixed %s", what, rms, len(used), K[0, 0], K[1, 1], fixed)
    return CameraCalibration(K=K, dist=dist, rms=float(rms), size=(int(size[0]), int(size[1])), names=names,
                             per_view=per, rvecs=list(rvecs), tvecs=list(tvecs), fixed=fixed, outliers=out)


def camera_block(cal: CameraCalibration) -> dict:
    """The rig file's camera intrinsics (``width``, ``height``, ``K``, ``dist``) of a calibration."""
    return {"width": cal.size[0], "height": cal.size[1], "K": cal.K.tolist(), "dist": cal.dist.tolist()}


def calibration_report(cal: CameraCalibration) -> dict:
    """A JSON-able summary: RMS overall and per view, what was fixed, the outliers."""
    return {"rms_px": cal.rms, "views": {n: float(e) for n, e in zip(cal.names, cal.per_view)},
            "fixed": list(cal.fixed), "outliers": list(cal.outliers),
            "fx": float(cal.K[0, 0]), "fy": float(cal.K[1, 1]), "cx": float(cal.K[0, 2]), "cy": float(cal.K[1, 2]),
            "dist": cal.dist.tolist()}
