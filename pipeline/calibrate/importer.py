"""Real Gray-code captures -> a ringscan scan folder of the ``decoded`` codec (docs/design.md §7).

:func:`import_captures` decodes every capture folder (one view each) to sub-pixel
projector positions (:mod:`graycode`) and writes them as the ``decoded`` codec's
frames (docs/formats.md), with the rig; ``ringscan reconstruct`` then meets each
pixel's camera ray with the cone of its rho = |p - c| around the projector's
principal point and picks the root by its polar angle.

:func:`read_opencv_calibration` reads an OpenCV calibration file (cam_int,
cam_dist, proj_int, proj_dist, rotation (or 'roration'), translation;
X_proj = R X_cam + T) into a rig; :func:`triangulate_codes` is the plain way
(camera and projector rays through ``cv2.triangulatePoints``), used for the
working volume of such a rig and by ``benchmarks/procam_plane.py``.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import GrayCodeSettings, decode_graycode, read_capture, subpixel_map
from ringscan.pipeline.calibrate.procam import depth_range, procam_rig
from ringscan.pipeline.formats.atomic import check_output_folder, lock_folder
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.limits import MAX_JSON_BYTES, check_regular_file
from ringscan.pipeline.formats.patterns import DECODED_SCALE, parse_patterns
from ringscan.pipeline.formats.rig import PerspectiveLight, Rig
from ringscan.pipeline.formats.scan import Scan, View, check_view_name, save_scan

__all__ = ["ImportSettings", "read_opencv_calibration", "triangulate_codes", "import_captures", "check_import_names",
           "encode_decoded", "procam_pose"]

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


def _mat(fs, path, *names):
    for n in names:
        node = fs.getNode(n)
        if not node.empty():
            m = node.mat()
            if m is None:
                raise CalibrationError(path, f"{n}: not a matrix")
            return np.asarray(m, float)
    raise CalibrationError(path, f"missing {' or '.join(names)}")


def read_opencv_calibration(path) -> dict:
    """An OpenCV FileStorage calibration (XML/YAML) as arrays.

    Returns:
        dict with cam_K, cam_dist, proj_K, proj_dist, R, T (X_proj = R X_cam + T) and
        cam_size ((W, H) from ``img_shape`` when present, else None).
    """
    path = Path(path)
    check_regular_file(path, what="calibration file", max_bytes=MAX_JSON_BYTES)  # a FIFO would block OpenCV
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise CalibrationError(path, "not an OpenCV FileStorage file (XML/YAML)")
    try:
        out = {"cam_K": _mat(fs, path, "cam_int"), "cam_dist": _mat(fs, path, "cam_dist").ravel(),
               "proj_K": _mat(fs, path, "proj_int"), "proj_dist": _mat(fs, path, "proj_dist").ravel(),
               "R": _mat(fs, path, "rotation", "roration"), "T": _mat(fs, path, "translation").ravel()}
        shp = fs.getNode("img_shape")
        out["cam_size"] = None
        if not shp.empty() and shp.mat() is not None and shp.mat().size == 2:
            h, w = (int(x) for x in shp.mat().ravel())
            out["cam_size"] = (w, h)
    finally:
        fs.release()
    for k in ("cam_K", "proj_K", "R"):
        if out[k].shape != (3, 3) or not np.all(np.isfinite(out[k])):
            raise CalibrationError(path, f"{k}: expected a finite 3x3 matrix, got shape {out[k].shape}")
    if out["T"].shape != (3,):
        raise CalibrationError(path, f"translation: expected 3 values, got {out['T'].shape}")
    R = out["R"]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4:
        raise CalibrationError(path, "rotation: not a rotation matrix")
    return out


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


def encode_decoded(u: np.ndarray, v: np.ndarray, contrast: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``decoded`` codec's three 16-bit frames of sub-pixel maps (NaN = not decoded)."""
    def enc(a):
        ok = np.isfinite(a) & (a > -1 + 1.0 / DECODED_SCALE) & (a < 65535.0 / DECODED_SCALE - 1)
        return np.where(ok, np.round((np.where(ok, a, 0) + 1.0) * DECODED_SCALE), 0).astype(np.uint16)

    fu, fv = enc(u), enc(v)
    bad = (fu == 0) | (fv == 0)
    fu[bad] = 0
    fv[bad] = 0
    fc = np.clip(np.asarray(contrast, np.float64) * 257.0, 0, 65535).astype(np.uint16)
    return fu, fv, fc


def check_import_names(captures: list) -> list[str]:
    """The view name of each capture folder: its own name (``.`` and ``DIR/sub/..`` by their real name),
    checked as a view name (:func:`~ringscan.pipeline.formats.scan.check_view_name`) and unique (ignoring
    case), before anything is decoded or written.

    Raises:
        FormatError: naming the capture folder: a name that is not folder-safe, or two captures with one name.
    """
    names, seen = [], {}
    for folder in captures:
        name = Path(os.path.abspath(folder)).resolve().name
        check_view_name(name, source=folder, where="the capture folder's name (the view's name)")
        key = name.casefold()
        if key in seen:
            raise FormatError(folder, f"has the name {name!r} of the capture {seen[key]}: two views of one name "
                                      "(give capture folders of different names)")
        seen[key] = folder
        names.append(name)
    return names


