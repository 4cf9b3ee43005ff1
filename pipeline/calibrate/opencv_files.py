"""OpenCV FileStorage calibrations: read (:func:`read_opencv_calibration`, camera-projector;
:func:`read_stereo_calibration`, camera-camera as OpenCV's structured-light sample has it;
:func:`opencv_calibration_kind`, which of the two; all three re-exported by
:mod:`~ringscan.pipeline.calibrate.importer`), and a rig written in those layouts."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.capture_files import open_filestorage
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.rig_refine import relative_pose
from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.limits import MAX_JSON_BYTES
from ringscan.pipeline.formats.rig import PerspectiveLight, Rig, read_distortion

__all__ = ["read_opencv_calibration", "read_stereo_calibration", "opencv_calibration_kind", "write_opencv_procam",
           "write_opencv_stereo", "write_opencv_stereo_cameras"]

STEREO_KEYS = ("cam1_intrinsics", "cam2_intrinsics")
PROCAM_KEYS = ("cam_int", "proj_int")

log = logging.getLogger("ringscan.pipeline.calibrate.importer")
"""The readers log as ``ringscan import`` always has (the log names its module)."""


# ----------------------------------------------------------------------------- reading

def _mat(fs, path, *names):
    for n in names:
        node = fs.getNode(n)
        if not node.empty():
            m = node.mat()
            if m is None:
                raise CalibrationError(path, f"{n}: not a matrix")
            return np.asarray(m, float)
    raise CalibrationError(path, f"missing {' or '.join(names)}")


def _has(fs, name) -> bool:
    node = fs.getNode(name)
    return not (node.empty() or node.isNone())


def _stereo_message(path) -> str:
    return (f"a camera-camera (stereo) calibration ({', '.join(STEREO_KEYS)}, R, T): it does not calibrate the "
            "projector, which a one-camera import needs. Import both cameras' captures with it (pattern_cam1/"
            "pattern_cam2 frames or an image list: `ringscan import CAPTURE --rig "
            f"{Path(path).name} --projector WxH --out SCAN`) for a two-camera scan, add the projector's calibration "
            "with --projector-rig PROCAM, or calibrate the projector from that scan with `ringscan calibrate "
            "projector-from-scan` (docs/calibration.md)")


def opencv_calibration_kind(path) -> str:
    """``procam`` (cam_int, proj_int, ...) or ``stereo`` (cam1_intrinsics, cam2_intrinsics, R, T) of an
    OpenCV FileStorage calibration file.

    Raises:
        CalibrationError: naming the file: not FileStorage, or neither kind (with the keys it has).
    """
    fs = open_filestorage(path, what="calibration file", max_bytes=MAX_JSON_BYTES)
    try:
        if all(_has(fs, k) for k in PROCAM_KEYS):
            return "procam"
        if any(_has(fs, k) for k in STEREO_KEYS):
            return "stereo"
        if any(_has(fs, k) for k in PROCAM_KEYS):
            return "procam"  # read_opencv_calibration names what is missing
        keys = ", ".join(list(fs.root().keys())[:8]) or "nothing"
    finally:
        fs.release()
    raise CalibrationError(path, f"neither a camera-projector calibration (cam_int, cam_dist, proj_int, proj_dist, "
                                 f"rotation, translation) nor a camera-camera one (cam1_intrinsics, cam1_distorsion, "
                                 f"cam2_..., R, T); it has {keys}")


def read_opencv_calibration(path) -> dict:
    """An OpenCV FileStorage camera-projector calibration (XML/YAML) as arrays.

    Returns:
        dict with cam_K, cam_dist, proj_K, proj_dist, R, T (X_proj = R X_cam + T) and
        cam_size ((W, H) from ``img_shape`` when present, else None).

    Raises:
        CalibrationError: naming the file; a camera-camera (stereo) file is named for what
            it is, with what to do instead.
    """
    path = Path(path)
    fs = open_filestorage(path, what="calibration file", max_bytes=MAX_JSON_BYTES)
    try:
        if not _has(fs, "cam_int") and any(_has(fs, k) for k in STEREO_KEYS):
            raise CalibrationError(path, _stereo_message(path))
        out = {"cam_K": _mat(fs, path, "cam_int"), "cam_dist": _lens(path, "cam_dist", _mat(fs, path, "cam_dist")),
               "proj_K": _mat(fs, path, "proj_int"), "proj_dist": _lens(path, "proj_dist", _mat(fs, path, "proj_dist")),
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


def _size_node(fs, path, name):
    """(W, H) of a cv::Size node ([w, h]) or a 2-element matrix; None when absent."""
    node = fs.getNode(name)
    if node.empty() or node.isNone():
        return None
    if node.isSeq():
        vals = [node.at(i).real() for i in range(node.size())]
    else:
        m = node.mat()
        vals = [] if m is None else list(np.asarray(m, float).ravel())
    if len(vals) != 2 or not all(np.isfinite(vals)) or any(v != int(v) or not 0 < v <= 65536 for v in vals):
        raise CalibrationError(path, f"{name}: expected an image size [width, height], got {vals}")
    return int(vals[0]), int(vals[1])


def _lens(path, name, d) -> np.ndarray:
    """OpenCV distortion as a rig keeps it (4, 5, 8 or 12 coefficients; 14 with a zero tilt)."""
    try:
        return read_distortion(np.asarray(d, float), source=path, where=name)
    except FormatError as e:
        raise CalibrationError(path, e.message) from None


def read_stereo_calibration(path) -> dict:
    """An OpenCV FileStorage camera-camera calibration as OpenCV's structured-light sample has it.

    Keys: ``cam1_intrinsics``, ``cam1_distorsion`` (sic; ``cam1_distortion`` too), optional
    ``cam1_size`` ([width, height]), the same for cam2, and ``R``, ``T`` (X_cam2 = R X_cam1 + T,
    as ``cv::stereoCalibrate`` gives them and ``cv::stereoRectify`` takes them) or
    ``RT_cam1_2_cam2`` (the same pose as [R | T]: 4x4 with the row 0 0 0 1, as in the file of
    OpenCV's structured-light test data, or 3x4) when R, T are absent. Other keys (the
    sample's file has ``stereo_error``, ``Q``, ``R1``, ``R2``, ``P1``, ``P2``) are not read.

    Returns:
        dict with cam1_K, cam1_dist (5), cam1_size ((W, H) or None), cam2_K, cam2_dist, cam2_size, R, T.

    Raises:
        CalibrationError: naming the file and the key; a camera-projector file is named for what it is.
    """
    path = Path(path)
    fs = open_filestorage(path, what="calibration file", max_bytes=MAX_JSON_BYTES)
    try:
        if _has(fs, "cam_int") and not any(_has(fs, k) for k in STEREO_KEYS):
            raise CalibrationError(path, "a camera-projector calibration (cam_int, proj_int, ...), not a camera-camera "
                                         "one: give it as --projector-rig, or alone for a one-camera import")
        out = {}
        for c in (1, 2):
            out[f"cam{c}_K"] = _mat(fs, path, f"cam{c}_intrinsics")
            out[f"cam{c}_dist"] = _lens(path, f"cam{c}_distorsion",
                                        _mat(fs, path, f"cam{c}_distorsion", f"cam{c}_distortion"))
            out[f"cam{c}_size"] = _size_node(fs, path, f"cam{c}_size")
        rt = _mat(fs, path, "RT_cam1_2_cam2") if _has(fs, "RT_cam1_2_cam2") else None
        if rt is not None and rt.shape not in ((3, 4), (4, 4)):
            raise CalibrationError(path, f"RT_cam1_2_cam2: expected a 3x4 or 4x4 [R | T], got shape {rt.shape}")
        if rt is not None and rt.shape == (4, 4) and not np.allclose(rt[3], [0, 0, 0, 1]):
            raise CalibrationError(path, f"RT_cam1_2_cam2: a 4x4 [R | T] ends in the row 0 0 0 1, not {rt[3].tolist()}")
        if _has(fs, "R") or _has(fs, "T") or rt is None:
            out["R"], out["T"] = _mat(fs, path, "R"), _mat(fs, path, "T").ravel()
        else:
            out["R"], out["T"] = rt[:3, :3].copy(), rt[:3, 3].copy()
    finally:
        fs.release()
    for k in ("cam1_K", "cam2_K", "R"):
        if out[k].shape != (3, 3) or not np.all(np.isfinite(out[k])):
            raise CalibrationError(path, f"{k}: expected a finite 3x3 matrix, got shape {out[k].shape}")
    if out["T"].shape != (3,) or not np.all(np.isfinite(out["T"])):
        raise CalibrationError(path, f"T: expected 3 finite values, got shape {out['T'].shape}")
    R = out["R"]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(R) - 1) > 1e-4:
        raise CalibrationError(path, "R: not a rotation matrix")
    if np.linalg.norm(out["T"]) <= 0:
        raise CalibrationError(path, "T: zero (the cameras at one place: no baseline)")
    if rt is not None and (np.abs(rt[:3, :3] - R).max() > 1e-4 or np.abs(rt[:3, 3] - out["T"]).max()
                           > 1e-4 * max(1.0, np.linalg.norm(out["T"]))):
        log.warning("%s: RT_cam1_2_cam2 differs from R, T; R, T are used", path)
    return out



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
    the layout :func:`read_opencv_calibration` reads. Atomic."""
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
