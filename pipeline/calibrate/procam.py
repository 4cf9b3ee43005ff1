"""Projector-camera calibration from Gray-code captures of a board (Moreno & Taubin, 3DIMPVT 2012).

For every capture (a board under the column/row Gray code, :mod:`graycode`):

1. the board's corners are found in the white frame (:mod:`board`);
2. every pixel is decoded to a sub-pixel projector position (u_p, v_p);
3. each corner's projector position comes from a *local homography* fitted to the
   decoded pixels in a window around it (camera pixel -> projector pixel; a plane
   seen by two pinhole devices is a homography, and the window spans many code
   steps, so the fit averages out the decoding noise); corners with too few
   decoded pixels around them are dropped.

Then the projector is calibrated like a camera from the board points and their
projector positions, and the pair is stereo-calibrated (intrinsics held, OpenCV
``stereoCalibrate``): ``X_p = R X_c + T``. :func:`procam_rig` turns the result
into a ringscan rig with the perspective light (see its docstring for the world
frame it chooses).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.board import Board, BoardSettings, BoardView, board_points, detect_board
from ringscan.pipeline.calibrate.camera import CameraCalibration, CameraSettings, calibrate_camera, distinct_views
from ringscan.pipeline.calibrate.capture_reader import read_capture
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import (
    Decoded,
    GrayCodeCapture,
    GrayCodeSettings,
    decode_graycode,
    subpixel_map,
)
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.progress import progress_bar
from ringscan.pipeline.formats.rig import Camera, PerspectiveLight, Rig, Volume, read_distortion

__all__ = ["ProcamSettings", "CaptureCorners", "ProcamCalibration", "projector_corners", "calibrate_procam",
           "procam_rig", "capture_corners", "capture_corners_of_folders", "depth_range", "principal_point_inside"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ProcamSettings:
    """Projector-camera calibration settings."""

    window_px: int = 25
    """Half-size of the local-homography window around each corner (camera px)."""
    min_window_pixels: int = 200
    """Fewest decoded pixels in a corner's window; fewer drops the corner."""
    min_corners: int = 12
    """Fewest corners with a projector position for a capture to count."""
    camera: CameraSettings = field(default_factory=CameraSettings)
    """Settings of the camera's and the projector's intrinsic fits."""
    graycode: GrayCodeSettings = field(default_factory=GrayCodeSettings)
    """Gray-code decoding settings."""
    board: BoardSettings = field(default_factory=BoardSettings)
    """Board detection settings."""
    max_stereo_rms_px: float = 2.0
    """Largest stereo RMS reprojection error of a calibration to stand behind (px):
    above it the camera's and the projector's fits disagree about the board poses."""


@dataclass
class CaptureCorners:
    """One capture's board corners in the camera and the projector."""

    name: str
    """The capture's name."""
    camera_view: BoardView
    """The board as the camera sees it (white frame)."""
    projector_view: BoardView
    """The same corners in projector pixels (only those with a local homography)."""


@dataclass
class ProcamCalibration:
    """Camera, projector and their relative pose."""

    camera: CameraCalibration
    """Camera intrinsics and per-view errors."""
    projector: CameraCalibration
    """Projector intrinsics and per-view errors."""
    R: np.ndarray
    """3x3 rotation camera -> projector: X_p = R X_c + T."""
    T: np.ndarray
    """(3,) translation camera -> projector (board units)."""
    stereo_rms: float
    """Stereo RMS reprojection error (px, camera and projector together)."""
    stereo_per_view: dict
    """Capture name -> stereo RMS (px) of that capture (camera and projector errors pooled)."""
    depths: np.ndarray
    """Depths along the projector's axis (projector-frame z) of every board corner used (board units)."""
    duplicates: list[str] = field(default_factory=list)
    """Captures left out as the same board pose as an earlier one ("name = earlier (d px)")."""
    problems: list[str] = field(default_factory=list)
    """What the captures do not determine: the camera's and the projector's problems and
    the stereo fit's (empty: a calibration to stand behind)."""


