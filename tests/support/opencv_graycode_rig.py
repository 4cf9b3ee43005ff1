"""Small virtual rigs for OpenCV's Gray code (tests/pipeline/simulate/test_opencv_graycode.py, the import
tests, benchmarks/opencv_sample_virtual.py and real_capture.py): a 320x256 camera and a distorted 128x96
perspective projector, and the same with a second camera."""

import dataclasses

import numpy as np

from ringscan.pipeline.formats.rig import Camera, default_rig

PW, PH = 128, 96
"""The projector's width and height (pixels)."""


def small_procam_rig(*, gamma=1.0):
    """The default perspective rig with a 320x256 camera and a 128x96 projector with lens distortion.

    One projector pixel covers about 1.2 mm on the plane, one camera pixel about
    0.65 mm: about 1.8 camera pixels per projector pixel, as the sub-pixel decode needs.
    """
    rig = default_rig(gamma=gamma, light_model="perspective", turntable=False)
    c = rig.camera
    K = np.array([[650.0, 0, 159.5], [0, 650.0, 127.5], [0, 0, 1.0]])
    cam = Camera(width=320, height=256, K=K, dist=c.dist, R=c.R, t=c.t, gamma=gamma)
    li = rig.light
    Kp = li.K.copy()
    Kp[:2] /= 8.0
    Kp[0, 2], Kp[1, 2] = (PW - 1) / 2, (PH - 1) / 2
    light = dataclasses.replace(li, width=PW, height=PH, K=Kp, dist=np.array([-0.08, 0.05, 0.001, 0.0, 0.0]))
    return dataclasses.replace(rig, camera=cam, light=light)


def small_stereo_rig(*, gamma=2.2):
    """:func:`small_procam_rig` with a second camera (camera 1 turned 180 degrees about the light axis):
    the virtual two-camera rig with a projector (the cameras 482 mm apart, 70 degrees between their axes)."""
    from ringscan.pipeline.simulate.scan import add_camera2

    return add_camera2(small_procam_rig(gamma=gamma))
