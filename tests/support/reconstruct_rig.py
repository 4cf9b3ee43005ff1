"""The end-to-end reconstruct tests' rig (tests/pipeline/reconstruct/test_reconstruct.py and others): the
default rig with a 320x256 camera, its 1024x768 projector's pattern fields, and OpenCV's rational and
thin-prism lenses for the camera and the projector."""

import dataclasses

import numpy as np

from ringscan.pipeline.formats.rig import default_rig

PROJ = {"width": 1024, "height": 768, "center": [511.5, 383.5]}
"""The default rig's projector as a pattern set names it: width, height, the rings' centre."""


def small_rig():
    """The default rig with a 320x256 camera (f scaled to match): fast tests."""
    rig = default_rig()
    cam = dataclasses.replace(rig.camera, width=320, height=256,
                              K=np.array([[650.0, 0, 159.5], [0, 650.0, 127.5], [0, 0, 1]]))
    return dataclasses.replace(rig, camera=cam)


WIDE_LENS = {  # the camera's (tests/pipeline/reconstruct/test_reconstruct.py, benchmarks/acceptance.py)
    # CALIB_RATIONAL_MODEL's 8 coefficients: -3 % barrel at this camera's corners (~5 px)
    "rational": [1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15],
    # + CALIB_THIN_PRISM_MODEL's s1..s4
    "thin-prism": [1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15, 0.002, -0.0005, -0.001, 0.0003],
}
PROJECTOR_LENS = {  # the projector's
    "rational": [-0.3, 0.5, 0.001, 0.0, 0.0, 0.5, 0.2, 0.0],
    "thin-prism": [-0.3, 0.5, 0.001, 0.0, 0.0, 0.5, 0.2, 0.0, 0.005, 0.0, -0.003, 0.0],
}
