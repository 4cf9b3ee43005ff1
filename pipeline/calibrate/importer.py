"""Real Gray-code captures -> a ringscan scan folder of the ``decoded`` codec (docs/design.md §7).

:func:`import_captures` decodes every capture (one view each: a folder of frames or an
image list, :func:`~ringscan.pipeline.calibrate.capture_files.list_capture`) to sub-pixel
projector positions (:mod:`graycode`) and writes them as the ``decoded`` codec's
frames (docs/formats.md), with the rig; ``ringscan reconstruct`` then meets each
pixel's camera ray with the cone of its rho = |p - c| around the projector's
principal point and picks the root by its polar angle. A capture of two cameras
(OpenCV's structured-light sample) becomes a two-camera scan: camera 1's decoded
frames are the view's, camera 2's go under the view's ``camera2``.

:func:`read_opencv_calibration` (:mod:`.opencv_files`, beside the writers) reads an
OpenCV camera-projector calibration file
(cam_int, cam_dist, proj_int, proj_dist, rotation (or 'roration'), translation;
X_proj = R X_cam + T); :func:`read_stereo_calibration` a camera-camera one as
OpenCV's structured-light sample has it (cam1_intrinsics, cam1_distorsion,
cam1_size, the same for cam2, R, T, RT_cam1_2_cam2; X_cam2 = R X_cam1 + T), which
:func:`stereo_rig` turns into a two-camera rig in camera 1's frame.
:func:`triangulate_codes` is the plain way (two views' rays through
``cv2.triangulatePoints``), used for the working volume of such rigs and by
``benchmarks/procam_plane.py``.
"""

from __future__ import annotations

import logging
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.capture_files import (
    LIST_SUFFIXES,
    TEXT_LIST_SUFFIXES,
    check_capture_sizes,
    list_capture,
)
from ringscan.pipeline.calibrate.capture_reader import cpu_cores, read_capture_files
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import (
    LOW_MODULATION_WARN_SHARE,
    GrayCodeSettings,
    decode_graycode,
    load_subpixel_kernels,
    subpixel_map,
)
from ringscan.pipeline.calibrate.opencv_files import _stereo_message
from ringscan.pipeline.calibrate.procam import depth_range, procam_rig
from ringscan.pipeline.formats.atomic import check_output_folder, lock_folder
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.patterns import DECODED_SCALE, decoded_scale, parse_patterns
from ringscan.pipeline.formats.rig import (
    Camera,
    PerspectiveLight,
    Rig,
    UncalibratedLight,
    Volume,
    has_calibrated_light,
    parse_rig,
    read_distortion,
    rig_to_dict,
)
from ringscan.pipeline.formats.scan import Scan, View, check_view_name, save_scan

__all__ = ["ImportSettings", "UNITS", "parse_units", "to_millimetres", "stereo_rig", "triangulate_codes", "import_captures", "check_import_names", "encode_decoded",
           "procam_pose", "CAMERA2_DIR"]

