"""A tiny simulated scan (160x128 camera, 256x192 projector of 0.6 mm pixels,
gray-rings with 3 bits and 4 sector bits, a 40 mm sphere): simulated and
reconstructed in about a second, for tests of files, folders and reports."""

from __future__ import annotations

import dataclasses

import numpy as np

from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import Camera, ParallelLight, default_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.simulate.scan import simulate_scan
from tests.support.shared_renders import shared_render

TINY_PATTERNS = {"codec": "gray-rings", "width": 256, "height": 192, "center": [127.5, 95.5], "rho0": 4.0,
                 "pitch": 3.0, "bits": 3, "sector_bits": 4}


def tiny_rig():
    """The default rig's pose with a 160x128 camera and a 256x192 projector."""
    rig = default_rig()
    c = rig.camera
    K = np.array([[325.0, 0, 79.5], [0, 325.0, 63.5], [0, 0, 1.0]])
    return dataclasses.replace(
        rig, camera=Camera(width=160, height=128, K=K, dist=c.dist, R=c.R, t=c.t, gamma=2.2),
        light=ParallelLight(R=np.eye(3), t=np.zeros(3), pixel_pitch_mm=0.6, axis_px=np.array([127.5, 95.5]),
                            width=256, height=192))


def simulate_tiny_scan(folder, *, turntable_deg=(0.0,)):
    """Write the tiny scan into ``folder``; returns the loaded scan.

    The virtual rig renders it once per test session and set of angles (tests/support/shared_renders.py);
    every call gets its own copy (tests change their scan's files), byte for byte what a render into
    ``folder`` writes."""
    key = tuple(float(a) for a in turntable_deg)

    def render(dst):
        simulate_scan(dst, scene="sphere", size_mm=40.0, rig=tiny_rig(), patterns=parse_patterns(TINY_PATTERNS),
                      turntable_deg=key, progress=False)

    shared_render(folder, "tiny", key, render)
    return load_scan(folder)
