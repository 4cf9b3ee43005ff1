"""What each sample's frames say of its light (docs/reconstruction.md, "Honest sigma"): the
white - black contrast under it (bilinear in the decode's contrast plane), a band edge's
predicted sigma from that contrast, and its share of light that did not come straight from the
projector (the finest band bits' pattern / inverse floor). One thread a sample, on the frames'
device: the NumPy statements are ``pipeline.codecs.angle_code.sample_contrast``, ``edge_sigma``
and ``sample_indirect`` (the same values to the bit)."""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from ringscan.kernels.launch import check_array, default_threads, launch_spans

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["sample_light_kernel", "sample_light"]

MAX_INDIRECT_BITS = 4
"""Most band bits whose pattern / inverse floor a sample's indirect share averages."""


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def sample_light_kernel(
    frames: wp.array3d(dtype=Any),
    contrast: wp.array2d(dtype=wp.float32),
    uv: wp.array(dtype=wp.vec2),
    planes: wp.vec4i,
    pairs: wp.array(dtype=wp.int32),
    scale: wp.float64,
    edge_num: wp.float64,
    i0: int,
    sigma: wp.array(dtype=wp.float32),
    indirect: wp.array(dtype=wp.float32),
):
    """Sample i0 + tid's edge sigma (projector px) and indirect share.

    The contrast c: ``contrast`` read bilinearly at uv (clamped inside the image), over ``scale``
    (257 for 16-bit frames); sigma = ``edge_num`` / (2 max(c, 1)) (``edge_num``: sqrt(2) noise x the
    edge's width). The share: at uv's nearest pixel, the mean over the frame pairs ``pairs`` (frame,
    inverse, ...) of min(frame, inverse), less black, over max(white - black, 1), within [0, 1].

    frames (F, H, W) uint8/uint16, contrast (H, W) float32, uv (n,) vec2, pairs (2 k,) int32 frame
    indices: read; ``planes``: (white, black, k, 0). sigma, indirect (n,) float32: written.

    Size: the frames, the contrast plane, the samples' positions, the frames' indices (white, black
    and the pairs), the two scalars of the sigma, the span's i0, two arrays out."""
    i = i0 + wp.tid()
    h = contrast.shape[0]
    w = contrast.shape[1]
    # clamped in float32 (the positions' own type), the weights in float64, as the NumPy statement
    xs = wp.min(wp.max(uv[i][0], 0.0), wp.float32(wp.float64(w) - wp.float64(1.001)))
    ys = wp.min(wp.max(uv[i][1], 0.0), wp.float32(wp.float64(h) - wp.float64(1.001)))
    x = wp.float64(xs)
    y = wp.float64(ys)
    x0 = int(wp.floor(x))
    y0 = int(wp.floor(y))
    fx = x - wp.float64(float(x0))
    fy = y - wp.float64(float(y0))
    one = wp.float64(1.0)
    a = wp.float64(contrast[y0, x0]) * (one - fx) + wp.float64(contrast[y0, x0 + 1]) * fx
    b = wp.float64(contrast[y0 + 1, x0]) * (one - fx) + wp.float64(contrast[y0 + 1, x0 + 1]) * fx
    c = (a * (one - fy) + b * fy) / scale
    sigma[i] = wp.float32(edge_num / (wp.float64(2.0) * wp.max(c, one)))
    px = wp.min(wp.max(int(wp.rint(wp.float64(uv[i][0]))), 0), w - 1)
    py = wp.min(wp.max(int(wp.rint(wp.float64(uv[i][1]))), 0), h - 1)
    black = float(frames[planes[1], py, px])
    span = wp.max(float(frames[planes[0], py, px]) - black, 1.0)
    k = planes[2]
    total = float(0.0)
    for j in range(k):
        total += wp.min(float(frames[pairs[2 * j], py, px]), float(frames[pairs[2 * j + 1], py, px]))
    floor = total / float(k) - black
    indirect[i] = wp.min(wp.max(floor / span, 0.0), 1.0)


for _t in (wp.uint8, wp.uint16):
    wp.overload(sample_light_kernel, {"frames": wp.array3d(dtype=_t)})


# ----------------------------------------------------------------------------- host


def sample_light(frames: wp.array, contrast: wp.array, uv: wp.array, *, white: int, black: int,
                 pairs: list[tuple[int, int]], edge_num: float,
                 threads: int | None = None) -> tuple[wp.array, wp.array]:
    """((n,) float32 edge sigma, (n,) float32 indirect share) of the samples at ``uv``, on the
    frames' device (:func:`sample_light_kernel`).

    Args:
        frames: (F, H, W) uint8/uint16 the view's frames.
        contrast: (H, W) float32 white - black (the decode's ``RingLabels.contrast``).
        uv: (n,) vec2 the samples' camera positions.
        white, black: the frames' indices of the white and black frames.
        pairs: (frame, inverse) indices of the band bits whose floor measures the indirect light.
        edge_num: sqrt(2) x the camera noise x the edge's width (``angle_code.edge_sigma``'s numerator).
        threads: CPU threads; default all cores.
    """
    fn = "sample_light"
    n = check_array("uv", uv, None, wp.vec2, fn)
    if not isinstance(frames, wp.array) or frames.ndim != 3 or frames.dtype not in (wp.uint8, wp.uint16):
        raise ValueError(f"{fn}: frames must be a (F, H, W) uint8/uint16 Warp array")
    if not isinstance(contrast, wp.array) or contrast.dtype != wp.float32 or tuple(contrast.shape) != tuple(
            frames.shape[1:]):
        raise ValueError(f"{fn}: contrast must be a {tuple(frames.shape[1:])} float32 Warp array")
    if not 1 <= len(pairs) <= MAX_INDIRECT_BITS:
        raise ValueError(f"{fn}: 1 to {MAX_INDIRECT_BITS} frame pairs, got {len(pairs)}")
    dev = frames.device
    sigma = wp.empty(n, dtype=wp.float32, device=dev)
    indirect = wp.empty(n, dtype=wp.float32, device=dev)
    if n:
        scale = 257.0 if frames.dtype == wp.uint16 else 1.0
        idx = wp.array(np.asarray(pairs, np.int32).reshape(-1), dtype=wp.int32, device=dev)
        args = [frames, contrast, uv, wp.vec4i(int(white), int(black), len(pairs), 0), idx, wp.float64(scale),
                wp.float64(edge_num)]
        launch_spans(sample_light_kernel, n, lambda i0: args + [i0], [sigma, indirect], dev,
                     default_threads() if threads is None else threads)
    return sigma, indirect
