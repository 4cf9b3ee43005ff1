"""Camera intrinsics from board views (OpenCV's ``calibrateCamera``).

With few views OpenCV's full model (k1, k2, p1, p2, k3) is not determined: with
three views of a board k3 runs away (to ~950 with k2 ~ -36 on the procam captures)
while the reprojection error hardly moves. :class:`CameraSettings` therefore fixes
k3 (and, with very few views, the tangential terms) unless enough views are given;
the choice is reported (``CameraCalibration.fixed``).

A wide-angle lens may need OpenCV's rational model (``lens_model="rational"``: k1..k6,
8 coefficients) or its thin-prism model (``"thin-prism"``: + s1..s4, 12). Their
coefficients trade against each other (numerator against denominator), so their
standard deviations say little; instead the fit is held against what the views
must show for such a model (:func:`lens_problems`): enough distinct views, board
corners reaching out towards every corner of the image (the model extrapolates
beyond them), and a radial map that still rises at the image's corners (a fitted
lens that folds back inside the image is wrong there).

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
           "lens_problems", "board_tilts", "tilt_problems", "MIN_VIEWS", "LENS_MODELS", "DIST_NAMES"]

log = logging.getLogger(__name__)

MIN_VIEWS = 3
"""Fewest distinct board poses any calibration accepts: two poses leave the focal
length and the principal point trading against each other (Zhang 2000)."""

LENS_MODELS = {"standard": 5, "rational": 8, "thin-prism": 12}
"""Lens model -> the count of distortion coefficients it fits (OpenCV's order, :data:`DIST_NAMES`)."""

DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")
"""OpenCV's distortion coefficients, in its order."""


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
    lens_model: str = "standard"
    """"standard" (k1, k2, p1, p2, k3), "rational" (+ k4, k5, k6: OpenCV's
    CALIB_RATIONAL_MODEL) or "thin-prism" (+ s1..s4 as well: CALIB_THIN_PRISM_MODEL)."""
    wide_min_views: int = 8
    """The rational and thin-prism models need this many distinct views (fewer: a problem)."""
    min_tilt_deg: float = 5.0
    """Least tilt of the board (the angle between its normal and the camera's optical axis) that some view must
    show: boards that all face the camera show no perspective, so the focal length trades against the board's
    distance, and the fit's own standard deviation of fx collapses with it (ten fronto-parallel views of a
    1500 px camera: fx 138481 +- 23 px at 0.068 px RMS; at 5 degrees of tilt it is 0.5 % off, its deviation
    0.3 %: tests/pipeline/calibrate/test_camera.py)."""
    min_corner_reach: float = 0.8
    """Rational and thin-prism models: in each quarter of the image the board's corners
    must reach this fraction of the way from the principal point to the image's corner
    (less: a problem; the model's high powers of r extrapolate beyond the corners seen)."""

    def __post_init__(self):
        if self.lens_model not in LENS_MODELS:
            raise ValueError(f"--lens-model: expected one of {', '.join(LENS_MODELS)}, got {self.lens_model!r}")
        if self.lens_model != "standard" and self.fix_k3 is not None:
            raise ValueError(f"--fix-k3 applies to the standard lens model only (the {self.lens_model} model always "
                             f"fits k3)")
        for name in ("min_views", "k3_min_views", "tangential_min_views", "wide_min_views"):
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
        t = self.min_tilt_deg
        if isinstance(t, bool) or not (isinstance(t, (int, float)) and math.isfinite(t) and 0 <= t < 90):
            raise ValueError(f"CameraSettings.min_tilt_deg: expected degrees from 0 to 90, got {t!r}")
        r = self.min_corner_reach
        if isinstance(r, bool) or not (isinstance(r, (int, float)) and math.isfinite(r) and 0 <= r <= 1):
            raise ValueError(f"CameraSettings.min_corner_reach: expected a number from 0 to 1, got {r!r}")


@dataclass
class CameraCalibration:
    """The result of a calibration."""

    K: np.ndarray
    """3x3 intrinsics."""
    dist: np.ndarray
    """(5,), (8,) or (12,) distortion in OpenCV's order (:data:`DIST_NAMES`), by the lens model."""
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
    lens_model: str = "standard"
    """The lens model fitted (:data:`LENS_MODELS`)."""
    std: np.ndarray = field(default_factory=lambda: np.zeros(9))
    """(4 + n,) standard deviations of fx, fy, cx, cy and the n distortion coefficients from the fit (0 where
    held fixed)."""
    duplicates: list[str] = field(default_factory=list)
    """Views left out as the same board pose as an earlier view ("name = earlier (d px)")."""
    problems: list[str] = field(default_factory=list)
    """What the views do not determine (empty: a calibration to stand behind)."""


def calibration_flags(n_views: int, settings: CameraSettings) -> tuple[int, list[str]]:
    """OpenCV flags for ``n_views`` views, and the names of what they hold fixed."""
    flags, fixed = 0, []
    fix_k3 = settings.fix_k3 if settings.fix_k3 is not None else n_views < settings.k3_min_views
    fix_tan = settings.fix_tangential if settings.fix_tangential is not None else n_views < settings.tangential_min_views
    if settings.lens_model != "standard":
        # the wide models fit k3 with k4..k6 (and s1..s4): --fix-k3 is refused for them
        flags |= cv2.CALIB_RATIONAL_MODEL
        if settings.lens_model == "thin-prism":
            flags |= cv2.CALIB_THIN_PRISM_MODEL
    elif fix_k3:
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


def board_tilts(rvecs) -> np.ndarray:
    """Each view's board tilt (degrees): the angle between the board's normal and the camera's optical axis."""
    return np.array([math.degrees(math.acos(min(1.0, abs(float(cv2.Rodrigues(np.asarray(r, float))[0][2, 2])))))
                     for r in rvecs])


def tilt_problems(rvecs, *, settings: CameraSettings, what: str) -> list[str]:
    """The views' board tilts, when every one is below ``settings.min_tilt_deg``: the focal length is not
    determined (and the fit's standard deviation of it cannot be trusted)."""
    tilts = board_tilts(rvecs)
    if not tilts.size or tilts.max() >= settings.min_tilt_deg:
        return []
    return [f"{what}: the board faces the camera in every view (tilted at most {tilts.max():.1f} degrees < "
            f"{settings.min_tilt_deg:g}): the views do not determine the focal length (it trades against the "
            "board's distance); add views with the board tilted 20 to 45 degrees"]


def _radial(dist: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Distorted radius r (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6) (normalised units)."""
    d = np.concatenate([np.asarray(dist, float).ravel(), np.zeros(8)])
    r2 = r * r
    num = 1 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
    den = 1 + r2 * (d[5] + r2 * (d[6] + r2 * d[7]))
    return r * num / den


def lens_problems(K: np.ndarray, dist: np.ndarray, img: list[np.ndarray], size: tuple[int, int], *,
                  settings: CameraSettings, what: str) -> list[str]:
    """What views cannot determine of a wide (rational, thin-prism) lens model.

    Args:
        K, dist: the fit.
        img: the detected corners of each view used, (N_i, 1, 2) px.
        size: image (width, height).

    Three checks: at least ``settings.wide_min_views`` views; in each quarter of the
    image (about the principal point) corners reaching ``settings.min_corner_reach``
    of the way to the image's corner; and a radial map r -> r_d that rises all the way
    out to the image's farthest corner (tangential and prism terms left out: they are
    small where the radial map can fold).
    """
    out = []
    n_coef = LENS_MODELS[settings.lens_model]
    if len(img) < settings.wide_min_views:
        out.append(f"{what} {settings.lens_model} lens model: {len(img)} distinct views < {settings.wide_min_views}: "
                   f"too few to determine its {n_coef} distortion coefficients")
    cx, cy = float(K[0, 2]), float(K[1, 2])
    w, h = size
    pts = np.concatenate([p.reshape(-1, 2) for p in img]).astype(np.float64) - (cx, cy)
    short = []
    for name, (u, v) in (("top-left", (0.0, 0.0)), ("top-right", (w - 1.0, 0.0)), ("bottom-left", (0.0, h - 1.0)),
                         ("bottom-right", (w - 1.0, h - 1.0))):
        corner = np.array([u - cx, v - cy])
        # corners in this quarter: on the image corner's side of the principal point both ways
        q = pts[(np.sign(pts[:, 0]) == np.sign(corner[0])) & (np.sign(pts[:, 1]) == np.sign(corner[1]))]
        reach = float(np.max(np.linalg.norm(q, axis=1))) / float(np.linalg.norm(corner)) if len(q) else 0.0
        if reach < settings.min_corner_reach:
            short.append(f"{name} {100 * reach:.0f} %")
    if short:
        out.append(f"{what} {settings.lens_model} lens model: the board's corners reach only {', '.join(short)} of the "
                   f"way to the image's corners (< {100 * settings.min_corner_reach:g} %): the model is not determined "
                   f"there; add views with the board in the image's corners")
    # the farthest image corner, in normalised distorted units
    far = max(math.hypot((u - cx) / K[0, 0], (v - cy) / K[1, 1]) for u in (0.0, w - 1.0) for v in (0.0, h - 1.0))
    r = np.linspace(0.0, 20.0, 20001)[1:]  # out to 87 degrees off axis, in steps of 0.001
    rd = _radial(dist, r)
    down = np.flatnonzero(np.diff(rd) <= 0)
    reached = np.flatnonzero(rd >= far)
    first_down = int(down[0]) if down.size else None
    if first_down is not None and (not reached.size or reached[0] > first_down):
        top = float(rd[first_down])
        out.append(f"{what} {settings.lens_model} lens model: its radial map turns back {top * K[0, 0]:.0f} px from "
                   f"the principal point, inside the image (its farthest corner is {far * K[0, 0]:.0f} px away): the "
                   f"fitted lens folds; the views do not determine it there")
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
    n = LENS_MODELS[settings.lens_model]
    rms, K, dist, rvecs, tvecs, std_int, _, _ = cv2.calibrateCameraExtended(obj, img, tuple(size), None, None,
                                                                            flags=flags, criteria=crit)
    if n > 5:
        # OpenCV starts from a distortion-free guess, from which a strong wide-angle lens can
        # lead it into a local minimum (RMS 0.1-0.5 px for 0.07 px of noise on the tests'
        # lenses); a second start from the standard model's fit finds the true one where the
        # first does not, and vice versa: the lower RMS is kept.
        std_flags = flags & ~(cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL)
        _, K0, d0, _, _ = cv2.calibrateCamera(obj, img, tuple(size), None, None, flags=std_flags, criteria=crit)
        d0 = np.concatenate([np.asarray(d0, float).ravel()[:5], np.zeros(n - 5)])
        second = cv2.calibrateCameraExtended(obj, img, tuple(size), K0, d0, flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS,
                                             criteria=crit)
        if np.isfinite(second[0]) and second[0] < rms:
            rms, K, dist, rvecs, tvecs, std_int = second[:6]
    std = np.full(4 + n, np.nan)
    si = np.asarray(std_int, float).ravel()[:4 + n]
    std[:si.size] = si
    dist = np.asarray(dist, float).ravel()[:n]
    dist = np.concatenate([dist, np.zeros(n - dist.size)])
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(None, f"{what} calibration diverged (K = {K.tolist()})")
    per = view_errors(obj, img, K, dist, rvecs, tvecs)
    names = [v.name for v in used]
    out = outlier_views(names, per, settings)
    problems = tilt_problems(rvecs, settings=settings, what=what) + intrinsics_problems(K, std, size,
                                                                                       settings=settings, what=what)
    if settings.lens_model != "standard":
        problems += lens_problems(K, dist, img, size, settings=settings, what=what)
    log.info("%s: RMS %.3f px over %d views, fx %.1f fy %.1f, fixed %s", what, rms, len(used), K[0, 0], K[1, 1], fixed)
    return CameraCalibration(K=K, dist=dist, rms=float(rms), size=(int(size[0]), int(size[1])), names=names,
                             per_view=per, rvecs=list(rvecs), tvecs=list(tvecs), fixed=fixed, outliers=out,
                             std=std, duplicates=dups, problems=problems, lens_model=settings.lens_model)


def camera_block(cal: CameraCalibration) -> dict:
    """The rig file's camera intrinsics (``width``, ``height``, ``K``, ``dist``) of a calibration."""
    return {"width": cal.size[0], "height": cal.size[1], "K": cal.K.tolist(), "dist": cal.dist.tolist()}


def calibration_report(cal: CameraCalibration) -> dict:
    """A JSON-able summary: RMS overall and per view, what was fixed, the outliers."""
    out = {"rms_px": cal.rms, "views": {n: float(e) for n, e in zip(cal.names, cal.per_view)},
           "fixed": list(cal.fixed), "outliers": list(cal.outliers),
           "fx": float(cal.K[0, 0]), "fy": float(cal.K[1, 1]), "cx": float(cal.K[0, 2]), "cy": float(cal.K[1, 2]),
           "dist": cal.dist.tolist(),
           "std": {k: float(v) for k, v in zip(("fx", "fy", "cx", "cy", *DIST_NAMES), cal.std)},
           "duplicates": list(cal.duplicates), "problems": list(cal.problems)}
    if cal.lens_model != "standard":  # the standard model's report is as it was
        out["lens_model"] = cal.lens_model
    return out
