"""A projector fitted to 3D points and their projector pixels (docs/calibration.md, "projector-from-scan").

:func:`fit_projector` fits a perspective projector (K, distortion, pose) to 3D
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
projector, and the decoded pixel's). :func:`decoded_pairs` reads a decoded
scan's camera-projector pairs.

Poses follow OpenCV: a device maps world points as ``X_d = R X_w + t``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.stats import chi2

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.rig_refine import ResidualStats, _check_pixels
from ringscan.pipeline.calibrate.procam import depth_range, procam_rig
from ringscan.pipeline.calibrate.two_view import _homog
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.rig import Camera, PerspectiveLight, Rig
from ringscan.pipeline.formats.scan import Scan, View, read_view_frames

__all__ = ["ProjectorSettings", "ProjectorFit", "fit_projector", "procam_rig_from_fit", "DISTORTION_CHOICES",
           "triangulation_covariance", "decoded_pairs", "no_pinhole_projector", "PARALLEL_RMS_PX"]

log = logging.getLogger(__name__)

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


@dataclass
class _FitProblem:
    """The pairs a projector is fitted to (``obj``: the points in the centred frame, a plane's own for a
    planar set) and how :func:`_calibrate` fits them."""

    obj: np.ndarray
    uv: np.ndarray
    size: tuple[int, int]
    K0: np.ndarray
    flags: int
    n_intrinsics: int
    settings: ProjectorSettings
    white: np.ndarray | None = None
    """(n, 2, 2): each pair's residual -> whitened residual (W^T W = its inverse covariance)."""


def _fit_inputs(points_world, proj_uv, size, point_cov, pixel_sigma, settings: ProjectorSettings):
    """(X, uv, (w, h), point covariances, pixel sigmas) checked, of the pairs with finite points."""
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
    return X, uv, (w, h), cov_x, sig_p


def _point_set_shape(X: np.ndarray, settings: ProjectorSettings):
    """(centre, centred points, principal axes, thickness, planar) of the points; a planar set needs a principal point."""
    n = X.shape[0]
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
    return c, Xc, Vt, thickness, planar


def _planar_start(Xc, Vt, uv, size, settings: ProjectorSettings):
    """(Rpl, obj, K0, flags, fixed) of a planar set: the plane in its own frame (z = 0); square pixels,
    the given principal point, no distortion."""
    Rpl = Vt.copy()
    if np.linalg.det(Rpl) < 0:
        Rpl[2] *= -1
    obj = Xc @ Rpl.T
    obj[:, 2] = 0.0
    K0 = cv2.initCameraMatrix2D([obj.reshape(-1, 1, 3).astype(np.float32)],
                                [uv.reshape(-1, 1, 2).astype(np.float32)], size)
    f0 = 0.5 * (K0[0, 0] + K0[1, 1])
    K0 = np.array([[f0, 0, settings.principal_point[0]], [0, f0, settings.principal_point[1]], [0, 0, 1.0]])
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
    return Rpl, obj, K0, flags, ["cx", "cy", "fy/fx"]


def _general_start(Xc, uv, settings: ProjectorSettings):
    """(K0, flags, fixed, base terms, candidate term groups) of a set with depth: the DLT's intrinsics."""
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    fixed: list[str] = []
    K0, _, _ = _decompose(_dlt(Xc, uv))
    K0[0, 1] = 0.0
    if settings.principal_point is not None:
        K0[0, 2], K0[1, 2] = settings.principal_point
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
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
    return K0, flags, fixed, frozenset(base), candidates


def _fit_problem(Xc, Vt, uv, size, planar: bool, settings: ProjectorSettings):
    """(the fit problem, Rpl, fixed, base terms, candidate term groups) of the centred points."""
    if planar:
        Rpl, obj, K0, flags, fixed = _planar_start(Xc, Vt, uv, size, settings)
        base, candidates = frozenset(), []
    else:
        Rpl = np.eye(3)
        obj = Xc
        K0, flags, fixed, base, candidates = _general_start(Xc, uv, settings)
    n_intrinsics = 4 - (2 if settings.principal_point is not None else 0) - (1 if planar else 0)
    return _FitProblem(obj, uv, size, K0, flags, n_intrinsics, settings), Rpl, fixed, base, candidates


