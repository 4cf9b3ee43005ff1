"""Calibration from a scan's own matches: extrinsics refined, a projector fitted (docs/calibration.md).

A decoded scan matches pixels between two devices (two cameras, or a camera and
the projector) without using the rig's extrinsics, so the matches can check and
re-estimate them:

- :func:`refine_extrinsics` re-estimates the pose of device 2 relative to device
  1: the matches are undistorted with the intrinsics, an essential matrix
  (RANSAC) gives a start independent of the rig, then a bundle adjustment over
  the matches refines rotation and translation direction with the 3D points
  eliminated (each match's Sampson distance, the first-order geometric
  reprojection error, under a robust loss); it starts from the rig's own pose
  too and keeps the better. Two views fix the pose only up to scale: the
  baseline length is kept from the input rig, or given (a measured baseline).
  Where a third calibrated device saw the matches (the calibrated projector when
  camera 2 is refined, camera 2 when a two-camera rig's projector is), it then
  joins a bundle adjustment of the reprojection errors in all three devices
  (points triangulated from the three rays at each step, each match weighted by
  its predicted standard deviation, the third device's pose held): the third view
  fixes the rotation that two narrow views trade against the baseline direction.
- :func:`fit_projector` fits a perspective projector (K, distortion, pose) to 3D
  points (triangulated by two cameras) and their projector pixels: a normalised
  DLT start, then OpenCV's ``calibrateCamera`` with the intrinsic guess on the
  non-planar point set, and the fit's own standard deviations and condition
  number, since a fit can match its own data and still be wrong (a nearly planar
  set leaves the focal length and the principal point trading against the
  pose). The distortion terms beyond k1 enter only where the points determine
  them (a chi-square test whose noise variance is scaled by the residuals'
  spatial correlation: decoding errors are shared by neighbouring pixels), the
  standard deviations carry that correlation too, and each pair may be weighted
  by its predicted uncertainty (the two-camera triangulation's, mapped into the
  projector, and the decoded pixel's).
- :func:`write_opencv_procam` / :func:`write_opencv_stereo` write the rig as OpenCV
  FileStorage (the layouts :func:`~ringscan.pipeline.calibrate.importer.read_opencv_calibration`
  and OpenCV's structured-light sample read).

Poses follow OpenCV: a device maps world points as ``X_d = R X_w + t``; the
relative pose of device 2 is ``X_2 = R X_1 + t``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.stats import chi2

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.procam import depth_range, procam_rig
from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.patterns import DECODED_SCALE
from ringscan.pipeline.formats.rig import Camera, PerspectiveLight, Rig
from ringscan.pipeline.formats.scan import Scan, View, read_view_frames

__all__ = ["RefineSettings", "ResidualStats", "Refinement", "refine_extrinsics", "refine_procam_rig",
           "refine_stereo_rig", "relative_pose", "ProjectorSettings", "ProjectorFit", "fit_projector",
           "triangulate_pair", "procam_rig_from_fit", "DISTORTION_CHOICES", "triangulation_covariance",
           "epipolar_distances", "reprojection_errors", "write_opencv_procam", "write_opencv_stereo", "write_opencv_stereo_cameras",
           "rotation_angle_deg", "decoded_pairs"]

log = logging.getLogger(__name__)

MAX_MATCHES = 5_000_000
"""Most matches any function here accepts (a 5 Mpx camera's worth); more is a caller's error."""

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 50, 1e-12)


# ----------------------------------------------------------------------------- shared helpers


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) of a rotation matrix."""
    c = (float(np.trace(R)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def relative_pose(dev1, dev2) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with X_2 = R X_1 + t of two devices with world poses (``R``, ``t``: X_d = R X_w + t)."""
    R = np.asarray(dev2.R, float) @ np.asarray(dev1.R, float).T
    return R, np.asarray(dev2.t, float) - R @ np.asarray(dev1.t, float)


def _check_pixels(uv, what: str, n: int | None = None) -> np.ndarray:
    a = np.asarray(uv, np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{what}: expected (n, 2) pixels, got shape {a.shape}")
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{what}: {a.shape[0]} pixels for {n} matches")
    if a.shape[0] > MAX_MATCHES:
        raise ValueError(f"{what}: {a.shape[0]} matches; at most {MAX_MATCHES}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: contains non-finite pixels")
    return a


def _normalize(uv: np.ndarray, K, dist) -> np.ndarray:
    """(n, 2) observed (distorted) pixels -> (n, 2) normalised undistorted image coordinates."""
    if uv.shape[0] == 0:
        return np.zeros((0, 2))
    out = cv2.undistortPoints(uv.reshape(-1, 1, 2), np.asarray(K, float), np.asarray(dist, float), None, None, None,
                              _UNDISTORT_CRITERIA)
    return out.reshape(-1, 2)


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _fundamental(R, t, K1, K2) -> np.ndarray:
    """F with x2^T F x1 = 0 for undistorted pixels of devices 1 and 2."""
    E = _skew(np.asarray(t, float) / max(np.linalg.norm(t), 1e-300)) @ R
    return np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)


def _homog(p):
    return np.concatenate([p, np.ones((p.shape[0], 1))], 1)


def _sampson(F, p1, p2) -> np.ndarray:
    """Signed Sampson distance (px) of undistorted pixel matches: the first-order
    length of the smallest correction of (p1, p2) onto the epipolar geometry."""
    x1, x2 = _homog(p1), _homog(p2)
    Fx1 = x1 @ F.T
    Ftx2 = x2 @ F
    num = np.sum(x2 * Fx1, 1)
    den = np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)
    return num / np.maximum(den, 1e-300)


def epipolar_distances(R, t, K1, K2, n1, n2) -> np.ndarray:
    """Per match, the mean of the distances (px) of each undistorted pixel from the
    epipolar line of the other, for normalised coordinates ``n1``, ``n2`` ((n, 2))."""
    F = _fundamental(R, t, K1, K2)
    p1 = n1 @ np.asarray(K1)[:2, :2].T + np.asarray(K1)[:2, 2]
    p2 = n2 @ np.asarray(K2)[:2, :2].T + np.asarray(K2)[:2, 2]
    x1, x2 = _homog(p1), _homog(p2)
    l2 = x1 @ F.T
    l1 = x2 @ F
    e = np.abs(np.sum(x2 * l2, 1))
    d2 = e / np.maximum(np.hypot(l2[:, 0], l2[:, 1]), 1e-300)
    d1 = e / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-300)
    return 0.5 * (d1 + d2)


def triangulate_pair(R, t, n1, n2) -> np.ndarray:
    """Device-1-frame points (n, 3) of normalised coordinates ``n1``, ``n2`` with X_2 = R X_1 + t."""
    if n1.shape[0] == 0:
        return np.zeros((0, 3))
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([np.asarray(R, float), np.asarray(t, float).reshape(3, 1)])
    X = cv2.triangulatePoints(P1, P2, n1.T.astype(np.float64), n2.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (X[:3] / X[3]).T


def reprojection_errors(R, t, dev1, dev2, uv1, uv2, n1, n2) -> tuple[np.ndarray, np.ndarray]:
    """Per match, the RMS over both devices of the reprojection error (px) of the
    triangulated point, and whether the point lies in front of both devices."""
    X = triangulate_pair(R, t, n1, n2)
    ok = np.all(np.isfinite(X), 1)
    X = np.where(ok[:, None], X, 0.0)
    X2 = X @ np.asarray(R).T + np.asarray(t).ravel()
    front = ok & (X[:, 2] > 0) & (X2[:, 2] > 0)
    zero = np.zeros(3)
    q1, _ = cv2.projectPoints(X.reshape(-1, 1, 3), zero, zero, np.asarray(dev1.K, float), np.asarray(dev1.dist, float))
    q2, _ = cv2.projectPoints(X2.reshape(-1, 1, 3), zero, zero, np.asarray(dev2.K, float), np.asarray(dev2.dist, float))
    e1 = np.sum((q1.reshape(-1, 2) - uv1) ** 2, 1)
    e2 = np.sum((q2.reshape(-1, 2) - uv2) ** 2, 1)
    err = np.sqrt(0.5 * (e1 + e2))
    return np.where(ok, err, np.inf), front


@dataclass(frozen=True)
class ResidualStats:
    """Median, 95th percentile and RMS of a residual (px) over the matches."""

    median_px: float
    """Median (px)."""
    p95_px: float
    """95th percentile (px)."""
    rms_px: float
    """Root mean square (px) of the finite values."""
    count: int
    """Matches it was computed over."""

    @classmethod
    def of(cls, r: np.ndarray) -> ResidualStats:
        r = np.abs(np.asarray(r, float))
        f = r[np.isfinite(r)]
        if f.size == 0:
            return cls(math.inf, math.inf, math.inf, int(r.size))
        return cls(float(np.median(f)), float(np.percentile(f, 95)), float(np.sqrt(np.mean(f * f))), int(r.size))

    def line(self) -> str:
        """'median 0.12 px, p95 0.31 px, RMS 0.15 px'."""
        return f"median {self.median_px:.3f} px, p95 {self.p95_px:.3f} px, RMS {self.rms_px:.3f} px"

    def to_dict(self) -> dict:
        return {"median_px": self.median_px, "p95_px": self.p95_px, "rms_px": self.rms_px, "count": self.count}


# ----------------------------------------------------------------------------- refine


@dataclass(frozen=True)
class RefineSettings:
    """Extrinsics refinement from matches."""

    ransac_px: float = 1.0
    """RANSAC inlier threshold of the essential-matrix start (px of device 1's focal length)."""
    loss: str = "soft_l1"
    """Robust loss of the bundle adjustment (scipy.optimize.least_squares: linear, soft_l1, huber, cauchy)."""
    loss_scale_px: float = 1.0
    """Residual (px) where the robust loss starts to down-weight a match in the first pass
    (the second pass takes 3 standard deviations of the matches' residuals, up to this)."""
    min_loss_scale_px: float = 0.01
    """Smallest robust-loss scale of the second pass (px)."""
    max_rotation_std_deg: float = 0.05
    """Largest standard deviation of the refined rotation (degrees, its worst axis) to stand behind."""
    max_points: int = 200_000
    """Most matches the adjustment uses (a seeded random subset; residuals are reported over all)."""
    min_points: int = 50
    """Fewest matches to refine from."""
    min_front: float = 0.9
    """Smallest share of matches that must triangulate in front of both devices."""
    max_nfev: int = 200
    """Most cost evaluations of the adjustment."""
    seed: int = 0
    """Seed of the subset."""
    bundle_points: int = 30_000
    """Most matches the three-device bundle adjustment uses (it triangulates each of them at every
    step; a seeded random subset of the adjustment's matches)."""
    max_light_epipolar_px: float = 1.0
    """Largest median epipolar distance (camera-1 px) of camera 1 against the calibrated projector
    under the input rig for the projector to join the adjustment (above it the projector's own
    pose does not fit the images, and holding it would pull device 2 off)."""

    def __post_init__(self):
        if not (isinstance(self.bundle_points, int) and self.bundle_points >= 8):
            raise ValueError(f"RefineSettings.bundle_points: expected an integer >= 8, got {self.bundle_points!r}")
        for name in ("ransac_px", "loss_scale_px", "min_loss_scale_px", "max_rotation_std_deg",
                     "max_light_epipolar_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"RefineSettings.{name}: expected a positive number, got {v!r}")
        if self.loss not in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
            raise ValueError(f"RefineSettings.loss: unknown loss {self.loss!r}")
        if not (isinstance(self.min_points, int) and 8 <= self.min_points <= self.max_points):
            raise ValueError(f"RefineSettings.min_points: expected 8 <= min_points <= max_points, "
                             f"got {self.min_points}")
        if not 0 < self.min_front <= 1:
            raise ValueError(f"RefineSettings.min_front: expected a share in (0, 1], got {self.min_front}")


@dataclass
class Refinement:
    """Device 2's pose relative to device 1, before and after refinement."""

    R: np.ndarray
    """3x3 refined rotation, X_2 = R X_1 + t."""
    t: np.ndarray
    """(3,) refined translation (the baseline length of ``baseline_mm``)."""
    R0: np.ndarray
    """The input rig's rotation."""
    t0: np.ndarray
    """The input rig's translation."""
    baseline_mm: float
    """|t|: kept from the input rig or given."""
    epipolar_before: ResidualStats
    """Epipolar distance (px) of the matches under the input pose."""
    epipolar_after: ResidualStats
    """... under the refined pose."""
    reprojection_before: ResidualStats
    """Reprojection error (px, RMS over both devices per match) of the triangulated matches, input pose."""
    reprojection_after: ResidualStats
    """... refined pose."""
    rotation_change_deg: float
    """Angle between the input and the refined rotation."""
    direction_change_deg: float
    """Angle between the input and the refined baseline direction."""
    used: int
    """Matches the adjustment used."""
    inliers: int
    """Matches within 3 robust-loss scales of the refined geometry."""
    start: str
    """Which start won: 'essential' (from the matches alone) or 'rig' (the input pose)."""
    rotation_std_deg: float = math.nan
    """Standard deviation of the refined rotation about its worst-determined axis (degrees), from the
    adjustment's Jacobian and the matches' residuals (noise only: systematic match errors come on top)."""
    direction_std_deg: float = math.nan
    """... of the baseline direction (degrees)."""
    vergence_std_deg: float = math.nan
    """Standard deviation of the rotation about the vergence axis (perpendicular to the baseline and
    the view), the one that scales depth: the larger of the adjustment's own (noise) and the spread
    of the pose fitted to each quarter of the image left out (a jackknife: the matches' systematic
    errors, an unmodelled lens, move it where noise does not)."""
    scale_std: float = math.nan
    """What that vergence leaves of the scene's scale: the relative standard deviation of the matches'
    median depth (vergence in radians x depth / baseline)."""
    loss_scale_px: float = math.nan
    """The robust loss's scale of the last pass (px)."""
    problems: list[str] = field(default_factory=list)
    """What the matches do not determine (empty: a pose to stand behind)."""
    method: str = "two-view"
    """'two-view' (the epipolar adjustment alone) or 'three-device' (then a bundle adjustment of
    the reprojection errors in device 1, device 2 and the calibrated projector, which is held)."""
    light_epipolar: ResidualStats | None = None
    """Epipolar distance (device-1 px) of device 1 against the third device (the calibrated projector, or
    camera 2 when the projector is refined) under the input rig (None: none given): whether it could join
    the adjustment."""
    third: str = ""
    """The third device given ('projector' or 'camera 2'; '' for none)."""
    bundle_used: int = 0
    """Matches the three-device adjustment used (0: it did not run)."""
    notes: list[str] = field(default_factory=list)
    """What the user should know that does not make the result wrong (e.g. why the projector was left out)."""

    def report(self) -> dict:
        """A JSON-able summary."""
        return {"R": self.R.tolist(), "t": self.t.tolist(), "baseline_mm": self.baseline_mm,
                "epipolar_px": {"before": self.epipolar_before.to_dict(), "after": self.epipolar_after.to_dict()},
                "reprojection_px": {"before": self.reprojection_before.to_dict(),
                                    "after": self.reprojection_after.to_dict()},
                "rotation_change_deg": self.rotation_change_deg, "direction_change_deg": self.direction_change_deg,
                "matches_used": self.used, "inliers": self.inliers, "start": self.start,
                "rotation_std_deg": self.rotation_std_deg, "direction_std_deg": self.direction_std_deg,
                "vergence_std_deg": self.vergence_std_deg, "scale_std": self.scale_std,
                "loss_scale_px": self.loss_scale_px, "method": self.method,
                "light_epipolar_px": None if self.light_epipolar is None else self.light_epipolar.to_dict(),
                "third_device": self.third or None,
                "bundle_matches_used": self.bundle_used, "notes": list(self.notes),
                "problems": list(self.problems)}


def _tangent_basis(d):
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


def _second_pass_scale(res, settings: RefineSettings) -> float:
    """The robust loss's scale for the second pass: 3 standard deviations of the first pass's
    residuals (1.4826 x their median absolute value), within [min_loss_scale_px, loss_scale_px]."""
    sigma = 1.4826 * float(np.median(np.abs(res.fun)))
    return min(settings.loss_scale_px, max(settings.min_loss_scale_px, 3.0 * sigma))


def _robust_covariance(res, scale: float, *, dof: int) -> np.ndarray:
    """(k, k) covariance of a least_squares result's parameters from its Jacobian, with the
    robust (Huber-like) weights at ``scale`` as the loss applied them; inf where singular."""
    r = res.fun
    w = np.sqrt(np.where(np.abs(r) <= scale, 1.0, scale / np.maximum(np.abs(r), 1e-300)))
    J = res.jac * w[:, None]
    s2 = float(np.sum((r * w) ** 2)) / dof
    try:
        return np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        return np.full((J.shape[1], J.shape[1]), np.inf)


def _adjust(R0, d0, p1, p2, K1, K2, settings: RefineSettings):
    """Bundle adjustment with the points eliminated: rotation vector + baseline direction (2 dof).

    Two passes: the first with ``loss_scale_px`` (to converge from a start pixels off), the
    second with the robust loss's scale at 3 standard deviations of the matches' own residuals
    (1.4826 x their median absolute value, at least ``min_loss_scale_px``), so that the few bad
    matches of a decode whose noise is hundredths of a pixel do not pull the pose.

    Returns:
        (R, unit baseline direction, cost, the scale of the last pass, (5, 5) covariance of
        the rotation vector and the direction's two tangent offsets, in radians).
    """
    scale = settings.loss_scale_px
    for rnd in range(2):
        e1, e2 = _tangent_basis(d0)
        rv0, _ = cv2.Rodrigues(R0)

        def unpack(x, e1=e1, e2=e2, d0=d0):
            R, _ = cv2.Rodrigues(x[:3].reshape(3, 1))
            d = d0 + x[3] * e1 + x[4] * e2
            return R, d / np.linalg.norm(d)

        def fun(x, unpack=unpack):
            R, d = unpack(x)
            return _sampson(_fundamental(R, d, K1, K2), p1, p2)

        x0 = np.concatenate([rv0.ravel(), [0.0, 0.0]])
        res = least_squares(fun, x0, loss=settings.loss, f_scale=scale, method="trf",
                            max_nfev=settings.max_nfev, x_scale="jac")
        R0, d0 = unpack(res.x)
        if rnd == 0:
            scale = _second_pass_scale(res, settings)
    cov = _robust_covariance(res, scale, dof=max(1, res.fun.size - 5))
    return R0, d0, float(res.cost), scale, cov


def _triangulate_views(poses, obs, wts) -> np.ndarray:
    """Device-1-frame points (n, 3) of matches seen by several devices: a weighted linear
    (DLT) solve, then two Gauss-Newton steps on the weighted reprojection error.

    Args:
        poses: per device (R, t) with X_d = R X_1 + t.
        obs: per device (n, 2) normalised undistorted coordinates.
        wts: per device (n,) weights (focal length / standard deviation: px of normalised error).
    """
    n = obs[0].shape[0]
    A = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    for (R, t), o, w in zip(poses, obs, wts):
        for k in range(2):
            row = (R[k][None, :] - o[:, k:k + 1] * R[2][None, :]) * w[:, None]
            rhs = -(t[k] - o[:, k] * t[2]) * w
            A += row[:, :, None] * row[:, None, :]
            b += row * rhs[:, None]
    with np.errstate(all="ignore"):
        X = np.linalg.solve(A + 1e-12 * np.eye(3), b[..., None])[..., 0]
        for _ in range(2):
            A[:] = 0.0
            b[:] = 0.0
            for (R, t), o, w in zip(poses, obs, wts):
                Y = X @ R.T + t
                z = Y[:, 2]
                for k in range(2):
                    g = (R[k][None, :] - (Y[:, k] / z)[:, None] * R[2][None, :]) * (w / z)[:, None]
                    r = (Y[:, k] / z - o[:, k]) * w
                    A += g[:, :, None] * g[:, None, :]
                    b -= g * r[:, None]
            X = X + np.linalg.solve(A + 1e-12 * np.eye(3), b[..., None])[..., 0]
    return X


def _views_residuals(poses, obs, wts, X) -> np.ndarray:
    """(n, 2 x devices) weighted reprojection residuals of points X (device-1 frame)."""
    out = []
    for (R, t), o, w in zip(poses, obs, wts):
        Y = X @ R.T + t
        with np.errstate(all="ignore"):
            out.append((Y[:, :2] / Y[:, 2:3] - o) * w[:, None])
    r = np.concatenate(out, 1)
    return np.where(np.isfinite(r), r, 0.0)


def _adjust_three(R0, t0, light_pose, obs, wts, settings: RefineSettings, scale0: float):
    """Bundle adjustment of device 2's pose (rotation, baseline direction; length kept) against
    device 1 and a held third device (the calibrated projector): the reprojection errors of every
    match in all three devices, each weighted by its predicted standard deviation, with the points
    triangulated from the three rays at every step (eliminated). The projector sees the scene from
    a third place, which fixes the rotation that two narrow views trade against the baseline direction.

    Two passes as in :func:`_adjust`, the second with the robust loss's scale at 3 standard deviations
    of the weighted residuals. Returns (R, t, scale of the last pass, (5, 5) covariance)."""
    base = float(np.linalg.norm(t0))
    d0 = np.asarray(t0, float) / base
    e1, e2 = _tangent_basis(d0)
    eye = (np.eye(3), np.zeros(3))

    def unpack(x):
        R = cv2.Rodrigues(x[:3].reshape(3, 1))[0] @ R0
        d = d0 + x[3] * e1 + x[4] * e2
        return R, base * d / np.linalg.norm(d)

    def fun(x):
        R, t = unpack(x)
        poses = [eye, (R, t), light_pose]
        return _views_residuals(poses, obs, wts, _triangulate_views(poses, obs, wts)).ravel()

    x = np.zeros(5)
    scale = scale0
    for rnd in range(2):
        res = least_squares(fun, x, loss=settings.loss, f_scale=scale, method="trf", max_nfev=settings.max_nfev,
                            x_scale="jac", diff_step=1e-8)
        x = res.x
        if rnd == 0:
            scale = _second_pass_scale(res, settings)
    cov = _robust_covariance(res, scale, dof=max(1, res.fun.size - 3 * obs[0].shape[0] - 5))
    R, t = unpack(x)
    return R, t, scale, cov


def _sigmas(sigma, n: int, what: str) -> np.ndarray:
    """(n,) standard deviations (px) of a match's pixel: given (n,) or (n, 2) (their mean), or 1 px."""
    if sigma is None:
        return np.ones(n)
    s = np.asarray(sigma, np.float64)
    if s.ndim == 2:
        s = s.mean(1)
    if s.shape != (n,):
        raise ValueError(f"{what}: {s.shape} standard deviations for {n} matches")
    s = np.where(np.isfinite(s) & (s > 0), s, np.nan)
    floor = max(1e-3, 0.1 * float(np.nanmedian(s))) if np.any(np.isfinite(s)) else 1.0
    return np.where(np.isfinite(s), np.maximum(s, floor), np.nanmax(np.r_[s[np.isfinite(s)], 1.0]))


def _axis_std_deg(cov) -> tuple[np.ndarray, np.ndarray]:
    """Standard deviations (degrees) along the principal axes of the rotation's and the direction's
    covariance blocks of a (5, 5) covariance (infinite where it is not finite)."""
    out = []
    for blk in (cov[:3, :3], cov[3:, 3:]):
        if not np.all(np.isfinite(blk)):
            out.append(np.full(blk.shape[0], np.inf))
            continue
        out.append(np.degrees(np.sqrt(np.maximum(np.linalg.eigvalsh(0.5 * (blk + blk.T)), 0.0))))
    return out[0], out[1]


MAX_SCALE_STD = 0.002
"""A refined pair whose matches fix the scene's scale (its vergence) only to more than this
(0.2 %) says so: two cameras fix their pose only up to a weakly determined vergence."""
JACKKNIFE_POINTS = 20_000
"""Matches (evenly drawn) each leave-a-quarter-out fit of the vergence uses."""


def _vergence(R, d, cov, p1, p2, n1, K1, K2, base: float, settings: "RefineSettings") -> tuple[float, float]:
    """(vergence standard deviation in degrees, relative scale standard deviation) of a refined pair.

    The vergence axis is perpendicular to the baseline and to the matches' mean viewing
    direction (camera 1's frame); a turn about it changes every disparity alike, so the depths
    scale by (turn x depth / baseline). Its standard deviation is the larger of the adjustment's
    covariance along it and the jackknife spread of the pose fitted with each quarter of
    camera 1's image left out."""
    v = np.c_[n1, np.ones(len(n1))].mean(axis=0)
    b = -R.T @ d  # camera 2's centre in camera 1's frame, a unit vector
    axis1 = np.cross(b, v)
    if not np.linalg.norm(axis1) > 0:
        return math.nan, math.nan
    axis1 /= np.linalg.norm(axis1)
    axis2 = R @ axis1  # the rotation vector's perturbations are in camera 2's frame
    blk = cov[:3, :3]
    sd_cov = math.sqrt(max(float(axis2 @ blk @ axis2), 0.0)) if np.all(np.isfinite(blk)) else math.inf
    n = len(p1)
    take = np.unique(np.linspace(0, n - 1, min(n, JACKKNIFE_POINTS)).astype(np.int64))
    q1, q2 = p1[take], p2[take]
    cx, cy = np.median(q1[:, 0]), np.median(q1[:, 1])
    quarter = (q1[:, 0] > cx).astype(int) + 2 * (q1[:, 1] > cy).astype(int)
    turns = []
    for k in range(4):
        keep = quarter != k
        if np.count_nonzero(keep) < settings.min_points:
            continue
        Rk, *_ = _adjust(R, d, q1[keep], q2[keep], K1, K2, settings)
        rv, _ = cv2.Rodrigues(Rk @ R.T)
        turns.append(float(rv.ravel() @ axis2))
    sd_jack = math.sqrt(0.75 * np.sum((np.asarray(turns) - np.mean(turns)) ** 2)) if len(turns) == 4 else 0.0
    sd = max(sd_cov, sd_jack)
    P1 = K1 @ np.eye(3, 4)
    P2 = K2 @ np.c_[R, d * base]
    X = cv2.triangulatePoints(P1, P2, q1.T.astype(np.float64), q2.T.astype(np.float64))
    z = X[2] / X[3]
    z = z[np.isfinite(z) & (z > 0)]
    if z.size == 0:
        return math.degrees(sd), math.nan
    return math.degrees(sd), sd * float(np.median(z)) / base


def _robust_cost(R, d, p1, p2, K1, K2, loss: str, scale: float) -> float:
    z = (_sampson(_fundamental(R, d, K1, K2), p1, p2) / scale) ** 2
    rho = {"linear": z, "soft_l1": 2 * (np.sqrt(1 + z) - 1), "huber": np.where(z <= 1, z, 2 * np.sqrt(z) - 1),
           "cauchy": np.log1p(z), "arctan": np.arctan(z)}[loss]
    return 0.5 * scale ** 2 * float(np.sum(rho))


def refine_extrinsics(dev1, dev2, uv1, uv2, *, baseline_mm: float | None = None,
                      settings: RefineSettings = RefineSettings(), sigma1=None, sigma2=None, light=None,
                      uv_light=None, sigma_light=None) -> Refinement:
    """Re-estimate device 2's pose relative to device 1 from matched pixels.

    Args:
        dev1, dev2: devices with ``K``, ``dist``, ``R``, ``t`` (world poses, X_d = R X_w + t): two
            :class:`Camera`, or a camera and a :class:`PerspectiveLight` (then ``uv2`` are projector pixels).
        uv1, uv2: (n, 2) matched pixels as observed (distorted).
        baseline_mm: the baseline length to give the result (a measured one); None keeps the input rig's.
        settings: see :class:`RefineSettings`.
        sigma1, sigma2: (n,) or (n, 2) predicted standard deviations (px) of uv1, uv2 (None: equal);
            they weight the three-device adjustment.
        light: a third device with its world pose that saw the matches at ``uv_light`` ((n, 2), standard
            deviations ``sigma_light``): the calibrated projector (:class:`PerspectiveLight`) when device 2
            is camera 2, or camera 2 (:class:`Camera`) when device 2 is the projector. It joins a bundle
            adjustment of the reprojection errors in all three devices, its own pose held (where it fits
            device 1: ``max_light_epipolar_px``), after the epipolar adjustment of the two.

    Returns:
        the :class:`Refinement` (the refined relative pose and the residuals before and after).

    Raises:
        CalibrationError: too few matches, a zero baseline, or matches that determine no pose.
    """
    uv1 = _check_pixels(uv1, "refine_extrinsics: uv1")
    uv2 = _check_pixels(uv2, "refine_extrinsics: uv2", uv1.shape[0])
    n = uv1.shape[0]
    if n < settings.min_points:
        raise CalibrationError(None, f"only {n} matches; refining a pose needs at least {settings.min_points}")
    R0, t0 = relative_pose(dev1, dev2)
    base = float(np.linalg.norm(t0)) if baseline_mm is None else float(baseline_mm)
    if not (math.isfinite(base) and base > 0):
        raise CalibrationError(None, f"baseline {base:g} mm: the rig's devices are at one place; give the baseline "
                                     "length")
    K1, K2 = np.asarray(dev1.K, float), np.asarray(dev2.K, float)
    n1 = _normalize(uv1, K1, dev1.dist)
    n2 = _normalize(uv2, K2, dev2.dist)
    p1 = n1 @ K1[:2, :2].T + K1[:2, 2]
    p2 = n2 @ K2[:2, :2].T + K2[:2, 2]
    rng = np.random.default_rng(settings.seed)
    sub = np.sort(rng.choice(n, settings.max_points, replace=False)) if n > settings.max_points else np.arange(n)

    # two starts: the matches' own essential matrix, and the rig's pose (kept only where clearly better)
    starts = []
    f1 = 0.5 * (K1[0, 0] + K1[1, 1])
    E, mask = cv2.findEssentialMat(n1[sub], n2[sub], np.eye(3), method=cv2.RANSAC, prob=0.999,
                                   threshold=settings.ransac_px / f1)
    if E is not None and E.shape == (3, 3):
        _, Re, te, _ = cv2.recoverPose(E, n1[sub], n2[sub], np.eye(3), mask=mask)
        starts.append(("essential", Re, te.ravel() / np.linalg.norm(te)))
    if np.linalg.norm(t0) > 0:
        starts.append(("rig", R0, t0 / np.linalg.norm(t0)))
    if not starts:
        raise CalibrationError(None, "the matches determine no pose (no essential matrix) and the rig has none")
    best = None
    for name, Rs, ds in starts:
        R, d, cost, scale, cov = _adjust(Rs, ds, p1[sub], p2[sub], K1, K2, settings)
        # costs compare only at one scale: evaluate each end at the first end's
        if best is not None:
            loss_scale = best[4]
            cost = _robust_cost(R, d, p1[sub], p2[sub], K1, K2, settings.loss, loss_scale)
            best_cost = _robust_cost(best[1], best[2], p1[sub], p2[sub], K1, K2, settings.loss, loss_scale)
            if cost < best_cost * (1 - 1e-6):
                best = (name, R, d, cost, scale, cov)
        else:
            best = (name, R, d, cost, scale, cov)
    name, R, d, _, scale, cov = best
    rot_std, dir_std = _axis_std_deg(cov)
    # the epipolar geometry does not see the sign of t: take the one that puts the points in front
    _, front_p = reprojection_errors(R, d * base, dev1, dev2, uv1[sub], uv2[sub], n1[sub], n2[sub])
    _, front_m = reprojection_errors(R, -d * base, dev1, dev2, uv1[sub], uv2[sub], n1[sub], n2[sub])
    if front_m.mean() > front_p.mean():
        d = -d
    t = d * base
    method, light_epi, bundle_used, notes = "two-view", None, 0, []
    third = ""
    if light is not None:
        if not isinstance(light, (PerspectiveLight, Camera)):
            raise ValueError("refine_extrinsics: light (the third device) must be a calibrated PerspectiveLight "
                             "or a Camera")
        third = "projector" if isinstance(light, PerspectiveLight) else "camera 2"
        uvl = _check_pixels(uv_light, "refine_extrinsics: uv_light", n)
        Rl, tl = relative_pose(dev1, light)
        Kl = np.asarray(light.K, float)
        nl = _normalize(uvl, Kl, light.dist)
        light_epi = ResidualStats.of(epipolar_distances(Rl, tl, K1, Kl, n1, nl))
        if light_epi.median_px <= settings.max_light_epipolar_px:
            s1 = _sigmas(sigma1, n, "refine_extrinsics: sigma1")
            s2 = _sigmas(sigma2, n, "refine_extrinsics: sigma2")
            sl = _sigmas(sigma_light, n, "refine_extrinsics: sigma_light")
            ref_px = float(np.median(s1))  # residuals in device-1 px of a median match
            bsub = sub
            if bsub.size > settings.bundle_points:
                bsub = np.sort(rng.choice(bsub, settings.bundle_points, replace=False))
            obs = [n1[bsub], n2[bsub], nl[bsub]]
            wts = [K1[0, 0] * ref_px / s1[bsub], K2[0, 0] * ref_px / s2[bsub], Kl[0, 0] * ref_px / sl[bsub]]
            R, t, scale, cov = _adjust_three(R, t, (Rl, tl), obs, wts, settings, settings.loss_scale_px)
            rot_std, dir_std = _axis_std_deg(cov)
            method, bundle_used = "three-device", int(bsub.size)
        else:
            notes.append(f"{'the projector' if third == 'projector' else 'camera 2'} was left out of the "
                         f"adjustment: camera 1's matches lie {light_epi.median_px:.2f} px (median) from its "
                         f"epipolar lines (> {settings.max_light_epipolar_px:g} px), so its pose does not fit the "
                         f"images; refine it first (--pair {'projector' if third == 'projector' else 'cameras'})")
    epi0 = epipolar_distances(R0, t0, K1, K2, n1, n2) if np.linalg.norm(t0) > 0 else np.full(n, np.inf)
    epi1 = epipolar_distances(R, t, K1, K2, n1, n2)
    rep0, _ = reprojection_errors(R0, t0, dev1, dev2, uv1, uv2, n1, n2)
    rep1, front = reprojection_errors(R, t, dev1, dev2, uv1, uv2, n1, n2)
    samp = np.abs(_sampson(_fundamental(R, t, K1, K2), p1, p2))
    inl = int(np.count_nonzero(samp <= 3 * settings.loss_scale_px))
    problems = []
    if front.mean() < settings.min_front:
        problems.append(f"only {100 * front.mean():.0f} % of the matches lie in front of both devices under the "
                        "refined pose: the matches do not determine it (too few, or mostly wrong)")
    if not rot_std.max() <= settings.max_rotation_std_deg:
        problems.append(f"the matches fix the rotation only to +- {rot_std.max():.3f} deg (> "
                        f"{settings.max_rotation_std_deg:g}) about its worst axis: too narrow a view of too shallow "
                        "a scene; scan an object with more depth, wider in the image")
    if inl < max(settings.min_points, 0.5 * n):
        problems.append(f"only {inl} of {n} matches fit the refined pose within {3 * settings.loss_scale_px:g} px")
    verg_std, scale_std = _vergence(R, t / np.linalg.norm(t), cov, p1[sub], p2[sub], n1[sub], K1, K2, base, settings)
    if scale_std > MAX_SCALE_STD:
        notes.append(f"the matches fix the scene's scale only to +- {100 * scale_std:.2f} % (a turn of "
                     f"+- {verg_std:.4f} deg about the vergence axis, which two cameras determine weakly): pin it "
                     "with a known distance in the scene, or refine with the calibrated projector as a third "
                     "device")
    dirc = math.degrees(math.acos(min(1.0, abs(float(np.dot(t / np.linalg.norm(t), t0 / np.linalg.norm(t0)))))
                                  if np.linalg.norm(t0) > 0 else 1.0))
    out = Refinement(R=R, t=t, R0=R0, t0=t0, baseline_mm=base, epipolar_before=ResidualStats.of(epi0),
                     epipolar_after=ResidualStats.of(epi1), reprojection_before=ResidualStats.of(rep0),
                     reprojection_after=ResidualStats.of(rep1), rotation_change_deg=rotation_angle_deg(R @ R0.T),
                     direction_change_deg=dirc, used=int(sub.size), inliers=inl, start=name,
                     rotation_std_deg=float(rot_std.max()), direction_std_deg=float(dir_std.max()),
                     vergence_std_deg=verg_std, scale_std=scale_std, loss_scale_px=float(scale), problems=problems, method=method, light_epipolar=light_epi,
                     bundle_used=bundle_used, notes=notes, third=third)
    log.info("refine: epipolar median %.3f -> %.3f px; rotation changed %.3f deg (start: %s, %s)",
             out.epipolar_before.median_px, out.epipolar_after.median_px, out.rotation_change_deg, name, method)
    return out


def refine_stereo_rig(rig: Rig, uv1, uv2, *, baseline_mm: float | None = None,
                      settings: RefineSettings = RefineSettings(), sigma1=None, sigma2=None, uv_light=None,
                      sigma_light=None) -> tuple[Rig, Refinement]:
    """A two-camera rig with camera 2's pose re-estimated from matches (camera 1 and the world frame kept).

    Where the rig's projector is calibrated and ``uv_light`` (the matches' projector pixels) is given,
    the projector (its pose held) joins the adjustment (:func:`refine_extrinsics`)."""
    cam2 = getattr(rig, "camera2", None)
    if cam2 is None:
        raise CalibrationError(None, "the rig has one camera; refining a stereo pose needs camera2")
    light = rig.light if isinstance(rig.light, PerspectiveLight) and uv_light is not None else None
    ref = refine_extrinsics(rig.camera, cam2, uv1, uv2, baseline_mm=baseline_mm, settings=settings, sigma1=sigma1,
                            sigma2=sigma2, light=light, uv_light=uv_light if light is not None else None,
                            sigma_light=sigma_light if light is not None else None)
    c1 = rig.camera
    new2 = replace(cam2, R=ref.R @ c1.R, t=ref.R @ c1.t + ref.t)
    return replace(rig, camera2=new2), ref


def refine_procam_rig(rig: Rig, uv_cam, uv_proj, *, baseline_mm: float | None = None, move: str | None = None,
                      settings: RefineSettings = RefineSettings(), uv_camera2=None, sigma_cam=None,
                      sigma_proj=None, sigma_camera2=None) -> tuple[Rig, Refinement]:
    """A rig with the pose between (first) camera and projector re-estimated from camera-projector matches.

    Args:
        move: "camera" (default for one-camera rigs): the projector keeps its pose, so the world
            frame (tied to the light axis, docs/design.md §2) and the working volume stay;
            "projector" (default for two-camera rigs, whose world frame is camera 1's): the cameras stay.
        uv_camera2: a two-camera rig's camera-2 pixels of the same matches ((n, 2)): camera 2 (its pose
            held) joins the adjustment as the third device (:func:`refine_extrinsics`).
        sigma_cam, sigma_proj, sigma_camera2: the matches' predicted standard deviations (px) in camera 1,
            the projector and camera 2 (None: equal); they weight the three-device adjustment.
    """
    li = rig.light
    if not isinstance(li, PerspectiveLight):
        raise CalibrationError(None, "the rig's light is not a calibrated perspective projector; refining the "
                                     "camera-projector pose needs one")
    two = getattr(rig, "camera2", None) is not None
    move = move or ("projector" if two else "camera")
    if move not in ("camera", "projector"):
        raise ValueError(f"refine_procam_rig: move must be 'camera' or 'projector', got {move!r}")
    if move == "camera" and two:
        raise ValueError("refine_procam_rig: a two-camera rig keeps its cameras (move='projector')")
    cam2 = getattr(rig, "camera2", None) if uv_camera2 is not None else None
    if uv_camera2 is not None and cam2 is None:
        raise ValueError("refine_procam_rig: uv_camera2 given for a rig with one camera")
    ref = refine_extrinsics(rig.camera, li, uv_cam, uv_proj, baseline_mm=baseline_mm, settings=settings,
                            sigma1=sigma_cam, sigma2=sigma_proj, light=cam2, uv_light=uv_camera2,
                            sigma_light=sigma_camera2 if cam2 is not None else None)
    c = rig.camera
    if move == "projector":
        return replace(rig, light=replace(li, R=ref.R @ c.R, t=ref.R @ c.t + ref.t)), ref
    # X_p = R X_c + t  =>  X_c = R^T (X_p - t) = R^T R_p X_w + R^T (t_p - t)
    return replace(rig, camera=replace(c, R=ref.R.T @ li.R, t=ref.R.T @ (li.t - ref.t))), ref


# ----------------------------------------------------------------------------- projector from points

DISTORTION_CHOICES = ("auto", "fit", "hold")
"""What :class:`ProjectorSettings` does with a distortion term: decide from the data, fit, hold at 0."""


@dataclass(frozen=True)
class ProjectorSettings:
    """Fitting a projector to 3D points and their projector pixels."""

    min_points: int = 100
    """Fewest point-pixel pairs (a DLT needs 6; a fit to stand behind many more)."""
    min_thickness: float = 0.02
    """Smallest ratio of the point set's least to largest spread (singular values):
    below it the set is nearly planar and one view of a plane does not determine
    the focal length and the principal point together."""
    principal_point: tuple[float, float] | None = None
    """A known principal point (px): held fixed, which lets a nearly planar set fit
    the focal length (square pixels, no distortion)."""
    radial: str = "auto"
    """Radial distortion: "auto" fits k1, and k2 (then k3) only where the points determine them
    (:attr:`alpha`); "fit" fits k1, k2 (k3 held at 0); "hold" holds k1, k2, k3 at 0. A projector's
    narrow field leaves k2 trading with k1 and the focal length: on the virtual Gray-code rig a k2 the
    data do not determine moved the focal length by 0.13 % and the position by 0.7 mm."""
    tangential: str = "auto"
    """Tangential distortion p1, p2: "auto" fits them where the points determine them (:attr:`alpha`),
    "fit" always, "hold" holds them at 0 (always held for a planar point set). A lens with them (p1 =
    0.001 on the virtual Gray-code rig) held at 0 moves the principal point (cy 1.3 %) and the pose
    (0.15 deg)."""
    alpha: float = 0.001
    """Significance level of "auto": a distortion term is fitted when the drop of the squared residuals
    it brings, over the residual variance scaled by :attr:`ProjectorFit.correlation` (the residuals of
    neighbouring points are not independent), exceeds the chi-square quantile 1 - alpha (one degree
    of freedom per parameter)."""
    correlation_cells: int = 4
    """Cells per side of the grid over the projector pixels in which the residuals' correlation is
    measured (the variance of a cell's mean residual against that of independent residuals). Coarse,
    since the terms tested vary smoothly over the whole image: it is the residuals' correlation at
    that scale that their estimates share (finer cells see less of it: 8x8 gave 9-22 on the virtual
    scans where 4x4 gives 10-56, and let k2 in on the Gray-code scan)."""
    min_depth_ratio: float = 0.03
    """Smallest spread of the points' distances along the projector's axis (5th to 95th percentile)
    as a share of their median distance: below it the focal length and the distance trade (a note)."""
    outlier_px: float = 3.0
    """Pairs whose reprojection error exceeds this (and 5x the median) after a first fit are left out."""
    max_focal_std: float = 0.005
    """Largest standard deviation of fx, fy as a fraction of their value."""
    max_center_std: float = 0.01
    """Largest standard deviation of cx, cy as a fraction of the image width, height."""
    max_rotation_std_deg: float = 0.1
    """Largest standard deviation of the pose's rotation (degrees)."""
    max_position_std: float = 0.001
    """Largest standard deviation of the projector's position as a fraction of its distance to the points."""

    def __post_init__(self):
        if not (isinstance(self.min_points, int) and self.min_points >= 6):
            raise ValueError(f"ProjectorSettings.min_points: expected an integer >= 6, got {self.min_points!r}")
        for name in ("radial", "tangential"):
            if getattr(self, name) not in DISTORTION_CHOICES:
                raise ValueError(f"ProjectorSettings.{name}: expected one of {', '.join(DISTORTION_CHOICES)}, "
                                 f"got {getattr(self, name)!r}")
        if not (isinstance(self.alpha, float) and 0 < self.alpha < 0.5):
            raise ValueError(f"ProjectorSettings.alpha: expected a level in (0, 0.5), got {self.alpha!r}")
        if not (isinstance(self.correlation_cells, int) and 1 <= self.correlation_cells <= 64):
            raise ValueError(f"ProjectorSettings.correlation_cells: expected an integer 1 to 64, "
                             f"got {self.correlation_cells!r}")
        for name in ("min_thickness", "outlier_px", "max_focal_std", "max_center_std", "max_rotation_std_deg",
                     "max_position_std", "min_depth_ratio"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"ProjectorSettings.{name}: expected a positive number, got {v!r}")


@dataclass
class ProjectorFit:
    """A projector fitted to points and its fit's figures."""

    light: PerspectiveLight
    """The projector in the points' frame."""
    rms_px: float
    """RMS reprojection error of the pairs used (px)."""
    residuals: ResidualStats
    """Per-pair reprojection error (px) of the pairs used."""
    used: int
    """Pairs used."""
    outliers: int
    """Pairs left out after the first fit."""
    thickness: float
    """Least to largest spread of the points (see :attr:`ProjectorSettings.min_thickness`)."""
    std: dict
    """Standard deviations from the fit: fx, fy, cx, cy (px), k1, k2, p1, p2, k3, rotation_deg, position
    (world units); the covariance of independent residuals scaled by :attr:`correlation` (what the
    residuals' correlated part leaves undetermined as well)."""
    condition: float
    """Condition number of the column-scaled Jacobian of the fit (large: parameters trade against each other)."""
    fixed: list[str] = field(default_factory=list)
    """Parameters held fixed."""
    problems: list[str] = field(default_factory=list)
    """What the points do not determine (empty: a projector to stand behind)."""
    std_noise: dict = field(default_factory=dict)
    """The same standard deviations were the residuals independent: the Cramer-Rao bound of the fit
    for noise of the residuals' size (no fit of these points does better). :attr:`problems` come from
    these (what the points' geometry leaves open), :attr:`notes` from :attr:`std`."""
    correlation: float = 1.0
    """How much the residuals of neighbouring points move together: the variance of the mean residual
    in a cell of the projector image over what independent residuals give (1: independent)."""
    depth_range: tuple = (math.nan, math.nan)
    """5th and 95th percentile of the points' distances along the projector's axis (world units)."""
    depth_ratio: float = math.nan
    """Their spread over the median distance: what tells the focal length from the distance."""
    focal_distance_correlation: float = math.nan
    """Correlation of fx with the distance of the points from the projector in the fit (near +-1: they trade)."""
    decisions: list[str] = field(default_factory=list)
    """Per distortion term, fitted or held and why (the "auto" test's statistic)."""
    notes: list[str] = field(default_factory=list)
    """What the user should know that does not make the fit wrong (e.g. little depth in the points)."""
    weighted: bool = False
    """Whether each pair was weighted by its predicted uncertainty (``point_cov``, ``pixel_sigma``)."""

    def report(self) -> dict:
        li = self.light
        return {"K": li.K.tolist(), "dist": li.dist.tolist(), "R": li.R.tolist(), "t": li.t.tolist(),
                "rms_px": self.rms_px, "residuals_px": self.residuals.to_dict(), "used": self.used,
                "outliers": self.outliers, "thickness": self.thickness, "std": dict(self.std),
                "std_noise": dict(self.std_noise), "correlation": self.correlation,
                "depth_range": list(self.depth_range), "depth_ratio": self.depth_ratio,
                "focal_distance_correlation": self.focal_distance_correlation, "decisions": list(self.decisions),
                "condition": self.condition, "fixed": list(self.fixed), "problems": list(self.problems),
                "notes": list(self.notes), "weighted": self.weighted}


def _dlt(X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """3x4 projection matrix by the normalised DLT (Hartley & Zisserman 7.1)."""
    cx = X.mean(0)
    sx = math.sqrt(3) / max(np.sqrt(np.mean(np.sum((X - cx) ** 2, 1))), 1e-300)
    cu = uv.mean(0)
    su = math.sqrt(2) / max(np.sqrt(np.mean(np.sum((uv - cu) ** 2, 1))), 1e-300)
    T3 = np.diag([sx, sx, sx, 1.0])
    T3[:3, 3] = -sx * cx
    T2 = np.diag([su, su, 1.0])
    T2[:2, 2] = -su * cu
    Xn = _homog((X - cx) * sx)
    un = (uv - cu) * su
    n = X.shape[0]
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xn
    A[0::2, 8:12] = -un[:, :1] * Xn
    A[1::2, 4:8] = Xn
    A[1::2, 8:12] = -un[:, 1:2] * Xn
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    Pn = Vt[-1].reshape(3, 4)
    return np.linalg.inv(T2) @ Pn @ T3


def _decompose(P: np.ndarray):
    """K (K[2,2] = 1, positive focal lengths), R, t of a projection matrix."""
    M = P[:, :3]
    if np.linalg.det(M) < 0:
        P = -P
        M = -M
    K, R = (np.asarray(a, float) for a in cv2.RQDecomp3x3(M)[1:3])
    D = np.diag(np.sign(np.diag(K)))
    K, R = K @ D, D @ R
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:
        R, t = -R, -t
    return K / K[2, 2], R, t


def _pose_std(J: np.ndarray, cols: list[int], resid: np.ndarray):
    """Covariance of the free parameters (columns ``cols`` of the projectPoints Jacobian) and the
    condition number of the column-scaled Jacobian."""
    A = J[:, cols]
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    s = np.linalg.svd(A / scale, compute_uv=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
    dof = max(1, A.shape[0] - A.shape[1])
    sigma2 = float(np.sum(resid ** 2)) / dof
    try:
        cov = np.linalg.inv(A.T @ A) * sigma2
    except np.linalg.LinAlgError:
        cov = np.full((len(cols), len(cols)), np.inf)
    return cov, cond


_DIST_NAMES = ("k1", "k2", "p1", "p2", "k3")
_PARAM_NAMES = ["rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "cx", "cy", *_DIST_NAMES]
"""The columns of cv2.projectPoints' Jacobian (rotation vector, translation, focal lengths, centre, distortion)."""


def _dist_flags(terms: frozenset) -> int:
    """calibrateCamera flags holding the distortion terms not in ``terms`` at 0."""
    f = 0
    for name, flag in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2), ("k3", cv2.CALIB_FIX_K3)):
        if name not in terms:
            f |= flag
    if "p1" not in terms:
        f |= cv2.CALIB_ZERO_TANGENT_DIST
    return f


def _residual_correlation(resid: np.ndarray, uv: np.ndarray, cells: int) -> float:
    """How much neighbouring residuals move together: over a cells x cells grid on the pixels ``uv``
    ((m, 2)), the mean of n_c * mean_c(r)^2 over the mean of r^2, averaged over both axes (about 1
    for independent residuals, up to the points in a cell where they are all alike). At least 1."""
    if cells <= 1 or uv.shape[0] < 8 * cells:
        return 1.0
    lo, hi = uv.min(0), uv.max(0)
    ij = np.clip(np.floor((uv - lo) / np.maximum(hi - lo, 1e-9) * cells).astype(np.int64), 0, cells - 1)
    key = ij[:, 0] * cells + ij[:, 1]
    cnt = np.bincount(key, minlength=cells * cells)
    full = cnt >= 5
    if full.sum() < 4:
        return 1.0
    ratios = []
    for k in range(2):
        var = float(np.mean(resid[:, k] ** 2))
        if var <= 0:
            continue
        sm = np.bincount(key, weights=resid[:, k], minlength=cells * cells)
        ratios.append(float(np.mean(sm[full] ** 2 / cnt[full])) / var)
    return max(1.0, float(np.mean(ratios))) if ratios else 1.0


def _free_columns(terms: frozenset, intrinsic_flags: int) -> list[int]:
    """Columns of the projectPoints Jacobian a fit with these distortion terms and flags moves."""
    free = list(range(6)) + [6, 7]
    if not intrinsic_flags & cv2.CALIB_FIX_PRINCIPAL_POINT:
        free += [8, 9]
    return free + [10 + i for i, nm in enumerate(_DIST_NAMES) if nm in terms]


def _weighted_refine(obj, uv, white, K, dist, rvec, tvec, cols):
    """(K, dist, rvec, tvec) minimising the whitened reprojection errors, from the given fit."""
    p0 = np.concatenate([rvec.ravel(), tvec.ravel(), [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist])
    o = obj.reshape(-1, 1, 3)

    def unpack(q):
        p = p0.copy()
        p[cols] = q
        return p[0:3], p[3:6], np.array([[p[6], 0, p[8]], [0, p[7], p[9]], [0, 0, 1.0]]), p[10:15]

    def fun(q):
        rv, tv, Kq, dq = unpack(q)
        pr, _ = cv2.projectPoints(o, rv, tv, Kq, dq)
        return np.einsum("nij,nj->ni", white, pr.reshape(-1, 2) - uv).ravel()

    def jac(q):
        rv, tv, Kq, dq = unpack(q)
        _, J = cv2.projectPoints(o, rv, tv, Kq, dq)
        return np.einsum("nij,njk->nik", white, J[:, :15].reshape(-1, 2, 15)).reshape(-1, 15)[:, cols]

    res = least_squares(fun, p0[cols], jac=jac, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12, max_nfev=100)
    rv, tv, Kq, dq = unpack(res.x)
    return Kq, dq, rv.reshape(3, 1), tv.reshape(3, 1)


def _point_jacobian(obj, rvec, tvec, K, dist, step: float = 1e-3) -> np.ndarray:
    """(n, 2, 3) derivative of the projected pixels by the points (central differences)."""
    J = np.zeros((obj.shape[0], 2, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = step
        qp, _ = cv2.projectPoints((obj + d).reshape(-1, 1, 3), rvec, tvec, K, dist)
        qm, _ = cv2.projectPoints((obj - d).reshape(-1, 1, 3), rvec, tvec, K, dist)
        J[:, :, k] = (qp - qm).reshape(-1, 2) / (2 * step)
    return J


def _whitening(obj, model, cov_x, sig_p) -> np.ndarray:
    """(n, 2, 2) W per pair with W S W^T = I for the residual's predicted covariance S (the point's
    covariance mapped into the projector under ``model``, plus the pixel's), scaled to a median
    weight of 1 (so the residuals stay in px of a typical pair)."""
    n = obj.shape[0]
    S = np.zeros((n, 2, 2))
    if cov_x is not None:
        Jp = _point_jacobian(obj, model.rvec, model.tvec, model.K, model.dist)  # the centred frame: world axes
        S += np.einsum("nij,njk,nlk->nil", Jp, cov_x, Jp)
    if sig_p is not None:
        S[:, 0, 0] += sig_p[:, 0] ** 2
        S[:, 1, 1] += sig_p[:, 1] ** 2
    tr = np.trace(S, axis1=1, axis2=2)
    floor = 1e-6 * max(float(np.median(tr)), 1e-300)
    S += floor * np.eye(2)  # no pair weighs infinitely
    L = np.linalg.cholesky(S)
    W = np.linalg.inv(L)
    scale = math.sqrt(float(np.median(tr)) / 2)
    return W * scale


@dataclass
class _Model:
    """One calibrateCamera fit of the kept pairs with a set of distortion terms."""

    terms: frozenset
    K: np.ndarray
    dist: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    resid: np.ndarray
    rss: float
    dof: int
    correlation: float


def fit_projector(points_world, proj_uv, *, size: tuple[int, int],
                  settings: ProjectorSettings = ProjectorSettings(), point_cov=None,
                  pixel_sigma=None) -> ProjectorFit:
    """A perspective projector fitted to 3D points and the projector pixels that lit them.

    Args:
        points_world: (n, 3) points (e.g. triangulated by two cameras) in the frame the
            projector's pose is wanted in.
        proj_uv: (n, 2) their projector pixels (u_p, v_p).
        size: the projector's (width, height) in pixels.
        settings: see :class:`ProjectorSettings`.
        point_cov: optional (n, 3, 3) covariance of each point (world units squared, e.g.
            :func:`triangulation_covariance`), and
        pixel_sigma: optional (n,) or (n, 2) standard deviation of ``proj_uv`` (px): with either,
            each pair's residual is weighted by its predicted covariance (the point's mapped into
            the projector under the unweighted fit, plus the pixel's): the first-order form of a
            bundle adjustment that lets the points move within their uncertainty. Non-planar sets only.

    Returns:
        the :class:`ProjectorFit`; its ``problems`` say what the points do not determine.

    Raises:
        CalibrationError: too few pairs, pixels outside the projector, or a nearly planar
            point set without a known principal point.
    """
    X = np.asarray(points_world, np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"fit_projector: points must be (n, 3), got shape {X.shape}")
    uv = _check_pixels(proj_uv, "fit_projector: proj_uv", X.shape[0])
    w, h = (int(size[0]), int(size[1]))
    if w <= 0 or h <= 0:
        raise ValueError(f"fit_projector: size must be (width, height) > 0, got {size}")
    cov_x = sig_p = None
    if point_cov is not None:
        cov_x = np.asarray(point_cov, np.float64)
        if cov_x.shape != (X.shape[0], 3, 3) or not np.all(np.isfinite(cov_x)):
            raise ValueError(f"fit_projector: point_cov must be finite (n, 3, 3), got shape {cov_x.shape}")
    if pixel_sigma is not None:
        sig_p = np.asarray(pixel_sigma, np.float64)
        sig_p = np.repeat(sig_p[:, None], 2, 1) if sig_p.ndim == 1 else sig_p
        if sig_p.shape != (X.shape[0], 2) or not np.all(np.isfinite(sig_p) & (sig_p >= 0)):
            raise ValueError(f"fit_projector: pixel_sigma must be (n,) or (n, 2) finite >= 0, got shape "
                             f"{np.shape(pixel_sigma)}")
    ok = np.all(np.isfinite(X), 1)
    X, uv = X[ok], uv[ok]
    cov_x = None if cov_x is None else cov_x[ok]
    sig_p = None if sig_p is None else sig_p[ok]
    n = X.shape[0]
    if n < settings.min_points:
        raise CalibrationError(None, f"only {n} points with projector pixels; fitting a projector needs at least "
                                     f"{settings.min_points}")
    outside = (uv[:, 0] < -1) | (uv[:, 0] > w) | (uv[:, 1] < -1) | (uv[:, 1] > h)
    if outside.mean() > 0.01:
        raise CalibrationError(None, f"{100 * outside.mean():.0f} % of the projector pixels lie outside a {w}x{h} "
                                     f"projector (u up to {uv[:, 0].max():.0f}, v up to {uv[:, 1].max():.0f}): "
                                     "wrong projector size?")
    c = X.mean(0)
    Xc = X - c  # centred: float32 object points keep their precision, the Jacobian its conditioning
    _, sv, Vt = np.linalg.svd(Xc[:: max(1, n // 20000)], full_matrices=False)
    thickness = float(sv[2] / sv[0]) if sv[0] > 0 else 0.0
    planar = thickness < settings.min_thickness
    if planar and settings.principal_point is None:
        raise CalibrationError(None, f"the points lie nearly on one plane (thickness {thickness:.3g} of their "
                                     f"extent < {settings.min_thickness:g}): one plane does not fix the projector's "
                                     "focal length and principal point together; scan an object with depth, or "
                                     "give the principal point")
    intrinsic_flags = cv2.CALIB_USE_INTRINSIC_GUESS
    fixed: list[str] = []
    if planar:
        # a plane in its own frame (z = 0); square pixels, the given principal point, no distortion
        Rpl = Vt.copy()
        if np.linalg.det(Rpl) < 0:
            Rpl[2] *= -1
        obj = Xc @ Rpl.T
        obj[:, 2] = 0.0
        K0 = cv2.initCameraMatrix2D([obj.reshape(-1, 1, 3).astype(np.float32)],
                                    [uv.reshape(-1, 1, 2).astype(np.float32)], (w, h))
        f0 = 0.5 * (K0[0, 0] + K0[1, 1])
        K0 = np.array([[f0, 0, settings.principal_point[0]], [0, f0, settings.principal_point[1]], [0, 0, 1.0]])
        intrinsic_flags |= cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
        fixed = ["cx", "cy", "fy/fx"]
        base, candidates = frozenset(), []
    else:
        Rpl = np.eye(3)
        obj = Xc
        K0, _, _ = _decompose(_dlt(Xc, uv))
        K0[0, 1] = 0.0
        if settings.principal_point is not None:
            K0[0, 2], K0[1, 2] = settings.principal_point
            intrinsic_flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
            fixed = ["cx", "cy"]
        if not (K0[0, 0] > 0 and K0[1, 1] > 0 and np.all(np.isfinite(K0))):
            raise CalibrationError(None, "the points determine no projector (the DLT start failed): are the "
                                         "projector pixels those of these points?")
        base = set()
        candidates = []  # groups "auto" decides, in the order they may enter
        if settings.radial != "hold":
            base.add("k1")
        if settings.radial == "fit":
            base.add("k2")
        elif settings.radial == "auto":
            candidates += [("k2",), ("k3",)]
        if settings.tangential == "fit":
            base |= {"p1", "p2"}
        elif settings.tangential == "auto":
            candidates.append(("p1", "p2"))
        base = frozenset(base)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    n_intrinsics = 4 - (2 if settings.principal_point is not None else 0) - (1 if planar else 0)

    white = None  # (n, 2, 2): each pair's residual -> whitened residual (W^T W = its inverse covariance)

    def calibrate(terms: frozenset, keep: np.ndarray, start: _Model | None = None) -> tuple[_Model, np.ndarray]:
        """The fit of the kept pairs with these distortion terms (weighted where ``white`` is set:
        OpenCV's fit, then a least-squares refinement of the whitened residuals), and every pair's
        reprojection error (px)."""
        o = obj[keep].reshape(-1, 1, 3).astype(np.float32)
        p = uv[keep].reshape(-1, 1, 2).astype(np.float32)
        K_in = (start.K if start is not None else K0).copy()
        d_in = start.dist.copy() if start is not None else np.zeros(5)
        try:
            _, K, dist, rv, tv = cv2.calibrateCamera([o], [p], (w, h), K_in, d_in,
                                                     flags=intrinsic_flags | _dist_flags(terms), criteria=crit)
        except cv2.error as e:
            raise CalibrationError(None, f"the projector fit failed ({str(e).strip().splitlines()[-1]})") from None
        dist = np.asarray(dist, float).ravel()[:5]
        dist = np.concatenate([dist, np.zeros(5 - dist.size)])
        rvec, tvec = np.asarray(rv[0], float).reshape(3, 1), np.asarray(tv[0], float).reshape(3, 1)
        K = np.asarray(K, float)
        if white is not None:
            K, dist, rvec, tvec = _weighted_refine(obj[keep], uv[keep], white[keep], K, dist, rvec, tvec,
                                                   _free_columns(terms, intrinsic_flags))
        q, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, dist)
        d = q.reshape(-1, 2) - uv
        r = d[keep] if white is None else np.einsum("nij,nj->ni", white[keep], d[keep])
        rss = float(np.sum(r * r))
        dof = max(1, r.size - 6 - n_intrinsics - len(terms))
        return (_Model(terms, np.asarray(K, float), dist, rvec, tvec, r, rss, dof,
                       _residual_correlation(r, uv[keep], settings.correlation_cells)), np.linalg.norm(d, axis=1))

    keep = np.ones(n, bool)
    model, err = calibrate(base, keep)
    for _ in range(2):
        lim = max(settings.outlier_px, 5 * float(np.median(err[keep])))
        new = err <= lim
        if new.sum() < settings.min_points:
            raise CalibrationError(None, f"only {int(new.sum())} of {n} pairs fit the projector within {lim:.1f} px")
        if np.array_equal(new, keep):
            break
        keep = new
        model, err = calibrate(base, keep)
    if (cov_x is not None or sig_p is not None) and not planar:
        white = _whitening(obj, model, cov_x, sig_p)
        model, err = calibrate(base, keep, model)
    # "auto": add the distortion term the data most clearly ask for while one passes the test; the
    # residuals' correlation scales their variance, since neighbouring pairs share their errors
    decided: dict[tuple, str] = {}
    while True:
        best = None
        for g in candidates:
            if set(g) <= model.terms or (g == ("k3",) and "k2" not in model.terms):
                continue
            trial, trial_err = calibrate(model.terms | set(g), keep, model)
            stat = (model.rss - trial.rss) / max(trial.rss / trial.dof * trial.correlation, 1e-300)
            limit = float(chi2.ppf(1.0 - settings.alpha, len(g)))
            decided[g] = (f"{', '.join(g)}: {{}} (auto: the drop of the squared residuals is {stat:.1f} times the "
                          f"correlated noise variance, {'>' if stat > limit else '<='} {limit:.1f})")
            if stat > limit and (best is None or stat / limit > best[0]):
                best = (stat / limit, g, trial, trial_err)
        if best is None:
            break
        _, g, model, err = best
        decided[g] = decided[g].format("fitted")
    decisions = []
    for g in [("k1",), ("k2",), ("k3",), ("p1", "p2")]:
        if g in decided:
            decisions.append(decided[g].format("held at 0") if "{}" in decided[g] else decided[g])
        elif set(g) <= model.terms:
            decisions.append(f"{', '.join(g)}: fitted")
        else:
            why = ("a planar point set" if planar else "k2 held" if g == ("k3",) and settings.radial == "auto"
                   else "held")
            decisions.append(f"{', '.join(g)}: held at 0 ({why})")
    fixed += [nm for nm in _DIST_NAMES if nm not in model.terms]
    K, dist, rvec, tvec = model.K, model.dist, model.rvec, model.tvec
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise CalibrationError(None, "the projector fit diverged")
    Rp, _ = cv2.Rodrigues(rvec)
    # X_p = Rp (Rpl (X - c)) + tvec
    R = Rp @ Rpl
    t = tvec.ravel() - R @ c
    light = PerspectiveLight(width=w, height=h, K=np.asarray(K, float), dist=dist, R=R, t=t)
    # conditioning: the fit's own covariance and the Jacobian's condition number
    _, J = cv2.projectPoints(obj[keep].reshape(-1, 1, 3), rvec, tvec, K, dist)
    if white is not None:
        J = np.einsum("nij,njk->nik", white[keep], J.reshape(-1, 2, J.shape[1])).reshape(-1, J.shape[1])
    names = _PARAM_NAMES
    free = [i for i, nme in enumerate(names) if nme not in fixed and not (nme == "fy" and "fy/fx" in fixed)]
    if "fy/fx" in fixed:  # fx and fy move together
        J = J.copy()
        J[:, 6] += J[:, 7]
    cov, cond = _pose_std(J, free, model.resid.ravel())
    free_names = [names[i] for i in free]

    def stds(cov):
        sd = dict(zip(free_names, np.sqrt(np.maximum(np.diag(cov), 0))))
        out = {nm: float(sd.get(nm, 0.0)) for nm in ("fx", "cx", "cy", *_DIST_NAMES)}
        out["fy"] = float(sd.get("fy", sd.get("fx", 0.0) * K[1, 1] / K[0, 0]))
        out["rotation_deg"] = math.degrees(math.sqrt(max(np.trace(cov[:3, :3]), 0.0)))
        out["position"] = math.sqrt(max(np.trace(cov[3:6, 3:6]), 0.0))  # of the centred frame's origin
        return out

    std_noise = stds(cov)
    std = stds(cov * model.correlation)
    ifx, itz = free_names.index("fx"), free_names.index("tz")
    fd_corr = float(cov[ifx, itz] / math.sqrt(max(cov[ifx, ifx] * cov[itz, itz], 1e-300)))
    dist_to_points = float(np.linalg.norm(tvec))
    zp = X[keep] @ R[2] + t[2]
    z5, z50, z95 = (float(v) for v in np.percentile(zp, [5, 50, 95]))
    depth_ratio = (z95 - z5) / max(z50, 1e-300)
    problems, notes = [], []
    if planar:
        problems.append(f"the points lie nearly on one plane (thickness {thickness:.3g}): the principal point is "
                        f"the one given, square pixels and no distortion are assumed")

    def undetermined(sd: dict) -> list[str]:
        out = []
        for nm, v in (("fx", K[0, 0]), ("fy", K[1, 1])):
            if not sd[nm] <= settings.max_focal_std * v:
                out.append(f"projector {nm} {v:.1f} +- {sd[nm]:.2f} px ({100 * sd[nm] / v:.2f} % > "
                           f"{100 * settings.max_focal_std:g} %): the points do not determine the focal length")
        for nm, v, s in (("cx", K[0, 2], w), ("cy", K[1, 2], h)):
            if not sd[nm] <= settings.max_center_std * s:
                out.append(f"projector {nm} {v:.1f} +- {sd[nm]:.1f} px (> {100 * settings.max_center_std:g} % of "
                           f"the image): the points do not determine the principal point")
        if not sd["rotation_deg"] <= settings.max_rotation_std_deg:
            out.append(f"projector rotation +- {sd['rotation_deg']:.3f} deg (> {settings.max_rotation_std_deg:g}): "
                       "the points do not determine its pose")
        if not sd["position"] <= settings.max_position_std * dist_to_points:
            out.append(f"projector position +- {sd['position']:.2f} (> {100 * settings.max_position_std:g} % of "
                       f"its distance {dist_to_points:.0f}): the points do not determine its pose")
        return out

    # refused: what even independent residuals of this size leave open (the geometry of the points);
    # noted: what the residuals' correlated part (systematic match errors) leaves open on top
    problems += undetermined(std_noise)
    first = {p.split(" +-")[0] for p in problems}
    notes += [f"{p.split(':')[0]} with the residuals' correlation ({model.correlation:.1f}x their variance): "
              "systematic errors in the matches, not noise, limit it" for p in undetermined(std)
              if p.split(" +-")[0] not in first]
    if not planar and depth_ratio < settings.min_depth_ratio:
        notes.append(f"the points span {100 * depth_ratio:.1f} % of their distance along the projector's axis "
                     f"({z5:.0f} to {z95:.0f}; < {100 * settings.min_depth_ratio:g} %): the focal length and the "
                     f"distance trade (correlation {fd_corr:+.3f}); scan an object with more depth")
    e = err[keep]
    fit = ProjectorFit(light=light, rms_px=float(np.sqrt(np.mean(e * e))), residuals=ResidualStats.of(e),
                       used=int(keep.sum()), outliers=int(n - keep.sum()), thickness=thickness, std=std,
                       condition=cond, fixed=fixed, problems=problems, std_noise=std_noise,
                       correlation=model.correlation, depth_range=(z5, z95), depth_ratio=float(depth_ratio),
                       focal_distance_correlation=fd_corr, decisions=decisions, notes=notes,
                       weighted=white is not None)
    log.info("projector fit: RMS %.3f px over %d points; fx %.1f fy %.1f; condition %.3g; %s", fit.rms_px, fit.used,
             K[0, 0], K[1, 1], cond, "; ".join(decisions))
    return fit


def triangulation_covariance(camera1: Camera, camera2: Camera, points_world, sigma1, sigma2) -> np.ndarray:
    """(n, 3, 3) covariance (world units squared) of points triangulated by two cameras from pixels
    with standard deviations ``sigma1``, ``sigma2`` ((n,) px per axis): the inverse of the two rays'
    information (first order). Points far from both cameras or seen at a narrow angle come out long
    along their depth."""
    X = np.asarray(points_world, np.float64)
    info = np.zeros((X.shape[0], 3, 3))
    for cam, sig in ((camera1, sigma1), (camera2, sigma2)):
        rv, _ = cv2.Rodrigues(np.asarray(cam.R, float))
        J = _point_jacobian(X, rv, np.asarray(cam.t, float).reshape(3, 1), np.asarray(cam.K, float),
                            np.asarray(cam.dist, float))
        sig = np.maximum(np.asarray(sig, np.float64).reshape(-1), 1e-6)
        info += np.einsum("nij,nik->njk", J, J) / (sig ** 2)[:, None, None]
    info += 1e-12 * np.trace(info, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    return np.linalg.inv(info)


def procam_rig_from_fit(camera: Camera, light: PerspectiveLight, points_world, *,
                        margin: float = 0.25) -> Rig:
    """A one-camera procam rig (the world frame of :func:`~ringscan.pipeline.calibrate.procam.procam_rig`,
    tied to the light axis) from a camera and a projector in one frame and the points they saw
    (the working volume spans their depths along the projector axis, widened by ``margin``)."""
    R = light.R @ camera.R.T
    T = light.t - R @ camera.t
    X = np.asarray(points_world, float)
    X = X[np.all(np.isfinite(X), 1)]
    z = X @ light.R[2] + light.t[2]
    z = z[z > 0]
    if z.size == 0:
        raise CalibrationError(None, "no point lies in front of the fitted projector")
    near, far = depth_range(np.percentile(z, [1, 99]), margin=margin)
    return procam_rig(cam_K=camera.K, cam_dist=camera.dist, cam_size=(camera.width, camera.height), proj_K=light.K,
                      proj_dist=light.dist, proj_size=(light.width, light.height), R=R, T=T, z_range=(near, far))


def decoded_pairs(scan: Scan, view: View, *, max_pairs: int = 200_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Camera pixels and their projector pixels of one view of a ``decoded``-codec scan
    (imported Gray code: the frames hold each pixel's projector coordinates).

    Returns:
        ((n, 2) camera pixels, (n, 2) projector pixels (u_p, v_p)), at most ``max_pairs``
        of them (a seeded random subset).

    Raises:
        FormatError: the scan is of another codec, or its frames cannot be read.
    """
    if scan.patterns.codec != "decoded":
        raise FormatError(scan.path, f"codec {scan.patterns.codec!r}: camera-projector pairs are read from "
                                     "imported (decoded) scans; a two-camera scan gives them by matching")
    fr = read_view_frames(scan, view, ["proj_u", "proj_v"])
    ok = (fr[0] > 0) & (fr[1] > 0)
    yy, xx = np.nonzero(ok)
    if yy.size > max_pairs:
        pick = np.sort(np.random.default_rng(seed).choice(yy.size, max_pairs, replace=False))
        yy, xx = yy[pick], xx[pick]
    uv = np.stack([xx, yy], 1).astype(np.float64)
    proj = np.stack([fr[0][yy, xx], fr[1][yy, xx]], 1).astype(np.float64) / DECODED_SCALE - 1.0
    return uv, proj


# ----------------------------------------------------------------------------- OpenCV FileStorage


def _write_storage(path, write) -> None:
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise CalibrationError(path, "OpenCV cannot write it (the extension must be .yml, .yaml, .xml or .json)")
        try:
            write(fs)
        finally:
            fs.release()


def _write_size(fs, name: str, w: int, h: int) -> None:
    # as cv::Size is written: a flow sequence [width, height]
    fs.startWriteStruct(name, cv2.FileNode_SEQ | cv2.FileNode_FLOW)
    fs.write("", int(w))
    fs.write("", int(h))
    fs.endWriteStruct()


def write_opencv_procam(path, rig: Rig) -> None:
    """A camera-projector rig as OpenCV FileStorage: cam_int, cam_dist, proj_int, proj_dist,
    rotation, translation (X_proj = R X_cam + T), img_shape (height, width) and proj_size;
    the layout :func:`~ringscan.pipeline.calibrate.importer.read_opencv_calibration` reads. Atomic."""
    li = rig.light
    if not isinstance(li, PerspectiveLight):
        raise CalibrationError(path, "the rig's light is not a perspective projector; OpenCV's procam layout needs one")
    c = rig.camera
    R, T = relative_pose(c, li)

    def write(fs):
        fs.write("cam_int", np.asarray(c.K, float))
        fs.write("cam_dist", np.asarray(c.dist, float).reshape(1, -1))
        fs.write("proj_int", np.asarray(li.K, float))
        fs.write("proj_dist", np.asarray(li.dist, float).reshape(1, -1))
        fs.write("rotation", R)
        fs.write("translation", T.reshape(3, 1))
        fs.write("img_shape", np.array([[c.height, c.width]], np.float64))
        _write_size(fs, "proj_size", li.width, li.height)

    _write_storage(path, write)


def write_opencv_stereo(path, rig: Rig) -> None:
    """A two-camera rig as OpenCV FileStorage in the layout of OpenCV's structured-light sample:
    cam1_intrinsics, cam1_distorsion (sic), cam1_size, the same for cam2, RT_cam1_2_cam2 (the 4x4
    [R | T; 0 0 0 1]), R, T (X_cam2 = R X_cam1 + T), in the order of the sample's own file. Atomic."""
    c1, c2 = rig.camera, getattr(rig, "camera2", None)
    if c2 is None:
        raise CalibrationError(path, "the rig has one camera; OpenCV's stereo layout needs two")
    write_opencv_stereo_cameras(path, c1, c2)


def write_opencv_stereo_cameras(path, c1, c2) -> None:
    """Two cameras (``Camera``: K, dist, size, world pose) as :func:`write_opencv_stereo` writes a rig's. Atomic."""
    R, T = relative_pose(c1, c2)

    def write(fs):
        for k, c in (("cam1", c1), ("cam2", c2)):
            fs.write(f"{k}_intrinsics", np.asarray(c.K, float))
            fs.write(f"{k}_distorsion", np.asarray(c.dist, float).reshape(1, -1))
            _write_size(fs, f"{k}_size", c.width, c.height)
        fs.write("RT_cam1_2_cam2", np.vstack([np.hstack([R, T.reshape(3, 1)]), [[0.0, 0.0, 0.0, 1.0]]]))
        fs.write("R", R)
        fs.write("T", T.reshape(3, 1))

    _write_storage(path, write)
