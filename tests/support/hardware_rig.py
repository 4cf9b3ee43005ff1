"""Small rigs, pattern sets and cameras for the hardware tests and the capture commands' tests (kept fast:
320x256 camera, 6-frame pattern sets); tests/hardware/conftest.py makes fixtures of them."""

from __future__ import annotations

import dataclasses

import numpy as np

from ringscan.hardware.devices.camera import CameraDevice
from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.formats.rig import default_rig

CAM_W, CAM_H = 320, 256
"""The small camera's width and height (pixels)."""


def small_rig(width: int = CAM_W, height: int = CAM_H):
    """The default rig with its camera scaled down (same field of view)."""
    rig = default_rig()
    cam = rig.camera
    s = width / cam.width
    K = cam.K.copy()
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 2] = (width - 1) / 2
    K[1, 2] = (height - 1) / 2
    return dataclasses.replace(rig, camera=dataclasses.replace(cam, width=width, height=height, K=K))


def small_patterns(bits: int = 2, sector_bits: int = 0):
    """A gray-rings set on the rig's 1024x768 projector: 2 + 2 * (bits + sector_bits) frames."""
    return parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 40.0, "bits": bits, "sector_bits": sector_bits})


def pattern_frames(spec):
    """Every frame of ``spec`` drawn, by name."""
    return {n: render_frame(spec, n) for n in frame_names(spec)}


class ProbeCamera(CameraDevice):
    """A test double (not a renderer): each frame encodes what the devices do now,
    pixel (0, 0) = index shown + 1 (0 = blank), pixel (0, 1) = table angle / 5 deg,
    so a test can see which frame was captured at which angle."""

    source = "probe"

    def __init__(self, projector, turntable, width=CAM_W, height=CAM_H):
        self.projector, self.turntable = projector, turntable
        self.shape = (height, width)
        self.grabs = 0

    def _read(self):
        img = np.zeros(self.shape, np.uint8)
        img[0, 0] = self.projector.current_index + 1
        img[0, 1] = int(round(self.turntable.angle_deg / 5.0))
        self.grabs += 1
        return img