def _calibrate(pb: _FitProblem, terms: frozenset, keep: np.ndarray,
               start: _Model | None = None) -> tuple[_Model, np.ndarray]:
    """The fit of the kept pairs with these distortion terms (weighted where ``white`` is set:
    OpenCV's fit, then a least-squares refinement of the whitened residuals), and every pair's
    reprojection error (px)."""
    obj, uv, white, settings = pb.obj, pb.uv, pb.white, pb.settings
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    o = obj[keep].reshape(-1, 1, 3).astype(np.float32)
    p = uv[keep].reshape(-1, 1, 2).astype(np.float32)
    K_in = (start.K if start is not None else pb.K0).copy()
    d_in = start.dist.copy() if start is not None else np.zeros(5)
    try:
        _, K, dist, rv, tv = cv2.calibrateCamera([o], [p], pb.size, K_in, d_in,
                                                 flags=pb.flags | _dist_flags(terms), criteria=crit)
    except cv2.error as e:
        raise CalibrationError(None, f"the projector fit failed ({str(e).strip().splitlines()[-1]})") from None
    dist = np.asarray(dist, float).ravel()[:5]
    dist = np.concatenate([dist, np.zeros(5 - dist.size)])
    rvec, tvec = np.asarray(rv[0], float).reshape(3, 1), np.asarray(tv[0], float).reshape(3, 1)
    K = np.asarray(K, float)
    if white is not None:
        K, dist, rvec, tvec = _weighted_refine(obj[keep], uv[keep], white[keep], K, dist, rvec, tvec,
                                               _free_columns(terms, pb.flags))
    q, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, dist)
    d = q.reshape(-1, 2) - uv
    r = d[keep] if white is None else np.einsum("nij,nj->ni", white[keep], d[keep])
    rss = float(np.sum(r * r))
    dof = max(1, r.size - 6 - pb.n_intrinsics - len(terms))
    return (_Model(terms, np.asarray(K, float), dist, rvec, tvec, r, rss, dof,
                   _residual_correlation(r, uv[keep], settings.correlation_cells)), np.linalg.norm(d, axis=1))


def _drop_outliers(pb: _FitProblem, base: frozenset):
    """(model, errors, kept pairs): the fit with the base terms, refitted twice without its outliers."""
    settings = pb.settings
    n = pb.obj.shape[0]
    keep = np.ones(n, bool)
    model, err = _calibrate(pb, base, keep)
    for _ in range(2):
        lim = max(settings.outlier_px, 5 * float(np.median(err[keep])))
        new = err <= lim
        if new.sum() < settings.min_points:
            raise CalibrationError(None, f"only {int(new.sum())} of {n} pairs fit the projector within {lim:.1f} px")
        if np.array_equal(new, keep):
            break
        keep = new
        model, err = _calibrate(pb, base, keep)
    return model, err, keep


def _auto_distortion(pb: _FitProblem, model: _Model, err, keep, candidates):
    """(model, errors, decided): "auto" adds the distortion term the data most clearly ask for while one
    passes the test; ``decided`` holds each tested group's message (``{}``: fitted or held)."""
    # the residuals' correlation scales their variance, since neighbouring pairs share their errors
    decided: dict[tuple, str] = {}
    while True:
        best = None
        for g in candidates:
            if set(g) <= model.terms or (g == ("k3",) and "k2" not in model.terms):
                continue
            trial, trial_err = _calibrate(pb, model.terms | set(g), keep, model)
            stat = (model.rss - trial.rss) / max(trial.rss / trial.dof * trial.correlation, 1e-300)
            limit = float(chi2.ppf(1.0 - pb.settings.alpha, len(g)))
            decided[g] = (f"{', '.join(g)}: {{}} (auto: the drop of the squared residuals is {stat:.1f} times the "
                          f"correlated noise variance, {'>' if stat > limit else '<='} {limit:.1f})")
            if stat > limit and (best is None or stat / limit > best[0]):
                best = (stat / limit, g, trial, trial_err)
        if best is None:
            break
        _, g, model, err = best
        decided[g] = decided[g].format("fitted")
    return model, err, decided


