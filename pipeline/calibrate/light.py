"""The paper's parallel light (docs/design.md §3) from ring captures of the reference
plane at two or more known heights.

Each capture (a gray-rings or phase-rings scan with sector bits, of the plane or a flat
plate at a known height) is decoded and sampled by the reconstruction's own stages; the
calibrated camera's ray through each sample meets its plane at a world point. A robust
fit of the ring condition gives the tilt, the pitch and the ring centre (it does not
depend on the roll about the light axis), and the decoded sectors give the roll. The
camera must be calibrated in the world frame first (:func:`camera_pose_on_plane`). The
model, the fit and its figures: docs/calibration.md §6 ("The parallel light").
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import warp as wp
from scipy.optimize import least_squares

from ringscan.kernels import init_warp, resolve_device
from ringscan.kernels.launch import cpu_threads
from ringscan.kernels.settings import AngleSettings, DecodeSettings, PhaseSettings, SampleSettings
from ringscan.pipeline.calibrate.board import Board, BoardView, board_points
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.codecs.registry import all_codecs, extract_samples
from ringscan.pipeline.formats.rig import Camera, ParallelLight, Rig, parse_rig
from ringscan.pipeline.formats.scan import Scan, View, read_view_frames
from ringscan.pipeline.geometry import camera_rays, project_points

__all__ = ["LightSettings", "PlaneSamples", "LightCalibration", "plane_samples", "fit_parallel_light",
           "calibrate_parallel_light", "rig_with_light", "camera_pose_on_plane", "rig_file_with_camera_pose",
           "LIGHT_CODECS"]

log = logging.getLogger(__name__)

LIGHT_CODECS = tuple(name for name, codec in all_codecs().items() if codec.calibrates_light)
"""Codecs whose captures calibrate the light: projected, and decoded without the rig's
geometry (``Codec.calibrates_light``): gray-rings and phase-rings."""


@dataclass(frozen=True)
class LightSettings:
    """Settings of the parallel-light calibration."""

    decode: DecodeSettings = field(default_factory=DecodeSettings)
    """Per-pixel decoding thresholds (as in ``ringscan reconstruct``)."""
    sample: SampleSettings = field(default_factory=SampleSettings)
    """Sub-pixel ring sampling thresholds (gray-rings)."""
    phase: PhaseSettings = field(default_factory=PhaseSettings)
    """Phase decoder settings (phase-rings)."""
    angle: AngleSettings = field(default_factory=AngleSettings)
    """The angle code's decoder (codecs with an angle code read their blocks from here too)."""
    min_confidence: float = 0.2
    """Samples below this decoding confidence are not used."""
    max_samples: int = 200_000
    """At most this many samples per capture enter the fit (an even subsample)."""
    robust_scale_px: float = 0.2
    """Soft-L1 scale of the ring fit (projector px): residuals beyond it count linearly."""
    max_residual_px: float = 1.0
    """After the robust fit, samples whose ring residual exceeds this (projector px)
    are dropped as mis-decoded and the fit is repeated."""
    min_height_span_mm: float = 5.0
    """The captures' heights must span at least this much: the tilt of the light is
    measured by how the rings move between heights."""
    min_samples: int = 500
    """Fewest usable samples per capture."""
    threads: int = 0
    """CPU threads for Warp launches (0: all cores)."""

    def __post_init__(self):
        for name in ("robust_scale_px", "max_residual_px", "min_height_span_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"LightSettings.{name}: expected a positive number, got {v!r}")
        for name in ("max_samples", "min_samples"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"LightSettings.{name}: expected a positive integer, got {v!r}")
        if not 0 <= self.min_confidence <= 1:
            raise ValueError(f"LightSettings.min_confidence: must be in [0, 1], got {self.min_confidence}")


@dataclass
class PlaneSamples:
    """The decoded samples of one capture of a plane at a known height."""

    name: str
    """The capture's name, for messages (scan folder / view)."""
    height_mm: float
    """The plane's height z (world, mm)."""
    points: np.ndarray
    """(n, 3) float64 world points: the camera rays through the samples met with z = height."""
    rho: np.ndarray
    """(n,) float64 decoded ring radius (projector px)."""
    sector: np.ndarray
    """(n,) int32 decoded sector (-1 unknown)."""
    center: tuple[float, float]
    """The pattern centre c (projector px)."""
    sector_bits: int
    """Sector bits of the pattern."""
    size: tuple[int, int]
    """The pattern's (width, height) in projector pixels."""


@dataclass
class LightCalibration:
    """The fitted parallel light and how well it fits."""

    light: ParallelLight
    """The light (R, t = 0, pixel pitch, axis pixel, size)."""
    rms_px: float
    """RMS ring residual |p - c| - rho of the samples kept (projector px)."""
    captures: dict
    """Per capture: ``height_mm``, ``samples`` (kept), ``dropped``, ``rms_px``, ``sector_agreement``
    (the share of samples with a decoded sector whose predicted sector is the decoded one)."""
    tilt_deg: float
    """Angle between the light axis and the world z axis (degrees)."""
    roll_deg: float
    """Turn of the projector image about the light axis (degrees)."""

    def report(self) -> dict:
        """A JSON-able summary."""
        li = self.light
        return {"pixel_pitch_mm": li.pixel_pitch_mm, "axis_px": li.axis_px.tolist(), "R": li.R.tolist(),
                "tilt_deg": self.tilt_deg, "roll_deg": self.roll_deg, "rms_px": self.rms_px, "captures": self.captures}


# ----------------------------------------------------------------------------- samples


def plane_samples(
    scan: Scan,
    view: View,
    *,
    height_mm: float,
    rig: Rig | None = None,
    settings: LightSettings = LightSettings(),
    device: str | None = None,
) -> PlaneSamples:
    """Decode one view of a plane capture into world points with their ring radius and sector.

    Args:
        scan: the capture's scan folder (gray-rings or phase-rings, with sector bits).
        view: one of ``scan.views``.
        height_mm: the plane's height (world z, mm).
        rig: whose camera (intrinsics and pose) to use; default the scan's rig.
        settings: decoding settings and limits.
        device: Warp device.

    Raises:
        CalibrationError: a codec that cannot calibrate the light, no sector code, too few samples.
    """
    spec = scan.patterns
    name = f"{scan.folder.name}/{view.name}"
    if spec.codec not in LIGHT_CODECS:
        raise CalibrationError(scan.path, f"codec {spec.codec!r} cannot calibrate the light "
                                          f"(use {' or '.join(LIGHT_CODECS)} captures with sector bits)")
    if spec.sector_bits < 1:
        raise CalibrationError(scan.path, "the patterns have no sector code (sector_bits = 0): the light's turn about "
                                          "its axis cannot be found; capture with --sector-bits 6")
    if not math.isfinite(height_mm):
        raise ValueError(f"height_mm: expected a finite number, got {height_mm!r}")
    rig = scan.rig if rig is None else rig
    cam = rig.camera
    init_warp()
    device = resolve_device(device)
    frames = read_view_frames(scan, view)
    if frames.shape[1:] != (cam.height, cam.width):
        raise CalibrationError(scan.path, f"view {view.name}: frames are {frames.shape[2]}x{frames.shape[1]}, the "
                                          f"camera is {cam.width}x{cam.height}")
    fr = wp.array(frames, dtype=wp.uint8 if frames.dtype == np.uint8 else wp.uint16, device=device)
    smp, _ = extract_samples(fr, scan, settings, settings.threads or cpu_threads())
    uv = smp.uv.numpy().astype(np.float64)
    rho = smp.rho.numpy().astype(np.float64)
    sector = smp.sector.numpy().astype(np.int32)
    keep = (smp.confidence.numpy() >= settings.min_confidence) & np.isfinite(rho) & (rho > 0)
    uv, rho, sector = uv[keep], rho[keep], sector[keep]
    if uv.shape[0] > settings.max_samples:
        idx = np.linspace(0, uv.shape[0] - 1, settings.max_samples).astype(np.int64)
        uv, rho, sector = uv[idx], rho[idx], sector[idx]
    if uv.shape[0] < settings.min_samples:
        raise CalibrationError(scan.path, f"view {view.name}: only {uv.shape[0]} ring samples decoded "
                                          f"(need {settings.min_samples}): is the plane lit and in view?")
    C, d = camera_rays(rig, uv)
    ok = np.abs(d[:, 2]) > 1e-9
    t = (height_mm - C[2]) / np.where(ok, d[:, 2], 1.0)
    ok &= t > 0
    X = C + t[:, None] * d
    log.info("%s: %d ring samples on z = %g mm", name, int(ok.sum()), height_mm)
    return PlaneSamples(name=name, height_mm=float(height_mm), points=X[ok], rho=rho[ok], sector=sector[ok],
                        center=(float(spec.center[0]), float(spec.center[1])), sector_bits=int(spec.sector_bits),
                        size=(int(spec.width), int(spec.height)))


# ----------------------------------------------------------------------------- fit


def _tilt(rx: float, ry: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([rx, ry, 0.0]))[0]


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ring_residuals(params: np.ndarray, X: np.ndarray, rho: np.ndarray) -> np.ndarray:
    rx, ry, log_s, ex, ey = params
    Y = X @ _tilt(rx, ry).T
    s = math.exp(log_s)
    return np.hypot(Y[:, 0] / s + ex, Y[:, 1] / s + ey) - rho


def _initial_guess(X: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Circle fit on one height, light along z: |X_xy - m| = s rho, linear in (m, s^2, |m|^2)."""
    A = np.stack([2 * X[:, 0], 2 * X[:, 1], rho ** 2, np.ones_like(rho)], 1)
    b = X[:, 0] ** 2 + X[:, 1] ** 2
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    mx, my, s2, _ = sol
    if not s2 > 0:
        raise CalibrationError(None, "light calibration: the decoded rings do not form circles on the plane "
                                     "(wrong heights, or a perspective projector?)")
    s = math.sqrt(s2)
    return np.array([0.0, 0.0, math.log(s), -mx / s, -my / s])


def _fit_roll(psi: np.ndarray, sector: np.ndarray, bits: int) -> tuple[float, float]:
    """The roll (radians) that puts the most samples inside their decoded sector.

    Sample i (polar angle psi_i before the roll, decoded sector k_i) fits the rolls
    [L_i, L_i + w] with L_i = -pi + k_i w - psi_i, w = 2 pi / 2^bits (modulo 2 pi).
    Returns (roll, share of samples it fits).
    """
    w = 2 * math.pi / (1 << bits)
    lo = -math.pi + sector * w - psi
    mid = lo + 0.5 * w
    r0 = math.atan2(np.sin(mid).mean(), np.cos(mid).mean())      # circular mean: a start
    lo = (lo - r0 + math.pi) % (2 * math.pi) - math.pi            # relative to r0, in [-pi, pi)
    hi = lo + w
    lo_s, hi_s = np.sort(lo), np.sort(hi)
    # The count of misfits changes only at the interval ends: try between each pair.
    cand = np.unique(np.concatenate([lo_s, hi_s]))
    cand = cand[(cand > -2 * w) & (cand < 2 * w)]
    if cand.size < 2:
        return r0, 0.0
    probe = 0.5 * (cand[1:] + cand[:-1])
    inside = np.searchsorted(lo_s, probe, side="right") - np.searchsorted(hi_s, probe, side="left")
    best = inside.max()
    top = np.flatnonzero(inside == best)
    # The longest run of best probes (adjacent indices), its middle.
    runs = np.split(top, np.flatnonzero(np.diff(top) > 1) + 1)
    run = max(runs, key=lambda r: cand[r[-1] + 1] - cand[r[0]])
    a, b = cand[run[0]], cand[run[-1] + 1]
    roll = r0 + 0.5 * (a + b)
    return math.atan2(math.sin(roll), math.cos(roll)), float(best) / lo.size


def _check_planes(planes: list, settings: LightSettings) -> None:
    """Raise unless ``planes`` are plane captures at heights spanning enough, all of one pattern."""
    if not planes or not all(isinstance(p, PlaneSamples) for p in planes):
        raise ValueError("planes: expected a non-empty list of PlaneSamples")
    heights = [p.height_mm for p in planes]
    if max(heights) - min(heights) < settings.min_height_span_mm:
        raise CalibrationError(None, f"light calibration: the captures' heights ({', '.join(f'{h:g}' for h in heights)}"
                                     f" mm) span less than {settings.min_height_span_mm:g} mm; one height pins the "
                                     "pitch but not the light's direction: capture the plane at two or more heights")
    ref = planes[0]
    for p in planes[1:]:
        if (p.center, p.sector_bits, p.size) != (ref.center, ref.sector_bits, ref.size):
            raise CalibrationError(None, f"light calibration: {p.name} has another pattern (centre {p.center}, "
                                         f"{p.sector_bits} sector bits, {p.size}) than {ref.name} ({ref.center}, "
                                         f"{ref.sector_bits}, {ref.size})")


def fit_parallel_light(
    planes: Sequence[PlaneSamples],
    *,
    settings: LightSettings = LightSettings(),
    gamma: float = 1.0,
) -> LightCalibration:
    """Fit the parallel light to decoded plane captures (see the module docstring).

    Args:
        planes: two or more captures at heights spanning ``settings.min_height_span_mm``,
            all of the same pattern (centre, size, sector bits).
        settings: fit settings.
        gamma: the light's response gamma to keep in the result (calibrated elsewhere).

    Raises:
        CalibrationError: too few captures or heights, patterns that differ, a fit that fails.
    """
    planes = list(planes)
    _check_planes(planes, settings)
    heights = [p.height_mm for p in planes]
    ref = planes[0]
    X = np.concatenate([p.points for p in planes])
    rho = np.concatenate([p.rho for p in planes])
    which = np.concatenate([np.full(p.rho.size, i) for i, p in enumerate(planes)])
    low = int(np.argmin(heights))
    x0 = _initial_guess(planes[low].points, planes[low].rho)
    fit = least_squares(_ring_residuals, x0, args=(X, rho), loss="soft_l1", f_scale=settings.robust_scale_px,
                        x_scale="jac")
    keep = np.abs(fit.fun) <= settings.max_residual_px
    if keep.sum() < 0.5 * keep.size:
        raise CalibrationError(None, f"light calibration: only {keep.sum()} of {keep.size} samples fit a parallel "
                                     f"light within {settings.max_residual_px:g} px (wrong heights, a camera that is "
                                     "not calibrated, or a perspective projector?)")
    fit = least_squares(_ring_residuals, fit.x, args=(X[keep], rho[keep]), x_scale="jac")
    rx, ry, log_s, ex, ey = fit.x
    s = math.exp(log_s)
    res = _ring_residuals(fit.x, X, rho)

    # Roll from the sectors.
    Rt = _tilt(rx, ry)
    Y = X @ Rt.T
    qx, qy = Y[:, 0] / s + ex, Y[:, 1] / s + ey
    psi = np.arctan2(qy, qx)
    sector = np.concatenate([p.sector for p in planes])
    known = keep & (sector >= 0)
    if known.sum() < settings.min_samples:
        raise CalibrationError(None, f"light calibration: only {known.sum()} samples carry a decoded sector "
                                     f"(need {settings.min_samples})")
    roll, share = _fit_roll(psi[known], sector[known], ref.sector_bits)
    R = _rot_z(roll) @ Rt
    c = np.asarray(ref.center)
    a = c + np.array([math.cos(roll) * ex - math.sin(roll) * ey, math.sin(roll) * ex + math.cos(roll) * ey])
    light = ParallelLight(R=R, t=np.zeros(3), pixel_pitch_mm=s, axis_px=a, width=ref.size[0], height=ref.size[1],
                          gamma=float(gamma))

    nsec = 1 << ref.sector_bits
    pred = np.floor((np.arctan2(np.sin(psi + roll), np.cos(psi + roll)) + math.pi) / (2 * math.pi) * nsec)
    pred = np.clip(pred.astype(np.int64), 0, nsec - 1)
    captures = {}
    for i, p in enumerate(planes):
        m = which == i
        k = m & keep
        ks = k & (sector >= 0)
        captures[p.name] = {"height_mm": p.height_mm, "samples": int(k.sum()), "dropped": int((m & ~keep).sum()),
                            "rms_px": float(np.sqrt(np.mean(res[k] ** 2))) if k.any() else float("nan"),
                            "sector_agreement": float(np.mean(pred[ks] == sector[ks])) if ks.any() else float("nan")}
    tilt = math.degrees(math.acos(min(1.0, abs(float(R[2, 2])))))
    cal = LightCalibration(light=light, rms_px=float(np.sqrt(np.mean(res[keep] ** 2))), captures=captures,
                           tilt_deg=tilt, roll_deg=math.degrees(roll))
    log.info("parallel light: s %.6f mm, axis (%.2f, %.2f) px, tilt %.3f deg, roll %.3f deg, RMS %.3f px, "
             "%.1f %% of sectors fit", s, a[0], a[1], tilt, cal.roll_deg, cal.rms_px, 100 * share)
    return cal


def calibrate_parallel_light(
    scans: Sequence[Scan],
    heights_mm: Sequence[float],
    *,
    rig: Rig | None = None,
    settings: LightSettings = LightSettings(),
    device: str | None = None,
) -> LightCalibration:
    """The parallel light from plane captures: every view of ``scans[i]`` shows the
    plane at ``heights_mm[i]``.

    Args:
        scans: the captures (scan folders, loaded).
        heights_mm: one height per scan (world z, mm).
        rig: the calibrated camera's rig (default: the first scan's); its light's
            gamma is kept.
        settings: decoding and fit settings.
        device: Warp device.
    """
    scans = list(scans)
    heights = [float(h) for h in heights_mm]
    if len(scans) != len(heights):
        raise ValueError(f"heights_mm: one height per scan expected, got {len(heights)} for {len(scans)} scans")
    if not scans:
        raise ValueError("scans: none given")
    rig = scans[0].rig if rig is None else rig
    planes = [plane_samples(sc, v, height_mm=h, rig=rig, settings=settings, device=device)
              for sc, h in zip(scans, heights) for v in sc.views]
    return fit_parallel_light(planes, settings=settings, gamma=float(getattr(rig.light, "gamma", 1.0)))


def rig_with_light(rig: Rig, light: ParallelLight) -> Rig:
    """``rig`` with its light replaced."""
    return dataclasses.replace(rig, light=light)


def camera_pose_on_plane(
    view: BoardView,
    *,
    board: Board,
    camera: Camera,
    thickness_mm: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The camera's pose in the world frame that a board lying on the reference plane defines.

    World frame (ringscan's choice for the paper's rig): origin on the plane z = 0
    under the middle of the board's inner corners, x along the board's columns
    (or against them: a chessboard's corner order is known only up to a half
    turn), z up from the plane toward the camera (and the light), y = z x x. The
    board's printed face lies at z = ``thickness_mm`` (the board's thickness).
    Place the board where the light axis will be, roughly: the working volume's
    radius is measured from the world z axis.

    Args:
        view: the board's detection in one image (found).
        board: the board.
        camera: the camera, whose intrinsics (K, dist) are used (its pose is not).
        thickness_mm: the board's thickness above the plane.

    Returns:
        (R, t, rms): X_c = R X_w + t, and the RMS reprojection error (px).

    Raises:
        CalibrationError: the view does not show the board.
    """
    if not view.found:
        raise CalibrationError(None, f"camera pose: {view.name}: {view.reason}")
    if not math.isfinite(thickness_mm):
        raise ValueError(f"thickness_mm: expected a finite number, got {thickness_mm!r}")
    obj = board_points(board)[view.ids].astype(np.float64)
    img = view.corners.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj.reshape(-1, 1, 3), img.reshape(-1, 1, 2), camera.K, camera.dist,
                                  flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError(None, f"camera pose: {view.name}: solvePnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj.reshape(-1, 1, 3), img.reshape(-1, 1, 2), camera.K, camera.dist, rvec, tvec)
    Rb, _ = cv2.Rodrigues(rvec)
    tb = tvec.ravel()
    # World axes in board coordinates: x along the columns, z toward the camera's side.
    cam_b = -Rb.T @ tb
    zw = np.array([0.0, 0.0, 1.0 if cam_b[2] > 0 else -1.0])
    xw = np.array([1.0, 0.0, 0.0])
    M = np.stack([xw, np.cross(zw, xw), zw], 1)          # board <- world rotation
    centre = np.array([(board.cols - 1) * board.square / 2, (board.rows - 1) * board.square / 2, 0.0])
    o_b = centre - thickness_mm * zw
    R = Rb @ M
    t = Rb @ o_b + tb
    proj = project_points(obj, Rb, tb, camera.K, camera.dist)
    rms = float(np.sqrt(np.mean(np.sum((proj - img) ** 2, 1))))
    log.info("camera pose from %s: centre (%.2f, %.2f, %.2f) mm, RMS %.3f px", view.name, *(-R.T @ t), rms)
    return R, t, rms


def rig_file_with_camera_pose(d: dict, *, rig: Rig, R: np.ndarray, t: np.ndarray,
                              source=None) -> tuple[Rig, float | None]:
    """The rig file's contents ``d`` (those of ``rig``) given the camera pose R, t of
    :func:`camera_pose_on_plane`, in place, and the rig they now hold. A perspective projector (calibrated
    with the camera: ``calibrate procam``) is fixed to the camera: it moves with it into the board's frame,
    so the baseline is kept.

    Returns:
        (the new rig, the camera-projector baseline kept; None where the light is not perspective).

    Raises:
        CalibrationError: naming ``source`` (the rig file): the baseline would change.
    """
    cam = rig.camera
    d["camera"]["R"], d["camera"]["t"] = R.tolist(), t.tolist()
    if rig.light.model == "perspective":
        Rrel = rig.light.R @ cam.R.T
        Trel = rig.light.t - Rrel @ cam.t
        d["light"]["R"], d["light"]["t"] = (Rrel @ R).tolist(), (Rrel @ t + Trel).tolist()
    new = parse_rig(d, source=source)
    if rig.light.model != "perspective":
        return new, None
    before = float(np.linalg.norm(-rig.light.R.T @ rig.light.t + cam.R.T @ cam.t))
    after = float(np.linalg.norm(-new.light.R.T @ new.light.t + new.camera.R.T @ new.camera.t))
    if abs(after - before) > 1e-6 * max(before, 1.0):
        raise CalibrationError(source, f"the camera-projector baseline would change from {before:.1f} to "
                                       f"{after:.1f}; not written")
    return new, after
