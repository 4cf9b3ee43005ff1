"""Crop a ``decoded``-codec scan (what ``ringscan import`` writes) to a window of its camera image.

The decoded frames (proj_u, proj_v, contrast) are per camera pixel, so a window of them is the scan a
camera of the window's size would have taken: the same rig with the camera's width and height the
window's and its principal point (K[0, 2], K[1, 2]) moved by the window's corner. Distortion is in the
camera's normalised coordinates and so unchanged; every pixel's ray is the one it had in the full image.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ringscan.pipeline.formats.images import read_image, write_image
from ringscan.pipeline.formats.scan import load_scan, save_scan


def crop_decoded_scan(folder: Path, x0: int, y0: int, width: int, height: int) -> None:
    """Rewrite the scan in ``folder`` (every view's frames and the rig's camera) as the window
    ``[x0, x0 + width) x [y0, y0 + height)`` of its camera image."""
    scan = load_scan(folder)
    assert scan.patterns.codec == "decoded", scan.patterns.codec
    cam = scan.rig.camera
    assert 0 <= x0 and 0 <= y0 and x0 + width <= cam.width and y0 + height <= cam.height
    for view in scan.views:
        for rel in view.frames.values():
            p = folder / rel
            img = read_image(p)
            assert img.shape[:2] == (cam.height, cam.width), (p, img.shape)
            write_image(p, img[y0:y0 + height, x0:x0 + width].copy())
    K = cam.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    rig = dataclasses.replace(scan.rig, camera=dataclasses.replace(cam, width=width, height=height, K=K))
    save_scan(dataclasses.replace(scan, rig=rig))
