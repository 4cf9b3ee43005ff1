"""The angle code, an add-on of ``gray-rings`` and ``phase-rings`` (``angle_steps`` > 0):
frames ``angle_<n>`` of phase-shifted angular fringes around the pattern centre
(drawn by ``codecs.drawing``), decoded per sample by ``kernels.angle`` so that every sample carries its polar
angle and both standard deviations (docs/dense.md, "The angle code"; the
triangulation that uses them: docs/reconstruction.md, "Rings and angle").

Also the ring coordinate's own standard deviation of the two codecs (the edge of a
band: noise over the slope of a frame and its inverse; the radial phase: the
N-step formula), which the triangulation weighs against the angle's.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ringscan.kernels.angle import ANGLE_STATUS_NAMES, decode_angle
from ringscan.kernels.compact import count_values, median, percentile32
from ringscan.kernels.response import response_tables
from ringscan.kernels.sample_light import (
    CLEAR_PAIR_TENTHS,
    NOISE_RADIUS,
    NOISE_STRIDE,
    sample_pair_noise,
    widen_for_pair_noise,
)
from ringscan.kernels.samples import Samples
from ringscan.kernels.settings import AngleSettings
from ringscan.pipeline.formats.patterns import PatternSpec, frame_names, spec_angle_zones
from ringscan.pipeline.formats.scan import Scan

__all__ = ["sample_indirect", "indirect_bits", "add_angle", "edge_sigma", "phase_sigma", "sample_contrast",
           "EDGE_WIDTH_PX", "noise_pairs", "pair_noise", "widen_for_frame_noise"]

EDGE_WIDTH_PX = 3.0
"""Width (projector px) over which a band edge goes from dark to lit, for the edge's
predicted standard deviation: the frames' one-pixel box filter widened by the
projector's defocus (a Gaussian of sigma 0.7 px, the virtual rig's default and a
sharp real projector's, spreads a box edge's 10-90 % rise over ~2.8 px). With 1 px
the virtual rig's edges scatter three times their prediction."""

MIN_PERIOD_CAMERA_PX = 2.5
"""Camera px the angle code's least period should span in the middle of the rig's volume; below it the view
warns with the ``--angle-period`` this camera needs. Finer fringes fade (the lens and the pixel's area) or,
under sharp optics, alias: the default patterns (periods of 8-16 projector px) on the sphere with a camera at a
quarter of the default's resolution (1.7-3.4 camera px a period): on Mitsuba's render 0.0269 mm median, p95
0.119 mm (the fit drops the faded fringes for their modulation), with ``--angle-period 16`` 0.0204 mm, p95
0.081; on ringscan's sharper render the aliases stay and put 11 % of the points beyond 3 sigma (16: 1.7 %).
Nothing is dropped for it: a period's reach in the camera changes across a view, and on Mitsuba's render leaving
out the angles of the periods under 2.5 px by the mid-volume figure cost 0.0269 -> 0.0356 mm."""


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = img.shape
    x = np.clip(uv[:, 0], 0, w - 1.001)
    y = np.clip(uv[:, 1], 0, h - 1.001)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    # flat indices and take(): the same values as img[y0, x0] etc., ~3x faster than fancy indexing
    flat = np.ascontiguousarray(img).reshape(-1)
    i = y0 * w + x0
    a = flat.take(i) * (1 - fx) + flat.take(i + 1) * fx
    i += w
    b = flat.take(i) * (1 - fx) + flat.take(i + 1) * fx
    return a * (1 - fy) + b * fy


def sample_contrast(frames: wp.array, spec: PatternSpec, uv: np.ndarray, *,
                    contrast: wp.array | None = None) -> np.ndarray:
    """White - black (8-bit levels) at each sample's camera position.

    ``contrast``: the decode's own (H, W) float32 white - black plane
    (``RingLabels.contrast``: the same values), where the caller has it; else the
    two frames are converted here (~2 ms a full-size view)."""
    names = frame_names(spec)
    scale = 257.0 if frames.dtype == wp.uint16 else 1.0
    if contrast is not None:
        return _bilinear(contrast.numpy(), uv) / scale
    white = frames[names.index("white")].numpy().astype(np.float32)
    black = frames[names.index("black")].numpy().astype(np.float32)
    return _bilinear(white - black, uv) / scale


INDIRECT_BITS = 2
"""The finest band bits whose pattern/inverse floor measures a sample's indirect light
(:func:`sample_indirect`): the finer a pattern, the more evenly bounced light fills
both halves of it."""


def sample_indirect(frames: wp.array, spec: PatternSpec, uv: np.ndarray) -> np.ndarray:
    """(n,) float32 :attr:`~ringscan.kernels.samples.Samples.indirect` at each sample's
    nearest camera pixel: the mean over the ``INDIRECT_BITS`` finest band bits of
    (min(pattern, inverse) - black) / (white - black), clipped to 0..1."""
    names = frame_names(spec)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    h, w = frames.shape[1], frames.shape[2]
    x = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)

    def at(name):
        return frames[names.index(name)].numpy()[y, x].astype(np.float32)

    black = at("black")
    span = np.maximum(at("white") - black, 1.0)
    floor = np.mean([np.minimum(at(f"gray_{b}"), at(f"gray_{b}_inv")) for b in indirect_bits(spec)], axis=0) - black
    return np.clip(floor / span, 0.0, 1.0).astype(np.float32)


