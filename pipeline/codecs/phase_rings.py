"""Dense reconstruction with phase-rings: a ring through every pixel (docs/design.md §7).

:func:`extract_phase_rings` is the ``phase-rings`` codec's decode + sampling stage
for :func:`ringscan.pipeline.reconstruct.reconstruct_scan`: it decodes the band
and sector Gray codes (``kernels.ring_labels``), the phase frames
(``kernels.phase``: linearisation, weighted N-step phase, unwrapping anchored at
band edges, smoothing) and hands one sample per valid camera pixel, in raster
order, to the triangulation (which meets each pixel's ray with the quadric of its
own continuous rho).

Response (gamma) handling, ``PhaseSettings.response``:

- ``rig`` (default): the rig file's ``camera.response.gamma`` linearises the
  recorded values and ``light.response.gamma`` is undone after normalising by the
  white and black frames;
- ``estimate``: the camera gamma is estimated from the view's own frames
  (:func:`estimate_camera_gamma`: the N phase samples of a clean fringe average
  to the middle of white and black only in linear units); the light gamma is
  still taken from the rig;
- ``linear``: no correction.

Frames pre-compensated for the light (``patterns.precompensated_gamma`` g_p,
``ringscan patterns --rig``) already emit the light the pattern means for a light
of gamma g_p; the decoder undoes only the residual exponent light gamma / g_p
(1 when the rig's light gamma is the one compensated for) in the ``rig`` and
``estimate`` modes.

This module also holds the vectorised NumPy twins of the dense stages
(:func:`phase_numpy`, :func:`smooth_numpy`, :func:`points_numpy`) that the tests
cross-check the kernels against and that :func:`bench_dense` times the kernels
against.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ringscan.kernels.compact import count_values
from ringscan.kernels.phase import (
    PHASE_STATUS_NAMES,
    compact_phase_points,
    decode_phase,
    drop_lone_fringes,
    smooth_phase,
)
from ringscan.kernels.response import response_tables
from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.sample_light import phase_light
from ringscan.kernels.samples import Samples
from ringscan.kernels.settings import AngleSettings, DecodeSettings, PhaseSettings
from ringscan.pipeline.codecs.angle_code import add_angle, indirect_bits, widen_for_frame_noise
from ringscan.pipeline.codecs.base import Codec, RigNeeds, StageSettings
from ringscan.pipeline.codecs.drawing import draw_frame
from ringscan.pipeline.codecs.gray_rings import explain_binary_view
from ringscan.pipeline.formats.patterns import PATTERN_LAYOUTS, PatternSpec, frame_names
from ringscan.pipeline.formats.scan import Scan

log = logging.getLogger(__name__)

GAMMA_RANGE = (0.3, 4.0)
"""Search interval of :func:`estimate_camera_gamma`."""

__all__ = ["NAME", "PhaseRingsCodec",
           "PhaseRingsSettings", "extract_phase_rings", "view_response", "residual_light_gamma",
           "estimate_camera_gamma", "PhaseSettings"]

NAME = "phase-rings"
"""The codec's name (scan.json ``patterns.codec``): what code outside the codec spells it by."""


@dataclass(frozen=True)
class PhaseRingsSettings:
    """Settings of the ``phase-rings`` codec."""

    decode: DecodeSettings = field(default_factory=DecodeSettings)
    """Per-pixel decoding thresholds of the band and sector codes."""
    phase: PhaseSettings = field(default_factory=PhaseSettings)
    """Phase decoder (response, modulation, unwrapping)."""
    angle: AngleSettings = field(default_factory=AngleSettings)
    """The angle code's decoder (with ``angle_steps`` > 0) and the camera noise of
    every sample's predicted standard deviation."""

    def __post_init__(self):
        if not isinstance(self.phase, PhaseSettings):
            raise ValueError(f"settings.phase: expected PhaseSettings, got {type(self.phase).__name__}")


