"""Drawing helpers of the projector frames (docs/design.md §7): 8-bit images with antialiased
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

from ringscan.pipeline.formats.patterns import PatternSpec, gray_encode

__all__ = ["polar", "band_coverage", "sector_coverage", "to_u8"]


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
