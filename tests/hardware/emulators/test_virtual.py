"""The virtual camera: what the virtual rig renders for the frame shown and the table's angle."""

import numpy as np

from ringscan.hardware.devices.projector import VirtualProjector
from ringscan.hardware.devices.turntable import VirtualTurntable
from ringscan.hardware.emulators.virtual import VirtualCamera
from tests.support.hardware_rig import pattern_frames, small_patterns


def test_virtual_camera_follows_projector_and_turntable(virtual_rig, rig):
    spec = small_patterns()
    proj = VirtualProjector(pattern_frames(spec))
    table = VirtualTurntable()
    cam = VirtualCamera(virtual_rig, proj, table, seed=5)
    proj.show(0)  # white
    white = cam.grab()
    assert white.shape == (rig.camera.height, rig.camera.width) and white.dtype == np.uint8
    np.testing.assert_array_equal(cam.grab(), white)  # same state, same seed: same image
    proj.show(1)  # black
    black = cam.grab()
    assert white.astype(float).mean() > black.astype(float).mean() + 20
    proj.show(0)
    table.move_to(90.0)
    turned = cam.grab()
    assert np.mean(np.abs(turned.astype(int) - white.astype(int)) > 12) > 0.02  # the terrain turned (noise: < 1e-4)
    # it is what the rig renders in that state, with the state's seed
    virtual_rig.set_turntable(90.0)
    np.testing.assert_array_equal(turned, virtual_rig.render(proj.current_frame(), seed=cam._state_seed(0, 90.0)))
    unseeded = VirtualCamera(virtual_rig, proj, table)
    assert not np.array_equal(unseeded.grab(), unseeded.grab())  # fresh noise
