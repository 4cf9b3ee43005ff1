"""Pattern codecs (DESIGN §5): parameters, frame lists and the projector frames.

All patterns live on the projector pixel grid (pixel centres at integers). Rings
are circles of radius rho (projector pixels) around the pattern centre c. Every
frame is an 8-bit image; edges are antialiased with an exact radial (or angular)
box filter one pixel wide, so the 50 % level of every edge lies exactly on the
ideal circle (or ray) and a frame and its inverse cross there.

Codecs:

- ``rings``: one frame ``rings``: ``count`` antialiased lines ``line_width`` px
  wide at rho_j = rho0 + j * pitch (the paper's single-shot pattern).
- ``gray-rings``: ``white``, ``black``, then ``gray_<b>``/``gray_<b>_inv`` for
  b = 0..bits-1 (b = 0 most significant): lit where bit b of gray(k) is 1, with
  band k = floor((rho - rho0) / pitch), 0 <= k < 2**bits; dark outside.
- ``phase-rings``: the gray-rings frames plus ``phase_<n>``, n = 0..steps-1:
  I = 0.5 + 0.5 cos(2 pi (rho - rho0) / pitch - 2 pi n / steps) in the annulus.
- sectors (``sector_bits`` > 0, multi-frame codecs): ``sector_<b>``/``sector_<b>_inv``,
  a Gray code over floor((phi + pi) / (2 pi) * 2**sector_bits),
  phi = atan2(v_p - c_v, u_p - c_u), inside the coded annulus only.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field

import numpy as np

from .errors import FormatError

CODECS = ("rings", "gray-rings", "phase-rings")

__all__ = [
    "CODECS",
    "PatternSpec",
    "parse_patterns",
    "frame_names",
    "render_frame",
    "render_frames",
    "gray_encode",
    "gray_decode",
]


def gray_encode(k):
    """Binary-reflected Gray code of ``k`` (int or integer array)."""
    return k ^ (k >> 1)


def gray_decode(g, bits: int):
    """Inverse of :func:`gray_encode` for codes of ``bits`` bits."""
    k = g
    shift = 1
    while shift < bits:
        k = k ^ (k >> shift)
        shift <<= 1
    return k


@dataclass(frozen=True)
class PatternSpec:
    """Parameters of a projected pattern set (scan.json ``patterns``)."""

    codec: str
    """One of ``rings``, ``gray-rings``, ``phase-rings``."""
    width: int
    """Projector width in pixels."""
    height: int
    """Projector height in pixels."""
    center: tuple[float, float]
    """Pattern centre (c_u, c_v) in projector pixels."""
    rho0: float
    """Inner radius in projector pixels: band 0 starts here (ring 0 lies here)."""
    pitch: float
    """Projector pixels per band (distance between rings)."""
    bits: int = 0
    """Gray-code bits of the band index (gray-rings, phase-rings)."""
    sector_bits: int = 0
    """Gray-code bits of the angular sector index; 0 = no sector code."""
    count: int = 0
    """Number of rings (single-shot ``rings``)."""
    line_width: float = 2.0
    """Width of each ring line in projector pixels (single-shot ``rings``)."""
    steps: int = 4
    """Phase steps (``phase-rings``)."""

    @property
    def n_bands(self) -> int:
        """Number of coded bands (2**bits), or of rings for the single-shot codec."""
        return self.count if self.codec == "rings" else 2 ** self.bits

    @property
    def rho_max(self) -> float:
        """Outer radius of the coded annulus (projector px)."""
        if self.codec == "rings":
            return self.rho0 + (self.count - 1) * self.pitch + 0.5 * self.line_width
        return self.rho0 + self.n_bands * self.pitch

    def ring_radii(self) -> np.ndarray:
        """Radii (projector px) of the sampled rings: the lines of ``rings``, or the
        band boundaries k = 1..2**bits-1 of the binary codecs (index k-1)."""
        if self.codec == "rings":
            return self.rho0 + self.pitch * np.arange(self.count)
        return self.rho0 + self.pitch * np.arange(1, self.n_bands)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["center"] = list(self.center)
        keep = {"codec", "width", "height", "center", "rho0", "pitch"}
        if self.codec == "rings":
            keep |= {"count", "line_width"}
        else:
            keep |= {"bits", "sector_bits"}
            if self.codec == "phase-rings":
                keep |= {"steps"}
        return {k: v for k, v in d.items() if k in keep}


def parse_patterns(d: dict, *, source: str | os.PathLike | None = None) -> PatternSpec:
    """Validate a ``patterns`` dictionary and build a :class:`PatternSpec`.

    Raises:
        FormatError: naming ``source`` and the field for every problem.
    """
    src = source
    if not isinstance(d, dict):
        raise FormatError(src, "patterns: expected an object")
    codec = d.get("codec")
    if codec not in CODECS:
        raise FormatError(src, f"patterns.codec: unknown codec {codec!r} (known: {', '.join(CODECS)})")

    def num(key, default=None, positive=False):
        v = d.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise FormatError(src, f"patterns.{key}: expected a finite number, got {v!r}")
        if positive and v <= 0:
            raise FormatError(src, f"patterns.{key}: must be > 0, got {v}")
        return v

    def integer(key, default=None, lo=None, hi=None):
        v = d.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise FormatError(src, f"patterns.{key}: expected an integer, got {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise FormatError(src, f"patterns.{key}: must be in [{lo}, {hi}], got {v}")
        return v

    width = integer("width", lo=1, hi=65536)
    height = integer("height", lo=1, hi=65536)
    center = d.get("center")
    if not (isinstance(center, (list, tuple)) and len(center) == 2
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in center)):
        raise FormatError(src, f"patterns.center: expected [c_u, c_v], got {center!r}")
    if not (0 <= center[0] <= width - 1 and 0 <= center[1] <= height - 1):
        raise FormatError(src, f"patterns.center: {list(center)} lies outside the {width}x{height} projector")
    rho0 = num("rho0")
    if rho0 < 0:
        raise FormatError(src, f"patterns.rho0: must be >= 0, got {rho0}")
    pitch = num("pitch", positive=True)
    kw = {}
    if codec == "rings":
        kw["count"] = integer("count", lo=1, hi=100000)
        kw["line_width"] = num("line_width", 2.0, positive=True)
        if kw["line_width"] >= pitch:
            raise FormatError(src, f"patterns.line_width: {kw['line_width']} px does not fit in pitch {pitch} px (rings would touch)")
    else:
        kw["bits"] = integer("bits", lo=1, hi=16)
        kw["sector_bits"] = integer("sector_bits", 0, lo=0, hi=12)
        if codec == "phase-rings":
            kw["steps"] = integer("steps", 4, lo=3, hi=64)
        if pitch < 1.0:
            raise FormatError(src, f"patterns.pitch: {pitch} px is below one projector pixel; binary bands cannot be shown")
    spec = PatternSpec(codec=codec, width=width, height=height, center=(float(center[0]), float(center[1])),
                       rho0=float(rho0), pitch=float(pitch), **kw)
    # The coded annulus must reach into the projector image.
    cu, cv = spec.center
    far = max(math.hypot(x - cu, y - cv) for x in (0, width - 1) for y in (0, height - 1))
    if spec.rho0 >= far:
        raise FormatError(src, f"patterns.rho0: {spec.rho0} px lies outside the projector (farthest corner {far:.1f} px)")
    if codec == "rings" and spec.ring_radii()[-1] > far:
        n_in = int(np.sum(spec.ring_radii() <= far))
        raise FormatError(src, f"patterns.count: only {n_in} of {spec.count} rings fit on the {width}x{height} projector")
    return spec


def frame_names(spec: PatternSpec) -> list[str]:
    """The frame names of a codec, in projection order."""
    if spec.codec == "rings":
        return ["rings"]
    names = ["white", "black"]
    for b in range(spec.bits):
        names += [f"gray_{b}", f"gray_{b}_inv"]
    for b in range(spec.sector_bits):
        names += [f"sector_{b}", f"sector_{b}_inv"]
    if spec.codec == "phase-rings":
        names += [f"phase_{n}" for n in range(spec.steps)]
    return names


# ----------------------------------------------------------------------------- rendering


def _polar(spec: PatternSpec):
    v, u = np.mgrid[0:spec.height, 0:spec.width].astype(np.float64)
    du, dv = u - spec.center[0], v - spec.center[1]
    return np.hypot(du, dv), np.arctan2(dv, du)


def _band_coverage(rho, rho0, pitch, lit, h=0.5):
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


def _sector_coverage(phi, rho, sector_bits, bit):
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


def render_frame(spec: PatternSpec, name: str) -> np.ndarray:
    """Render one projector frame as a (height, width) uint8 image."""
    if name not in frame_names(spec):
        raise ValueError(f"frame {name!r} is not part of the {spec.codec} codec")
    rho, phi = _polar(spec)
    if name == "white":
        return np.full((spec.height, spec.width), 255, np.uint8)
    if name == "black":
        return np.zeros((spec.height, spec.width), np.uint8)
    if name == "rings":
        img = np.zeros_like(rho)
        w, h = spec.line_width, 0.5
        for r in spec.ring_radii():
            lo = np.maximum(rho - h, r - w / 2)
            hi = np.minimum(rho + h, r + w / 2)
            img += np.clip(hi - lo, 0, None) / (2 * h)
        return _to_u8(img)
    n = spec.n_bands
    inside = _band_coverage(rho, spec.rho0, spec.pitch, np.ones(n))
    kind, b, *inv = name.split("_")
    b = int(b)
    if kind == "gray":
        lit = (gray_encode(np.arange(n)) >> (spec.bits - 1 - b)) & 1
        if inv:
            lit = 1 - lit
        return _to_u8(_band_coverage(rho, spec.rho0, spec.pitch, lit))
    if kind == "sector":
        cov = _sector_coverage(phi, rho, spec.sector_bits, b)
        if inv:
            cov = 1.0 - cov
        return _to_u8(cov * inside)
    if kind == "phase":
        ph = 2 * math.pi * (rho - spec.rho0) / spec.pitch - 2 * math.pi * b / spec.steps
        return _to_u8((0.5 + 0.5 * np.cos(ph)) * inside)
    raise AssertionError(name)


def render_frames(spec: PatternSpec) -> dict[str, np.ndarray]:
    """All frames of a codec, in projection order."""
    return {name: render_frame(spec, name) for name in frame_names(spec)}


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)