def _decisions(decided: dict, model: _Model, planar: bool, settings: ProjectorSettings) -> list[str]:
    """Per distortion term, fitted or held and why."""
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
    return decisions


def _fitted_light(model: _Model, Rpl, c, size) -> tuple[PerspectiveLight, np.ndarray, np.ndarray]:
    """(the projector, R, t) in the points' frame of the model fitted in the centred (plane's) frame."""
    K, dist, rvec, tvec = model.K, model.dist, model.rvec, model.tvec
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise CalibrationError(None, "the projector fit diverged")
    Rp, _ = cv2.Rodrigues(rvec)
    # X_p = Rp (Rpl (X - c)) + tvec
    R = Rp @ Rpl
    t = tvec.ravel() - R @ c
    return PerspectiveLight(width=size[0], height=size[1], K=np.asarray(K, float), dist=dist, R=R, t=t), R, t


def _fit_stds(pb: _FitProblem, model: _Model, keep, fixed: list[str]):
    """(condition, stds of independent residuals, stds with their correlation, focal-distance correlation)
    of the fit: its own covariance and the Jacobian's condition number."""
    K, dist, rvec, tvec = model.K, model.dist, model.rvec, model.tvec
    _, J = cv2.projectPoints(pb.obj[keep].reshape(-1, 1, 3), rvec, tvec, K, dist)
    if pb.white is not None:
        J = np.einsum("nij,njk->nik", pb.white[keep], J.reshape(-1, 2, J.shape[1])).reshape(-1, J.shape[1])
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

    ifx, itz = free_names.index("fx"), free_names.index("tz")
    fd_corr = float(cov[ifx, itz] / math.sqrt(max(cov[ifx, ifx] * cov[itz, itz], 1e-300)))
    return cond, stds(cov), stds(cov * model.correlation), fd_corr


def _undetermined(sd: dict, K, size, dist_to_points: float, settings: ProjectorSettings) -> list[str]:
    """What standard deviations ``sd`` leave the points not determining about the projector."""
    w, h = size
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


