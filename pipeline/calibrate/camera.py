"""Camera intrinsics from board views (OpenCV's ``calibrateCamera``).

With few views OpenCV's full model (k1, k2, p1, p2, k3) is not determined: with
three views of a board k3 runs away (to ~950 with k2 ~ -36 on the procam captures)
while the reprojection error hardly moves. :class:`CameraSettings` therefore fixes
k3 (and, with very few views, the tangential terms) unless enough views are given;
the choice is reported (``CameraCalibration.fixed``).

A calibration also says what it cannot determine (``CameraCalibration.problems``):
views that show the same board pose (the same capture given twice, a board that
did not move) are counted once and left out of the fit, and too few *distinct*
views is an error; the standard deviations of the intrinsics that the fit itself
gives (``cv2.calibrateCameraExtended``) are held against
:class:`CameraSettings`' bounds, and so is the pixel aspect fy / fx. One pose given
three times fits at 0.35 px RMS with fx 12 % off: the RMS alone says nothing.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ringscan.pipeline.calibrate.board import Board, BoardView, board_points
from ringscan.pipeline.calibrate.errors import CalibrationError

__all__ = ["CameraSettings", "CameraCalibration", "calibrate_camera", "calibration_flags", "view_errors",
           "reprojection_residuals", "camera_block", "calibration_report", "distinct_views", "intrinsics_problems",
           "MIN_VIEWS"]

log = logging.getLogger(__name__)

MIN_VIEWS = 3
"""Fewest distinct board poses any calibration accepts: two poses leave the focal
length and the principal point trading against each other (Zhang 2000)."""


@dataclass(frozen=True)
class CameraSettings:
    """Camera (and projector) calibration settings."""

    min_views: int = 3
    """Fewest usable *distinct* views (at least :data:`MIN_VIEWS`); fewer is an error."""
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
    duplicate_px: float = 1.0
    """Two views whose common corners lie within this RMS distance (px) show the same
    board pose: the later one is left out (it adds no constraint, only weight)."""
    max_focal_std: float = 0.02
    """Largest standard deviation of fx, fy as a fraction of their value (the fit's
    own estimate); above it the views do not determine the focal length."""
    max_center_std: float = 0.05
    """Largest standard deviation of cx, cy as a fraction of the image width, height."""
    max_aspect: float = 1.25
    """Largest fy / fx (or fx / fy): cameras and projectors have square pixels to a
    few percent, so a larger ratio is a fit that ran away."""

    def __post_init__(self):
        for name in ("min_views", "k3_min_views", "tangential_min_views"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int):
                raise ValueError(f"CameraSettings.{name}: expected an integer, got {v!r}")
        if self.min_views < MIN_VIEWS:
            raise ValueError(f"--min-views: expected an integer >= {MIN_VIEWS} (fewer distinct board poses cannot "
                             f"determine the focal length and principal point), got {self.min_views}")
        for name in ("outlier_factor", "duplicate_px", "max_focal_std", "max_center_std"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"CameraSettings.{name}: expected a positive number, got {v!r}")
        if not (isinstance(self.max_aspect, (int, float)) and math.isfinite(self.max_aspect) and self.max_aspect > 1):
            raise ValueError(f"CameraSettings.max_aspect: expected a number > 1, got {self.max_aspect!r}")


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
    std: np.ndarray = field(default_factory=lambda: np.zeros(9))
    """(9,) standard deviations of fx, fy, cx, cy, k1, k2, p1, p2, k3 from the fit (0 where held fixed)."""
    duplicates: list[str] = field(default_factory=list)
    """Views left out as the same board pose as an earlier view ("name = earlier (d px)")."""
    problems: list[str] = field(default_factory=list)
    """What the views do not determine (empty: a calibration to stand behind)."""


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


def _same_pose_px(a: BoardView, b: BoardView) -> float | None:
    """RMS distance (px) between the common corners of two views; None with fewer than 4 in common."""
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if common.size < 4:
        return None
    d = a.corners.reshape(-1, 2)[ia].astype(np.float64) - b.corners.reshape(-1, 2)[ib].astype(np.float64)
    return float(np.sqrt(np.mean(np.sum(d * d, 1))))


def distinct_views(views: list[BoardView], *, tol_px: float) -> tuple[list[int], list[str]]:
    """Indices of the views that show distinct board poses (the first of each), and
    a note per view left out ("name = earlier (d px)").

    Two found views show the same pose when their common corners lie within
    ``tol_px`` RMS of each other (the same image given twice, a board that did not
    move between shots).
    """
    keep: list[int] = []
    notes: list[str] = []
    for i, v in enumerate(views):
        same = None
        for k in keep:
            d = _same_pose_px(views[k], v)
            if d is not None and d <= tol_px:
                same = (k, d)
                break
        if same is None:
            keep.append(i)
        else:
            notes.append(f"{v.name} = {views[same[0]].name} ({same[1]:.2f} px)")
    return keep, notes


def intrinsics_problems(K: np.ndarray, std: np.ndarray, size: tuple[int, int], *, settings: CameraSettings,
                        what: str) -> list[str]:
    """What a fit's intrinsics and their standard deviations say the views do not determine."""
    out = []
    fx, fy = float(K[0, 0]), float(K[1, 1])
    for name, v, s in (("fx", fx, std[0]), ("fy", fy, std[1])):
        if not (np.isfinite(s) and s <= settings.max_focal_std * v):
            out.append(f"{what} {name} {v:.1f} +- {s:.1f} px ({100 * s / v:.1f} % > "
                       f"{100 * settings.max_focal_std:g} %): the views do not determine the focal length")
    for name, v, s, n in (("cx", K[0, 2], std[2], size[0]), ("cy", K[1, 2], std[3], size[1])):
        if not (np.isfinite(s) and s <= settings.max_center_std * n):
            out.append(f"{what} {name} {v:.1f} +- {s:.1f} px (> {100 * settings.max_center_std:g} % of the "
                       f"image): the views do not determine the principal point")
    if max(fx / fy, fy / fx) > settings.max_aspect:
        out.append(f"{what} fy / fx = {fy / fx:.2f} (fx {fx:.1f}, fy {fy:.1f}): pixels are square to a few "
                   f"percent; the fit ran away")
    return out


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

    Views of the same board pose count once (see :func:`distinct_views`); what the
    fit leaves undetermined is listed in ``problems`` (the caller decides whether
    to write such a calibration).

    Raises:
        CalibrationError: no view shows the board, or fewer than ``settings.min_views``
            distinct ones do.
    """
    if len(size) != 2 or min(size) <= 0:
        raise ValueError(f"calibrate_camera: size must be (width, height) > 0, got {size}")
    found = [v for v in views if v.found]
    if not found:
        why = "; ".join(f"{v.name}: {v.reason}" for v in views[:8]) or "no images given"
        raise CalibrationError(None, f"{what} calibration: no image shows the {board.cols}x{board.rows} board ({why})")
    keep, dups = distinct_views(found, tol_px=settings.duplicate_px)
    used = [found[i] for i in keep]
    if len(used) < settings.min_views:
        same = f"; the same board pose: {', '.join(dups)}" if dups else ""
        raise CalibrationError(None, f"{what} calibration: only {len(used)} distinct board pose(s) "
                                     f"({', '.join(v.name for v in used)}); need at least {settings.min_views}"
                                     f"{same}")
    if dups:
        log.info("%s: left out as the same board pose as an earlier view: %s", what, ", ".join(dups))
    pts = board_points(board)
    obj = [pts[v.ids].reshape(-1, 1, 3) for v in used]
    img = [v.corners.reshape(-1, 1, 2).astype(np.float32) for v in used]
    flags, fixed = calibration_flags(len(used), settings)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs, std_int, _, _ = cv2.calibrateCameraExtended(obj, img, tuple(size), None, None,
                                                                            flags=flags, criteria=crit)
    std = np.full(9, np.nan)
    si = np.asarray(std_int, float).ravel()[:9]
    std[:si.size] = si
    dist = np.asarray(dist, float).ravel()[:5]
    dist = np.concatenate([dist, np.zeros(5 - dist.size)])
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(None, f"{what} calibration diverged (K = {K.tolist()})")
    per = view_errors(obj, img, K, dist, rvecs, tvecs)
    names = [v.name for v in used]
    out = outlier_views(names, per, settings)
    problems = intrinsics_problems(K, std, size, settings=settings, what=what)
    log.info("%s: RMS %.3f px over %d views, fx %.1f fy %.1f, fixed %s", what, rms, len(used), K[0, 0], K[1, 1], fixed)
    return CameraCalibration(K=K, dist=dist, rms=float(rms), size=(int(size[0]), int(size[1])), names=names,
                             per_view=per, rvecs=list(rvecs), tvecs=list(tvecs), fixed=fixed, outliers=out,
                             std=std, duplicates=dups, problems=problems)


def camera_block(cal: CameraCalibration) -> dict:
    """The rig file's camera intrinsics (``width``, ``height``, ``K``, ``dist``) of a calibration."""
    return {"width": cal.size[0], "height": cal.size[1], "K": cal.K.tolist(), "dist": cal.dist.tolist()}


def calibration_report(cal: CameraCalibration) -> dict:
    """A JSON-able summary: RMS overall and per view, what was fixed, the outliers."""
    return {"rms_px": cal.rms, "views": {n: float(e) for n, e in zip(cal.names, cal.per_view)},
            "fixed": list(cal.fixed), "outliers": list(cal.outliers),
            "fx": float(cal.K[0, 0]), "fy": float(cal.K[1, 1]), "cx": float(cal.K[0, 2]), "cy": float(cal.K[1, 2]),
            "dist": cal.dist.tolist(),
            "std": {k: float(v) for k, v in zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"), cal.std)},
            "duplicates": list(cal.duplicates), "problems": list(cal.problems)}