def projector_corners(corners: np.ndarray, dec: Decoded, *, settings: ProcamSettings = ProcamSettings()):
    """Projector positions of camera ``corners`` ((n, 2)) through local homographies.

    Returns:
        ((n, 2) float64 projector positions, (n,) bool found).
    """
    c = np.asarray(corners, np.float64)
    if c.ndim != 2 or c.shape[1] != 2:
        raise ValueError(f"projector_corners: corners must be (n, 2), got {c.shape}")
    H, W = dec.valid.shape
    good = dec.valid & np.isfinite(dec.u) & np.isfinite(dec.v)
    if dec.subpixel is not None:
        good &= dec.subpixel
    out = np.full((c.shape[0], 2), np.nan)
    ok = np.zeros(c.shape[0], bool)
    h = settings.window_px
    for i, (x, y) in enumerate(c):
        x0, x1 = max(0, int(round(x)) - h), min(W, int(round(x)) + h + 1)
        y0, y1 = max(0, int(round(y)) - h), min(H, int(round(y)) + h + 1)
        m = good[y0:y1, x0:x1]
        if np.count_nonzero(m) < settings.min_window_pixels:
            continue
        yy, xx = np.nonzero(m)
        src = np.stack([xx + x0, yy + y0], 1).astype(np.float64)
        dst = np.stack([dec.u[y0:y1, x0:x1][m], dec.v[y0:y1, x0:x1][m]], 1)
        Hm, inl = cv2.findHomography(src, dst, cv2.RANSAC, 1.0)
        if Hm is None:
            continue
        keep = inl.ravel().astype(bool)
        if np.count_nonzero(keep) < settings.min_window_pixels // 2:
            continue
        Hm, _ = cv2.findHomography(src[keep], dst[keep], 0)
        if Hm is None:
            continue
        p = cv2.perspectiveTransform(np.array([[[x, y]]], np.float64), Hm).reshape(2)
        out[i] = p
        ok[i] = True
    return out, ok


def capture_corners(cap: GrayCodeCapture, *, board: Board, name: str,
                    settings: ProcamSettings = ProcamSettings(), decoded: Decoded | None = None) -> CaptureCorners:
    """Board corners of one capture in the camera (white frame) and in the projector."""
    white8 = np.clip(cap.white + 0.5, 0, 255).astype(np.uint8)
    cv_view = detect_board(white8, board=board, name=name, settings=settings.board)
    if not cv_view.found:
        return CaptureCorners(name, cv_view, BoardView(name, False, cv_view.reason, None, None))
    dec = decoded
    if dec is None:
        dec = decode_graycode(cap, settings=settings.graycode)
        subpixel_map(cap, dec, settings=settings.graycode)
    pp, ok = projector_corners(cv_view.corners, dec, settings=settings)
    n = int(ok.sum())
    if n < settings.min_corners:
        reason = f"only {n} corners decoded in the projector (need {settings.min_corners})"
        return CaptureCorners(name, cv_view, BoardView(name, False, reason, None, None))
    pv = BoardView(name, True, "", pp[ok].astype(np.float32), cv_view.ids[ok])
    log.info("%s: %d of %d corners located in the projector", name, n, len(ok))
    return CaptureCorners(name, cv_view, pv)



def capture_corners_of_folders(folders, *, board: Board, projector: tuple[int, int], layout: str = "opencv-graycode",
                               settings: ProcamSettings = ProcamSettings(), progress: bool = True,
                               on_capture: Callable[[CaptureCorners], None] | None = None,
                               ) -> tuple[list[CaptureCorners], tuple[int, int] | None]:
    """:func:`capture_corners` of each capture folder of ``graycode_NN`` frames (read in ``layout``), in order,
    and the camera's frame size (width, height). A folder given again is not decoded again: it gets a copy of
    its first result (its own object; :func:`calibrate_procam` leaves the repeat out). ``on_capture`` is
    called with each result as it comes.

    Raises:
        FormatError: naming the folder: frames of another size than the first capture's.
        CalibrationError: as :func:`~ringscan.pipeline.calibrate.capture_reader.read_capture`.
    """
    caps, size, done = [], None, {}
    for folder in progress_bar(folders, desc="decoding captures", unit="capture", disable=not progress,
                               leave=False):
        key = os.path.realpath(folder)
        if key in done:  # a folder given again is not decoded again; calibrate_procam leaves the repeat out
            cc = dataclasses.replace(done[key])  # its own object: repeats are told apart by identity
        else:
            cap = read_capture(folder, projector=projector, layout=layout)
            s = (cap.white.shape[1], cap.white.shape[0])
            if size is None:
                size = s
            elif s != size:
                raise FormatError(folder, f"frames are {s[0]}x{s[1]}, {folders[0]} has {size[0]}x{size[1]}")
            cc = done[key] = capture_corners(cap, board=board, name=Path(folder).name, settings=settings)
            del cap
        if on_capture is not None:
            on_capture(cc)
        caps.append(cc)
    return caps, size


