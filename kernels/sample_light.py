"""What each sample's frames say of its light (docs/reconstruction.md, "Honest sigma"): the
white - black contrast under it (bilinear in the decode's contrast plane), a band edge's
predicted sigma from that contrast (gray-rings: :func:`sample_light`) or a phase's from that
contrast and its fringe's modulation (phase-rings: :func:`phase_light`), its share of light
that did not come straight from the projector (the finest band bits' pattern / inverse floor),
and how fast the light its surface sends back changes across the image there (the shading).
One thread a sample, on the frames' device: the NumPy statements are
``pipeline.codecs.angle_code.sample_contrast``, ``edge_sigma``, ``phase_sigma``,
``sample_indirect``, and ``pipeline.codecs.shading.sample_shading`` (the same values to the bit)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import warp as wp

from ringscan.kernels.launch import check_array, default_threads, launch_spans
from ringscan.kernels.light_gradient import shading_at

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["sample_light_kernel", "phase_light_kernel", "sample_light", "phase_light"]

MAX_INDIRECT_BITS = 4
"""Most band bits whose pattern / inverse floor a sample's indirect share averages."""


# ----------------------------------------------------------------------------- kernels


@wp.func
def contrast_at(contrast: wp.array2d(dtype=wp.float32), uv: wp.vec2, scale: wp.float64):
    """The contrast plane read bilinearly at uv (clamped inside the image), over ``scale``: float64, as
    ``angle_code.sample_contrast`` gives it (positions clamped in float32, their own type; weights in float64)."""
    h = contrast.shape[0]
    w = contrast.shape[1]
    xs = wp.min(wp.max(uv[0], 0.0), wp.float32(wp.float64(w) - wp.float64(1.001)))
    ys = wp.min(wp.max(uv[1], 0.0), wp.float32(wp.float64(h) - wp.float64(1.001)))
    x = wp.float64(xs)
    y = wp.float64(ys)
    x0 = int(wp.floor(x))
    y0 = int(wp.floor(y))
    fx = x - wp.float64(float(x0))
    fy = y - wp.float64(float(y0))
    one = wp.float64(1.0)
    a = wp.float64(contrast[y0, x0]) * (one - fx) + wp.float64(contrast[y0, x0 + 1]) * fx
    b = wp.float64(contrast[y0 + 1, x0]) * (one - fx) + wp.float64(contrast[y0 + 1, x0 + 1]) * fx
    return (a * (one - fy) + b * fy) / scale


@wp.func
def indirect_at(frames: wp.array3d(dtype=Any), uv: wp.vec2, planes: wp.vec4i, pairs: wp.array(dtype=wp.int32)):
    """At uv's nearest pixel, the mean over the frame pairs ``pairs`` (frame, inverse, ...; ``planes[2]`` of
    them) of min(frame, inverse), less black, over max(white - black, 1), within [0, 1] (``planes``: white,
    black, k, 0): ``angle_code.sample_indirect``."""
    h = frames.shape[1]
    w = frames.shape[2]
    px = wp.min(wp.max(int(wp.rint(wp.float64(uv[0]))), 0), w - 1)
    py = wp.min(wp.max(int(wp.rint(wp.float64(uv[1]))), 0), h - 1)
    black = float(frames[planes[1], py, px])
    span = wp.max(float(frames[planes[0], py, px]) - black, 1.0)
    k = planes[2]
    total = float(0.0)
    for j in range(k):
        total += wp.min(float(frames[pairs[2 * j], py, px]), float(frames[pairs[2 * j + 1], py, px]))
    floor = total / float(k) - black
    return wp.min(wp.max(floor / span, 0.0), 1.0)


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
    shading: wp.array(dtype=wp.float32),
):
    """Sample i0 + tid's edge sigma (projector px), indirect share and shading.

    The contrast c (:func:`contrast_at`); sigma = ``edge_num`` / (2 max(c, 1)) (``edge_num``: sqrt(2) noise x
    the edge's width). The share: :func:`indirect_at`; the shading: ``light_gradient.shading_at``.

    frames (F, H, W) uint8/uint16, contrast (H, W) float32, uv (n,) vec2, pairs (2 k,) int32 frame
    indices: read; ``planes``: (white, black, k, 0). sigma, indirect, shading (n,) float32: written.

    Size: the frames, the contrast plane, the samples' positions, the frames' indices (white, black
    and the pairs), the two scalars of the sigma, the span's i0, three arrays out."""
    i = i0 + wp.tid()
    c = contrast_at(contrast, uv[i], scale)
    sigma[i] = wp.float32(edge_num / (wp.float64(2.0) * wp.max(c, wp.float64(1.0))))
    indirect[i] = indirect_at(frames, uv[i], planes, pairs)
    shading[i] = wp.float32(shading_at(contrast, uv[i], scale))


@wp.kernel
def phase_light_kernel(
    frames: wp.array3d(dtype=Any),
    contrast: wp.array2d(dtype=wp.float32),
    uv: wp.array(dtype=wp.vec2),
    modulation: wp.array(dtype=wp.float32),
    planes: wp.vec4i,
    pairs: wp.array(dtype=wp.int32),
    scale: wp.float64,
    phase_num: wp.vec2d,
    i0: int,
    sigma: wp.array(dtype=wp.float32),
    indirect: wp.array(dtype=wp.float32),
    shading: wp.array(dtype=wp.float32),
):
    """Sample i0 + tid's phase sigma of rho (projector px), indirect share and shading (phase-rings).

    sigma = ``phase_num[0]`` / amp / ``phase_num[1]``, amp = 0.5 max(modulation, 1e-3) (float32) x
    max(c, 1) (:func:`contrast_at`): ``angle_code.phase_sigma`` (``phase_num``: its pitch / 2 pi x
    sqrt(2 / N) x noise, and the smoothing window's side). The share: :func:`indirect_at`; the
    shading: ``light_gradient.shading_at``.

    frames (F, H, W) uint8/uint16, contrast (H, W) float32, uv (n,) vec2, modulation (n,) float32, pairs
    (2 k,) int32: read; ``planes``: (white, black, k, 0). sigma, indirect, shading (n,) float32: written.

    Size: :func:`sample_light_kernel`'s, with each sample's fringe modulation."""
    i = i0 + wp.tid()
    c = contrast_at(contrast, uv[i], scale)
    amp = wp.float64(wp.float32(0.5) * wp.max(modulation[i], wp.float32(1.0e-3))) * wp.max(c, wp.float64(1.0))
    sigma[i] = wp.float32(phase_num[0] / amp / phase_num[1])
    indirect[i] = indirect_at(frames, uv[i], planes, pairs)
    shading[i] = wp.float32(shading_at(contrast, uv[i], scale))


