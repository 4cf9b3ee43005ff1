"""A decoded scan written from given frames (the ``decoded`` codec: projector coordinates per camera pixel),
for the calibrate commands' tests on the oblique rig of tests/support/stereo_truth.py."""

from __future__ import annotations

import numpy as np

from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.formats.rig import Rig, Volume
from ringscan.pipeline.formats.scan import Scan, View, save_scan


def write_decoded_scan(folder, rig: Rig, frames: dict | None = None, frames2: dict | None = None) -> None:
    """Write a one-view ``decoded``-codec scan (OpenCV's Gray code as ``ringscan import`` writes it: proj_u, proj_v,
    contrast) of ``rig`` in ``folder``: camera 1's ``frames`` and camera 2's ``frames2`` (zeros where not given)."""
    spec = parse_patterns({"codec": "decoded", "width": 1280, "height": 800, "center": [661.5, 758.8],
                           "rho0": 0.0, "pitch": 1.0, "sector_bits": 8}, source="test")
    views = []
    for name in ("v1",):
        rel, rel2 = {}, {}
        for k in frame_names(spec):
            img = frames[k] if frames else np.zeros((rig.camera.height, rig.camera.width), np.uint16)
            write_image(folder / name / f"{k}.png", img)
            rel[k] = f"{name}/{k}.png"
            if rig.camera2 is not None:
                c2 = rig.camera2
                img2 = frames2[k] if frames2 else np.zeros((c2.height, c2.width), np.uint16)
                write_image(folder / name / "cam2" / f"{k}.png", img2)
                rel2[k] = f"{name}/cam2/{k}.png"
        cam2 = View(name=name, turntable_deg=0.0, frames=rel2) if rel2 else None
        views.append(View(name=name, turntable_deg=0.0, frames=rel, camera2=cam2))
    save_scan(Scan(folder=folder, rig=rig, patterns=spec, views=tuple(views)))


VOLUME = Volume(z_min=0.0, z_max=2000.0, r_max=3000.0)
"""A volume holding the oblique rig's surface (tests/support/stereo_truth.py)."""
