"""Two cameras that see about one projector pixel per camera pixel (issue 34): the rig, the plain
camera-camera decode to compare with, and the plane fit that measures both.

The rig is a public capture's (two 2048x1500 cameras 40 mm apart beside a 1920x1080 projector,
all about 1 m from the object) scaled down by ``scale``: the cameras' and the projector's sizes and
focal lengths alike, so every angle and the ratio of camera to projector pixels at the object stay.
The plain way is what a user would write with OpenCV: integer Gray codes (contrast above 20 levels,
pattern > inverse), camera 1's pixel matched to the mean of camera 2's pixels of the same code, both
triangulated with ``cv2.triangulatePoints`` (:func:`pipeline.calibrate.importer.triangulate_codes`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.graycode import graycode_bits
from ringscan.pipeline.calibrate.importer import triangulate_codes
from ringscan.pipeline.calibrate.opencv_files import read_stereo_calibration
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import gray_decode
from ringscan.pipeline.formats.rig import Camera, PerspectiveLight, Rig, Volume, look_at

FULL_CAMERA = (2048, 1500)
FULL_PROJECTOR = (1920, 1080)
FULL_PROJECTOR_F = 2000.0
"""The projector's focal length at full size (px): 1920 px span ~52 degrees."""
DISTANCE_MM = 1000.0
BASELINE_MM = 40.0
CAMERA_OFFSET_MM = 100.0
"""The cameras stand this far beside the projector (along world y)."""


def one_to_one_rig(*, scale: int = 4, ratio: float = 0.9) -> Rig:
    """Two cameras ``BASELINE_MM`` apart and a perspective projector, ``DISTANCE_MM`` above the plane z = 0,
    at ``1 / scale`` of the full size.

    ``ratio``: the cameras' focal length over the projector's. The cameras and the projector stand
    about as far from the object, so a camera pixel covers ``1 / ratio`` projector pixels there (0.9:
    1.11, about one; 1.0 exactly one, where integer codes alias into long beats no neighbourhood
    averages out).
    """
    cw, ch = (s // scale for s in FULL_CAMERA)
    pw, ph = (s // scale for s in FULL_PROJECTOR)
    fp = FULL_PROJECTOR_F / scale
    Kp = np.array([[fp, 0, (pw - 1) / 2], [0, fp, (ph - 1) / 2], [0, 0, 1.0]])
    Rp, tp = look_at([0.0, 0.0, DISTANCE_MM], [0.0, 0.0, 0.0])
    light = PerspectiveLight(width=pw, height=ph, K=Kp, dist=np.zeros(5), R=Rp, t=tp)
    fc = fp * ratio
    Kc = np.array([[fc, 0, (cw - 1) / 2], [0, fc, (ch - 1) / 2], [0, 0, 1.0]])
    cams = []
    for x in (-BASELINE_MM / 2, BASELINE_MM / 2):
        R, t = look_at([x, -CAMERA_OFFSET_MM, DISTANCE_MM], [0.0, 0.0, 0.0])
        cams.append(Camera(width=cw, height=ch, K=Kc, dist=np.array([0.01, -0.02, 0.0, 0.0, 0.0]), R=R, t=t,
                           gamma=2.2))
    return Rig(camera=cams[0], light=light, volume=Volume(z_min=-50.0, z_max=300.0, r_max=800.0), camera2=cams[1])


def plain_decode(paths, projector) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer column, row and the decoded mask of one camera's frames (OpenCV's order: column
    pattern/inverse pairs, row pairs, white, black)."""
    fr = np.stack([read_image(p).astype(np.float32) for p in paths])
    cb, rb = graycode_bits(projector)
    white, black = fr[-2], fr[-1]

    def code(first, bits):
        g = np.zeros(white.shape, np.int64)
        for k in range(bits):
            g = (g << 1) | (fr[first + 2 * k] > fr[first + 2 * k + 1])
        return gray_decode(g, bits)

    col, row = code(0, cb), code(2 * cb, rb)
    return col, row, (white - black >= 20) & (col < projector[0]) & (row < projector[1])


def plain_camera_camera(image_list, calibration, projector) -> tuple[np.ndarray, int]:
    """The plain way on an image list (cam1, cam2) and its stereo calibration: camera-1-frame points
    and camera 1's decoded pixels."""
    image_list = Path(image_list)
    fs = cv2.FileStorage(str(image_list), cv2.FILE_STORAGE_READ)
    cams = []
    for c in (1, 2):
        node = fs.getNode(f"cam{c}")
        cams.append(plain_decode([image_list.parent / node.at(i).string() for i in range(node.size())], projector))
    fs.release()
    cal = read_stereo_calibration(calibration)
    (c1, r1, v1), (c2, r2, v2) = cams
    w, n = int(projector[0]), int(projector[0]) * int(projector[1])
    y2, x2 = np.nonzero(v2)
    k2 = r2[v2] * w + c2[v2]
    cnt = np.bincount(k2, minlength=n)
    sx, sy = np.bincount(k2, x2, n), np.bincount(k2, y2, n)
    y1, x1 = np.nonzero(v1)
    k1 = r1[v1] * w + c1[v1]
    ok = cnt[k1] > 0
    k = k1[ok]
    X = triangulate_codes(np.stack([x1[ok], y1[ok]], 1).astype(np.float64), np.stack([sx[k], sy[k]], 1) / cnt[k, None],
                          cam_K=cal["cam1_K"], cam_dist=cal["cam1_dist"], proj_K=cal["cam2_K"],
                          proj_dist=cal["cam2_dist"], R=cal["R"], T=cal["T"])
    return X[np.isfinite(X).all(1) & (X[:, 2] > 0)], int(v1.sum())


def plane_rms(P: np.ndarray) -> float:
    """RMS distance of points from their least-squares plane (every point counts, as a user's fit)."""
    P = np.asarray(P, np.float64)
    c = P.mean(0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    return float(np.sqrt(np.mean(((P - c) @ vt[2]) ** 2)))