CAMERA2_DIR = "cam2"
"""Camera 2's decoded frames of a view go to ``<view>/cam2/`` in the scan folder."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImportSettings:
    """Import settings."""

    sector_bits: int = 8
    """Bits of the polar-angle sector handed to the root choice (2**bits sectors)."""
    integer_only: bool = False
    """Write the integer codes (no sub-pixel boundaries): the plain decode, for comparison."""
    graycode: GrayCodeSettings = GrayCodeSettings()
    """Decoding settings."""
    frame_bits: int | None = None
    """Bits the captures' 16-bit frames hold (9..16: a 12-bit camera's values 0..4095), scaled
    to 16 bits as they are read (as a scan's ``frame_bits``); 8 for 8-bit frames; None: the
    frames' own bits."""


UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
"""Named units of an OpenCV calibration's translations, in millimetres."""
MAX_MM_PER_UNIT = 1.0e4
"""Largest millimetres per calibration unit (10 m: beyond it no rig fits the rig file's ranges)."""


def parse_units(text: str) -> float:
    """Millimetres per unit of ``--units``: mm, cm, m, in, or a number of millimetres (a board square's
    size when the calibration counted in squares, say).

    Raises:
        ValueError: anything else, saying what is read.
    """
    t = str(text).strip().lower()
    if t in UNITS:
        return UNITS[t]
    try:
        v = float(t)
    except ValueError:
        v = float("nan")
    if not (np.isfinite(v) and 0 < v <= MAX_MM_PER_UNIT):
        raise ValueError(f"expected mm, cm, m, in or the millimetres of one unit (a number in (0, "
                         f"{MAX_MM_PER_UNIT:g}]), got {text!r}")
    return v


def to_millimetres(cal: dict, mm_per_unit: float) -> dict:
    """An OpenCV calibration's arrays (:func:`read_opencv_calibration`, :func:`read_stereo_calibration`) with
    its translation ``T`` in millimetres (intrinsics and rotations have no units)."""
    if mm_per_unit == 1.0:
        return cal
    return {**cal, "T": np.asarray(cal["T"], float) * float(mm_per_unit)}


def stereo_rig(cal: dict, *, projector: tuple[int, int], z_range: tuple[float, float],
               light: PerspectiveLight | None = None, r_max: float | None = None) -> Rig:
    """A two-camera rig of :func:`read_stereo_calibration`'s arrays, in camera 1's frame (R = I, t = 0).

    Args:
        cal: cam1_K, cam1_dist, cam1_size, cam2_K, cam2_dist, cam2_size, R, T (X_cam2 = R X_cam1 + T);
            the sizes must be known ((W, H)).
        projector: the projector's (width, height).
        z_range: (near, far) depths along camera 1's optical axis: the working volume.
        light: the projector in camera 1's frame (X_p = R X_cam1 + t), or None for an
            ``UncalibratedLight`` of ``projector``'s size.
        r_max: largest distance from camera 1's axis in the volume (default: 1.5x the far
            plane's half-diagonal of camera 1's image).
    """
    near, far = float(z_range[0]), float(z_range[1])
    if not (0 < near < far):
        raise ValueError(f"stereo_rig: z_range must be 0 < near < far, got {z_range}")
    K1 = np.asarray(cal["cam1_K"], float)
    w1, h1 = cal["cam1_size"]
    w2, h2 = cal["cam2_size"]
    if r_max is None:
        corners = np.array([[0, 0], [w1 - 1, 0], [0, h1 - 1], [w1 - 1, h1 - 1]], float)
        rays = np.linalg.solve(K1, np.concatenate([corners, np.ones((4, 1))], 1).T).T
        r_max = 1.5 * far * float(np.max(np.hypot(rays[:, 0], rays[:, 1])))
    cam1 = Camera(width=int(w1), height=int(h1), K=K1, dist=read_distortion(np.asarray(cal["cam1_dist"], float)),
                  R=np.eye(3), t=np.zeros(3))
    cam2 = Camera(width=int(w2), height=int(h2), K=np.asarray(cal["cam2_K"], float),
                  dist=read_distortion(np.asarray(cal["cam2_dist"], float)), R=np.asarray(cal["R"], float),
                  t=np.asarray(cal["T"], float).ravel())
    li = light if light is not None else UncalibratedLight(width=int(projector[0]), height=int(projector[1]))
    return Rig(camera=cam1, light=li, volume=Volume(z_min=near, z_max=far, r_max=float(r_max)), camera2=cam2)


def procam_pose(rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) with X_proj = R X_cam + T of a rig with a perspective light."""
    li = rig.light
    if not isinstance(li, PerspectiveLight):
        raise ValueError("procam_pose: the rig's light is not perspective")
    c = rig.camera
    # X_c = Rc X_w + tc, X_p = Rp X_w + tp  =>  X_p = Rp Rc^T (X_c - tc) + tp
    R = li.R @ c.R.T
    return R, li.t - R @ c.t


def triangulate_codes(cam_px: np.ndarray, proj_px: np.ndarray, *, cam_K, cam_dist, proj_K, proj_dist, R, T):
    """Plain triangulation (OpenCV): (n, 2) camera and projector pixels -> (n, 3) camera-frame points."""
    a = np.asarray(cam_px, np.float64).reshape(-1, 1, 2)
    b = np.asarray(proj_px, np.float64).reshape(-1, 1, 2)
    if a.shape != b.shape:
        raise ValueError(f"triangulate_codes: {a.shape[0]} camera but {b.shape[0]} projector pixels")
    if a.shape[0] == 0:
        return np.zeros((0, 3))
    na = cv2.undistortPoints(a, np.asarray(cam_K, float), np.asarray(cam_dist, float)).reshape(-1, 2)
    nb = cv2.undistortPoints(b, np.asarray(proj_K, float), np.asarray(proj_dist, float)).reshape(-1, 2)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([np.asarray(R, float), np.asarray(T, float).reshape(3, 1)])
    X = cv2.triangulatePoints(P1, P2, na.T, nb.T)
    return (X[:3] / X[3]).T


def encode_decoded(u: np.ndarray, v: np.ndarray, contrast: np.ndarray,
                   scale: int = DECODED_SCALE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``decoded`` codec's three 16-bit frames of sub-pixel maps (NaN = not decoded; ``scale``: fixed-point
    steps a projector px, ``patterns.decoded_scale`` of the projector).

    A whole-pixel value is an integer code (a pixel the sub-pixel walk could not place: the reader gives it an
    integer code's sigma); a sub-pixel value that rounds onto a whole pixel (1 in ``scale``) is written one step
    beside it, on its own side (at most 1 / scale px off), so that the reader does not take it for one."""
    lo, hi = -1 + 1.0 / scale, 65535.0 / scale - 1
    pow2 = float(scale).is_integer() and int(scale) & (int(scale) - 1) == 0  # (the codec's scales are)

    def enc(a):
        # in place and in uint16 where it can be (the same values as the plain expressions, ~2.5x faster: a
        # 1920x1280 camera's maps take a tenth of a second less of the import)
        a = np.asarray(a, np.float64)
        ok = a > lo  # (False for NaN; +-inf fail one side)
        ok &= a < hi
        x = a + 1.0
        x *= scale
        q = np.rint(x)
        with np.errstate(invalid="ignore"):  # (NaN and inf cast: zeroed next)
            out = q.astype(np.uint16, order="C")
        np.copyto(out, 0, where=~ok)
        if scale > 1:  # a sub-pixel value on the integer grid: one step beside it, on its own side
            if pow2:
                grid = (out & np.uint16(int(scale) - 1)) == 0
            else:
                with np.errstate(invalid="ignore"):  # (NaN and inf: not ok)
                    grid = q % scale == 0
            grid &= ok
            at = np.flatnonzero(grid)
            a1, x1, q1 = a.ravel()[at], x.ravel()[at], q.ravel()[at]
            sub = a1 != np.rint(a1)
            out.reshape(-1)[at[sub]] = (q1[sub] + np.where(x1[sub] >= q1[sub], 1.0, -1.0)).astype(np.uint16)
        return out

    fu, fv = enc(u), enc(v)
    bad = (fu == 0) | (fv == 0)
    fu[bad] = 0
    fv[bad] = 0
    fc = np.asarray(contrast, np.float64) * 257.0
    np.clip(fc, 0, 65535, out=fc)
    fc = fc.astype(np.uint16)
    return fu, fv, fc


def check_import_names(captures: list) -> list[str]:
    """The view name of each capture: a folder's own name (``.`` and ``DIR/sub/..`` by their real name),
    an image list's name without its suffix (``capture_0.yml``: ``capture_0``), checked as a view name
    (:func:`~ringscan.pipeline.formats.scan.check_view_name`) and unique (ignoring
    case), before anything is decoded or written.

    Raises:
        FormatError: naming the capture folder: a name that is not folder-safe, or two captures with one name.
    """
    names, seen = [], {}
    for folder in captures:
        real = Path(os.path.abspath(folder)).resolve()
        is_list = real.suffix.lower() in LIST_SUFFIXES + TEXT_LIST_SUFFIXES and not real.is_dir()
        name = real.stem if is_list else real.name
        check_view_name(name, source=folder, where="the image list's name (the view's name)" if is_list else
                        "the capture folder's name (the view's name)")
        key = name.casefold()
        if key in seen:
            raise FormatError(folder, f"has the name {name!r} of the capture {seen[key]}: two views of one name "
                                      "(give capture folders of different names)")
        seen[key] = folder
        names.append(name)
    return names


DEPTH_PIXELS = 65536
"""Most camera-1 pixels the working depth is triangulated from (every 4th pixel each way, or every 8th, 16th
... where that is more): its 1st and 99th percentiles are as good from these, and OpenCV's triangulation of
every 4th pixel of a statue-sized capture cost 0.06 s."""


def _stereo_depths(d1, d2, cal: dict, projector) -> np.ndarray:
    """Camera-1 depths of pixels matched between the cameras by their integer projector code
    (camera 2's pixels of one code averaged): the plain way, for the working volume."""
    step = 4
    while int(d1.valid.sum()) > DEPTH_PIXELS * step * step:
        step *= 2
    wp_, hp_ = projector
    n = int(wp_) * int(hp_)
    v2 = d2.valid
    y2, x2 = np.nonzero(v2)
    code2 = d2.row[v2].astype(np.int64) * wp_ + d2.col[v2]
    cnt = np.bincount(code2, minlength=n)
    sx = np.bincount(code2, weights=x2, minlength=n)
    sy = np.bincount(code2, weights=y2, minlength=n)
    v1 = d1.valid[::step, ::step]
    yy, xx = np.nonzero(v1)
    code1 = d1.row[::step, ::step][yy, xx].astype(np.int64) * wp_ + d1.col[::step, ::step][yy, xx]
    ok = cnt[code1] > 0
    c = code1[ok]
    p1 = np.stack([xx[ok] * step, yy[ok] * step], 1).astype(np.float64)
    p2 = np.stack([sx[c] / cnt[c], sy[c] / cnt[c]], 1)
    X = triangulate_codes(p1, p2, cam_K=cal["cam1_K"], cam_dist=cal["cam1_dist"], proj_K=cal["cam2_K"],
                          proj_dist=cal["cam2_dist"], R=cal["R"], T=cal["T"])
    z2 = (X @ np.asarray(cal["R"]).T + np.asarray(cal["T"]).ravel())[:, 2] if len(X) else np.zeros(0)
    z1 = X[:, 2] if len(X) else np.zeros(0)
    return z1[np.isfinite(z1) & (z1 > 0) & (z2 > 0)]


def _procam_light(projector_rig, path, cam1_K, projector) -> PerspectiveLight:
    """The projector of a camera-projector calibration (OpenCV arrays or a ringscan rig) in camera 1's frame."""
    if isinstance(projector_rig, Rig):
        li = projector_rig.light
        if not isinstance(li, PerspectiveLight):
            raise CalibrationError(path, "--projector-rig: its light is not a calibrated perspective projector")
        R, T = procam_pose(projector_rig)
        K, dist, size, camK = li.K, li.dist, (li.width, li.height), projector_rig.camera.K
    else:
        R, T = projector_rig["R"], projector_rig["T"]
        K, dist, size, camK = projector_rig["proj_K"], projector_rig["proj_dist"], tuple(projector), \
            projector_rig["cam_K"]
    if tuple(size) != tuple(projector):
        raise CalibrationError(path, f"its projector is {size[0]}x{size[1]}, --projector says "
                                     f"{projector[0]}x{projector[1]}")
    rel = abs(camK[0, 0] - cam1_K[0, 0]) / cam1_K[0, 0]
    if rel > 0.01:
        log.warning("%s: its camera (fx %.1f) is not camera 1 of the stereo calibration (fx %.1f, %.1f %% apart); "
                    "the projector's pose is taken relative to camera 1", path, camK[0, 0], cam1_K[0, 0], 100 * rel)
    return PerspectiveLight(width=int(projector[0]), height=int(projector[1]), K=np.asarray(K, float),
                            dist=read_distortion(np.asarray(dist, float)), R=np.asarray(R, float),
                            t=np.asarray(T, float).ravel())


def _one_camera(rig: Rig, camera: int, source) -> Rig:
    """Camera ``camera`` of a two-camera rig with the rig's projector: a one-camera rig."""
    if not has_calibrated_light(rig):
        raise CalibrationError(source, "the rig's projector is not calibrated (a two-camera rig): a one-camera import "
                                       "needs it. Import both cameras for a two-camera scan, or calibrate the "
                                       "projector from such a scan (`ringscan calibrate projector-from-scan`)")
    cam = rig.camera if camera == 1 else rig.camera2
    return Rig(camera=cam, light=rig.light, volume=rig.volume, turntable=rig.turntable)


def _check_import_args(captures: list, rig, opencv, stereo, projector_rig, camera, mm_per_unit,
                       projector) -> None:
    """Raise ValueError for a call of :func:`import_captures` that cannot be right, before anything is read."""
    if sum(x is not None for x in (rig, opencv, stereo)) != 1:
        raise ValueError("import_captures: give exactly one of rig, opencv and stereo")
    if projector_rig is not None and stereo is None:
        raise ValueError("import_captures: projector_rig goes with stereo")
    if camera not in (None, 1, 2):
        raise ValueError(f"import_captures: camera must be 1 or 2, got {camera!r}")
    if not captures:
        raise ValueError("import_captures: no capture folders")
    if mm_per_unit is not None and not (np.isfinite(mm_per_unit) and 0 < mm_per_unit <= MAX_MM_PER_UNIT):
        raise ValueError(f"import_captures: mm_per_unit must be in (0, {MAX_MM_PER_UNIT:g}], got {mm_per_unit!r}")
    decoded_scale(*projector)  # (raises ValueError: a side the scan's 16-bit maps cannot hold)


def _in_millimetres(opencv, stereo, projector_rig, depth, mm_per_unit, sources: dict):
    """(opencv, stereo, projector_rig, depth, units): the OpenCV calibrations and ``depth`` in mm, and the
    calibration's units as scan.json ``imported.units`` records them (a ringscan rig states them, an OpenCV
    file does not)."""
    opencv_files = [k for k, v in (("rig", opencv if opencv is not None else stereo),
                                   ("projector_rig", projector_rig)) if isinstance(v, dict)]
    if mm_per_unit is not None and not opencv_files:
        raise CalibrationError(sources.get("rig"), "units: a ringscan rig states its own (mm); units apply to an "
                                                   "OpenCV calibration file, which states none")
    units = {"mm_per_unit": 1.0, "source": "rig"}
    if opencv_files:
        f = 1.0 if mm_per_unit is None else float(mm_per_unit)
        units = {"mm_per_unit": f, "source": "given" if mm_per_unit is not None else "assumed"}
        if opencv is not None:
            opencv = to_millimetres(opencv, f)
        if stereo is not None:
            stereo = to_millimetres(stereo, f)
        if isinstance(projector_rig, dict):
            projector_rig = to_millimetres(projector_rig, f)
        if depth is not None:
            depth = (depth[0] * f, depth[1] * f)
        if mm_per_unit is None:
            log.info("%s: an OpenCV calibration states no units: assuming millimetres",
                     sources.get("rig") or "the calibration")
    return opencv, stereo, projector_rig, depth, units


def _rig_cameras(rig: Rig | None, stereo: dict | None) -> int:
    """The cameras of the calibration: 2 for a stereo file or a rig with ``camera2``, else 1."""
    return 2 if stereo is not None or (rig is not None and rig.camera2 is not None) else 1


def _selected_cameras(files: list, rig_cams: int, stereo, projector_rig, camera, rig_src) -> tuple[int, ...]:
    """The cameras to import (1, 2 or both), the captures' cameras checked against the rig's."""
    if camera is not None:
        for f in files:
            if len(f.cameras) < camera:
                raise CalibrationError(f.source, f"camera {camera}'s frames are missing (--camera {camera}): the "
                                                 "capture holds camera 1's only")
        if stereo is not None and projector_rig is None:
            raise CalibrationError(rig_src, _stereo_message(rig_src or "the stereo file"))
        return (camera,)
    for f in files:
        if len(f.cameras) == 2 and rig_cams == 1:
            named = f" {rig_src}" if rig_src else ""
            raise CalibrationError(f.source, f"holds two cameras' frames, but the rig{named} has one camera: "
                                             "give --camera 1 (or 2) to import one camera's frames, or a "
                                             "two-camera rig (a stereo calibration file) for a two-camera scan")
        if len(f.cameras) == 1 and rig_cams == 2:
            if stereo is not None and f.kind in ("graycode", "named", "text"):
                # a one-camera capture: a procam file was meant
                raise CalibrationError(rig_src, _stereo_message(rig_src or "the stereo file"))
            what = {"graycode": "name its frames pattern_cam1_imK and pattern_cam2_imK",
                    "named": "name its frames pattern_cam1_imK and pattern_cam2_imK",
                    "pattern": "pattern_cam2_imK frames", "list": "a cam2 list",
                    "text": "a FileStorage list with cam1 and cam2"}[f.kind]
            raise CalibrationError(f.source, "camera 2's frames are missing: the rig has two cameras, the capture "
                                             f"holds camera 1's only ({what}); or give --camera 1 with a "
                                             "calibrated projector")
    return (1, 2) if rig_cams == 2 else (1,)


def _frame_sizes(files: list, sel: tuple[int, ...]) -> dict[int, tuple[int, int]]:
    """Each selected camera's frame size (headers only), one size per camera across the captures."""
    sizes: dict[int, tuple[int, int]] = {}
    for f in files:
        got = check_capture_sizes(f)
        for c in sel:
            wh = got[c - 1]
            if c in sizes and wh != sizes[c]:
                raise CalibrationError(f.frames_of(c)[0], f"frame is {wh[0]}x{wh[1]}, camera {c}'s frames of "
                                                          f"{files[0].source} are {sizes[c][0]}x{sizes[c][1]}")
            sizes.setdefault(c, wh)
    return sizes


def _check_rig_sizes(files: list, sel, sizes: dict, rig, opencv, stereo, rig_src) -> None:
    """The frames' sizes against the calibration's cameras (where it states them)."""
    rig_cams = _rig_cameras(rig, stereo)
    if rig is not None:
        rig_size = {1: (rig.camera.width, rig.camera.height)}
        if rig.camera2 is not None:
            rig_size[2] = (rig.camera2.width, rig.camera2.height)
    elif stereo is not None:
        rig_size = {c: stereo[f"cam{c}_size"] for c in (1, 2) if stereo[f"cam{c}_size"] is not None}
    else:
        rig_size = {1: opencv["cam_size"]} if opencv["cam_size"] else {}
    for c in sel:
        rc = rig_size.get(c if rig_cams == 2 else 1)
        if rc is not None and tuple(rc) != sizes[c]:
            src = next(f.frames_of(c)[0] for f in files)
            raise CalibrationError(src, f"camera {c}'s frames are {sizes[c][0]}x{sizes[c][1]}, the rig's camera"
                                        f"{' 2' if rig_cams == 2 and c == 2 else ''} is {rc[0]}x{rc[1]}"
                                        f"{f' ({rig_src})' if rig_src else ''}")


def _checked_rig(rig: Rig, projector, camera, rig_src) -> Rig:
    """A ringscan rig's projector checked (a real one of ``projector``'s size); its one camera for ``camera``."""
    li = rig.light
    if not isinstance(li, (PerspectiveLight, UncalibratedLight)):
        raise CalibrationError(rig_src, "import: the rig's light must be perspective (a real projector)")
    if (li.width, li.height) != tuple(projector):
        raise CalibrationError(rig_src, f"import: --projector {projector[0]}x{projector[1]} does not match the "
                                        f"rig's {li.width}x{li.height} projector")
    if camera is not None and rig.camera2 is not None:
        rig = _one_camera(rig, camera, rig_src)
    elif rig.camera2 is None and not has_calibrated_light(rig):
        raise CalibrationError(rig_src, "import: the rig's light must be perspective (a real projector)")
    return rig


def _stereo_with_light(stereo: dict, projector_rig, sizes: dict, sel, projector, sources: dict):
    """(stereo, light): the stereo arrays with the cameras' sizes (the frames' where the file has none), and
    the projector of ``projector_rig`` in camera 1's frame (None: uncalibrated)."""
    if stereo["cam1_size"] is None or stereo["cam2_size"] is None:
        stereo = {**stereo, "cam1_size": stereo["cam1_size"] or sizes.get(1, sizes[sel[0]]),
                  "cam2_size": stereo["cam2_size"] or sizes.get(2, sizes[sel[0]])}
    light = None
    if projector_rig is not None:
        light = _procam_light(projector_rig, sources.get("projector_rig"), stereo["cam1_K"], projector)
    return stereo, light


def _decode_camera(f, c: int, projector, layout: str, settings: ImportSettings, threads: int):
    """Camera ``c``'s frames of capture ``f`` decoded to projector positions (sub-pixel unless integer_only)."""
    cap = read_capture_files(f.frames_of(c), projector=projector, layout=layout, source=f.source,
                             frame_bits=settings.frame_bits, threads=threads)
    dec = decode_graycode(cap, settings=settings.graycode, threads=threads)
    if settings.integer_only:
        # an integer code whose finest bits do not stand clear of the noise is a guess: left out
        guess = dec.valid & ((dec.coarse[..., 0] | dec.coarse[..., 1]) != 0)
        dec.low_modulation |= guess
        dec.valid &= ~guess
        dec.u = np.where(dec.valid, dec.col, np.nan)
        dec.v = np.where(dec.valid, dec.row, np.nan)
        dec.subpixel = np.zeros_like(dec.valid)
    else:
        subpixel_map(cap, dec, settings=settings.graycode, threads=threads)
    return dec


def _unresolved_share(dec, n: int) -> float:
    """The share of a camera's ``n`` decoded pixels where it spans more than one projector px (its finest bits
    unresolved: positions from coarser ones; ``graycode.resolution_levels``)."""
    if dec.unresolved is None or not dec.unresolved.any():
        return 0.0
    return float(np.count_nonzero(dec.valid & ((dec.unresolved[..., 0] | dec.unresolved[..., 1]) != 0)) / n)


def _decode_stats(name: str, per_cam: dict, sel) -> dict:
    """A view's decode stats (camera 2's under ``camera2``), with a warning where the finest bits barely modulate."""
    st = {}
    for c, dec in per_cam.items():
        n = max(1, int(dec.valid.sum()))
        coarse = dec.valid & ((dec.coarse[..., 0] | dec.coarse[..., 1]) != 0)  # (a max over the last axis: 10x slower)
        s = {"decoded": int(dec.valid.sum()), "subpixel_share": float(dec.subpixel.sum() / n),
             "low_modulation": int(dec.low_modulation.sum()), "coarse_share": float(coarse.sum() / n),
             "unresolved_share": _unresolved_share(dec, n),
             "noise": round(float(dec.noise), 3)}
        weak = (int(coarse.sum()) + s["low_modulation"]) / max(1, s["decoded"] + s["low_modulation"])
        if weak > LOW_MODULATION_WARN_SHARE:
            log.warning("%s%s: the finest projector bits barely modulate at %.0f %% of the decoded pixels (a "
                        "far, dark, grazing or defocused surface): %d of them take their positions from "
                        "coarser bits, %d are left out (low_modulation)", name,
                        " (camera 2)" if len(sel) == 2 and c == 2 else "", 100 * weak, int(coarse.sum()),
                        s["low_modulation"])
        if len(sel) == 2 and c == 2:
            st["camera2"] = s
        else:
            st.update(s)
    return st


def _load_kernels_aside() -> None:
    try:
        load_subpixel_kernels()
    except Exception:  # noqa: BLE001 (the camera that needs the module imports it again and raises this as itself)
        log.debug("the sub-pixel kernels' import failed on its own thread", exc_info=True)


def _decode_captures(files: list, names: list, sel, projector, layout: str, settings: ImportSettings):
    """(decs: (capture, name, {camera: decoded}) per view, stats per view): a view's cameras at once."""
    # decode: a view's cameras at once, on threads of their own (NumPy's and OpenCV's loops and the
    # image decoders release the GIL); each camera's result is the one it gets alone
    workers = max(1, min(len(sel), cpu_cores()))
    per_threads = max(1, cpu_cores() // workers)
    if not settings.integer_only:
        # the sub-pixel kernels' import (Warp's: ~0.2 s of Python) runs beside the frames' reading, which
        # leaves the interpreter free; a camera that needs them first waits for it (Python's import lock),
        # and an import that fails there fails again, with its own error, in that camera's thread
        threading.Thread(target=_load_kernels_aside, name="ringscan-import-kernels", daemon=True).start()
    decs, stats = [], {}
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="ringscan-import") as pool:
        for f, name in zip(files, names):
            futs = {c: pool.submit(_decode_camera, f, c, projector, layout, settings, per_threads) for c in sel}
            try:
                per_cam = {c: futs[c].result() for c in sel}  # camera 1's error first, as decoded in turn
            finally:
                for fu in futs.values():
                    fu.cancel()
            decs.append((f, name, per_cam))
            st = _decode_stats(name, per_cam, sel)
            if f.kind == "named":  # the order the frames were taken in, for the user to check
                st["frames_in_name_order"] = [f.cameras[0][0].name, f.cameras[0][-1].name]
            stats[name] = st
    return decs, stats


def _procam_depths(dec, cam_K, cam_dist, proj_K, proj_dist, R, T) -> np.ndarray:
    """Camera-projector triangulation of every 8th pixel's integer code: the points (camera frame)."""
    yy, xx = np.nonzero(dec.valid[::8, ::8])
    return triangulate_codes(np.stack([xx * 8, yy * 8], 1),
                             np.stack([dec.col[::8, ::8][yy, xx], dec.row[::8, ::8][yy, xx]], 1),
                             cam_K=cam_K, cam_dist=cam_dist, proj_K=proj_K, proj_dist=proj_dist, R=R, T=T)


def _opencv_rig(opencv: dict, decs: list, sel, sizes: dict, projector, depth) -> Rig:
    """The rig of a camera-projector calibration, its working depth from the captures where not given."""
    dec0 = [d[sel[0]] for _, _, d in decs]
    size = opencv["cam_size"] or sizes[sel[0]]
    if depth is None:
        zs = []
        for dec in dec0:
            X = _procam_depths(dec, opencv["cam_K"], opencv["cam_dist"], opencv["proj_K"], opencv["proj_dist"],
                               opencv["R"], opencv["T"])
            zp = (X @ opencv["R"].T + opencv["T"])[:, 2]
            zs.append(zp[np.isfinite(zp) & (zp > 0)])
        z = np.concatenate(zs)
        if z.size < 100:
            raise CalibrationError(None, "import: too few decoded pixels to find the working depth; give --depth")
        depth = depth_range(np.percentile(z, [1, 99]), margin=0.25)
    return procam_rig(cam_K=opencv["cam_K"], cam_dist=opencv["cam_dist"], cam_size=size, proj_K=opencv["proj_K"],
                      proj_dist=opencv["proj_dist"], proj_size=projector, R=opencv["R"], T=opencv["T"],
                      z_range=depth)


def _stereo_depth(stereo: dict, decs: list, sel, projector, light, rig_src) -> tuple[float, float]:
    """The working depth along camera 1's axis of a stereo calibration, from the captures."""
    if len(sel) == 2:
        z = np.concatenate([_stereo_depths(d[1], d[2], stereo, projector) for _, _, d in decs])
    else:
        z = np.zeros(0)
        for _, _, d in decs:  # one camera with the projector: camera 1 - projector
            X = _procam_depths(d[sel[0]], stereo[f"cam{sel[0]}_K"], stereo[f"cam{sel[0]}_dist"], light.K, light.dist,
                               light.R, light.t)
            z = np.concatenate([z, X[:, 2][np.isfinite(X[:, 2]) & (X[:, 2] > 0)]])
    if z.size < 100:
        raise CalibrationError(rig_src, "import: too few pixels matched between the cameras to find the "
                                        "working depth (a calibration that does not fit the captures?); give "
                                        "--depth NEAR FAR")
    return depth_range(np.percentile(z, [1, 99]), margin=0.25)


def _decoded_spec(rig: Rig, settings: ImportSettings):
    """The ``decoded`` codec's pattern spec of the rig's projector (centred on its principal point)."""
    li = rig.light
    center = (float(li.K[0, 2]), float(li.K[1, 2])) if has_calibrated_light(rig) else \
        ((li.width - 1) / 2.0, (li.height - 1) / 2.0)
    return parse_patterns({"codec": "decoded", "width": li.width, "height": li.height, "center": list(center),
                           "rho0": 0.0, "pitch": 1.0, "sector_bits": settings.sector_bits,
                           "scale": decoded_scale(li.width, li.height)}, source="import")


def _write_camera(out: Path, sub: str, dec, scale: int) -> dict:
    """A camera's three decoded frames, encoded and written (PNG encoders release the GIL): their paths."""
    fu, fv, fc = encode_decoded(dec.u, dec.v, dec.contrast, scale)
    rels = {}
    for key, img in (("proj_u", fu), ("proj_v", fv), ("contrast", fc)):
        rels[key] = f"{sub}/{key}.png"
        write_image(out / rels[key], img, smooth=True)
    return rels


def _write_scan(out: Path, rig: Rig, spec, decs: list, sel, imported: dict) -> Scan:
    """The scan folder written under its lock: every view's decoded frames, then scan.json."""
    out.mkdir(parents=True, exist_ok=True)
    with lock_folder(out, what="import"):
        if (out / "scan.json").exists():  # written by another import since _new_scan_folder's check
            raise FormatError(out, "already holds a scan (scan.json); choose another folder")
        views = []
        with ThreadPoolExecutor(max_workers=cpu_cores(), thread_name_prefix="ringscan-import-write") as pool:
            written = []
            for f, name, per_cam in decs:
                subs = {c: f"{name}/{CAMERA2_DIR}" if (len(sel) == 2 and c == 2) else name for c in per_cam}
                written.append((f, name, {c: pool.submit(_write_camera, out, subs[c], dec, spec.scale)
                                          for c, dec in per_cam.items()}))
            for f, name, futs in written:
                frames = {c: fu.result() for c, fu in futs.items()}  # the first failure in order is raised
                second = View(name=name, turntable_deg=0.0, frames=frames[2]) if len(sel) == 2 else None
                views.append(View(name=name, turntable_deg=0.0, frames=frames[sel[0]], camera2=second))
        scan = Scan(folder=out, rig=rig, patterns=spec, views=tuple(views), extra={"imported": imported})
        save_scan(scan)
    return scan


def _new_scan_folder(out) -> Path:
    """The scan folder to write, checked: one that holds no scan yet."""
    out = check_output_folder(out, what="scan folder (--out)")
    if (out / "scan.json").exists():
        raise FormatError(out, "already holds a scan (scan.json); choose another folder (import writes a new scan)")
    return out


def _stereo_import_rig(stereo: dict, decs: list, sel, projector, depth, light, camera, rig_src) -> Rig:
    """The two-camera rig of a stereo calibration (one camera's for ``camera``), its depth found where not given."""
    if depth is None:
        depth = _stereo_depth(stereo, decs, sel, projector, light, rig_src)
    rig = stereo_rig(stereo, projector=projector, z_range=depth, light=light)
    if camera is not None:
        rig = _one_camera(rig, camera, rig_src)
    return rig


def _saved_rig(rig: Rig, size: tuple[int, int], source, rig_src) -> Rig:
    """The rig with the checks a saved rig gets, its camera checked against the frames' ``size``."""
    rig = parse_rig(rig_to_dict(rig), source=rig_src or "the imported rig")
    if (rig.camera.width, rig.camera.height) != size:
        raise CalibrationError(source, f"frames are {size[0]}x{size[1]}, the rig's camera "
                                       f"is {rig.camera.width}x{rig.camera.height}")
    return rig


def _imported_extra(layout: str, units: dict, decs: list, stats: dict, camera, settings: ImportSettings) -> dict:
    """Scan.json's ``imported`` entry: the layout, units, captures, their kinds and decode stats."""
    imported = {"layout": layout, "units": units, "captures": [str(f.source) for f, _, _ in decs],
                "kinds": [f.kind for f, _, _ in decs], "stats": stats}
    if camera is not None:
        imported["camera"] = camera
    if settings.frame_bits is not None:  # the captures' bits (the decoded frames are coordinates: no frame_bits)
        imported["frame_bits"] = settings.frame_bits
    return imported


def import_captures(
    captures: list,
    *,
    out,
    rig: Rig | None = None,
    opencv: dict | None = None,
    stereo: dict | None = None,
    projector_rig: dict | Rig | None = None,
    projector: tuple[int, int],
    layout: str = "opencv-graycode",
    depth: tuple[float, float] | None = None,
    camera: int | None = None,
    settings: ImportSettings = ImportSettings(),
    sources: dict | None = None,
    mm_per_unit: float | None = None,
) -> tuple[Scan, dict]:
    """Decode captures into a scan folder of the ``decoded`` codec.

    Every input is checked before anything is decoded or written: the captures' names,
    frame counts and sizes (from the files' headers), the cameras they hold against the
    rig's, the projector size.

    Args:
        captures: capture folders or image lists, one view each
            (:func:`~ringscan.pipeline.calibrate.capture_files.list_capture`).
        out: the scan folder to write (frames, scan.json last).
        rig: a ringscan rig with a perspective light (one camera), or with ``camera2``
            (a two-camera rig, its light perspective or uncalibrated); or
        opencv: the arrays of :func:`read_opencv_calibration` (one camera and the projector); or
        stereo: the arrays of :func:`read_stereo_calibration` (two cameras; the rig's world
            is camera 1's frame), with
        projector_rig: the projector's calibration for ``stereo`` (arrays of
            :func:`read_opencv_calibration` or a ringscan rig; camera 1 and the projector),
            or None: the projector stays uncalibrated.
        projector: projector (width, height).
        layout: the captures' frame order (``graycode.LAYOUTS``).
        depth: (near, far) working depths (along the projector axis for ``opencv``, along
            camera 1's axis for ``stereo``); None: from a plain triangulation of the captures.
        camera: import only this camera's frames (1 or 2) of two-camera captures: a one-camera
            scan (the rig must then calibrate the projector). None: every camera the captures hold.
        settings: decoding settings.
        sources: the calibration files' paths for messages (``rig``, ``projector_rig``).
        mm_per_unit: millimetres per unit of the OpenCV calibrations' translations (and of
            ``depth`` with them): an OpenCV file states no units (:func:`parse_units`). None: assumed
            millimetres (1), said in the log. A ringscan rig is in mm (its ``units``) and takes none.

    Returns:
        (the scan, stats per view: decoded pixels and the share with sub-pixel positions,
        and ``camera2``'s likewise).

    Size: a public function (ringscan import's): the capture folders and its documented keyword-only options,
    one per user-facing setting (output, the calibration in one of its forms, projector size, layout, depths,
    camera, settings, units) and the calibration files' names for messages.
    """
    _check_import_args(captures, rig, opencv, stereo, projector_rig, camera, mm_per_unit, projector)
    sources = sources or {}
    opencv, stereo, projector_rig, depth, units = _in_millimetres(opencv, stereo, projector_rig, depth,
                                                                  mm_per_unit, sources)
    rig_src = sources.get("rig")
    names = check_import_names(captures)
    out = _new_scan_folder(out)
    files = [list_capture(c, projector=projector, layout=layout) for c in captures]
    sel = _selected_cameras(files, _rig_cameras(rig, stereo), stereo, projector_rig, camera, rig_src)
    sizes = _frame_sizes(files, sel)
    _check_rig_sizes(files, sel, sizes, rig, opencv, stereo, rig_src)
    if rig is not None:
        rig = _checked_rig(rig, projector, camera, rig_src)
    light = None
    if stereo is not None:
        stereo, light = _stereo_with_light(stereo, projector_rig, sizes, sel, projector, sources)
    decs, stats = _decode_captures(files, names, sel, projector, layout, settings)
    if opencv is not None:
        rig = _opencv_rig(opencv, decs, sel, sizes, projector, depth)
    elif stereo is not None:
        rig = _stereo_import_rig(stereo, decs, sel, projector, depth, light, camera, rig_src)
    rig = _saved_rig(rig, sizes[sel[0]], files[0].source, rig_src)
    spec = _decoded_spec(rig, settings)
    scan = _write_scan(out, rig, spec, decs, sel, _imported_extra(layout, units, decs, stats, camera, settings))
    log.info("imported %d capture(s) into %s", len(scan.views), out)
    return scan, stats
