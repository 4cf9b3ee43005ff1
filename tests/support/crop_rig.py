"""The default rig's camera cropped to its middle, its projector cut to the window that camera sees: the
rig of the phase-rings and gray-rings codec tests (tests/pipeline/codecs/test_phase_rings.py,
test_gray_rings.py)."""

import dataclasses

from ringscan.pipeline.formats.rig import default_rig
from tests.support.projector_window import projector_window

FULL_PROJ = {"width": 1024, "height": 768, "center": [511.5, 383.5]}
"""The default rig's projector."""
WINDOW = (320, 96, 384, 304)
"""x0, y0, width, height: the window of the default rig's projector that the cameras of :func:`crop_rig` see
(its 320x256 crop sees projector pixels u 352..671, v 123..319 of the sphere scene; the window also holds the
rings' centre, 511.5, 383.5). The rigs of :func:`crop_rig` have their projector cut to it
(tests/support/projector_window.py): the camera frames are the full projector's to a grey level in ~1e-5 of
the pixels (measured on test_phase_rings' PHASE: 28 of 2.5M at 320x256, the same points and medians to
1e-6 mm). The virtual rig windows its render by itself (VirtualRig.emit_window); the cut projector also draws
its patterns at the window's size: test_phase_rings ~20 s instead of ~23 s through the whole projector (two
cores)."""
PROJ = projector_window(default_rig(), FULL_PROJ, *WINDOW)[1]
"""The projector of :func:`crop_rig`'s rigs: the window's width, height and the rings' centre in it."""


def crop_rig(gamma=2.2, width=320, height=256):
    """The default rig's camera cropped to its central ``width`` x ``height`` pixels: the same
    0.16 mm pixels (fine enough for gamma's phase error to show), a 16th of the work at 320x256
    (a 64th at 160x128, still all on the sphere); its projector cut to :data:`WINDOW`."""
    rig = default_rig(gamma=gamma)
    K = rig.camera.K.copy()
    K[0, 2] -= (rig.camera.width - width) / 2
    K[1, 2] -= (rig.camera.height - height) / 2
    rig = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, width=width, height=height, K=K))
    return projector_window(rig, FULL_PROJ, *WINDOW)[0]