def calibrate_procam(
    captures: list[CaptureCorners],
    *,
    board: Board,
    camera_size: tuple[int, int],
    projector_size: tuple[int, int],
    settings: ProcamSettings = ProcamSettings(),
) -> ProcamCalibration:
    """Camera, projector and stereo calibration from the corners of every capture.

    Captures whose camera views show the same board pose (the same folder given
    twice) count once: the later ones are left out (``duplicates``).

    Raises:
        CalibrationError: no capture shows the board, or too few distinct ones do.
    """
    seen = [c for c in captures if c.camera_view.found]
    keep, dups = distinct_views([c.camera_view for c in seen], tol_px=settings.camera.duplicate_px)
    if dups:
        log.info("procam: left out as the same board pose as an earlier capture: %s", ", ".join(dups))
        if len(keep) < settings.camera.min_views:
            raise CalibrationError(None, f"only {len(keep)} distinct board pose(s) "
                                         f"({', '.join(seen[i].name for i in keep)}); need at least "
                                         f"{settings.camera.min_views}; the same board pose: {', '.join(dups)}")
        kept = {id(seen[i]) for i in keep}
        captures = [c for c in captures if not c.camera_view.found or id(c) in kept]
    cams = [c.camera_view for c in captures]
    cam = calibrate_camera(cams, board=board, size=camera_size, settings=settings.camera, what="camera")
    both = [c for c in captures if c.camera_view.found and c.projector_view.found]
    if len(both) < settings.camera.min_views:
        why = "; ".join(f"{c.name}: {c.projector_view.reason}" for c in captures if not c.projector_view.found)
        raise CalibrationError(None, f"projector calibration: only {len(both)} capture(s) with the board decoded "
                                     f"in the projector; need {settings.camera.min_views}" + (f" ({why})" if why else ""))
    proj = calibrate_camera([c.projector_view for c in both], board=board, size=projector_size,
                            settings=settings.camera, what="projector")
    pts = board_points(board)
    obj, ic, ip = [], [], []
    for c in both:
        common = np.intersect1d(c.camera_view.ids, c.projector_view.ids)
        ci = {int(k): i for i, k in enumerate(c.camera_view.ids)}
        pi = {int(k): i for i, k in enumerate(c.projector_view.ids)}
        obj.append(pts[common].reshape(-1, 1, 3))
        ic.append(c.camera_view.corners[[ci[int(k)] for k in common]].reshape(-1, 1, 2))
        ip.append(c.projector_view.corners[[pi[int(k)] for k in common]].reshape(-1, 1, 2))
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    n = len(obj)
    rv0 = [np.zeros((3, 1)) for _ in range(n)]
    rms, _, _, _, _, R, T, _, _, rvecs, tvecs, per_err = cv2.stereoCalibrateExtended(
        obj, ic, ip, cam.K, cam.dist, proj.K, proj.dist, tuple(camera_size), np.eye(3), np.zeros((3, 1)),
        rvecs=rv0, tvecs=[np.zeros((3, 1)) for _ in range(n)], flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    T = np.asarray(T, float).ravel()
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(T))) or np.linalg.norm(T) == 0:
        raise CalibrationError(None, "stereo calibration diverged")
    per_err = np.asarray(per_err, float).reshape(n, 2)
    per = {c.name: float(np.sqrt(np.mean(e ** 2))) for c, e in zip(both, per_err)}
    depths = []
    for o, rv, tv in zip(obj, rvecs, tvecs):
        Rb, _ = cv2.Rodrigues(rv)
        depths.append(((o.reshape(-1, 3) @ Rb.T + np.ravel(tv)) @ R.T + T)[:, 2])
    log.info("stereo RMS %.3f px; baseline %.1f", rms, float(np.linalg.norm(T)))
    problems = cam.problems + proj.problems
    if not rms <= settings.max_stereo_rms_px:
        problems.append(f"stereo RMS {rms:.2f} px > {settings.max_stereo_rms_px:g} px: the camera's and the "
                        f"projector's fits disagree about the board poses")
    return ProcamCalibration(camera=cam, projector=proj, R=np.asarray(R, float), T=T, stereo_rms=float(rms),
                             stereo_per_view=per, depths=np.concatenate(depths), duplicates=dups, problems=problems)


