"""The virtual rig's tests' small rig (tests/pipeline/simulate/test_simulate.py, test_poses): the default
rig's geometry with a 320 x 256 camera and a 256 x 192 projector, and a pattern set for it."""

import dataclasses

import numpy as np

from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import Camera, ParallelLight, default_rig

PW, PH, S = 256, 192, 0.6     # projector of the small rig: 153.6 x 115.2 mm like the default one


def small_rig(*, gamma=2.2, light_gamma=1.0, light_model="parallel", turntable=True):
    """The default rig's geometry with a 320 x 256 camera and a 256 x 192 projector."""
    rig = default_rig(gamma=gamma, light_model=light_model, turntable=turntable)
    c = rig.camera
    K = np.array([[650.0, 0, 159.5], [0, 650.0, 127.5], [0, 0, 1.0]])
    cam = Camera(width=320, height=256, K=K, dist=c.dist, R=c.R, t=c.t, gamma=gamma)
    if light_model == "parallel":
        light = ParallelLight(R=np.eye(3), t=np.zeros(3), pixel_pitch_mm=S, axis_px=np.array([127.5, 95.5]),
                              width=PW, height=PH, gamma=light_gamma)
    else:
        li = rig.light
        K2 = li.K.copy()
        K2[:2] /= 4.0
        K2[0, 2], K2[1, 2] = 127.5, 95.5
        light = dataclasses.replace(li, width=PW, height=PH, K=K2, gamma=light_gamma)
    return dataclasses.replace(rig, camera=cam, light=light)


def small_spec(**kw):
    """A 3-bit gray-rings pattern set on the small projector (``kw`` replaces any field)."""
    d = {"codec": "gray-rings", "width": PW, "height": PH, "center": [127.5, 95.5], "rho0": 4.0, "pitch": 3.0,
         "bits": 3, "sector_bits": 2}
    d.update(kw)
    return parse_patterns(d)
