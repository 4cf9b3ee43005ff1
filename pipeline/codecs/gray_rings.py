"""The ``gray-rings`` codec (docs/design.md §7): decode the band Gray code per pixel, then
sample every band boundary to sub-pixel precision where the frame that flips there
crosses its inverse (``kernels.ring_labels``, ``kernels.ring_sampling``)."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ringscan.kernels.ring_labels import count_labels, decode_gray_rings
from ringscan.kernels.ring_sampling import sample_gray_rings
from ringscan.kernels.sample_light import sample_light
from ringscan.kernels.samples import Samples
from ringscan.kernels.settings import AngleSettings, DecodeSettings, SampleSettings
from ringscan.pipeline.codecs.angle_code import EDGE_WIDTH_PX, add_angle, indirect_bits, widen_for_frame_noise
from ringscan.pipeline.codecs.base import Codec, StageSettings, describe_lighting, frame_bits_hint
from ringscan.pipeline.codecs.drawing import draw_frame
from ringscan.pipeline.formats.patterns import PATTERN_LAYOUTS, PatternSpec, frame_names
from ringscan.pipeline.formats.scan import Scan

log = logging.getLogger(__name__)

__all__ = ["NAME", "GrayRingsCodec", "GrayRingsSettings", "extract_gray_rings", "explain_binary_view",
           "low_modulation_pixels"]

NAME = "gray-rings"
"""The codec's name (scan.json ``patterns.codec``): what code outside the codec spells it by."""

MIN_OVERSAMPLING = 1.5
"""Camera px a projector px spans (``pipeline.geometry.projector_px_span``) above which the sampler's ``min_slope`` is taken per
projector px, not per camera px: a camera zoomed 3x on the default rig's projector found 1.4 % of its edges, 4x
none. At most 1.5 (the default rig: 0.9) nothing changes."""
ERROR_GROUPS = 3
"""Edges grouped by the pattern that places them (:meth:`GrayRingsCodec.error_groups`): the
finest, the next, and every coarser one together (an eighth of the samples and fewer each)."""


@dataclass(frozen=True)
class GrayRingsSettings:
    """Settings of the ``gray-rings`` codec."""

    decode: DecodeSettings = field(default_factory=DecodeSettings)
    """Per-pixel decoding thresholds."""
    sample: SampleSettings = field(default_factory=SampleSettings)
    """Sub-pixel edge sampler thresholds."""
    angle: AngleSettings = field(default_factory=AngleSettings)
    """The angle code's decoder (with ``angle_steps`` > 0) and the camera noise of
    every sample's predicted standard deviation."""


def low_modulation_pixels(labels, *, bits: int, min_contrast: float) -> tuple[int, int]:
    """(low, lit): of the ``lit`` pixels (white - black >= ``min_contrast``, recorded
    levels), the ``low`` ones whose finest band bit is weak (``labels.weak`` bit 0) while
    their coarsest is strong, away from that bit's own edges (no two opposite neighbours
    with the finest bit strong and different): a finest bit that barely modulates there
    (a far, dark, grazing or defocused surface), whose rings are not found. A pixel on
    one of the finest bit's edges is weak in that bit by design and is not counted.

    labels: :class:`~ringscan.kernels.ring_labels.RingLabels` of ``bits`` band bits,
    read to the host (weak, code, contrast)."""
    weak = labels.weak.numpy()
    code = labels.code.numpy()
    lit = labels.contrast.numpy() >= min_contrast
    finest_weak = (weak & 1) != 0
    strong = lit & ~finest_weak
    bit = code & 1
    edge = np.zeros_like(finest_weak)
    h, w = weak.shape
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        # neighbours p - (dy, dx) and p + (dy, dx) of every pixel p inside the frame
        ys, xs = slice(dy, h - dy), slice(max(dx, -dx), w - max(dx, -dx))
        a = (slice(0, h - 2 * dy), slice(max(0, -2 * dx), w - max(0, 2 * dx)))
        b = (slice(2 * dy, h), slice(max(0, 2 * dx), w - max(0, -2 * dx)))
        edge[ys, xs] |= strong[a] & strong[b] & (bit[a] != bit[b])
    coarse_strong = (weak & (1 << (bits - 1))) == 0
    return int(np.count_nonzero(lit & finest_weak & coarse_strong & ~edge)), int(np.count_nonzero(lit))


