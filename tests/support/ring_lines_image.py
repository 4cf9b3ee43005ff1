"""An image of bright circles whose centre lines are known, for the single-shot ``rings`` codec's line
detection tests (tests/kernels/test_ring_lines.py, test_launch.py)."""

import cv2
import numpy as np

CENTER = (100.3, 80.7)
RADII = (22.0, 37.0, 52.0, 67.0)


def circles_image(radii=RADII, center=CENTER, size=(160, 200), width=2.5, blur=0.8, level=120.0, dtype=np.uint8,
             background=50.0, noise=0.0, seed=0):
    """Antialiased bright circles (exact box profile of ``width`` px across, 8x8
    sub-samples per pixel), blurred, on a flat background."""
    h, w = size
    s = 8
    v, u = np.mgrid[0:h * s, 0:w * s].astype(np.float64)
    u = (u + 0.5) / s - 0.5
    v = (v + 0.5) / s - 0.5
    r = np.hypot(u - center[0], v - center[1])
    lit = np.zeros_like(r)
    for rk in radii:
        lit += np.abs(r - rk) <= width / 2
    img = lit.reshape(h, s, w, s).mean(axis=(1, 3))
    img = background + level * img
    if blur:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    if noise:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    if dtype == np.uint16:
        img = img * 257.0
    return np.clip(np.rint(img), 0, np.iinfo(dtype).max).astype(dtype)
