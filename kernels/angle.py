"""The angle code, per sample: the polar angle around the pattern centre from
phase-shifted angular fringes, unwrapped by the sector code (docs/design.md,
"Rings and angle"; docs/dense.md, "The angle code").

The frames ``angle_<n>``, n = 0..N-1, show I_n = 0.5 + 0.5 cos(P phi - 2 pi n / N)
inside the coded annulus, phi = atan2(v_p - c_v, u_p - c_u). The number of
periods P doubles outward in zones (``formats.patterns.angle_zones``, a part of the
pattern's definition the decoder is given as arrays) so that one period is
never shorter than ``min_period_px`` projector pixels at a zone's inner radius:
the fringes stay resolvable near the centre and sharp far from it. Zone edges
lie on band centres, away from the ring edges that the gray-rings samples sit on.
Per sample (a sub-pixel camera position and its decoded rho and sector):

1. The white, black and angle frames are interpolated bilinearly in linear
   irradiance (the camera's response table), normalised by white and black and
   raised to 1 / gamma_light (the light's response), as the ring phase does.
2. The wrapped angular phase psi = P phi mod 2 pi and the modulation q (1 for a
   perfect fringe) from the classic N-step sums.
3. Unwrapping by the sector code: with 2^S sectors and P <= 2^(S-1) periods, the
   sector centre phi_s is within half a sector of phi, well inside the half
   period a wrong period would need: phi = (psi + 2 pi round((P phi_s - psi) /
   2 pi)) / P.
   A sample whose sector did not decode (a weak sector bit at both pixels of its
   edge: it lies on a sector edge, or finer sectors than the camera resolves)
   reads the sector frames again at its own position, but only the coarse code
   unwrapping needs: the top m = log2(P) + 1 bits, 2P sectors half a period wide
   (the top bits of a reflected Gray code are the Gray code of the coarse sector).
   All strong: the coarse sector's centre is the reference, a quarter period from
   phi at most. Exactly one weak, and its two readings name neighbouring coarse
   sectors: the sample lies on their shared edge, which is the reference (either
   neighbour unwraps it alike; half a period spare). Otherwise: no sector.
4. The tangential standard deviation rho * sigma_phi, sigma_phi = sqrt(2 / N)
   sigma_v / (P a), with a the fringe amplitude and sigma_v the camera noise over
   the pixel's white - black contrast: what the triangulation weights by.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from ringscan.kernels.geometry import polar_angle
from ringscan.kernels.launch import default_threads, launch_spans
from ringscan.kernels.ring_labels import gray_to_binary
from ringscan.kernels.settings import AngleSettings

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

ANGLE_OK = wp.constant(0)
ANGLE_DARK = wp.constant(1)
ANGLE_MODULATION = wp.constant(2)
ANGLE_NO_SECTOR = wp.constant(3)
ANGLE_STATUS_NAMES = ("ok", "dark", "modulation", "no_sector")
PI = wp.constant(3.141592653589793)
TWO_PI = wp.constant(6.283185307179586)

__all__ = ["AngleSamples", "ANGLE_STATUS_NAMES", "decode_angle"]


@wp.struct
class AngleParams:
    """The scalar settings of :func:`angle_kernel`, filled once by :func:`decode_angle`
    (the frame layout, the light's response and :class:`AngleSettings`)."""

    white: wp.int32
    """Frame index of white."""
    black: wp.int32
    """Frame index of black."""
    angle0: wp.int32
    """Frame index of ``angle_0``."""
    steps: wp.int32
    """The number of angle frames N."""
    n_sectors: wp.int32
    """2 ** sector_bits, 0 without sectors."""
    sector0: wp.int32
    """Frame index of ``sector_0`` (the coarse sector re-read), -1: none."""
    level_scale: wp.float32
    """Full scale / 255: 8-bit grey levels -> recorded levels (1 or 257)."""
    inv_light_gamma: wp.float32
    """1 / the light's response exponent."""
    min_contrast: wp.float32
    """``AngleSettings.min_contrast`` (8-bit grey levels)."""
    bit_margin: wp.float32
    """``AngleSettings.bit_margin``."""
    min_modulation: wp.float32
    """``AngleSettings.min_modulation``."""
    noise: wp.float32
    """``AngleSettings.noise`` (8-bit grey levels)."""


@dataclass
class AngleSamples:
    """Per-sample angle results (Warp arrays of length n)."""

    phi: wp.array
    """float32 polar angle (rad, in (-pi, pi]), NaN where status != 0."""
    sigma_tan: wp.array
    """float32 standard deviation of the tangential position rho * phi (projector px), 0 where status != 0."""
    modulation: wp.array
    """float32 fringe modulation q."""
    status: wp.array
    """int32 status code (see ``ANGLE_STATUS_NAMES``)."""


# ----------------------------------------------------------------------------- helpers


@wp.func
def bilinear_taps(frames: wp.array3d(dtype=Any), x: float, y: float):
    """(x0, y0, fx, fy): the top-left pixel and the weights of (x, y), clamped inside the frame."""
    x0 = wp.clamp(int(wp.floor(x)), 0, frames.shape[2] - 2)
    y0 = wp.clamp(int(wp.floor(y)), 0, frames.shape[1] - 2)
    return wp.vec4(float(x0), float(y0), wp.clamp(x - float(x0), 0.0, 1.0), wp.clamp(y - float(y0), 0.0, 1.0))


@wp.func
def bilinear(frames: wp.array3d(dtype=Any), f: int, x: float, y: float, lut: wp.array(dtype=wp.float32)):
    """Linearised value of frame f at camera position (x, y), bilinear."""
    k = bilinear_taps(frames, x, y)
    x0 = int(k[0])
    y0 = int(k[1])
    a = lut[int(frames[f, y0, x0])] * (1.0 - k[2]) + lut[int(frames[f, y0, x0 + 1])] * k[2]
    b = lut[int(frames[f, y0 + 1, x0])] * (1.0 - k[2]) + lut[int(frames[f, y0 + 1, x0 + 1])] * k[2]
    return a * (1.0 - k[3]) + b * k[3]


@wp.func
def raw_bilinear(frames: wp.array3d(dtype=Any), f: int, x: float, y: float):
    """Recorded value of frame f at camera position (x, y), bilinear."""
    k = bilinear_taps(frames, x, y)
    x0 = int(k[0])
    y0 = int(k[1])
    a = float(frames[f, y0, x0]) * (1.0 - k[2]) + float(frames[f, y0, x0 + 1]) * k[2]
    b = float(frames[f, y0 + 1, x0]) * (1.0 - k[2]) + float(frames[f, y0 + 1, x0 + 1]) * k[2]
    return a * (1.0 - k[3]) + b * k[3]


@wp.func
def coarse_sector_reference(frames: wp.array3d(dtype=Any), sector0: int, bits: int, x: float, y: float,
                            margin: float):
    """(reference angle, 1) from the top ``bits`` sector bits read at (x, y): the
    coarse sector's centre where every bit is strong, the edge between two
    neighbouring coarse sectors where exactly one is weak; (0, 0) otherwise.
    ``margin``: the weak threshold in recorded levels."""
    g = int(0)
    weak = int(0)
    flip = int(0)
    for b in range(bits):
        d = raw_bilinear(frames, sector0 + 2 * b, x, y) - raw_bilinear(frames, sector0 + 2 * b + 1, x, y)
        g = g * 2
        if d > 0.0:
            g = g + 1
        if wp.abs(d) < margin:
            weak = weak + 1
            flip = 1 << (bits - 1 - b)
    n = 1 << bits
    width = TWO_PI / float(n)
    s0 = gray_to_binary(g, bits)
    if weak == 0:
        return wp.vec2((float(s0) + 0.5) * width - PI, 1.0)
    if weak == 1:
        s1 = gray_to_binary(g ^ flip, bits)
        lo = wp.min(s0, s1)
        hi = wp.max(s0, s1)
        if hi - lo == 1:
            return wp.vec2(float(hi) * width - PI, 1.0)
        if lo == 0 and hi == n - 1:
            return wp.vec2(-PI, 1.0)
    return wp.vec2(0.0, 0.0)


@wp.func
def wrap_angle(a: float):
    """a wrapped into (-pi, pi]."""
    return a - TWO_PI * wp.ceil((a - PI) / TWO_PI)


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def angle_kernel(
    frames: wp.array3d(dtype=Any),
    lut: wp.array(dtype=wp.float32),
    trig: wp.array(dtype=wp.vec2),
    zone_rho: wp.array(dtype=wp.float32),
    zone_periods: wp.array(dtype=wp.int32),
    uv: wp.array(dtype=wp.vec2),
    rho: wp.array(dtype=wp.float32),
    sector: wp.array(dtype=wp.int32),
    params: AngleParams,
    i0: int,
    phi: wp.array(dtype=wp.float32),
    sigma_tan: wp.array(dtype=wp.float32),
    modulation: wp.array(dtype=wp.float32),
    status: wp.array(dtype=wp.int32),
):
    """Angle of sample i0 + tid.

    frames: (n_frames, H, W) uint8/uint16, read (the frames ``params`` names:
        ``white``, ``black``, the angle frames from index ``angle0`` and, for
        samples without a sector, the sector frame pairs from ``sector0``; -1:
        none). lut: (full + 1,) float32, read.
    trig: (steps,) vec2 (cos, sin) of 2 pi n / steps, read.
    zone_rho: (Z,) float32 inner radius of each zone, ascending; zone_periods:
        (Z,) int32 its number of periods, read.
    uv (n,) vec2 camera position, rho (n,) float32, sector (n,) int32, read.
    params: the frame indices, thresholds and noise model (:class:`AngleParams`).
    phi, sigma_tan, modulation (n,) float32, status (n,) int32, written.

    Size: one thread per sample; the phase fit over the angle frames, the zone's period, the sector (re-read
    from the sector frames where unknown) and the unwrapping share the sample's locals. Over a third of its
    length is its signature, its docstring and AngleParams unpacked into locals. Warp kernels take each array as
    its own argument; the scalar settings already travel in AngleParams.
    """
    i = i0 + wp.tid()
    white = params.white
    black = params.black
    angle0 = params.angle0
    steps = params.steps
    n_sectors = params.n_sectors
    sector0 = params.sector0
    level_scale = params.level_scale
    inv_light_gamma = params.inv_light_gamma
    min_contrast = params.min_contrast
    bit_margin = params.bit_margin
    min_modulation = params.min_modulation
    noise = params.noise
    x = uv[i][0]
    y = uv[i][1]
    phi[i] = wp.nan
    sigma_tan[i] = 0.0
    modulation[i] = 0.0
    contrast = (raw_bilinear(frames, white, x, y) - raw_bilinear(frames, black, x, y)) / level_scale
    lw = bilinear(frames, white, x, y, lut)
    lb = bilinear(frames, black, x, y, lut)
    span = lw - lb
    if contrast < min_contrast or span <= 0.0:
        status[i] = ANGLE_DARK
        return
    bc = float(0.0)
    bs = float(0.0)
    for n in range(steps):
        v = wp.clamp((bilinear(frames, angle0 + n, x, y, lut) - lb) / span, 1.0e-6, 1.0)
        if inv_light_gamma != 1.0:
            v = wp.pow(v, inv_light_gamma)
        bc += v * trig[n][0]
        bs += v * trig[n][1]
    bc = bc * 2.0 / float(steps)
    bs = bs * 2.0 / float(steps)
    amp = wp.sqrt(bc * bc + bs * bs)
    q = 2.0 * amp
    modulation[i] = q
    if q < min_modulation:
        status[i] = ANGLE_MODULATION
        return
    r = rho[i]
    p = int(zone_periods[0])
    for z in range(zone_rho.shape[0]):
        if r >= zone_rho[z]:
            p = zone_periods[z]
    psi = polar_angle(bs, bc)
    a = psi
    if p > 1:
        s = sector[i]
        if n_sectors <= 0:
            status[i] = ANGLE_NO_SECTOR
            return
        phi_s = (float(s) + 0.5) * TWO_PI / float(n_sectors) - PI
        if s < 0:
            if sector0 < 0:
                status[i] = ANGLE_NO_SECTOR
                return
            m = int(1)
            while (1 << (m - 1)) < p:
                m = m + 1
            ref = coarse_sector_reference(frames, sector0, m, x, y, bit_margin * contrast * level_scale)
            if ref[1] == 0.0:
                status[i] = ANGLE_NO_SECTOR
                return
            phi_s = ref[0]
        k = wp.round((float(p) * phi_s - psi) / TWO_PI)
        a = (psi + TWO_PI * k) / float(p)
    phi[i] = wrap_angle(a)
    sigma_v = noise / contrast
    sigma_tan[i] = r * wp.sqrt(2.0 / float(steps)) * sigma_v / (float(p) * amp)
    status[i] = ANGLE_OK


for _t in (wp.uint8, wp.uint16):
    wp.overload(angle_kernel, {"frames": wp.array3d(dtype=_t)})


# ----------------------------------------------------------------------------- host


def decode_angle(
    frames: wp.array,
    uv: wp.array,
    rho: wp.array,
    sector: wp.array,
    *,
    white: int,
    black: int,
    angle0: int,
    steps: int,
    sector_bits: int,
    zones: tuple[np.ndarray, np.ndarray],
    lut: wp.array,
    light_gamma: float = 1.0,
    sector0: int = -1,
    settings: AngleSettings = AngleSettings(),
    threads: int | None = None,
) -> AngleSamples:
    """The polar angle of every sample from the angle frames.

    Args:
        frames: (n_frames, H, W) uint8/uint16 Warp array of the view (read).
        uv: (n,) vec2 camera positions of the samples; rho: (n,) float32 their
            ring radius (projector px); sector: (n,) int32 their sector (-1 unknown).
        white, black, angle0: frame indices of white, black and ``angle_0``.
        steps: the number of angle frames N (>= 3).
        sector_bits: the scan's sector bits S.
        zones: (rho_start, periods) from ``pipeline.formats.patterns.angle_zones``.
        lut: (full_scale + 1,) float32 Warp array: recorded value -> linear
            irradiance (``kernels.response.response_tables``).
        light_gamma: the light's response exponent (1: linear).
        sector0: frame index of ``sector_0`` (its inverse follows, then the
            next bit's pair): samples without a sector re-read the coarse
            sector code there; -1: none (they get no angle where P > 1).
        settings: thresholds and the noise model.
        threads: CPU threads; default all cores.

    Size: a public function: its parameters are the sample arrays and its documented keyword-only options (frame
    indices, pattern figures, tables, settings); most of its length is their signature, documentation and
    checks, the rest packs AngleParams and launches one kernel.
    """
    if not isinstance(frames, wp.array) or frames.ndim != 3 or frames.dtype not in (wp.uint8, wp.uint16):
        raise ValueError("decode_angle: frames must be a (n, H, W) uint8/uint16 Warp array")
    n_frames = frames.shape[0]
    if steps < 3 or angle0 < 0 or angle0 + steps > n_frames or not (0 <= white < n_frames and 0 <= black < n_frames):
        raise ValueError(f"decode_angle: frames {white}, {black}, {angle0}..{angle0 + steps - 1} are not all among "
                         f"the {n_frames} frames (steps must be >= 3)")
    if not isinstance(uv, wp.array) or uv.dtype != wp.vec2:
        raise ValueError("decode_angle: uv must be a Warp array of vec2")
    if sector0 >= 0 and (sector_bits <= 0 or sector0 + 2 * sector_bits > n_frames):
        raise ValueError(f"decode_angle: sector frames {sector0}..{sector0 + 2 * sector_bits - 1} are not all among "
                         f"the {n_frames} frames")
    n = uv.shape[0]
    for name, a, dt in (("rho", rho, wp.float32), ("sector", sector, wp.int32)):
        if not isinstance(a, wp.array) or a.dtype != dt or a.shape != (n,):
            raise ValueError(f"decode_angle: {name} must be a ({n},) {dt.__name__} Warp array")
    starts, periods = (np.asarray(z) for z in zones)
    if starts.ndim != 1 or starts.shape != periods.shape or starts.size == 0:
        raise ValueError("decode_angle: zones must be two equal-length non-empty 1-D arrays")
    dev = frames.device
    out = AngleSamples(phi=wp.empty(n, dtype=wp.float32, device=dev),
                       sigma_tan=wp.empty(n, dtype=wp.float32, device=dev),
                       modulation=wp.empty(n, dtype=wp.float32, device=dev),
                       status=wp.empty(n, dtype=wp.int32, device=dev))
    if n == 0:
        return out
    full = 255.0 if frames.dtype == wp.uint8 else 65535.0
    shifts = 2 * np.pi * np.arange(steps) / steps
    trig = wp.array(np.c_[np.cos(shifts), np.sin(shifts)].astype(np.float32), dtype=wp.vec2, device=dev)
    params = AngleParams()
    params.white = int(white)
    params.black = int(black)
    params.angle0 = int(angle0)
    params.steps = int(steps)
    params.n_sectors = 2 ** sector_bits if sector_bits > 0 else 0
    params.sector0 = int(sector0)
    params.level_scale = full / 255.0
    params.inv_light_gamma = 1.0 / float(light_gamma)
    params.min_contrast = float(settings.min_contrast)
    params.bit_margin = float(settings.bit_margin)
    params.min_modulation = float(settings.min_modulation)
    params.noise = float(settings.noise)
    args = [frames, lut, trig, wp.array(starts.astype(np.float32), device=dev),
            wp.array(periods.astype(np.int32), device=dev), uv, rho, sector, params]
    outputs = [out.phi, out.sigma_tan, out.modulation, out.status]
    threads = default_threads() if threads is None else threads
    launch_spans(angle_kernel, n, lambda i0: args + [i0], outputs, dev, threads)
    return out
