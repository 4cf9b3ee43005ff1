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

from ringscan.kernels.launch import check_array, default_threads, launch_rows, launch_spans, row_run
from ringscan.kernels.light_gradient import shading_at

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["sample_light_kernel", "phase_light_kernel", "pair_sums_kernel", "pair_noise_kernel", "noise_widen_kernel",
           "sample_light", "phase_light", "sample_pair_noise", "widen_for_pair_noise"]

MAX_INDIRECT_BITS = 4
"""Most band bits whose pattern / inverse floor a sample's indirect share averages."""
NOISE_STRIDE = 2
"""A sample's frame noise is read on every other pixel in x and y (a quarter of the pixels: summing 7 pairs at
every pixel of a full-size view took 60 ms on one thread, this ~15)."""
NOISE_RADIUS = 2
"""... over the (2 r + 1)^2 such pixels nearest it (5 x 5 of them, 9 x 9 camera px: with a code's 7 band
pairs ~150 degrees of freedom, its noise to ~6 %)."""
MAX_NOISE_PAIRS = 32
"""Most frame pairs a sample's noise is measured over."""
CLEAR_PAIR_TENTHS = 9
"""A pair measures the noise at a pixel where |frame - inverse| is at least this many tenths of white - black: on
a blurred edge the two mix, and a camera's response curve (or a renderer's) makes their sum differ from the
unmixed one by far more than the noise (gamma 2.2 at a 90 / 10 mix: 30 % of the span); at 0.9 the virtual
rig's frames read their own noise (1.8 levels for 1.5 rendered; 6.3 where 6 more were added)."""
CLEAR_TENTHS = wp.constant(CLEAR_PAIR_TENTHS)
NOISE_STEP = wp.constant(NOISE_STRIDE)


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


@wp.kernel
def pair_sums_kernel(
    frames: wp.array3d(dtype=Any),
    planes: wp.vec4i,
    pairs: wp.array(dtype=wp.int32),
    row0: int,
    chunk: int,
    spread: wp.array2d(dtype=wp.vec2),
):
    """Every ``NOISE_STRIDE``-th pixel's spread of its clear pairs' sums (in x and y: grid pixel (gy, gx) is
    camera pixel (2 gy, 2 gx)), ``chunk`` grid pixels of one grid row per thread: where a pair
    stands clear (10 |frame - inverse| >= ``CLEAR_PAIR_TENTHS`` x (white - black): the one lit, the other dark,
    away from the pair's edges), frame + inverse is the same light whatever the pattern and whatever the
    camera's response, so the clear pairs' sums s_j differ by the noise alone: ss = sum_j (s_j - mean)^2 =
    (m sum s_j^2 - (sum s_j)^2) / m over the m clear pairs (integer sums, the quotient in float64, then
    float32) and dof = m - 1 (both 0 with fewer than two clear pairs).

    frames (F, H, W) uint8/uint16, pairs (2 k,) int32 frame indices (frame, inverse, ...): read; ``planes``:
    (white, black, 0, 0). spread (ceil(H / 2), ceil(W / 2)) vec2 (ss, dof: one read a grid pixel for the
    samples' windows): written.
    ``angle_code.pair_noise``
    states it in NumPy, the same sums in the same order."""
    run = row_run(wp.tid(), spread.shape[1], row0, chunk)
    gy = run[0]
    y = gy * NOISE_STEP
    k = pairs.shape[0] / 2
    for gx in range(run[1], run[2]):
        x = gx * NOISE_STEP
        # in whole levels (exact, and ~3x faster than float64): clear where 10 |a - b| >= 9 (white - black)
        span = CLEAR_TENTHS * (int(frames[planes[0], y, x]) - int(frames[planes[1], y, x]))
        s1 = wp.int64(0)
        s2 = wp.int64(0)
        used = int(0)
        for j in range(k):
            a = int(frames[pairs[2 * j], y, x])
            b = int(frames[pairs[2 * j + 1], y, x])
            on = wp.where(10 * wp.abs(a - b) >= span, 1, 0)
            s1 += wp.int64(on * (a + b))
            s2 += wp.int64(on * (a + b)) * wp.int64(a + b)
            used += on
        if used >= 2:
            # (used s2 - s1^2) / used: the sum of squared deviations, its numerator exact
            spread[gy, gx] = wp.vec2(wp.float32(wp.float64(wp.int64(used) * s2 - s1 * s1) / wp.float64(float(used))),
                                     wp.float32(used - 1))
        else:
            spread[gy, gx] = wp.vec2(0.0, 0.0)


@wp.kernel
def pair_noise_kernel(
    spread: wp.array2d(dtype=wp.vec2),
    uv: wp.array(dtype=wp.vec2),
    radius: int,
    scale: wp.float64,
    i0: int,
    noise: wp.array(dtype=wp.float32),
):
    """Sample i0 + tid's frame noise (8-bit levels): the grid pixels' spreads (:func:`pair_sums_kernel`)
    pooled over the (2 radius + 1)^2 grid pixels around its nearest one (uv / 2 rounded; those inside the
    image), sqrt(sum ss / sum dof / 2) (Var(frame + inverse) = 2 noise^2) over ``scale``; 0 where no pixel
    there has two clear pairs.

    spread (grid) vec2, uv (n,) vec2: read. noise (n,) float32: written."""
    i = i0 + wp.tid()
    h = spread.shape[0]
    w = spread.shape[1]
    step = wp.float64(float(NOISE_STEP))
    px = wp.min(wp.max(int(wp.rint(wp.float64(uv[i][0]) / step)), 0), w - 1)
    py = wp.min(wp.max(int(wp.rint(wp.float64(uv[i][1]) / step)), 0), h - 1)
    total = wp.float64(0.0)
    count = float(0.0)  # (whole numbers, exact in float32 up to 2^24)
    for y in range(wp.max(py - radius, 0), wp.min(py + radius + 1, h)):
        for x in range(wp.max(px - radius, 0), wp.min(px + radius + 1, w)):
            c = spread[y, x]
            total += wp.float64(c[0])
            count += c[1]
    out = wp.float64(0.0)
    if count > 0.0:
        out = wp.sqrt(total / wp.float64(count) / wp.float64(2.0)) / scale
    noise[i] = wp.float32(out)


