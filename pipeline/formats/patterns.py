"""Pattern codecs (docs/design.md §7): parameters, frame lists and the projector frames.

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
- ``decoded`` (imported captures, ``ringscan import``): frames ``proj_u``, ``proj_v``
  (16-bit, fixed point, see :data:`DECODED_SCALE`) and ``contrast`` (16-bit, white -
  black x 257): each camera pixel's projector position; rho = |p - c| and the polar
  angle about the centre c (the projector's principal point, which may lie outside
  the projector image); ``sector_bits`` quantises that angle for the root choice.
- sectors (``sector_bits`` > 0, multi-frame codecs): ``sector_<b>``/``sector_<b>_inv``,
  a Gray code over floor((phi + pi) / (2 pi) * 2**sector_bits),
  phi = atan2(v_p - c_v, u_p - c_u), inside the coded annulus only.

Pre-compensation (``precompensated_gamma`` g, projectable codecs, default 1 = none):
every frame value v (0..1, the light the pattern means) is written as
round(255 * v**(1/g)), so that a light of response emitted = (value / 255)**g
emits v. Full and no light (white, black, binary bands away from their edges) are
unchanged; antialiased edges and phase fringes change. A decoder that undoes the
light's response uses the residual exponent light gamma / g.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass

import numpy as np

from ringscan.pipeline.formats.errors import FormatError

CODECS = ("rings", "gray-rings", "phase-rings")
IMPORTED_CODECS = ("decoded",)
"""Codecs of imported captures (not projectable): ``decoded`` holds each camera pixel's
decoded projector position (``ringscan import``)."""
PRECOMPENSATED_GAMMA_RANGE = (0.1, 10.0)
"""Accepted ``precompensated_gamma`` (the rig's range of response gammas)."""
DECODED_SCALE = 32
"""``decoded`` frames: 16-bit value = round((projector coordinate + 1) * DECODED_SCALE), 0 = not decoded."""

__all__ = ["CODECS", "IMPORTED_CODECS", "DECODED_SCALE", "PRECOMPENSATED_GAMMA_RANGE", "CODEC_DEFAULTS", "PatternSpec", "parse_patterns",
           "default_patterns", "frame_names", "gray_encode", "gray_decode"]

CODEC_DEFAULTS: dict[str, dict] = {
    "rings": {"count": 9, "pitch": 40.0, "line_width": 3.0},
    "gray-rings": {"rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 6},
    "phase-rings": {"rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 6, "steps": 4},
}
"""Default parameters of each projectable codec (``ringscan patterns`` and
``simulate`` use them for every option not given). ``rings`` has no fixed
``rho0``: it defaults to the pitch, so ring 0 is a circle one ring spacing
across the centre, large enough to be seen as the loop that anchors the labels
of the rings wholly on an object (docs/single_shot.md)."""


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
    precompensated_gamma: float = 1.0
    """Light gamma the frames were pre-compensated for (value = v**(1/g)); 1 = none."""

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
        elif self.codec == "decoded":
            keep |= {"sector_bits"}
        else:
            keep |= {"bits", "sector_bits"}
            if self.codec == "phase-rings":
                keep |= {"steps"}
        if self.precompensated_gamma != 1.0:
            keep |= {"precompensated_gamma"}
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
    if codec not in CODECS + IMPORTED_CODECS:
        raise FormatError(src, f"patterns.codec: unknown codec {codec!r} (known: {', '.join(CODECS + IMPORTED_CODECS)})")

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
    if codec != "decoded" and not (0 <= center[0] <= width - 1 and 0 <= center[1] <= height - 1):
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
    elif codec == "decoded":
        kw["sector_bits"] = integer("sector_bits", 8, lo=0, hi=12)
    else:
        kw["bits"] = integer("bits", lo=1, hi=16)
        kw["sector_bits"] = integer("sector_bits", 0, lo=0, hi=12)
        if codec == "phase-rings":
            kw["steps"] = integer("steps", 4, lo=3, hi=64)
        if pitch < 1.0:
            raise FormatError(src, f"patterns.pitch: {pitch} px is below one projector pixel; binary bands cannot be shown")
    if "precompensated_gamma" in d:
        if codec in IMPORTED_CODECS:
            raise FormatError(src, f"patterns.precompensated_gamma: not for the {codec} codec (nothing is projected)")
        g = num("precompensated_gamma", positive=True)
        if not (PRECOMPENSATED_GAMMA_RANGE[0] <= g <= PRECOMPENSATED_GAMMA_RANGE[1]):
            lo, hi = PRECOMPENSATED_GAMMA_RANGE
            raise FormatError(src, f"patterns.precompensated_gamma: must be in [{lo:g}, {hi:g}], got {g}")
        kw["precompensated_gamma"] = float(g)
    spec = PatternSpec(codec=codec, width=width, height=height, center=(float(center[0]), float(center[1])),
                       rho0=float(rho0), pitch=float(pitch), **kw)
    # The coded annulus must reach into the projector image.
    cu, cv = spec.center
    far = max(math.hypot(x - cu, y - cv) for x in (0, width - 1) for y in (0, height - 1))
    if codec != "decoded" and spec.rho0 >= far:
        raise FormatError(src, f"patterns.rho0: {spec.rho0} px lies outside the projector (farthest corner {far:.1f} px)")
    if codec == "rings" and spec.ring_radii()[-1] > far:
        n_in = int(np.sum(spec.ring_radii() <= far))
        raise FormatError(src, f"patterns.count: only {n_in} of {spec.count} rings fit on the {width}x{height} projector")
    return spec


def default_patterns(codec: str, *, width: int = 1024, height: int = 768, center=None, source=None,
                     **given) -> PatternSpec:
    """A validated :class:`PatternSpec` of ``codec`` from :data:`CODEC_DEFAULTS`,
    each overridden by a keyword in ``given`` that is not None (``rho0``,
    ``pitch``, ``count``, ``line_width``, ``bits``, ``sector_bits``, ``steps``,
    ``precompensated_gamma``; keywords another codec uses are ignored). ``center`` defaults to the image
    centre ((W-1)/2, (H-1)/2); ``rings``' ``rho0`` to its pitch.

    Raises:
        FormatError: naming ``source`` and the field, as :func:`parse_patterns` does.
    """
    if codec not in CODEC_DEFAULTS:
        raise FormatError(source, f"patterns.codec: unknown codec {codec!r} (known: {', '.join(CODECS)})")
    d = dict(CODEC_DEFAULTS[codec])
    keys = set(d) | {"rho0", "pitch", "precompensated_gamma"}
    d.update({k: v for k, v in given.items() if v is not None and k in keys})
    if codec == "rings" and d.get("rho0") is None:
        d["rho0"] = d["pitch"]
    if center is None:
        center = [(width - 1) / 2.0, (height - 1) / 2.0]
    return parse_patterns({"codec": codec, "width": width, "height": height, "center": list(center), **d},
                          source=source)


def frame_names(spec: PatternSpec) -> list[str]:
    """The frame names of a codec, in projection order."""
    if spec.codec == "rings":
        return ["rings"]
    if spec.codec == "decoded":
        return ["proj_u", "proj_v", "contrast"]
    names = ["white", "black"]
    for b in range(spec.bits):
        names += [f"gray_{b}", f"gray_{b}_inv"]
    for b in range(spec.sector_bits):
        names += [f"sector_{b}", f"sector_{b}_inv"]
    if spec.codec == "phase-rings":
        names += [f"phase_{n}" for n in range(spec.steps)]
    return names


# ----------------------------------------------------------------------------- rendering


