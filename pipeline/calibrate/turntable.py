"""The turntable axis from a board seen at several table angles (the rig's ``turntable``
block, docs/design.md §11; docs/calibration.md, "The turntable axis").

A chessboard (or ChArUco board) lies or stands on the turntable and is
photographed at several table angles theta_k. The camera is calibrated in the world
frame (intrinsics and pose). Steps:

1. the board's corners in each view (:func:`~ringscan.pipeline.calibrate.board.detect_board`),
   its pose by ``cv2.solvePnP`` (board -> camera), turned into the world frame;
2. a plain chessboard's corner order may come out turned by 180 degrees in some
   views (OpenCV cannot tell a board from itself turned half a turn); each view
   takes the order whose turn relative to the first view is nearest to the
   table's own (about ``prior_axis``, world z by default);
3. a first axis from those relative turns: the direction every one of them leaves
   unchanged, and the point they all fix;
4. one joint least-squares fit of every corner in every view: the board's pose at
   table angle 0 (6 parameters) and the axis (direction 2, point 2), each view's
   board being the angle-0 board turned by theta_k about the axis (the
   turntable transform of docs/design.md §11), projected through the calibrated camera. Views whose
   reprojection error spoils the fit are named and left out, and the fit repeated.

The axis point written is where the axis meets the reference plane z = 0 (or,
for an axis nearly parallel to it, the point nearest the world origin).
``angle_error_deg`` per view compares the board's own turn with the table's: a
turntable that missed steps shows there.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from ringscan.pipeline.calibrate.board import Board, BoardSettings, BoardView, board_points, detect_board
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.rig import Camera, Rig, Turntable, Volume, turntable_transform
from ringscan.pipeline.formats.scan import Scan, read_view_frame
from ringscan.pipeline.geometry import project_points

__all__ = ["TurntableSettings", "TurntableCalibration", "board_views_of_scan", "calibrate_turntable",
           "rig_with_turntable", "axis_distance"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TurntableSettings:
    """Settings of the turntable-axis calibration."""

    board: BoardSettings = field(default_factory=BoardSettings)
    """Board detection thresholds."""
    min_views: int = 3
    """Fewest views with the board found."""
    min_span_deg: float = 30.0
    """The found views' table angles must span at least this (degrees): a small turn
    pins the axis direction badly."""
    outlier_factor: float = 3.0
    """A view whose RMS reprojection error exceeds this many times the median view's
    (and 0.5 px) spoils the fit: it is named and left out."""
    max_rms_px: float = 2.0
    """A fit whose RMS reprojection error exceeds this is refused: the views do not
    show one board turning about one axis (wrong angles, a board that slid, a camera
    calibrated for another pose)."""
    prior_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """A rough axis line (world; either sense), used only to choose between a chessboard's
    two corner orders; it must be within ~45 degrees of the true axis."""

    def __post_init__(self):
        if isinstance(self.min_views, bool) or not isinstance(self.min_views, int) or self.min_views < 2:
            raise ValueError(f"TurntableSettings.min_views: expected an integer >= 2, got {self.min_views!r}")
        for name in ("min_span_deg", "outlier_factor", "max_rms_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"TurntableSettings.{name}: expected a positive number, got {v!r}")
        a = np.asarray(self.prior_axis, float)
        if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-9:
            raise ValueError(f"TurntableSettings.prior_axis: expected a non-zero 3-vector, got {self.prior_axis!r}")


@dataclass
class TurntableCalibration:
    """The fitted turntable axis and how well it fits."""

    turntable: Turntable
    """The axis: ``axis_point`` (world, mm; on z = 0 where the axis crosses it) and unit ``axis_dir``."""
    rms_px: float
    """RMS reprojection error of every corner of the views used (px)."""
    names: list[str]
    """The views used."""
    angles_deg: np.ndarray
    """Their table angles."""
    per_view_px: np.ndarray
    """RMS reprojection error per view used (px)."""
    angle_error_deg: np.ndarray
    """Per view used: the board's own turn (from its pose alone) minus the table's angle (degrees)."""
    board_pose: np.ndarray
    """4x4 board -> world transform at table angle 0."""
    views: list[BoardView]
    """Every view's detection (found, or why not)."""
    outliers: list[str] = field(default_factory=list)
    """Views that spoiled the fit and were left out."""
    problems: list[str] = field(default_factory=list)
    """Why the result is implausible for the rig it was fitted in (empty: none found)."""

    def report(self) -> dict:
        """A JSON-able summary."""
        t = self.turntable
        return {"axis_point": t.axis_point.tolist(), "axis_dir": t.axis_dir.tolist(), "rms_px": self.rms_px,
                "views": {n: {"angle_deg": float(a), "rms_px": float(e), "angle_error_deg": float(d)}
                          for n, a, e, d in zip(self.names, self.angles_deg, self.per_view_px, self.angle_error_deg)},
                "outliers": list(self.outliers), "problems": list(self.problems),
                "not_used": {v.name: v.reason for v in self.views if not v.found}}


