"""A rig written as OpenCV FileStorage: the layouts
:func:`~ringscan.pipeline.calibrate.importer.read_opencv_calibration` and OpenCV's
structured-light sample read (camera-projector, and camera-camera)."""

from __future__ import annotations


import cv2
import numpy as np

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.rig_refine import relative_pose
from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.rig import PerspectiveLight, Rig

__all__ = ["write_opencv_procam", "write_opencv_stereo", "write_opencv_stereo_cameras"]


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