def residual_light_gamma(scan: Scan) -> float:
    """The light exponent left in a scan's frames: the rig's light gamma over the
    gamma its patterns were pre-compensated for (1.0 when they match)."""
    light_gamma = float(getattr(scan.rig.light, "gamma", 1.0))
    pre = float(getattr(scan.patterns, "precompensated_gamma", 1.0))
    if pre != 1.0 and abs(light_gamma / pre - 1.0) > 0.05:
        log.warning("the patterns were pre-compensated for a light gamma of %.3g but the rig's light has %.3g: "
                    "decoding with the residual exponent %.3g", pre, light_gamma, light_gamma / pre)
    return light_gamma / pre


def view_response(frames: np.ndarray | wp.array, scan: Scan, settings: PhaseSettings) -> tuple[float, float]:
    """(camera gamma, light exponent) used to linearise one view (see the module docstring);
    the light exponent is :func:`residual_light_gamma`."""
    rig = scan.rig
    if settings.response == "linear":
        return 1.0, 1.0
    light_gamma = residual_light_gamma(scan)
    if settings.response == "rig":
        return float(rig.camera.gamma), light_gamma
    fr = frames.numpy() if isinstance(frames, wp.array) else np.asarray(frames)
    spec = scan.patterns
    return estimate_camera_gamma(fr, bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps,
                                 light_gamma=light_gamma), light_gamma


