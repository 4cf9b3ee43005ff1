"""A rig's projector cut to the window of its image that a camera sees.

The virtual rig computes the light of the window of the projector's image that its camera sees by itself
(VirtualRig.emit_window, the same frames byte for byte), but the patterns are still drawn whole: for a
camera cropped to the middle of the default rig's image (0.16 mm pixels), drawing the 1024x768 frames takes
about as long as rendering them. Cut to a window around what the camera sees, the projector lights every
camera pixel as before and its frames are drawn at the window's size, so the camera's frames are the same
(to the rounding of float sums: a grey level here and there), and the points the same, in less time
(tests/pipeline/codecs/test_phase_rings.py: ~20 s with its 384x304 window, ~23 s with the whole projector).

The window is the same projector, its pixels renumbered: the image's width and height the window's, the
light's axis (``axis_px``, a parallel light's) and the patterns' centre moved by the window's corner; rings
and sectors stay where they were on the object. The window must hold the patterns' centre (a pattern set is
refused otherwise) and every projector pixel the camera sees (:func:`seen_projector_pixels`), with a few
pixels to spare for the defocus blur. tests/test_support.py checks a window's frames against the whole
projector's.
"""

from __future__ import annotations

import dataclasses


def projector_window(rig, patterns: dict, x0: int, y0: int, width: int, height: int):
    """(``rig``, ``patterns``) with the (parallel) projector cut to ``[x0, x0 + width) x [y0, y0 + height)`` of
    its image (``patterns``: the dict that parse_patterns reads)."""
    li = rig.light
    assert li.model == "parallel", li.model
    assert 0 <= x0 and 0 <= y0 and x0 + width <= li.width and y0 + height <= li.height, (x0, y0, width, height)
    assert (patterns["width"], patterns["height"]) == (li.width, li.height), "patterns for another projector"
    light = dataclasses.replace(li, width=width, height=height, axis_px=li.axis_px - [x0, y0])
    cu, cv = patterns["center"]
    moved = {**patterns, "width": width, "height": height, "center": [cu - x0, cv - y0]}
    return dataclasses.replace(rig, light=light), moved


def seen_projector_pixels(scan, view_name: str = "view_000"):
    """(n, 2) projector pixels under the points that the scan's camera sees (the truth depth of every pixel
    that sees the scene, lit or not): a window holding them all (and a few pixels to spare) lights what
    the whole projector lights."""
    import cv2
    import numpy as np

    from ringscan.pipeline.geometry import projector_pixels, undistort_normalized

    depth = cv2.imread(str(scan.folder / scan.extra["truth"]["views"][view_name]["depth"]), cv2.IMREAD_UNCHANGED)
    vv, uu = np.nonzero(np.isfinite(depth))
    cam = scan.rig.camera
    x, y = undistort_normalized(cam, uu.astype(np.float64), vv.astype(np.float64))
    z = depth[vv, uu].astype(np.float64)
    X = (np.stack([x * z, y * z, z], -1) - cam.t) @ cam.R
    return projector_pixels(scan.rig, X)