def explain_binary_view(frames: np.ndarray, spec: PatternSpec, stats: dict, decode: DecodeSettings, *,
                        frame_bits: int | None = None) -> str | None:
    """Why a view of a white/black-framed codec gave no point, from its white and
    black frames, or None where they do not tell (``frame_bits``: the scan's, for the
    hint that dark 16-bit frames may want it)."""
    frames = np.asarray(frames)
    names = frame_names(spec)
    full = 65535.0 if frames.dtype == np.uint16 else 255.0
    brightest = int(frames[names.index("white")].max())
    white = frames[names.index("white")].astype(np.float32)
    black = frames[names.index("black")].astype(np.float32)
    thr = decode.min_contrast * full / 255.0
    lit = int(np.count_nonzero(white - black >= thr))
    if lit == 0:
        return (f"no ring found: no contrast between the white and black frames (white - black is below "
                f"{thr:g} grey levels at every pixel; white {white.mean():.0f}, black {black.mean():.0f} on "
                f"average): {describe_lighting(float(black.mean()), float(white.mean()), full)}"
                f"{frame_bits_hint(brightest, frames.dtype, frame_bits)}")
    if stats.get("pixels_decoded", 0) == 0:
        return (f"no ring found: {lit} pixels have contrast, but none decodes to a ring band (every bit too "
                f"weak: check the frame order and the exposure)")
    return None


def extract_gray_rings(frames: wp.array, scan: Scan, settings: GrayRingsSettings, threads: int) -> tuple[Samples, dict]:
    """Decode + sampling of one view of a ``gray-rings`` scan.

    Args:
        frames: (F, H, W) uint8/uint16 Warp stack in the order of the scan's frame names (read).
        scan: the scan (its patterns give bits, sector bits, rho0 and pitch).
        settings: the codec's settings.
        threads: CPU threads for the row-run kernels.

    Returns:
        (samples, stats) with stats ``pixels_decoded``, ``samples`` and ``times_s``.
    """
    spec = scan.patterns
    t0 = time.perf_counter()
    labels = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits, settings=settings.decode,
                               threads=threads)
    wp.synchronize_device(frames.device)
    t1 = time.perf_counter()
    from ringscan.pipeline.geometry import projector_px_span  # (cv2's import: only where a view is decoded)

    span = projector_px_span(scan.rig)
    sample = settings.sample
    if span > MIN_OVERSAMPLING:
        # a projector px spread over `span` camera px: an edge's step between two neighbouring pixels is that
        # much flatter at the same sharpness against the band (what min_slope judges)
        sample = dataclasses.replace(sample, min_slope=sample.min_slope / span)
    samples = sample_gray_rings(frames, labels, bits=spec.bits, settings=sample, threads=threads,
                                rho0=spec.rho0, pitch=spec.pitch)
    wp.synchronize_device(frames.device)
    t2 = time.perf_counter()
    # the view's counts on the frames' device: decoded pixels, lit ones, and the lit ones whose finest bit
    # barely modulates (low_modulation_pixels states the test in NumPy)
    decoded, lit, low = count_labels(labels, bits=spec.bits,
                                     min_contrast=_recorded(settings.decode.min_contrast, frames), threads=threads)
    if decoded == 0 and len(samples):
        # Edges sampled where no pixel decodes (every pixel below decode.min_contrast, every bit weak) carry
        # a ring index no band label confirms and no sector: no point may come of them.
        log.info("%d edge samples, but no pixel decoded to a ring band: none kept", len(samples))
        samples = _no_samples(samples)
    # each edge's sigma from the contrast under it and its indirect-light share, on the frames' device
    # (angle_code.edge_sigma, sample_contrast and sample_indirect state them in NumPy)
    names = frame_names(spec)
    sigma_rho, indirect, shading = sample_light(
        frames, labels.contrast, samples.uv, white=names.index("white"), black=names.index("black"),
        pairs=[(names.index(f"gray_{b}"), names.index(f"gray_{b}_inv")) for b in indirect_bits(spec)],
        edge_num=np.sqrt(2.0) * settings.angle.noise * EDGE_WIDTH_PX, threads=threads)
    rig = scan.rig
    samples, angle_stats = add_angle(frames, scan, samples, sigma_rho=sigma_rho,
                                     settings=settings.angle, camera_gamma=float(rig.camera.gamma),
                                     light_gamma=float(getattr(rig.light, "gamma", 1.0)) / spec.precompensated_gamma,
                                     threads=threads)
    samples.indirect = indirect
    samples.shading = shading
    noise_stats = widen_for_frame_noise(frames, spec, samples, noise=settings.angle.noise, threads=threads)
    wp.synchronize_device(frames.device)
    t3 = time.perf_counter()
    stats = {"pixels_decoded": decoded, "samples": len(samples), "pixels_lit": lit, "low_modulation": low,
             **angle_stats,
             **noise_stats,
             "times_s": {"decode": t1 - t0, "sample": t2 - t1, "angle": t3 - t2}}
    return samples, stats


