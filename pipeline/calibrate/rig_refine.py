"""A rig's extrinsics refined from a scan's own matches (docs/calibration.md, "calibrate refine").

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
The projector fitted to the same kind of matches is :mod:`.projector_fit`; the rig
written as OpenCV files, :mod:`.opencv_files`; the two-view geometry (epipolar
distances, triangulation of a pair) these adjust with, :mod:`.two_view`.

Poses follow OpenCV: a device maps world points as ``X_d = R X_w + t``; the
relative pose of device 2 is ``X_2 = R X_1 + t``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.two_view import (
    _fundamental,
    _normalize,
    _sampson,
    epipolar_distances,
    reprojection_errors,
    triangulate_pair,
)
from ringscan.pipeline.formats.rig import Camera, PerspectiveLight, Rig

__all__ = ["RefineSettings", "ResidualStats", "Refinement", "refine_extrinsics", "refine_procam_rig", "refine_stereo_rig",
           "relative_pose", "triangulate_pair", "epipolar_distances", "reprojection_errors", "rotation_angle_deg",
           "MAX_MATCHES"]

log = logging.getLogger(__name__)

MAX_MATCHES = 5_000_000
"""Most matches any function here accepts (a 5 Mpx camera's worth); more is a caller's error."""


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
    from scipy.optimize import least_squares  # here, not at import: ringscan import's start-up (0.35 s)

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
    from scipy.optimize import least_squares  # here, not at import: ringscan import's start-up (0.35 s)

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
    camera 1's image left out.

    Size: a private step of refine_extrinsics: the fitted rotation and baseline direction (R, d), their
    covariance, the matches' pixels and camera 1's normalised coordinates (p1, p2, n1: the fields of a subset of
    its matches), the two intrinsics, the baseline and the settings.
    """
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


@dataclass(frozen=True)
class _Matches:
    """The matches :func:`refine_extrinsics` adjusts to: as observed, normalized, undistorted, and the subset used."""

    uv1: np.ndarray
    uv2: np.ndarray
    n1: np.ndarray
    n2: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    K1: np.ndarray
    K2: np.ndarray
    sub: np.ndarray


def _matches(dev1, dev2, uv1, uv2, settings: RefineSettings, rng) -> _Matches:
    """The matches normalized and undistorted, with the seeded subset the adjustment uses."""
    n = uv1.shape[0]
    K1, K2 = np.asarray(dev1.K, float), np.asarray(dev2.K, float)
    n1 = _normalize(uv1, K1, dev1.dist)
    n2 = _normalize(uv2, K2, dev2.dist)
    p1 = n1 @ K1[:2, :2].T + K1[:2, 2]
    p2 = n2 @ K2[:2, :2].T + K2[:2, 2]
    sub = np.sort(rng.choice(n, settings.max_points, replace=False)) if n > settings.max_points else np.arange(n)
    return _Matches(uv1, uv2, n1, n2, p1, p2, K1, K2, sub)


def _best_start(m: _Matches, R0, t0, settings: RefineSettings):
    """(start's name, R, unit d, loss scale, covariance) of the better adjustment of two starts: the matches'
    own essential matrix, and the rig's pose (kept only where clearly better)."""
    sub, K1, K2 = m.sub, m.K1, m.K2
    starts = []
    f1 = 0.5 * (K1[0, 0] + K1[1, 1])
    E, mask = cv2.findEssentialMat(m.n1[sub], m.n2[sub], np.eye(3), method=cv2.RANSAC, prob=0.999,
                                   threshold=settings.ransac_px / f1)
    if E is not None and E.shape == (3, 3):
        _, Re, te, _ = cv2.recoverPose(E, m.n1[sub], m.n2[sub], np.eye(3), mask=mask)
        starts.append(("essential", Re, te.ravel() / np.linalg.norm(te)))
    if np.linalg.norm(t0) > 0:
        starts.append(("rig", R0, t0 / np.linalg.norm(t0)))
    if not starts:
        raise CalibrationError(None, "the matches determine no pose (no essential matrix) and the rig has none")
    best = None
    for name, Rs, ds in starts:
        R, d, cost, scale, cov = _adjust(Rs, ds, m.p1[sub], m.p2[sub], K1, K2, settings)
        # costs compare only at one scale: evaluate each end at the first end's
        if best is not None:
            loss_scale = best[4]
            cost = _robust_cost(R, d, m.p1[sub], m.p2[sub], K1, K2, settings.loss, loss_scale)
            best_cost = _robust_cost(best[1], best[2], m.p1[sub], m.p2[sub], K1, K2, settings.loss, loss_scale)
            if cost < best_cost * (1 - 1e-6):
                best = (name, R, d, cost, scale, cov)
        else:
            best = (name, R, d, cost, scale, cov)
    name, R, d, _, scale, cov = best
    return name, R, d, scale, cov


def _third_device(m: _Matches, dev1, seen: tuple, sigmas: tuple, R, t, rng, settings: RefineSettings):
    """(name, epipolar stats against device 1, the three-device adjustment's (R, t, scale, cov, matches used)
    or the note why it was left out) of the third device: ``seen`` is (it, its pixels)."""
    light, uv_light = seen
    if not isinstance(light, (PerspectiveLight, Camera)):
        raise ValueError("refine_extrinsics: light (the third device) must be a calibrated PerspectiveLight "
                         "or a Camera")
    n, sub, K1, K2 = m.uv1.shape[0], m.sub, m.K1, m.K2
    third = "projector" if isinstance(light, PerspectiveLight) else "camera 2"
    uvl = _check_pixels(uv_light, "refine_extrinsics: uv_light", n)
    Rl, tl = relative_pose(dev1, light)
    Kl = np.asarray(light.K, float)
    nl = _normalize(uvl, Kl, light.dist)
    light_epi = ResidualStats.of(epipolar_distances(Rl, tl, K1, Kl, m.n1, nl))
    if not light_epi.median_px <= settings.max_light_epipolar_px:
        return third, light_epi, (f"{'the projector' if third == 'projector' else 'camera 2'} was left out of the "
                                  f"adjustment: camera 1's matches lie {light_epi.median_px:.2f} px (median) from its "
                                  f"epipolar lines (> {settings.max_light_epipolar_px:g} px), so its pose does not "
                                  f"fit the images; refine it first (--pair "
                                  f"{'projector' if third == 'projector' else 'cameras'})")
    sigma1, sigma2, sigma_light = sigmas
    s1 = _sigmas(sigma1, n, "refine_extrinsics: sigma1")
    s2 = _sigmas(sigma2, n, "refine_extrinsics: sigma2")
    sl = _sigmas(sigma_light, n, "refine_extrinsics: sigma_light")
    ref_px = float(np.median(s1))  # residuals in device-1 px of a median match
    bsub = sub
    if bsub.size > settings.bundle_points:
        bsub = np.sort(rng.choice(bsub, settings.bundle_points, replace=False))
    obs = [m.n1[bsub], m.n2[bsub], nl[bsub]]
    wts = [K1[0, 0] * ref_px / s1[bsub], K2[0, 0] * ref_px / s2[bsub], Kl[0, 0] * ref_px / sl[bsub]]
    R, t, scale, cov = _adjust_three(R, t, (Rl, tl), obs, wts, settings, settings.loss_scale_px)
    return third, light_epi, (R, t, scale, cov, int(bsub.size))


def _refined_residuals(m: _Matches, dev1, dev2, R0, t0, R, t, settings: RefineSettings):
    """(epipolar before, after, reprojection before, after, in front of both, inliers) over all the matches."""
    n, K1, K2 = m.uv1.shape[0], m.K1, m.K2
    epi0 = epipolar_distances(R0, t0, K1, K2, m.n1, m.n2) if np.linalg.norm(t0) > 0 else np.full(n, np.inf)
    epi1 = epipolar_distances(R, t, K1, K2, m.n1, m.n2)
    rep0, _ = reprojection_errors(R0, t0, dev1, dev2, m.uv1, m.uv2, m.n1, m.n2)
    rep1, front = reprojection_errors(R, t, dev1, dev2, m.uv1, m.uv2, m.n1, m.n2)
    samp = np.abs(_sampson(_fundamental(R, t, K1, K2), m.p1, m.p2))
    inl = int(np.count_nonzero(samp <= 3 * settings.loss_scale_px))
    return epi0, epi1, rep0, rep1, front, inl


def _pose_problems(front, rot_std, inl: int, n: int, settings: RefineSettings) -> list[str]:
    """What the matches do not determine about the refined pose."""
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
    return problems


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

    Size: a public function: the two devices and their matched pixels, and its documented keyword-only options:
    the baseline, the settings, and the optional sigmas and third device (the light) with its pixels.
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
    rng = np.random.default_rng(settings.seed)
    m = _matches(dev1, dev2, uv1, uv2, settings, rng)
    name, R, d, scale, cov = _best_start(m, R0, t0, settings)
    rot_std, dir_std = _axis_std_deg(cov)
    # the epipolar geometry does not see the sign of t: take the one that puts the points in front
    sub = m.sub
    _, front_p = reprojection_errors(R, d * base, dev1, dev2, uv1[sub], uv2[sub], m.n1[sub], m.n2[sub])
    _, front_m = reprojection_errors(R, -d * base, dev1, dev2, uv1[sub], uv2[sub], m.n1[sub], m.n2[sub])
    t = (-d if front_m.mean() > front_p.mean() else d) * base
    method, light_epi, bundle_used, notes = "two-view", None, 0, []
    third = ""
    if light is not None:
        third, light_epi, bundle = _third_device(m, dev1, (light, uv_light), (sigma1, sigma2, sigma_light), R, t,
                                                 rng, settings)
        if isinstance(bundle, str):
            notes.append(bundle)
        else:
            R, t, scale, cov, bundle_used = bundle
            rot_std, dir_std = _axis_std_deg(cov)
            method = "three-device"
    epi0, epi1, rep0, rep1, front, inl = _refined_residuals(m, dev1, dev2, R0, t0, R, t, settings)
    problems = _pose_problems(front, rot_std, inl, n, settings)
    verg_std, scale_std = _vergence(R, t / np.linalg.norm(t), cov, m.p1[sub], m.p2[sub], m.n1[sub], m.K1, m.K2, base,
                                    settings)
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
    the projector (its pose held) joins the adjustment (:func:`refine_extrinsics`).

    Size: the rig, the two cameras' matches and the keyword-only options it passes on to refine_extrinsics
    (baseline, settings, sigmas, the light's pixels).
    """
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

    Size: the rig, the camera-projector matches and its documented keyword-only options (baseline, which device
    to move, settings, a second camera's pixels, the sigmas).
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
