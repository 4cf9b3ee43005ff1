"""How fast the light a surface sends back changes across the camera image: its relative gradient
(|grad ln(white - black)| where it changes smoothly) at a sample's pixel, one ``@wp.func`` that the
samplers call in their kernels (``kernels.sample_light`` for the ring and phase codecs,
``kernels.decoded_maps`` for imported captures). The camera's blur weighs every edge and fringe by the
light around it, so where that light changes fast the sample reads off its place
(``pipeline.reconstruct.error_scale``). The NumPy statement is ``pipeline.codecs.shading.sample_shading``."""

from __future__ import annotations

from typing import Any

import warp as wp

__all__ = ["light_at", "shading_at"]


@wp.func
def light_at(contrast: wp.array2d(dtype=Any), x: int, y: int, scale: wp.float64):
    """max(contrast[y, x] / scale, 1): the light in 8-bit levels, a level at least;
    the plane float32 (a decode's white - black) or uint16 (an imported scan's contrast frame)."""
    return wp.max(wp.float64(contrast[y, x]) / scale, wp.float64(1.0))


@wp.func
def shading_at(contrast: wp.array2d(dtype=Any), uv: wp.vec2, scale: wp.float64):
    """The light's relative gradient (per camera px) at uv's nearest pixel, moved inside by one px at the
    border: each direction's 3 x 3 Sobel sums (weights 1, 2, 1 of :func:`light_at`) on either side, their
    difference over their sum (``pipeline.codecs.shading.sample_shading``; 0 on an image under 3 px a side). That is
    |grad ln(white - black)| where the light changes smoothly (the log of the sides' ratio over the 2 px
    between them, to first order) and at most 1 across a step, with no logarithm to take. The camera's
    blur weighs an edge or a fringe by the light around it, so a pattern seen across a light that
    changes fast reads off its place."""
    h = contrast.shape[0]
    w = contrast.shape[1]
    if h < 3 or w < 3:
        return wp.float64(0.0)
    x = wp.min(wp.max(int(wp.rint(wp.float64(uv[0]))), 1), w - 2)
    y = wp.min(wp.max(int(wp.rint(wp.float64(uv[1]))), 1), h - 2)
    two = wp.float64(2.0)
    right = light_at(contrast, x + 1, y - 1, scale) + two * light_at(contrast, x + 1, y, scale) + light_at(
        contrast, x + 1, y + 1, scale)
    left = light_at(contrast, x - 1, y - 1, scale) + two * light_at(contrast, x - 1, y, scale) + light_at(
        contrast, x - 1, y + 1, scale)
    below = light_at(contrast, x - 1, y + 1, scale) + two * light_at(contrast, x, y + 1, scale) + light_at(
        contrast, x + 1, y + 1, scale)
    above = light_at(contrast, x - 1, y - 1, scale) + two * light_at(contrast, x, y - 1, scale) + light_at(
        contrast, x + 1, y - 1, scale)
    gx = (right - left) / (right + left)
    gy = (below - above) / (below + above)
    return wp.sqrt(gx * gx + gy * gy)
