"""The NumPy statement of :attr:`Samples.shading <ringscan.kernels.samples.Samples.shading>`
(``kernels.light_gradient.shading_at``, which the codecs' kernels call): the light's relative gradient at
each sample, shared by the codecs' NumPy statements (``decoded.decoded_samples``, the tests of
``kernels.sample_light``)."""

from __future__ import annotations

import numpy as np

__all__ = ["sample_shading"]


def sample_shading(contrast: np.ndarray, uv: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(n,) float32 :attr:`~ringscan.kernels.samples.Samples.shading` at each sample's nearest
    camera pixel (moved one px inside at the border): the light's relative gradient per camera px,
    each direction's two 3 x 3 Sobel sums (weights 1, 2, 1) of max(white - black, 1) on either side,
    their difference over their sum, of the (H, W) ``contrast`` plane in 8-bit levels (its values over
    ``scale``); tanh of the log's gradient on an exponential ramp, so |grad ln(white - black)| where
    the light changes smoothly and at most 1 across a step; 0 on an image under 3 px a side."""
    c = np.asarray(contrast, np.float64)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    h, w = c.shape
    if h < 3 or w < 3:
        return np.zeros(len(uv), np.float32)
    x = np.clip(np.rint(uv[:, 0]).astype(np.int64), 1, w - 2)
    y = np.clip(np.rint(uv[:, 1]).astype(np.int64), 1, h - 2)

    def at(dx, dy):
        return np.maximum(c[y + dy, x + dx] / scale, 1.0)

    right = at(1, -1) + 2.0 * at(1, 0) + at(1, 1)  # the kernel's order of operations
    left = at(-1, -1) + 2.0 * at(-1, 0) + at(-1, 1)
    below = at(-1, 1) + 2.0 * at(0, 1) + at(1, 1)
    above = at(-1, -1) + 2.0 * at(0, -1) + at(1, -1)
    gx = (right - left) / (right + left)
    gy = (below - above) / (below + above)
    return np.sqrt(gx * gx + gy * gy).astype(np.float32)
