"""The virtual camera: renders each frame with the virtual rig (Warp) for the
pattern the projector shows and the angle the turntable reached. An emulator (it
uses the virtual rig, which the real drivers may not import); the virtual rig is
imported on first use, so importing ringscan.hardware never loads Warp.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from ringscan.hardware.devices.camera import CameraDevice

log = logging.getLogger(__name__)

__all__ = ["make_virtual_rig", "VirtualCamera"]


def make_virtual_rig(rig, scene, *, size_mm: float = 80.0, settings=None, device=None):
    """The virtual rig's renderer (pipeline.simulate.VirtualRig) for ``rig`` and a scene.

    Args:
        rig: a pipeline.formats.rig.Rig.
        scene: a scene name or mesh path (pipeline.simulate.scenes.make_scene), or a mesh.
        size_mm: scene size for make_scene.
        settings: the renderer's RenderSettings (default: its defaults).
        device: Warp device.
    """
    from ringscan.pipeline.simulate.scenes import make_scene
    from ringscan.pipeline.simulate.virtual_rig import RenderSettings, VirtualRig

    mesh = make_scene(scene, size_mm=size_mm) if isinstance(scene, (str, os.PathLike)) else scene
    return VirtualRig(rig, mesh, settings=RenderSettings() if settings is None else settings, device=device)


class VirtualCamera(CameraDevice):
    """The virtual rig's camera: renders the scene lit by what the projector shows
    now, with the object at the turntable's current angle.

    Args:
        virtual_rig: a renderer with ``set_turntable(deg)`` and
            ``render(frame, *, seed=None) -> (H, W) uint8`` (pipeline.simulate.VirtualRig;
            see :func:`make_virtual_rig`).
        projector: anything with ``current_frame()`` and ``current_index`` (a
            VirtualProjector, an emulated projector).
        turntable: anything with ``angle_deg`` (a VirtualTurntable, an emulated one);
            None: the object stays at 0 degrees.
        seed: None for fresh sensor noise on every grab; an integer makes the noise
            a function of (seed, frame index shown, table angle), so a frame captured
            again in the same state is the same image (resumed captures compare
            exactly against uninterrupted ones).
    """

    source = "virtual"

    def __init__(self, virtual_rig, projector, turntable=None, *, seed: int | None = None):
        self.virtual_rig = virtual_rig
        self.projector = projector
        self.turntable = turntable
        self.seed = seed
        self.grabs = 0

    def _state_seed(self, index: int, angle: float) -> int | None:
        if self.seed is None:
            return None
        mdeg = int(round(angle * 1000.0)) % (2 ** 32)
        ss = np.random.SeedSequence([int(self.seed) % (2 ** 32), index + 1, mdeg])
        return int(ss.generate_state(1)[0]) & 0x7FFFFFFF

    def _read(self) -> np.ndarray:
        angle = 0.0 if self.turntable is None else float(self.turntable.angle_deg)
        frame = self.projector.current_frame()
        self.virtual_rig.set_turntable(angle)
        self.grabs += 1
        return self.virtual_rig.render(frame, seed=self._state_seed(int(self.projector.current_index), angle))