@wp.kernel
def noise_widen_kernel(
    noise: wp.array(dtype=wp.float32),
    sigma: wp.array(dtype=wp.float32),
    reference: wp.float64,
    i0: int,
    out: wp.array(dtype=wp.float32),
):
    """out = sigma x max(1, noise / reference) at sample i0 + tid (float64, then float32).

    noise, sigma (n,) float32: read. out (n,) float32: written."""
    i = i0 + wp.tid()
    f = wp.max(wp.float64(1.0), wp.float64(noise[i]) / reference)
    out[i] = wp.float32(wp.float64(sigma[i]) * f)


for _t in (wp.uint8, wp.uint16):
    wp.overload(sample_light_kernel, {"frames": wp.array3d(dtype=_t)})
    wp.overload(phase_light_kernel, {"frames": wp.array3d(dtype=_t)})
    wp.overload(pair_sums_kernel, {"frames": wp.array3d(dtype=_t)})


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


def sample_pair_noise(frames: wp.array, uv: wp.array, *, white: int, black: int, pairs: list[tuple[int, int]],
                      radius: int = NOISE_RADIUS, threads: int | None = None) -> wp.array:
    """(n,) float32 each sample's frame noise (8-bit levels) measured from its own frames: the pattern /
    inverse ``pairs`` (frame indices) that stand clear summed, over the (2 ``radius`` + 1)^2 pixels of every
    other row and column around it (:func:`pair_sums_kernel`, :func:`pair_noise_kernel`), on the frames'
    device.

    Args:
        frames: (F, H, W) uint8/uint16 the view's frames.
        uv: (n,) vec2 the samples' camera positions.
        white, black: the frames' indices of the white and black frames.
        pairs: (frame, inverse) indices, at least 2.
        radius: the window's half side, in grid pixels (``NOISE_STRIDE`` camera px each).
        threads: CPU threads; default all cores.
    """
    fn = "sample_pair_noise"
    n = check_array("uv", uv, None, wp.vec2, fn)
    if not isinstance(frames, wp.array) or frames.ndim != 3 or frames.dtype not in (wp.uint8, wp.uint16):
        raise ValueError(f"{fn}: frames must be a (F, H, W) uint8/uint16 Warp array")
    if not 2 <= len(pairs) <= MAX_NOISE_PAIRS:
        raise ValueError(f"{fn}: 2 to {MAX_NOISE_PAIRS} frame pairs, got {len(pairs)}")
    if not 0 <= int(radius) <= 8:
        raise ValueError(f"{fn}: radius must be 0..8 px, got {radius!r}")
    dev = frames.device
    th = default_threads() if threads is None else threads
    idx = wp.array(np.asarray(pairs, np.int32).reshape(-1), dtype=wp.int32, device=dev)
    h, w = -(-frames.shape[1] // NOISE_STRIDE), -(-frames.shape[2] // NOISE_STRIDE)
    spread = wp.empty((h, w), dtype=wp.vec2, device=dev)
    planes = wp.vec4i(int(white), int(black), 0, 0)
    out = wp.empty(n, dtype=wp.float32, device=dev)
    if n:
        # each grid pixel's spread once, then each sample's window of them (summing 7 pairs x 25 pixels a
        # sample instead took 125 ms a full-size view on one thread)
        launch_rows(pair_sums_kernel, h, w, lambda r0, c: [frames, planes, idx, r0, c], [spread], dev, th)
        scale = wp.float64(257.0 if frames.dtype == wp.uint16 else 1.0)
        launch_spans(pair_noise_kernel, n, lambda i0: [spread, uv, int(radius), scale, i0], [out], dev, th)
    return out


def widen_for_pair_noise(noise: wp.array, sigmas: list[wp.array | None], *, reference: float,
                         threads: int | None = None) -> list[wp.array | None]:
    """Each of ``sigmas`` ((n,) float32, None left as None) times max(1, ``noise`` / ``reference``), on
    their device (:func:`noise_widen_kernel`)."""
    n = check_array("noise", noise, None, wp.float32, "widen_for_pair_noise")
    if not reference > 0:
        raise ValueError(f"widen_for_pair_noise: reference must be > 0, got {reference!r}")
    out = []
    for s in sigmas:
        if s is None:
            out.append(None)
            continue
        check_array("sigma", s, n, wp.float32, "widen_for_pair_noise")
        o = wp.empty(n, dtype=wp.float32, device=s.device)
        if n:
            launch_spans(noise_widen_kernel, n, lambda i0, s=s: [noise, s, wp.float64(reference), i0], [o], s.device,
                         default_threads() if threads is None else threads)
        out.append(o)
    return out