# ----------------------------------------------------------------------------- input


def board_views_of_scan(
    scan: Scan,
    *,
    board: Board,
    frame: str = "white",
    settings: TurntableSettings = TurntableSettings(),
) -> tuple[list[BoardView], list[float]]:
    """Detect the board in one frame (default ``white``) of every view of a scan.

    Returns:
        (views, table angles in degrees), one each per scan view.

    Raises:
        FormatError: a view without that frame, or an unreadable frame.
    """
    views, angles = [], []
    for v in scan.views:
        if frame not in v.frames:
            raise FormatError(scan.path, f"view {v.name}: no {frame!r} frame (frames: {', '.join(sorted(v.frames))})")
        img = read_view_frame(scan, v, frame)
        views.append(detect_board(img, board=board, name=v.name, settings=settings.board))
        angles.append(float(v.turntable_deg))
    return views, angles


# ----------------------------------------------------------------------------- geometry helpers


def _rotation_angle(R: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(cv2.Rodrigues(R)[0])))


def _axis_rotation(d: np.ndarray, deg: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(d, float) * math.radians(deg))[0]


def _perp_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


def _canonical_point(p: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The axis point on z = 0, or the one nearest the origin for an axis nearly parallel to z = 0."""
    if abs(d[2]) > 1e-3:
        return p - (p[2] / d[2]) * d
    return p - np.dot(p, d) * d


def axis_distance(a: Turntable, b: Turntable, *, z_range=(0.0, 80.0)) -> tuple[float, float]:
    """(angle between the axes in degrees, largest distance of b's axis from a's over
    the heights ``z_range`` of a's axis, mm): how far apart two turntable axes are
    where objects stand."""
    da, db = (np.asarray(t.axis_dir, float) / np.linalg.norm(t.axis_dir) for t in (a, b))
    ang = math.degrees(math.acos(min(1.0, float(np.dot(da, db)))))
    worst = 0.0
    for z in z_range:
        pa = np.asarray(a.axis_point, float) + (z - a.axis_point[2]) / da[2] * da if abs(da[2]) > 1e-6 \
            else np.asarray(a.axis_point, float)
        v = pa - np.asarray(b.axis_point, float)
        worst = max(worst, float(np.linalg.norm(v - np.dot(v, db) * db)))
    return ang, worst


# ----------------------------------------------------------------------------- fit


def _board_to_world(camera: Camera, rvec, tvec) -> tuple[np.ndarray, np.ndarray]:
    Rb, _ = cv2.Rodrigues(rvec)
    return camera.R.T @ Rb, camera.R.T @ (np.asarray(tvec, float).ravel() - camera.t)


def _solve_pose(obj: np.ndarray, img: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    obj = obj.astype(np.float64).reshape(-1, 1, 3)
    img = img.astype(np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec)
    return _board_to_world(camera, rvec, tvec)


def _initial_axis(Rs, ts, angles, prior) -> tuple[np.ndarray, np.ndarray]:
    """Direction and point of the axis from the relative turns of the board poses to the first."""
    M = np.zeros((3, 3))
    A, b = [], []
    for Rk, tk in zip(Rs[1:], ts[1:]):
        Rrel = Rk @ Rs[0].T
        E = Rrel - np.eye(3)
        M += E.T @ E
        A.append(np.eye(3) - Rrel)
        b.append(tk - Rrel @ ts[0])
    w, V = np.linalg.eigh(M)
    d = V[:, 0]
    # Sense: turning by +theta about d (right-handed) must give the table's angles. A
    # turn by theta has the rotation vector wrap(theta) d, whose sign is sin(theta)'s
    # (a half turn, sin = 0, has no sign to give).
    votes = 0.0
    for Rk, a in zip(Rs[1:], angles[1:] - angles[0]):
        rv = cv2.Rodrigues(Rk @ Rs[0].T)[0].ravel()
        votes += float(np.dot(rv, d)) * math.sin(math.radians(a))
    if votes < 0 or (votes == 0 and np.dot(d, prior) < 0):
        d = -d
    A.append(d[None, :])
    b.append(np.zeros(1))
    p, *_ = np.linalg.lstsq(np.concatenate(A), np.concatenate(b), rcond=None)
    return d, p


def _residuals(x, d0, e1, e2, obj_list, img_list, angles, camera):
    rvec, tvec = x[:3], x[3:6]
    d = d0 + x[6] * e1 + x[7] * e2
    d = d / np.linalg.norm(d)
    p = x[8] * e1 + x[9] * e2
    Rb, _ = cv2.Rodrigues(rvec)
    tt = Turntable(axis_point=p, axis_dir=d)
    out = []
    for obj, img, a in zip(obj_list, img_list, angles):
        T = turntable_transform(tt, a)
        X = obj @ (T[:3, :3] @ Rb).T + (T[:3, :3] @ tvec + T[:3, 3])
        out.append((project_points(X, camera.R, camera.t, camera.K, camera.dist) - img).ravel())
    return np.concatenate(out)


def _unpack(x, d0, e1, e2):
    d = d0 + x[6] * e1 + x[7] * e2
    d /= np.linalg.norm(d)
    return cv2.Rodrigues(x[:3])[0], x[3:6].copy(), d, x[8] * e1 + x[9] * e2


def _undo_half_turns(Rs: list, ts: list, obj: list, views: list, ang: np.ndarray, prior: np.ndarray, board: Board,
                     pts: np.ndarray) -> None:
    """A chessboard's corner order is known only up to a half turn of the board: turn
    the poses (and corner lists) of the views after the first whose order fits the
    table's turn worse than the half-turned order does. Edits ``Rs``, ``ts`` and
    ``obj`` in place (one entry per view with the board)."""
    W, H = (board.cols - 1) * board.square, (board.rows - 1) * board.square
    F = np.diag([-1.0, -1.0, 1.0])
    f = np.array([W, H, 0.0])
    n = board.n_corners
    # Which sense the table turns about the prior axis: the one that both orders fit best.
    best = None
    for sense in (1.0, -1.0):
        cost, flips = 0.0, []
        for k in range(1, len(views)):
            want = _axis_rotation(sense * prior, ang[k] - ang[0])
            as_is = _rotation_angle(Rs[k] @ Rs[0].T @ want.T)
            flipped = _rotation_angle(Rs[k] @ F @ Rs[0].T @ want.T)
            cost += min(as_is, flipped)
            flips.append(flipped < as_is)
        if best is None or cost < best[0] - 1e-6:
            best = (cost, flips)
    for k, flip in zip(range(1, len(views)), best[1]):
        if flip:
            ts[k] = Rs[k] @ f + ts[k]
            Rs[k] = Rs[k] @ F
            obj[k] = pts[n - 1 - views[k].ids]
            log.debug("%s: corner order turned by 180 deg", views[k].name)


def _fit_axis(x0: np.ndarray, d0, e1, e2, obj: list, img: list, ang: np.ndarray, camera: Camera, names: list[str],
              settings: TurntableSettings) -> tuple:
    """The least-squares fit of the board at angle 0 and the axis, repeated once or
    twice with the views that spoil it left out.

    Returns:
        (fit, residuals of every view, RMS per view (px), mask of the views used,
        names of the views left out).

    Size: a private step of calibrate_turntable: it takes the initial guess and the axis's basis (x0, d0, e1,
    e2), the per-view board corners, image points, angles and names, and the camera and settings: separate
    values the caller has already built, most of which (the basis, corners, angles, names) it reads again after
    the fit.
    """
    use = np.ones(len(obj), bool)
    outliers: list[str] = []
    for _ in range(2):
        idx = np.flatnonzero(use)
        fit = least_squares(_residuals, x0, x_scale="jac",
                            args=(d0, e1, e2, [obj[i] for i in idx], [img[i] for i in idx], ang[idx], camera))
        if not fit.success and fit.status <= 0:
            raise CalibrationError(None, f"turntable calibration: the fit failed ({fit.message})")
        res = _residuals(fit.x, d0, e1, e2, obj, img, ang, camera)
        sizes = np.cumsum([0] + [o.shape[0] for o in obj])
        per = np.array([math.sqrt(np.mean(res[2 * sizes[k]:2 * sizes[k + 1]] ** 2)) for k in range(len(obj))])
        lim = max(settings.outlier_factor * float(np.median(per[use])), 0.5)
        bad = use & (per > lim)
        if not bad.any() or use.sum() - bad.sum() < settings.min_views:
            break
        outliers += [names[k] for k in np.flatnonzero(bad)]
        log.warning("turntable: view(s) %s spoil the fit (RMS %s px > %.2f px), left out",
                    ", ".join(names[k] for k in np.flatnonzero(bad)),
                    ", ".join(f"{per[k]:.2f}" for k in np.flatnonzero(bad)), lim)
        use &= ~bad
        x0 = fit.x
    return fit, res, per, use, outliers


def calibrate_turntable(
    views: Sequence[BoardView],
    angles_deg: Sequence[float],
    *,
    board: Board,
    camera: Camera,
    volume: Volume | None = None,
    settings: TurntableSettings = TurntableSettings(),
) -> TurntableCalibration:
    """The turntable axis from board detections at known table angles (see the module docstring).

    Args:
        views: one detection per image (rejected ones are skipped and reported).
        angles_deg: the table angle of each image (degrees, right-handed about the axis).
        board: the board.
        camera: the calibrated camera (intrinsics and its pose in the world frame).
        volume: the rig's working volume: a board (or axis) found far outside it
            (a wrong ``--square`` scales every board pose's distance) is listed in
            ``problems``.
        settings: limits.

    Raises:
        CalibrationError: too few views with the board, angles that span too little,
            or a fit that fails.
    """
    views = list(views)
    angles = np.asarray(angles_deg, float).ravel()
    found = _usable_views(views, angles, board, settings)
    pts = board_points(board).astype(np.float64)
    obj = [pts[views[i].ids] for i in found]
    img = [views[i].corners.astype(np.float64) for i in found]
    ang = angles[found]
    poses = [_solve_pose(o, m, camera) for o, m in zip(obj, img)]
    Rs, ts = [p[0] for p in poses], [p[1] for p in poses]

    prior = np.asarray(settings.prior_axis, float)
    prior /= np.linalg.norm(prior)
    if board.charuco is None:
        _undo_half_turns(Rs, ts, obj, [views[i] for i in found], ang, prior, board, pts)

    d0, p0 = _initial_axis(Rs, ts, ang, prior)
    # The board at table angle 0: view 0's board turned back by its angle.
    T0 = turntable_transform(Turntable(axis_point=p0, axis_dir=d0), -ang[0])
    Rb0 = T0[:3, :3] @ Rs[0]
    tb0 = T0[:3, :3] @ ts[0] + T0[:3, 3]
    e1, e2 = _perp_basis(d0)
    x0 = np.concatenate([cv2.Rodrigues(Rb0)[0].ravel(), tb0, [0.0, 0.0], [np.dot(p0, e1), np.dot(p0, e2)]])

    names = [views[i].name for i in found]
    fit, res, per, use, outliers = _fit_axis(x0, d0, e1, e2, obj, img, ang, camera, names, settings)

    Rb, tb, d, p = _unpack(fit.x, d0, e1, e2)
    k_used = np.flatnonzero(use)
    sizes = np.cumsum([0] + [o.shape[0] for o in obj])
    sel = np.concatenate([np.arange(2 * sizes[k], 2 * sizes[k + 1]) for k in k_used])
    rms = float(math.sqrt(np.mean(res[sel] ** 2)))
    if not rms <= settings.max_rms_px:
        raise CalibrationError(None, f"turntable calibration: the views do not fit one board turning about one axis "
                                     f"(RMS {rms:.2f} px > {settings.max_rms_px:g}; per view: "
                                     + ", ".join(f"{names[k]} {per[k]:.2f}" for k in k_used)
                                     + "): check the table angles, that the board did not slide, and the camera's pose")
    # Each view's own turn about the fitted axis, against the table's angle.
    err = []
    for Rk, a in zip(Rs, ang):
        rv = cv2.Rodrigues(Rk @ Rb.T)[0].ravel()
        turn = math.degrees(float(np.dot(rv, d)))
        err.append((turn - a + 180.0) % 360.0 - 180.0)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = Rb, tb
    tt = Turntable(axis_point=_canonical_point(p, d), axis_dir=d)
    problems = [] if volume is None else _outside_volume(tt, [Rs[k] @ obj[k].T + ts[k][:, None] for k in k_used],
                                                         volume)
    cal = TurntableCalibration(turntable=tt, rms_px=rms, names=[names[k] for k in k_used], angles_deg=ang[k_used],
                               per_view_px=per[k_used], angle_error_deg=np.asarray(err)[k_used], board_pose=pose,
                               views=views, outliers=outliers, problems=problems)
    log.info("turntable: axis through (%.3f, %.3f, %.3f) along (%.5f, %.5f, %.5f), RMS %.3f px over %d views",
             *tt.axis_point, *tt.axis_dir, rms, len(k_used))
    return cal


def _usable_views(views: list, angles: np.ndarray, board: Board, settings: TurntableSettings) -> list[int]:
    """The indices of the views with the board, checked to be enough and to span enough table angle.

    Raises:
        ValueError: not one finite angle per view.
        CalibrationError: too few views with the board, or angles that span too little.
    """
    if len(views) != angles.size:
        raise ValueError(f"angles_deg: one angle per view expected, got {angles.size} for {len(views)} views")
    if not np.all(np.isfinite(angles)):
        raise ValueError("angles_deg: contains non-finite values")
    found = [i for i, v in enumerate(views) if v.found]
    if len(found) < settings.min_views:
        why = "; ".join(f"{v.name}: {v.reason}" for v in views if not v.found)[:400]
        raise CalibrationError(None, f"turntable calibration: the {board.cols}x{board.rows} board was found in "
                                     f"{len(found)} of {len(views)} views, need {settings.min_views}"
                                     + (f" ({why})" if why else ""))
    span = float(np.ptp(angles[found]))
    if span < settings.min_span_deg:
        raise CalibrationError(None, f"turntable calibration: the views with the board span {span:g} deg of table "
                                     f"angle, need {settings.min_span_deg:g}: turn the table further")
    return found


def _outside_volume(tt: Turntable, corners_world: list[np.ndarray], volume: Volume) -> list[str]:
    """The board's corners ((3, n) world, per view) and the axis point against the
    working volume widened by its own height (z) and its radius (r): a board on the
    table stands in the volume the rig scans."""
    span = volume.z_max - volume.z_min
    z_lo, z_hi, r_hi = volume.z_min - span, volume.z_max + span, 2.0 * volume.r_max
    c = np.concatenate(corners_world, 1)
    r = np.hypot(c[0], c[1])
    out = []
    if c[2].min() < z_lo or c[2].max() > z_hi or r.max() > r_hi:
        out.append(f"the board is seen at z {c[2].min():.0f}..{c[2].max():.0f}, up to {r.max():.0f} from the "
                   f"world z axis: far outside the rig's working volume (z {volume.z_min:g}..{volume.z_max:g}, "
                   f"r {volume.r_max:g}); a wrong --square, or a camera pose from another setup?")
    ra = float(np.hypot(tt.axis_point[0], tt.axis_point[1]))
    if ra > r_hi:
        out.append(f"the axis point lies {ra:.0f} from the world z axis, the working volume's radius is "
                   f"{volume.r_max:g}")
    return out


def rig_with_turntable(rig: Rig, turntable: Turntable) -> Rig:
    """``rig`` with its turntable replaced."""
    return dataclasses.replace(rig, turntable=turntable)