for _t in (wp.uint8, wp.uint16):
    wp.overload(sample_light_kernel, {"frames": wp.array3d(dtype=_t)})
    wp.overload(phase_light_kernel, {"frames": wp.array3d(dtype=_t)})


# ----------------------------------------------------------------------------- host


def _light_inputs(fn: str, frames: wp.array, contrast: wp.array, uv: wp.array, white: int, black: int,
                  pairs: list[tuple[int, int]]) -> tuple[int, list]:
    """(n, the kernels' first inputs: frames, contrast, uv; then planes, pairs, scale), checked."""
    n = check_array("uv", uv, None, wp.vec2, fn)
    if not isinstance(frames, wp.array) or frames.ndim != 3 or frames.dtype not in (wp.uint8, wp.uint16):
        raise ValueError(f"{fn}: frames must be a (F, H, W) uint8/uint16 Warp array")
    if not isinstance(contrast, wp.array) or contrast.dtype != wp.float32 or tuple(contrast.shape) != tuple(
            frames.shape[1:]):
        raise ValueError(f"{fn}: contrast must be a {tuple(frames.shape[1:])} float32 Warp array")
    if not 1 <= len(pairs) <= MAX_INDIRECT_BITS:
        raise ValueError(f"{fn}: 1 to {MAX_INDIRECT_BITS} frame pairs, got {len(pairs)}")
    scale = 257.0 if frames.dtype == wp.uint16 else 1.0
    idx = wp.array(np.asarray(pairs, np.int32).reshape(-1), dtype=wp.int32, device=frames.device)
    return n, [frames, contrast, uv, wp.vec4i(int(white), int(black), len(pairs), 0), idx, wp.float64(scale)]


def sample_light(frames: wp.array, contrast: wp.array, uv: wp.array, *, white: int, black: int,
                 pairs: list[tuple[int, int]], edge_num: float,
                 threads: int | None = None) -> tuple[wp.array, wp.array, wp.array]:
    """((n,) float32 edge sigma, (n,) float32 indirect share, (n,) float32 shading) of the samples at
    ``uv``, on the frames' device (:func:`sample_light_kernel`).

    Args:
        frames: (F, H, W) uint8/uint16 the view's frames.
        contrast: (H, W) float32 white - black (the decode's ``RingLabels.contrast``).
        uv: (n,) vec2 the samples' camera positions.
        white, black: the frames' indices of the white and black frames.
        pairs: (frame, inverse) indices of the band bits whose floor measures the indirect light.
        edge_num: sqrt(2) x the camera noise x the edge's width (``angle_code.edge_sigma``'s numerator).
        threads: CPU threads; default all cores.
    """
    n, inputs = _light_inputs("sample_light", frames, contrast, uv, white, black, pairs)
    return _launch_light(sample_light_kernel, n, inputs + [wp.float64(edge_num)], frames.device, threads)


def phase_light(frames: wp.array, contrast: wp.array, uv: wp.array, modulation: wp.array, *, white: int, black: int,
                pairs: list[tuple[int, int]], noise: float, pitch: float, steps: int, smooth_radius: int,
                threads: int | None = None) -> tuple[wp.array, wp.array, wp.array]:
    """((n,) float32 sigma of rho from the radial phase, (n,) float32 indirect share, (n,) float32
    shading) of phase-rings' samples at ``uv`` with fringe ``modulation`` ((n,) float32), on the frames' device
    (:func:`phase_light_kernel`; ``angle_code.phase_sigma`` with ``sample_contrast`` and
    ``sample_indirect`` state it in NumPy). ``noise``, ``pitch``, ``steps``, ``smooth_radius``: as
    ``phase_sigma``'s; the others as :func:`sample_light`'s.

    Size: :func:`sample_light`'s arguments, with the fringes' modulation and the four numbers of their
    sigma (the camera noise, the pitch, the steps and the smoothing's radius) in place of its one."""
    n, inputs = _light_inputs("phase_light", frames, contrast, uv, white, black, pairs)
    check_array("modulation", modulation, n, wp.float32, "phase_light")
    num = pitch / (2 * math.pi) * math.sqrt(2.0 / steps) * noise  # (phase_sigma's order of operations)
    inputs = inputs[:3] + [modulation] + inputs[3:] + [wp.vec2d(num, float(2 * smooth_radius + 1))]
    return _launch_light(phase_light_kernel, n, inputs, frames.device, threads)


def _launch_light(kernel, n: int, inputs: list, dev, threads: int | None) -> tuple[wp.array, wp.array, wp.array]:
    out = [wp.empty(n, dtype=wp.float32, device=dev) for _ in range(3)]  # sigma, indirect, shading
    if n:
        launch_spans(kernel, n, lambda i0: inputs + [i0], out, dev, default_threads() if threads is None else threads)
    return out[0], out[1], out[2]