def estimate_camera_gamma(
    frames: np.ndarray,
    *,
    bits: int,
    sector_bits: int,
    steps: int,
    light_gamma: float = 1.0,
    min_contrast: float = 12.0,
    stride: int = 4,
) -> float:
    """Estimate the camera's gamma from a phase-rings view.

    For a clean fringe the linearised phase samples average to the middle of the
    linearised white and black, (1/N) sum_n v_n = 1/2 with
    v_n = ((L_n - L_b) / (L_w - L_b))^(1 / light_gamma) and L = (r / full)^g, and
    only for the right g (a wrong exponent bends the samples, and the bend does
    not average out). The estimate is the g in ``GAMMA_RANGE`` that minimises the
    mean squared departure over the pixels with contrast, unsaturated white and a
    strong fringe (every ``stride``-th row and column), by golden-section search.

    Args:
        frames: (n, H, W) uint8/uint16 frames of one view (``frame_names`` order).
        bits, sector_bits, steps: the pattern's parameters.
        light_gamma: the light's exponent (from the rig).
        min_contrast: least white - black (8-bit levels, x257 for 16-bit).
        stride: pixel subsampling.

    Raises:
        ValueError: too few usable pixels (fewer than 100).
    """
    fr = np.asarray(frames)
    if fr.ndim != 3 or fr.dtype not in (np.uint8, np.uint16):
        raise ValueError("estimate_camera_gamma: frames must be (n, H, W) uint8 or uint16")
    phase0 = 2 + 2 * bits + 2 * sector_bits
    if fr.shape[0] < phase0 + steps:
        raise ValueError(f"estimate_camera_gamma: expected {phase0 + steps} frames, got {fr.shape[0]}")
    full = 255.0 if fr.dtype == np.uint8 else 65535.0
    sub = fr[:, ::stride, ::stride].astype(np.float64) / full
    w, b, p = sub[0], sub[1], sub[phase0:phase0 + steps]
    ok = ((w - b) * full >= min_contrast * (full / 255.0)) & (w < 0.97) & (b > 0.5 / full)
    # a strong fringe: the phase samples spread over most of white - black
    ok &= (p.max(0) - p.min(0)) >= 0.5 * (w - b)
    if np.count_nonzero(ok) < 100:
        raise ValueError(f"estimate_camera_gamma: only {int(np.count_nonzero(ok))} usable pixels (need 100): "
                         "too little fringe contrast to estimate the response")
    w, b, p = w[ok], b[ok], p[:, ok]
    ig = 1.0 / float(light_gamma)

    def cost(g):
        lw, lb, lp = w ** g, b ** g, p ** g
        u = np.clip((lp - lb) / (lw - lb), 0.0, 1.0) ** ig
        return float(np.mean((u.mean(0) - 0.5) ** 2))

    lo, hi = GAMMA_RANGE
    grid = np.linspace(lo, hi, 38)
    costs = [cost(g) for g in grid]
    i = int(np.argmin(costs))
    a, c = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    r = (math.sqrt(5) - 1) / 2
    x1, x2 = c - r * (c - a), a + r * (c - a)
    f1, f2 = cost(x1), cost(x2)
    for _ in range(40):
        if f1 < f2:
            c, x2, f2 = x2, x1, f1
            x1 = c - r * (c - a)
            f1 = cost(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + r * (c - a)
            f2 = cost(x2)
    g = 0.5 * (a + c)
    log.info("estimated camera gamma %.3f from %d pixels", g, w.size)
    return float(g)


def extract_phase_rings(frames: wp.array, scan: Scan, settings: PhaseRingsSettings,
                        threads: int) -> tuple[Samples, dict]:
    """Decode + sampling stage of the ``phase-rings`` codec (:class:`PhaseRingsCodec`).

    Args:
        frames: (n, H, W) uint8/uint16 Warp array of one view.
        scan: the scan (patterns, rig).
        settings: the codec's settings.
        threads: CPU threads.

    Returns:
        (Samples, stats) with stats ``pixels_decoded`` (pixels with a phase),
        ``samples`` (points handed on), ``phase_dropped`` (pixels per reason),
        ``camera_gamma``/``light_gamma`` used (the latter the residual exponent of
        :func:`residual_light_gamma`), ``precompensated_gamma`` and ``times_s``.
    """

    spec = scan.patterns
    if spec.codec != NAME:
        raise ValueError(f"extract_phase_rings: the scan's codec is {spec.codec!r}, not {NAME}")
    ps = settings.phase
    dev = frames.device
    t0 = time.perf_counter()
    labels = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits, settings=settings.decode,
                               threads=threads)
    g_cam, g_light = view_response(frames, scan, ps)
    full = 255 if frames.dtype == wp.uint8 else 65535
    lut_np, wlut_np = response_tables(full, camera_gamma=g_cam, weighted=ps.weighted)
    lut = wp.array(lut_np, dtype=wp.float32, device=dev)
    wlut = wp.array(wlut_np, dtype=wp.float32, device=dev)
    phase = decode_phase(frames, labels, bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps, lut=lut,
                         wlut=wlut, light_gamma=g_light, settings=ps, threads=threads)
    wp.synchronize_device(dev)
    t1 = time.perf_counter()
    sm = smooth_phase(phase, labels.sector, settings=ps, rho0=spec.rho0, pitch=spec.pitch, threads=threads)
    sm = drop_lone_fringes(sm, size=LONE_FRINGE_PX, share=LONE_FRINGE_SHARE, threads=threads)
    pts = compact_phase_points(sm, rho0=spec.rho0, pitch=spec.pitch, threads=threads)
    wp.synchronize_device(dev)
    t2 = time.perf_counter()
    # each sample's sigma of rho from its fringe and the contrast under it, and its indirect-light share, on
    # the frames' device (angle_code.phase_sigma, sample_contrast and sample_indirect state them in NumPy)
    names = frame_names(spec)
    sig, indirect, shading = phase_light(
        frames, labels.contrast, pts.uv, pts.confidence, white=names.index("white"), black=names.index("black"),
        pairs=[(names.index(f"gray_{b}"), names.index(f"gray_{b}_inv")) for b in indirect_bits(spec)],
        noise=settings.angle.noise, pitch=spec.pitch, steps=spec.steps, smooth_radius=ps.smooth_radius,
        threads=threads)
    pts, angle_stats = add_angle(frames, scan, pts, sigma_rho=sig, settings=settings.angle, camera_gamma=g_cam,
                                 light_gamma=g_light, threads=threads)
    pts.indirect = indirect
    pts.shading = shading
    noise_stats = widen_for_frame_noise(frames, spec, pts, noise=settings.angle.noise, threads=threads)
    wp.synchronize_device(dev)
    t3 = time.perf_counter()
    # the statuses counted on the device (the lone fringes dropped are counted as modulation)
    counts = count_values(sm.status.flatten(), len(PHASE_STATUS_NAMES), threads=threads)
    decoded = int(count_values(phase.status.flatten(), 1, threads=threads)[0])
    stats = {
        "pixels_decoded": decoded,
        "samples": len(pts),
        "phase_dropped": {name: int(counts[i]) for i, name in enumerate(PHASE_STATUS_NAMES) if i > 0},
        # the fringe that barely modulates: pixels with contrast whose phase is dropped for it
        "pixels_lit": int(counts.sum() - counts[PHASE_STATUS_NAMES.index("dark")]),
        "low_modulation": int(counts[PHASE_STATUS_NAMES.index("modulation")]),
        "camera_gamma": g_cam,
        "light_gamma": g_light,
        "precompensated_gamma": spec.precompensated_gamma,
        **angle_stats,
        **noise_stats,
        "times_s": {"decode": t1 - t0, "sample": t2 - t1, "angle": t3 - t2},
    }
    return pts, stats