def import_captures(
    captures: list,
    *,
    out,
    rig: Rig | None = None,
    opencv: dict | None = None,
    projector: tuple[int, int],
    layout: str = "opencv-graycode",
    depth: tuple[float, float] | None = None,
    settings: ImportSettings = ImportSettings(),
) -> tuple[Scan, dict]:
    """Decode capture folders into a scan folder of the ``decoded`` codec.

    Args:
        captures: capture folders, one view each.
        out: the scan folder to write (frames, rig.json, scan.json last).
        rig: a ringscan rig with a perspective light, or
        opencv: the arrays of :func:`read_opencv_calibration` (then the working
            volume comes from ``depth``, or from a plain triangulation of the captures).
        projector: projector (width, height).
        layout: the captures' frame order (``graycode.LAYOUTS``).
        depth: (near, far) depths along the projector axis of the working volume.

    Returns:
        (the scan, stats per view: decoded pixels and the share with sub-pixel positions).
    """
    if (rig is None) == (opencv is None):
        raise ValueError("import_captures: give exactly one of rig and opencv")
    if not captures:
        raise ValueError("import_captures: no capture folders")
    names = check_import_names(captures)
    out = check_output_folder(out, what="scan folder (--out)")
    if (out / "scan.json").exists():
        raise FormatError(out, "already holds a scan (scan.json); choose another folder (import writes a new scan)")
    decs, stats = [], {}
    for folder, name in zip(captures, names):
        cap = read_capture(folder, projector=projector, layout=layout)
        dec = decode_graycode(cap, settings=settings.graycode)
        if settings.integer_only:
            dec.u = np.where(dec.valid, dec.col, np.nan)
            dec.v = np.where(dec.valid, dec.row, np.nan)
            dec.subpixel = np.zeros_like(dec.valid)
        else:
            subpixel_map(cap, dec, settings=settings.graycode)
        decs.append((Path(folder), name, dec))
        stats[name] = {"decoded": int(dec.valid.sum()),
                                    "subpixel_share": float(dec.subpixel.sum() / max(1, dec.valid.sum()))}
        del cap
    H, W = decs[0][2].valid.shape
    if rig is None:
        size = opencv["cam_size"] or (W, H)
        if depth is None:
            zs = []
            for _, _, dec in decs:
                yy, xx = np.nonzero(dec.valid[::8, ::8])
                X = triangulate_codes(np.stack([xx * 8, yy * 8], 1), np.stack([dec.col[::8, ::8][yy, xx],
                                                                             dec.row[::8, ::8][yy, xx]], 1),
                                      cam_K=opencv["cam_K"], cam_dist=opencv["cam_dist"], proj_K=opencv["proj_K"],
                                      proj_dist=opencv["proj_dist"], R=opencv["R"], T=opencv["T"])
                zp = (X @ opencv["R"].T + opencv["T"])[:, 2]
                zs.append(zp[np.isfinite(zp) & (zp > 0)])
            z = np.concatenate(zs)
            if z.size < 100:
                raise CalibrationError(None, "import: too few decoded pixels to find the working depth; give --depth")
            depth = depth_range(np.percentile(z, [1, 99]), margin=0.25)
        rig = procam_rig(cam_K=opencv["cam_K"], cam_dist=opencv["cam_dist"], cam_size=size, proj_K=opencv["proj_K"],
                         proj_dist=opencv["proj_dist"], proj_size=projector, R=opencv["R"], T=opencv["T"], z_range=depth)
    li = rig.light
    if not isinstance(li, PerspectiveLight):
        raise CalibrationError(None, "import: the rig's light must be perspective (a real projector)")
    if (li.width, li.height) != tuple(projector):
        raise CalibrationError(None, f"import: --projector {projector[0]}x{projector[1]} does not match the rig's "
                                     f"{li.width}x{li.height} projector")
    if (rig.camera.width, rig.camera.height) != (W, H):
        raise CalibrationError(captures[0], f"frames are {W}x{H}, the rig's camera is "
                                            f"{rig.camera.width}x{rig.camera.height}")
    center = (float(li.K[0, 2]), float(li.K[1, 2]))
    spec = parse_patterns({"codec": "decoded", "width": li.width, "height": li.height, "center": list(center),
                           "rho0": 0.0, "pitch": 1.0, "sector_bits": settings.sector_bits}, source="import")
    out.mkdir(parents=True, exist_ok=True)
    with lock_folder(out, what="import"):
        if (out / "scan.json").exists():  # written by another import between the check above and the lock
            raise FormatError(out, "already holds a scan (scan.json); choose another folder")
        views = []
        for folder, name, dec in decs:
            fu, fv, fc = encode_decoded(dec.u, dec.v, dec.contrast)
            frames = {}
            for key, img in (("proj_u", fu), ("proj_v", fv), ("contrast", fc)):
                rel = f"{name}/{key}.png"
                write_image(out / rel, img)
                frames[key] = rel
            views.append(View(name=name, turntable_deg=0.0, frames=frames))
        scan = Scan(folder=out, rig=rig, patterns=spec, views=tuple(views),
                    extra={"imported": {"layout": layout, "captures": [str(f) for f, _, _ in decs], "stats": stats}})
        save_scan(scan)
    log.info("imported %d capture(s) into %s", len(views), out)
    return scan, stats