def _recorded(levels: float, frames: wp.array) -> float:
    """8-bit grey levels in the frames' recorded units (x257 for 16-bit)."""
    return levels * (257.0 if frames.dtype == wp.uint16 else 1.0)


def _no_samples(samples: Samples) -> Samples:
    """Samples of the same fields, dtypes and device, none of them."""
    def empty(a):
        return None if a is None else wp.empty(0, dtype=a.dtype, device=a.device)

    return Samples(**{f.name: empty(getattr(samples, f.name)) for f in dataclasses.fields(samples)})


class GrayRingsCodec(Codec[GrayRingsSettings]):
    """Gray-coded ring bands (``bits``), optional Gray-coded sectors (``sector_bits``)
    and angle code (``angle_steps``): frames ``white``, ``black``,
    ``gray_<b>``/``gray_<b>_inv``, ``sector_<b>``/``sector_<b>_inv``, ``angle_<n>``."""

    layout = PATTERN_LAYOUTS[NAME]
    settings_type = GrayRingsSettings

    def render_frame(self, spec: PatternSpec, name: str) -> np.ndarray:
        return draw_frame(spec, name)

    def full_coordinate(self, spec: PatternSpec) -> bool:
        return spec.angle_steps > 0  # the polar angle comes from the angle code only

    def settings_from(self, stages: StageSettings) -> GrayRingsSettings:
        return GrayRingsSettings(decode=stages.decode, sample=stages.sample, angle=stages.angle)

    def extract(self, frames: wp.array, scan: Scan, settings: GrayRingsSettings, *,
                threads: int) -> tuple[Samples, dict]:
        return extract_gray_rings(frames, scan, settings, threads)

    def error_groups(self, spec: PatternSpec, ring: np.ndarray) -> np.ndarray:
        """The band bit whose frame pair places each edge: at boundary k it is the bit
        that flips between the Gray codes of bands k - 1 and k (the lowest set bit of
        k): 0 the finest pattern (every other edge), 1 the next, 2 every coarser one (-1:
        boundary 0). The finest pattern is the first to wash out (a far, faint or
        defocused surface: its edges' errors 1.5x the others' on ringscan's far faint
        plane), and its edges are half the samples."""
        k = np.asarray(ring, np.int64)
        low = k & -k  # the lowest set bit of k
        bit = np.where(k > 0, np.log2(np.maximum(low, 1)).astype(np.int64), -1)
        return np.where(bit >= 0, np.minimum(bit, ERROR_GROUPS - 1), -1)

    def explain_no_points(self, frames: np.ndarray, scan: Scan, stats: dict, settings: GrayRingsSettings) -> str | None:
        return explain_binary_view(frames, scan.patterns, stats, settings.decode, frame_bits=scan.frame_bits)