def indirect_bits(spec: PatternSpec) -> range:
    """The band bits whose pattern / inverse floor measures a sample's indirect light: the
    ``INDIRECT_BITS`` finest, the finest first."""
    return range(spec.bits - 1, max(spec.bits - 1 - INDIRECT_BITS, -1), -1)


def noise_pairs(spec: PatternSpec) -> list[tuple[int, int]]:
    """The (frame, inverse) indices of every band bit: the pairs a sample's frame noise is measured over
    (:func:`widen_for_frame_noise`)."""
    names = frame_names(spec)
    return [(names.index(f"gray_{b}"), names.index(f"gray_{b}_inv")) for b in range(spec.bits)]


def pair_noise(frames: np.ndarray, uv: np.ndarray, white: int, black: int, pairs: list[tuple[int, int]],
               radius: int = NOISE_RADIUS) -> np.ndarray:
    """(n,) float32 each sample's frame noise (8-bit levels) around its nearest pixel, the NumPy statement
    of ``kernels.sample_light.sample_pair_noise`` (the same sums in the same order): at every other pixel
    of every other row (``NOISE_STRIDE``), s_j = frame_j + inverse_j of the pairs that stand clear
    (10 |frame - inverse| >= 9 (white - black)), their squared deviations from their mean summed (float32;
    0 with fewer than two) with their count - 1; both summed over the (2 radius + 1)^2 such pixels nearest
    the sample (uv / 2 rounded) inside the image; sqrt(sum / count / 2), over 257 for 16-bit frames.
    ``frames`` (F, H, W) uint8/uint16."""
    f = np.asarray(frames)[:, ::NOISE_STRIDE, ::NOISE_STRIDE]
    scale = 257.0 if f.dtype == np.uint16 else 1.0
    h, w = f.shape[1], f.shape[2]
    span = CLEAR_PAIR_TENTHS * (f[white].astype(np.int64) - f[black].astype(np.int64))
    s1, s2, used = np.zeros((h, w), np.int64), np.zeros((h, w), np.int64), np.zeros((h, w), np.int64)
    for a, b in pairs:
        fa, fb = f[a].astype(np.int64), f[b].astype(np.int64)
        on = (10 * np.abs(fa - fb) >= span).astype(np.int64)
        s1 += on * (fa + fb)
        s2 += on * (fa + fb) * (fa + fb)
        used += on
    two = used >= 2
    with np.errstate(invalid="ignore", divide="ignore"):
        q = (used * s2 - s1 * s1).astype(np.float64) / np.maximum(used, 1).astype(np.float64)
    ss = np.where(two, q.astype(np.float32), np.float32(0.0))
    dof = np.where(two, used - 1, 0)
    uv = np.asarray(uv, np.float32).reshape(-1, 2).astype(np.float64)
    px = np.clip(np.rint(uv[:, 0] / NOISE_STRIDE).astype(np.int64), 0, w - 1)
    py = np.clip(np.rint(uv[:, 1] / NOISE_STRIDE).astype(np.int64), 0, h - 1)
    total, count = np.zeros(len(uv)), np.zeros(len(uv), np.int64)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            y, x = py + dy, px + dx
            inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
            yc, xc = np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)
            total = np.where(inside, total + ss[yc, xc].astype(np.float64), total)
            count += np.where(inside, dof[yc, xc], 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(count > 0, np.sqrt(total / np.maximum(count, 1) / 2.0) / scale, 0.0)
    return out.astype(np.float32)


NOISE_STAT_PERCENT = 90
"""The percentile of the samples' measured noise a view reports beside its median."""


def widen_for_frame_noise(frames: wp.array, spec: PatternSpec, samples: Samples, *, noise: float,
                          threads: int) -> dict:
    """Each sample's standard deviations (``sigma_rho``, and ``sigma_tan`` where set) times its pixel's
    measured frame noise over the view's, where that is larger: the decode's model carries one noise for
    the view (``angle.noise``, which the error model's fit then scales to what the frames show), but a
    camera's noise is not even (shot noise grows with the light; light bounced into a concave part, or a
    renderer's Monte Carlo, adds its own), and a sample in a noisier part errs more than the view's one
    number says. Measured from the frames themselves (:func:`pair_noise`, every band bit's pair over the
    5 x 5 pixels of every other row and column around it), against the view's median (floored at
    ``noise``, for near-noiseless frames); never narrowed. On the samples' device; returns the view's
    stats ``frame_noise``: median and 90th percentile, levels."""
    pairs = noise_pairs(spec)
    if len(pairs) < 2 or len(samples) == 0 or samples.sigma_rho is None:
        return {}
    names = frame_names(spec)
    m = sample_pair_noise(frames, samples.uv, white=names.index("white"), black=names.index("black"), pairs=pairs,
                          threads=threads)
    mid = median(m)
    reference = max(mid, float(noise))
    samples.sigma_rho, samples.sigma_tan = widen_for_pair_noise(m, [samples.sigma_rho, samples.sigma_tan],
                                                                reference=reference, threads=threads)
    return {"frame_noise": {"median_levels": round(mid, 3),
                            f"p{NOISE_STAT_PERCENT}_levels": round(percentile32(m, NOISE_STAT_PERCENT), 3)}}


def edge_sigma(contrast: np.ndarray, noise: float) -> np.ndarray:
    """Standard deviation (projector px) of a band edge sampled where a frame
    crosses its inverse: the difference of the two rises by 2 x contrast over
    ``EDGE_WIDTH_PX`` and carries sqrt(2) x the camera noise."""
    return np.sqrt(2.0) * noise * EDGE_WIDTH_PX / (2.0 * np.maximum(contrast, 1.0))


def phase_sigma(contrast: np.ndarray, modulation: np.ndarray, noise: float, *, pitch: float, steps: int,
                smooth_radius: int = 0) -> np.ndarray:
    """Standard deviation (projector px) of rho from the radial phase: the N-step
    formula, sqrt(2 / N) sigma / amplitude radians of a period of ``pitch`` px,
    over the square root of the pixels the phase smoothing averages (its window,
    (2 r + 1)^2, where every neighbour pair agrees)."""
    amp = 0.5 * np.maximum(modulation, 1e-3) * np.maximum(contrast, 1.0)
    return pitch / (2 * math.pi) * math.sqrt(2.0 / steps) * noise / amp / (2 * smooth_radius + 1)


def add_angle(frames: wp.array, scan: Scan, samples: Samples, *, sigma_rho: wp.array | np.ndarray, settings: AngleSettings,
              camera_gamma: float, light_gamma: float, threads: int) -> tuple[Samples, dict]:
    """The samples with their standard deviations, and their polar angle where
    the pattern has an angle code.

    Args:
        frames: (F, H, W) the view's frames (read).
        scan: the scan (patterns).
        samples: the codec's samples (uv, rho, sector set).
        sigma_rho: (n,) the ring coordinate's standard deviation (projector px): float32 Warp
            array on the frames' device (kept as it is) or NumPy.
        settings: the angle decoder's settings.
        camera_gamma, light_gamma: the responses to undo (1: linear).
        threads: CPU threads.

    Returns:
        (samples with ``sigma_rho`` and, with an angle code, ``phi`` (NaN where it
        did not decode) and ``sigma_tan``; stats ``angle_decoded`` and
        ``angle_dropped`` by reason, and where the least period spans fewer than
        ``MIN_PERIOD_CAMERA_PX`` camera px mid-volume ``angle_period_camera_px``, what it spans).
    """
    spec = scan.patterns
    dev = frames.device
    samples.sigma_rho = (sigma_rho if isinstance(sigma_rho, wp.array) else
                         wp.array(np.asarray(sigma_rho, np.float32), dtype=wp.float32, device=dev))
    if not spec.angle_steps:
        return samples, {}
    if len(samples) == 0:  # none to decode, but an angle code: the samples have one, of none
        samples.phi = wp.empty(0, dtype=wp.float32, device=dev)
        samples.sigma_tan = wp.empty(0, dtype=wp.float32, device=dev)
        return samples, {"angle_decoded": 0, "angle_dropped": {k: 0 for k in ANGLE_STATUS_NAMES[1:]}}
    from ringscan.pipeline.geometry import projector_px_span  # (cv2's import: only where a view is decoded)

    names = frame_names(spec)
    full = 255 if frames.dtype == wp.uint8 else 65535
    lut, _ = response_tables(full, camera_gamma=camera_gamma, weighted=False)
    # what the least period spans in the camera mid-volume (1 camera px a projector px where the rig cannot say)
    least = float(spec.angle_period) * projector_px_span(scan.rig)
    res = decode_angle(frames, samples.uv, samples.rho, samples.sector, white=names.index("white"),
                       black=names.index("black"), angle0=names.index("angle_0"), steps=spec.angle_steps,
                       sector_bits=spec.sector_bits, zones=spec_angle_zones(spec),
                       lut=wp.array(lut, dtype=wp.float32, device=dev), light_gamma=light_gamma,
                       sector0=names.index("sector_0") if spec.sector_bits else -1,
                       settings=settings, threads=threads)
    samples.phi = res.phi
    samples.sigma_tan = res.sigma_tan
    counts = count_values(res.status, len(ANGLE_STATUS_NAMES), threads=threads)  # counted on the device
    stats = {"angle_decoded": int(counts[0]),
             "angle_dropped": {k: int(counts[i]) for i, k in enumerate(ANGLE_STATUS_NAMES) if i > 0}}
    if least < MIN_PERIOD_CAMERA_PX:
        stats["angle_period_camera_px"] = round(least, 2)  # (for the view's warning)
    return samples, stats
