"""The true ring of a sub-pixel sample on a virtual-rig scan (the paper's single-shot rings)."""

from __future__ import annotations

import cv2
import numpy as np

from ringscan.pipeline.geometry import undistort_normalized


def truth_rings(scan, view, uv):
    """True ring index of each sub-pixel sample (the truth depth, bilinear, back
    to the world, then to the pattern), and a mask of samples where that is
    well defined (on a ring's line, away from depth edges)."""
    depth = cv2.imread(str(scan.folder / scan.extra["truth"]["views"][view]["depth"]), cv2.IMREAD_UNCHANGED)
    cam, li, spec = scan.rig.camera, scan.rig.light, scan.patterns
    u, v = uv[:, 0].astype(np.float64), uv[:, 1].astype(np.float64)
    x0 = np.clip(np.floor(u).astype(int), 0, cam.width - 2)
    y0 = np.clip(np.floor(v).astype(int), 0, cam.height - 2)
    fx, fy = u - x0, v - y0
    c = np.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]]).astype(np.float64)
    z = c[0] * (1 - fx) * (1 - fy) + c[1] * fx * (1 - fy) + c[2] * (1 - fx) * fy + c[3] * fx * fy
    xn, yn = undistort_normalized(cam, u, v)
    X = (np.stack([xn * z, yn * z, z], -1) - cam.t) @ cam.R
    p = (X @ li.R.T + li.t)[:, :2] / li.pixel_pitch_mm + li.axis_px
    rho = np.hypot(p[:, 0] - spec.center[0], p[:, 1] - spec.center[1])
    radii = spec.ring_radii()
    j = np.argmin(np.abs(np.nan_to_num(rho)[:, None] - radii[None]), 1)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(rho) & (np.abs(rho - radii[j]) < 0.6 * spec.line_width + 1.0) & (np.ptp(c, 0) < 0.5)
    return j, ok, X
