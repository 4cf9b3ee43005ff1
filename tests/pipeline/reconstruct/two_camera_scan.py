"""A small two-camera scan for tests: the virtual rig renders the same scene twice,
once from each camera, and the two one-camera scans are put together into one
two-camera scan folder (camera 2's frames under ``<view>/cam2/``); the ground
truth is camera 1's."""

from __future__ import annotations

import dataclasses
import math
import shutil

import numpy as np

from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import UncalibratedLight, default_rig, look_at
from ringscan.pipeline.formats.scan import View, load_scan, save_scan
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.virtual_rig import RenderSettings

PROJ = {"width": 1024, "height": 768, "center": [511.5, 383.5]}
ANGLE_PATTERNS = {"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 16.0, "bits": 5, "sector_bits": 6,
                  "angle_steps": 4, "angle_period": 12.0}


def two_camera_rig(*, turn_deg: float = 70.0):
    """The default rig with a 320x256 camera 1 and a camera 2 turned by ``turn_deg``
    about the light axis (same distance and tilt)."""
    rig = default_rig()
    K = np.array([[650.0, 0, 159.5], [0, 650.0, 127.5], [0, 0, 1]])
    c1 = dataclasses.replace(rig.camera, width=320, height=256, K=K)
    a = math.radians(turn_deg)
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
    target = np.array([0.0, 0.0, 25.0])
    eye2 = Rz @ c1.center
    R2, t2 = look_at(eye2, target, up_hint=Rz @ np.array([1.0, 0.0, 0.0]))
    c2 = dataclasses.replace(c1, R=R2, t=t2, dist=np.array([-0.01, 0.02, 0.0, 0.0, 0.0]))
    return dataclasses.replace(rig, camera=c1, camera2=c2)


def simulate_two_camera_scan(folder, *, patterns=None, rig=None, uncalibrated: bool = False,
                             turntable_deg=(0.0,)):
    """Write a two-camera scan of a 80 mm sphere into ``folder``; returns it loaded."""
    rig = two_camera_rig() if rig is None else rig
    spec = parse_patterns(ANGLE_PATTERNS if patterns is None else patterns)
    one = dataclasses.replace(rig, camera2=None)
    scan1 = simulate_scan(folder, scene="sphere", rig=one, patterns=spec, turntable_deg=turntable_deg,
                          progress=False)
    tmp = folder.parent / (folder.name + "_camera2")
    scan2 = simulate_scan(tmp, scene="sphere", rig=dataclasses.replace(one, camera=rig.camera2), patterns=spec,
                          turntable_deg=turntable_deg, progress=False, settings=RenderSettings(seed=7))
    views = []
    for v1, v2 in zip(scan1.views, scan2.views):
        frames2 = {}
        for name, rel in v2.frames.items():
            dst = f"{v1.name}/cam2/{name}.png"
            (folder / dst).parent.mkdir(parents=True, exist_ok=True)
            shutil.move(tmp / rel, folder / dst)
            frames2[name] = dst
        views.append(dataclasses.replace(v1, camera2=View(name=v1.name, turntable_deg=v1.turntable_deg,
                                                          frames=frames2)))
    shutil.rmtree(tmp)
    full = rig if not uncalibrated else dataclasses.replace(
        rig, light=UncalibratedLight(width=rig.light.width, height=rig.light.height, gamma=rig.light.gamma))
    save_scan(dataclasses.replace(scan1, rig=full, rig_ref=None, views=tuple(views)))
    return load_scan(folder)