def _add_findings(fit: ProjectorFit, model: _Model, planar: bool, settings: ProjectorSettings) -> None:
    """The fit's problems (what the points' geometry leaves open) and notes (what else the user should know)."""
    problems, notes = fit.problems, fit.notes
    K, size, dist_to_points = model.K, (fit.light.width, fit.light.height), float(np.linalg.norm(model.tvec))
    if planar:
        problems.append(f"the points lie nearly on one plane (thickness {fit.thickness:.3g}): the principal point is "
                        f"the one given, square pixels and no distortion are assumed")
    # refused: what even independent residuals of this size leave open (the geometry of the points);
    # noted: what the residuals' correlated part (systematic match errors) leaves open on top
    problems += _undetermined(fit.std_noise, K, size, dist_to_points, settings)
    first = {p.split(" +-")[0] for p in problems}
    notes += [f"{p.split(':')[0]} with the residuals' correlation ({model.correlation:.1f}x their variance): "
              "systematic errors in the matches, not noise, limit it"
              for p in _undetermined(fit.std, K, size, dist_to_points, settings) if p.split(" +-")[0] not in first]
    z5, z95 = fit.depth_range
    if not planar and fit.depth_ratio < settings.min_depth_ratio:
        notes.append(f"the points span {100 * fit.depth_ratio:.1f} % of their distance along the projector's axis "
                     f"({z5:.0f} to {z95:.0f}; < {100 * settings.min_depth_ratio:g} %): the focal length and the "
                     f"distance trade (correlation {fit.focal_distance_correlation:+.3f}); scan an object with more "
                     "depth")


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
    X, uv, (w, h), cov_x, sig_p = _fit_inputs(points_world, proj_uv, size, point_cov, pixel_sigma, settings)
    n = X.shape[0]
    c, Xc, Vt, thickness, planar = _point_set_shape(X, settings)
    pb, Rpl, fixed, base, candidates = _fit_problem(Xc, Vt, uv, (w, h), planar, settings)
    model, err, keep = _drop_outliers(pb, base)
    if (cov_x is not None or sig_p is not None) and not planar:
        pb.white = _whitening(pb.obj, model, cov_x, sig_p)
        model, err = _calibrate(pb, base, keep, model)
    model, err, decided = _auto_distortion(pb, model, err, keep, candidates)
    decisions = _decisions(decided, model, planar, settings)
    fixed += [nm for nm in _DIST_NAMES if nm not in model.terms]
    light, R, t = _fitted_light(model, Rpl, c, (w, h))
    cond, std_noise, std, fd_corr = _fit_stds(pb, model, keep, fixed)
    zp = X[keep] @ R[2] + t[2]
    z5, z50, z95 = (float(v) for v in np.percentile(zp, [5, 50, 95]))
    depth_ratio = (z95 - z5) / max(z50, 1e-300)
    e = err[keep]
    fit = ProjectorFit(light=light, rms_px=float(np.sqrt(np.mean(e * e))), residuals=ResidualStats.of(e),
                       used=int(keep.sum()), outliers=int(n - keep.sum()), thickness=thickness, std=std,
                       condition=cond, fixed=fixed, problems=[], std_noise=std_noise,
                       correlation=model.correlation, depth_range=(z5, z95), depth_ratio=float(depth_ratio),
                       focal_distance_correlation=fd_corr, decisions=decisions, notes=[],
                       weighted=pb.white is not None)
    _add_findings(fit, model, planar, settings)
    log.info("projector fit: RMS %.3f px over %d points; fx %.1f fy %.1f; condition %.3g; %s", fit.rms_px, fit.used,
             model.K[0, 0], model.K[1, 1], cond, "; ".join(decisions))
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
    proj = np.stack([fr[0][yy, xx], fr[1][yy, xx]], 1).astype(np.float64) / scan.patterns.scale - 1.0
    return uv, proj


PARALLEL_RMS_PX = 0.5
"""A projector whose pixels are an affine function of the points to within this (px RMS) is a parallel
(collimated) light: a pinhole's are not, unless the points lie in one plane."""


def no_pinhole_projector(X: np.ndarray, uv: np.ndarray) -> str:
    """Why no pinhole projector fits the points' projector pixels (OpenCV only says that the principal
    point left the image): an affine map fits them (a parallel light), or they fit no camera model."""
    A = np.c_[X, np.ones(len(X))]
    coef, *_ = np.linalg.lstsq(A, uv, rcond=None)
    rms = float(np.sqrt(np.mean(np.sum((A @ coef - uv) ** 2, axis=1))))
    thick = float(np.linalg.svd(X - X.mean(0), compute_uv=False)[-1] / np.sqrt(len(X)))
    if rms <= PARALLEL_RMS_PX and thick > 1.0:
        return (f"no pinhole projector fits the scan: its projector pixels are an affine function of the points "
                f"(RMS {rms:.2f} px), the mark of a parallel (collimated) light such as the virtual rig's default "
                "(`ringscan simulate --light parallel`); projector-from-scan fits a perspective projector; a "
                "parallel light is calibrated with `ringscan calibrate light` (docs/calibration.md)")
    return ("no pinhole projector fits the scan's projector pixels (the fit put the principal point outside the "
            f"projector image; an affine map leaves {rms:.1f} px RMS): check --projector WxH and that the scan's "
            "projector coordinates are the projector's pixels")