def procam_rig(
    *,
    cam_K, cam_dist, cam_size: tuple[int, int],
    proj_K, proj_dist, proj_size: tuple[int, int],
    R, T,
    z_range: tuple[float, float],
    r_max: float | None = None,
) -> Rig:
    """A ringscan rig of a camera and a perspective projector with X_p = R X_c + T.

    The world frame (docs/design.md §2 puts its origin where the light axis meets the
    reference plane, z toward the light) is chosen here: its z axis is the
    projector's optical axis pointing back toward the projector, x along the
    projector's x, and its origin on that axis at projector depth ``z_ref`` = the
    far end of ``z_range`` (camera-frame depths of the scene, e.g. the calibration
    board's, with margins). So world z is height above that far plane toward the
    projector, and the working volume spans the near-to-far depths.

    Args:
        z_range: (near, far) depths along the projector axis (board units) of the
            working volume.
        r_max: largest distance from the projector axis in the volume (default: the
            far plane's half-diagonal of the projector image, x1.5).

    Size: a public function: each array of an OpenCV camera-projector calibration (camera and projector
    intrinsics, distortion and size, the pose R, T) is a keyword-only argument of its own, as OpenCV's stereo
    calibration names them, plus the working depths and radius.
    """
    Kc, Kp = np.asarray(cam_K, float), np.asarray(proj_K, float)
    Rcp, Tcp = np.asarray(R, float), np.asarray(T, float).ravel()
    near, far = float(z_range[0]), float(z_range[1])
    if not (0 < near < far):
        raise ValueError(f"procam_rig: z_range must be 0 < near < far, got {z_range}")
    # world -> projector: X_p = Rw X_w + tw with Rw = diag(1, -1, -1) and the origin at (0, 0, far)_p
    Rw = np.diag([1.0, -1.0, -1.0])
    tw = np.array([0.0, 0.0, far])
    # world -> camera: X_c = Rcp^T (X_p - T)
    Rc = Rcp.T @ Rw
    tc = Rcp.T @ (tw - Tcp)
    if r_max is None:
        w, h = proj_size
        corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
        rays = np.linalg.solve(Kp, np.concatenate([corners, np.ones((4, 1))], 1).T).T
        r_max = 1.5 * far * float(np.max(np.hypot(rays[:, 0], rays[:, 1])))
    cam = Camera(width=int(cam_size[0]), height=int(cam_size[1]), K=Kc,
                 dist=read_distortion(np.asarray(cam_dist, float)), R=Rc, t=tc)
    light = PerspectiveLight(width=int(proj_size[0]), height=int(proj_size[1]), K=Kp,
                             dist=read_distortion(np.asarray(proj_dist, float)), R=Rw, t=tw)
    return Rig(camera=cam, light=light, volume=Volume(z_min=0.0, z_max=far - near, r_max=float(r_max)))


def depth_range(depths: np.ndarray, *, margin: float = 0.25) -> tuple[float, float]:
    """A working depth range around observed depths: [min, max] widened by ``margin`` of each end."""
    d = np.asarray(depths, float)
    d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        raise ValueError("depth_range: no positive depths")
    lo, hi = float(d.min()), float(d.max())
    return lo * (1 - margin), hi * (1 + margin)


def principal_point_inside(K: np.ndarray, size: tuple[int, int]) -> bool:
    """Whether the principal point lies inside the image (else rings about it are arcs)."""
    return 0 <= K[0, 2] <= size[0] - 1 and 0 <= K[1, 2] <= size[1] - 1