LONE_FRINGE_SHARE = 0.5
"""A pixel whose fringe passes ``phase.min_modulation`` while more than this share of the
lit pixels of the ``LONE_FRINGE_PX`` square around it are dropped for modulation is dropped too (as
``modulation``; ``kernels.phase.drop_lone_fringes``): a fringe's modulation changes smoothly with the
blur across a surface, so a lone pass where it has washed out is the camera's noise, not a fringe
(phase-rings at pitch 4 under a projector defocused by 1.5 px: 514 such points, median error 0.22 mm
against a predicted 0.002)."""
LONE_FRINGE_PX = 5


class PhaseRingsCodec(Codec[PhaseRingsSettings]):
    """The ``gray-rings`` frames plus ``phase_<n>``, n = 0..steps-1 (N-step phase
    shifted radial fringes): one sample per decoded pixel."""

    layout = PATTERN_LAYOUTS[NAME]
    settings_type = PhaseRingsSettings
    rig_needs = RigNeeds(response=True)

    def render_frame(self, spec: PatternSpec, name: str) -> np.ndarray:
        return draw_frame(spec, name)

    def full_coordinate(self, spec: PatternSpec) -> bool:
        return spec.angle_steps > 0  # the polar angle comes from the angle code only

    def settings_from(self, stages: StageSettings) -> PhaseRingsSettings:
        return PhaseRingsSettings(decode=stages.decode, phase=stages.phase, angle=stages.angle)

    def pixel_window(self, settings: PhaseRingsSettings) -> int:
        """The phase smoothing's window, 2 r + 1 (checked against the truth on ringscan's
        renderer: docs/accuracy.md, "Codecs without the angle")."""
        return 2 * settings.phase.smooth_radius + 1

    def extract(self, frames: wp.array, scan: Scan, settings: PhaseRingsSettings, *,
                threads: int) -> tuple[Samples, dict]:
        return extract_phase_rings(frames, scan, settings, threads)

    def explain_no_points(self, frames: np.ndarray, scan: Scan, stats: dict,
                          settings: PhaseRingsSettings) -> str | None:
        why = explain_binary_view(frames, scan.patterns, stats, settings.decode, frame_bits=scan.frame_bits)
        lit, low = stats.get("pixels_lit", 0), stats.get("low_modulation", 0)
        if why is None and lit and low > 0.5 * lit:
            return (f"no ring found: the phase fringes barely modulate on {100.0 * low / lit:.0f} % of the lit "
                    f"pixels (below phase.min_modulation {settings.phase.min_modulation:g}): a projector out of "
                    f"focus or a pitch ({scan.patterns.pitch:g} px) finer than the optics resolve; focus the "
                    "projector or use a coarser --pitch")
        return why


# ----------------------------------------------------------------------------- NumPy twins


# ----------------------------------------------------------------------------- bench


