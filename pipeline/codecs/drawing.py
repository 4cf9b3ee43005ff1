"""The projector frames of every codec, drawn with NumPy alone (so that showing
patterns, in ``ringscan capture`` and the display projector, loads no kernels),
and their helpers (docs/design.md §7): 8-bit images with antialiased
edges, each pixel's value the lit fraction of its area (rings, bands, sectors). Each
codec draws its own frames with them (its ``render_frame``).

With ``spec.precompensated_gamma`` g != 1 each value v (0..1, the light the
pattern means) is written as round(255 * v**(1/g)): a light whose response is
emitted = (value / 255)**g then emits v. 0 and 1 stay 0 and 255, so white, black
and the binary bands away from their edges are unchanged.
"""

from __future__ import annotations

import math

import numpy as np

from ringscan.pipeline.formats.patterns import PatternSpec, angle_periods, gray_encode, spec_angle_zones

__all__ = ["polar", "band_coverage", "sector_coverage", "to_u8", "draw_frame", "binary_frame", "phase_frame",
           "angle_frame", "rings_frame"]


def polar(spec: PatternSpec):
    v, u = np.mgrid[0:spec.height, 0:spec.width].astype(np.float64)
    du, dv = u - spec.center[0], v - spec.center[1]
    return np.hypot(du, dv), np.arctan2(dv, du)


def band_coverage(rho, rho0, pitch, lit, h=0.5):
    """Fraction of the radial interval [rho-h, rho+h] covered by lit bands.

    ``lit`` is a 0/1 array over bands k = 0..N-1 (band k = [rho0+k p, rho0+(k+1) p)).
    """
    lit = np.asarray(lit, np.float64)
    cum = np.concatenate([[0.0], np.cumsum(lit)]) * pitch

    def F(r):
        x = (r - rho0) / pitch
        k = np.clip(np.floor(x), 0, lit.size - 1).astype(np.int64)
        frac = np.clip(x - k, 0.0, 1.0)
        val = cum[k] + lit[k] * frac * pitch
        return np.where(x <= 0, 0.0, np.where(x >= lit.size, cum[-1], val))

    return (F(rho + h) - F(rho - h)) / (2 * h)


def sector_coverage(phi, rho, sector_bits, bit):
    """Fraction of the angular interval [phi-h, phi+h] (h = 0.5 px / rho) where the
    sector's Gray code has ``bit`` set."""
    n = 2 ** sector_bits
    lit = (gray_encode(np.arange(n)) >> (sector_bits - 1 - bit)) & 1
    h = np.minimum(0.5 / np.maximum(rho, 1e-6), math.pi / n)
    width = 2 * math.pi / n
    t = phi + math.pi  # in [0, 2 pi]
    lit3 = np.tile(lit, 3).astype(np.float64)  # wrap around once each way
    cum = np.concatenate([[0.0], np.cumsum(lit3)]) * width

    def F(a):
        x = (a + 2 * math.pi) / width
        k = np.clip(np.floor(x), 0, lit3.size - 1).astype(np.int64)
        return cum[k] + lit3[k] * (x - k) * width

    return (F(t + h) - F(t - h)) / (2 * h)


def to_u8(spec: PatternSpec, x: np.ndarray) -> np.ndarray:
    """Light fractions ``x`` (0..1) as 8-bit frame values, pre-compensated for the spec's gamma."""
    x = np.clip(x, 0.0, 1.0)
    g = spec.precompensated_gamma
    if g != 1.0:
        x = x ** (1.0 / g)
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------- frames by kind


def binary_frame(spec: PatternSpec, name: str) -> np.ndarray:
    """``white``, ``black``, ``gray_<b>[_inv]``, ``sector_<b>[_inv]``."""
    if name == "white":
        return np.full((spec.height, spec.width), 255, np.uint8)
    if name == "black":
        return np.zeros((spec.height, spec.width), np.uint8)
    rho, phi = polar(spec)
    n = spec.n_bands
    kind, b, *inv = name.split("_")
    b = int(b)
    if kind == "gray":
        lit = (gray_encode(np.arange(n)) >> (spec.bits - 1 - b)) & 1
        if inv:
            lit = 1 - lit
        return to_u8(spec, band_coverage(rho, spec.rho0, spec.pitch, lit))
    inside = band_coverage(rho, spec.rho0, spec.pitch, np.ones(n))
    cov = sector_coverage(phi, rho, spec.sector_bits, b)
    if inv:
        cov = 1.0 - cov
    return to_u8(spec, cov * inside)


def phase_frame(spec: PatternSpec, name: str) -> np.ndarray:
    """``phase_<n>``: 0.5 + 0.5 cos(2 pi (rho - rho0) / pitch - 2 pi n / steps) in the annulus."""
    n = int(name.split("_")[1])
    rho, _ = polar(spec)
    inside = band_coverage(rho, spec.rho0, spec.pitch, np.ones(spec.n_bands))
    ph = 2 * math.pi * (rho - spec.rho0) / spec.pitch - 2 * math.pi * n / spec.steps
    return to_u8(spec, (0.5 + 0.5 * np.cos(ph)) * inside)


def angle_frame(spec: PatternSpec, name: str) -> np.ndarray:
    """``angle_<n>``: 0.5 + 0.5 cos(P phi - 2 pi n / N) in the annulus, P from the
    pattern's zones (``formats.patterns.angle_zones``)."""
    n = int(name.split("_")[1])
    rho, phi = polar(spec)
    inside = band_coverage(rho, spec.rho0, spec.pitch, np.ones(spec.n_bands))
    P = angle_periods(rho, *spec_angle_zones(spec))
    return to_u8(spec, (0.5 + 0.5 * np.cos(P * phi - 2 * math.pi * n / spec.angle_steps)) * inside)


def rings_frame(spec: PatternSpec, name: str) -> np.ndarray:
    """``rings``: the single-shot codec's antialiased ring lines."""
    rho, _ = polar(spec)
    img = np.zeros_like(rho)
    w, h = spec.line_width, 0.5
    for r in spec.ring_radii():
        lo = np.maximum(rho - h, r - w / 2)
        hi = np.minimum(rho + h, r + w / 2)
        img += np.clip(hi - lo, 0, None) / (2 * h)
    return to_u8(spec, img)


FRAME_KINDS = {"white": binary_frame, "black": binary_frame, "gray": binary_frame, "sector": binary_frame,
               "phase": phase_frame, "angle": angle_frame, "rings": rings_frame}
"""A frame name's first word -> what draws it (a frame name means the same in every codec)."""


def draw_frame(spec: PatternSpec, name: str) -> np.ndarray:
    """Projector frame ``name`` of ``spec`` as a (height, width) uint8 image.

    Raises:
        ValueError: the frame is not one of the spec's (``frame_names``).
    """
    from_spec = spec.layout.frame_names(spec)
    if name not in from_spec or not spec.layout.projectable:
        raise ValueError(f"frame {name!r} is not part of the {spec.codec} codec")
    return FRAME_KINDS[name.split("_")[0]](spec, name)
