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
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass

import numpy as np

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.limits import MAX_IMAGE_PIXELS

PRECOMPENSATED_GAMMA_RANGE = (0.1, 10.0)
"""Accepted ``precompensated_gamma`` (the rig's range of response gammas)."""
MAX_ANGLE_ZONES = 16
"""Most zones of the angle code (P doubles from one to the next)."""
DECODED_SCALE = 32
"""``decoded`` frames: 16-bit value = round((projector coordinate + 1) * scale), 0 = not decoded; ``scale``
(scan.json ``patterns.scale``) is this for a projector of up to 2047 px a side, and halves for each doubling
beyond (:func:`decoded_scale`), so that every coordinate fits 16 bits."""


def decoded_scale(width: int, height: int) -> int:
    """The ``decoded`` maps' fixed-point steps a projector px for a projector of ``width`` x ``height``: the
    largest power of two up to ``DECODED_SCALE`` at which (the largest coordinate + 1) fits 16 bits (a
    coordinate reaches side - 0.5): 32 up to 2047 px, 16 up to 4095, 8 up to 8191, ... 1 up to 65534.

    Raises:
        ValueError: a side of 65535 px or more (no 16-bit map holds it)."""
    side = max(int(width), int(height))
    s = DECODED_SCALE
    while s > 1 and (side + 0.5) * s > 65535:
        s //= 2
    if (side + 0.5) * s > 65535:
        raise ValueError(f"a projector side of {side} px does not fit the 16-bit decoded maps (at most 65534)")
    return s

__all__ = ["CODECS", "IMPORTED_CODECS", "DECODED_SCALE", "decoded_scale", "PRECOMPENSATED_GAMMA_RANGE", "CODEC_DEFAULTS", "PatternSpec",
           "PatternLayout", "Parameter", "PATTERN_LAYOUTS", "angle_zones", "angle_periods", "spec_angle_zones", "pattern_layout", "parse_patterns", "default_patterns",
           "frame_names", "gray_encode", "gray_decode",
           "PatternOption", "pattern_options"]


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
    angle_steps: int = 0
    """Phase steps of the angle code (``angle_<n>`` frames: angular fringes around the
    centre, gray-rings and phase-rings); 0 = no angle code."""
    angle_period: float = 12.0
    """Least period (projector px) of the angular fringes at the inner radius of each
    zone; the number of periods doubles outward in zones (:func:`angle_zones`)."""
    scale: int = DECODED_SCALE
    """Fixed-point steps a projector px of the ``decoded`` maps (:func:`decoded_scale`)."""

    @property
    def layout(self) -> PatternLayout:
        """The data-level description of this spec's codec (:data:`PATTERN_LAYOUTS`).

        Raises:
            FormatError: an unknown codec.
        """
        return pattern_layout(self.codec)

    @property
    def n_bands(self) -> int:
        """Number of coded bands (2**bits), or of rings for the single-shot codec."""
        return self.layout.n_bands(self)

    @property
    def rho_max(self) -> float:
        """Outer radius of the coded annulus (projector px)."""
        return self.layout.rho_max(self)

    def ring_radii(self) -> np.ndarray:
        """Radii (projector px) of the sampled rings: the lines of ``rings``, or the
        band boundaries k = 1..2**bits-1 of the binary codecs (index k-1)."""
        return self.layout.ring_radii(self)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["center"] = list(self.center)
        keep = {"codec", "width", "height", "center", "rho0", "pitch"} | {p.name for p in self.layout.parameters}
        if self.precompensated_gamma != 1.0:
            keep |= {"precompensated_gamma"}
        if not self.angle_steps:  # scans without an angle code keep their scan.json as it was
            keep -= {"angle_steps", "angle_period"}
        return {k: v for k, v in d.items() if k in keep}


# ----------------------------------------------------------------------------- codec layouts


@dataclass(frozen=True)
class Parameter:
    """One codec-specific field of scan.json ``patterns`` (a :class:`PatternSpec` field)."""

    name: str
    """Field name (also the ``PatternSpec`` attribute)."""
    kind: type
    """``int`` or ``float``."""
    default: int | float | None = None
    """Value when the field is absent; None = required."""
    lo: int | float | None = None
    """Least value (integers: inclusive); for floats only ``positive`` is checked."""
    hi: int | float | None = None
    """Largest value (integers: inclusive)."""
    positive: bool = False
    """Floats: must be > 0."""
    doc: str = ""
    """What it means (``ringscan patterns --help``, docs/formats.md)."""

    def parse(self, d: dict, src) -> int | float:
        """The checked value of this field in ``d``.

        Raises:
            FormatError: naming ``src`` and ``patterns.<name>``.
        """
        v = d.get(self.name, self.default)
        if self.kind is int:
            if isinstance(v, bool) or not isinstance(v, int):
                raise FormatError(src, f"patterns.{self.name}: expected an integer, got {v!r}")
            if (self.lo is not None and v < self.lo) or (self.hi is not None and v > self.hi):
                raise FormatError(src, f"patterns.{self.name}: must be in [{self.lo}, {self.hi}], got {v}")
            return v
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise FormatError(src, f"patterns.{self.name}: expected a finite number, got {v!r}")
        if self.positive and v <= 0:
            raise FormatError(src, f"patterns.{self.name}: must be > 0, got {v}")
        return v


class PatternLayout(ABC):
    """The data-level description of one codec: its name, its parameters (with
    defaults and ranges), its frame names and the checks of its values. It lives
    here, below the codecs, because reading a scan folder needs the frame names;
    the codec's behaviour (render, extract, explain) is its ``Codec`` class in
    ``pipeline.codecs``. A layout's frame list may depend on any of its parameters.
    """

    name: str = ""
    """The codec name (scan.json ``patterns.codec``)."""
    projectable: bool = True
    """Its frames are projected (False: imported captures, nothing to render)."""
    dense: bool = False
    """One sample per decoded pixel (no rings: samples are not one band apart)."""
    parameters: tuple[Parameter, ...] = ()
    """Codec-specific fields, in scan.json order (beyond width, height, center, rho0, pitch)."""
    defaults: dict = {}
    """Defaults of ``ringscan patterns`` / ``simulate`` for every option not given."""

    @abstractmethod
    def frame_names(self, spec: PatternSpec) -> list[str]:
        """The frame names, in projection (and file) order."""

    def n_bands(self, spec: PatternSpec) -> int:
        return 2 ** spec.bits

    def ring_radii(self, spec: PatternSpec) -> np.ndarray:
        return spec.rho0 + spec.pitch * np.arange(1, self.n_bands(spec))

    def rho_max(self, spec: PatternSpec) -> float:
        return spec.rho0 + self.n_bands(spec) * spec.pitch

    def fill_defaults(self, d: dict) -> None:
        """Fill defaults that depend on other values (``default_patterns``)."""

    def check_values(self, kw: dict, pitch: float, src) -> None:
        """Checks between parameters, before the spec is built (raise FormatError)."""

    def check_fits(self, spec: PatternSpec, far: float, src) -> None:
        """Checks against the projector image (``far``: centre to farthest corner, px)."""


ANGLE_PARAMETERS = (
    Parameter("angle_steps", int, 0, 0, 16, doc="phase steps of the angle code (angle_<n> frames); 0 = none, else >= 3"),
    Parameter("angle_period", float, 12.0, positive=True,
              doc="least period (projector px) of the angular fringes at each zone's inner radius"),
)


def angle_frame_names(spec: PatternSpec) -> list[str]:
    """The frames of the angle code (none without one)."""
    return [f"angle_{n}" for n in range(spec.angle_steps)]


def check_angle_values(kw: dict, src) -> None:
    if kw["angle_steps"] in (1, 2):
        raise FormatError(src, f"patterns.angle_steps: {kw['angle_steps']} steps cannot give a phase; use 0 (none) or >= 3")
    if kw["angle_period"] < 4.0:
        raise FormatError(src, f"patterns.angle_period: {kw['angle_period']} px is too fine to project (>= 4)")


def angle_zones(*, rho0: float, pitch: float, bands: int, sector_bits: int, min_period_px: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """The zones of the angle code: (inner radius of each zone, its periods P).

    P is a power of two, the largest whose period 2 pi rho / P at the zone's
    inner radius is at least ``min_period_px``, at most 2^(sector_bits - 1) (so the
    sector code unwraps it with half a period to spare), at least 1. Zones start
    at ``rho0`` and then at band centres rho0 + (k + 0.5) pitch, k < ``bands``.

    Returns:
        (rho_start (Z,) float32 ascending, periods (Z,) int32 doubling).
    """
    if not (pitch > 0 and rho0 >= 0 and bands >= 1 and min_period_px > 0):
        raise ValueError(f"angle_zones: need pitch > 0, rho0 >= 0, bands >= 1, min_period_px > 0; got "
                         f"{pitch}, {rho0}, {bands}, {min_period_px}")
    if sector_bits < 0:
        raise ValueError(f"angle_zones: sector_bits must be >= 0, got {sector_bits}")
    p_max = 2 ** max(sector_bits - 1, 0)

    def fits(rho):  # largest power of two with 2 pi rho / P >= min_period
        n = 2 * math.pi * rho / min_period_px
        return 1 if n < 2 else min(p_max, 2 ** int(math.floor(math.log2(n))))

    starts, periods = [float(rho0)], [fits(rho0)]
    for k in range(bands):
        r = rho0 + (k + 0.5) * pitch
        if periods[-1] >= p_max or len(starts) >= MAX_ANGLE_ZONES:
            break
        p = fits(r)
        if p > periods[-1]:
            starts.append(r)
            periods.append(p)
    return np.asarray(starts, np.float32), np.asarray(periods, np.int32)


def angle_periods(rho, starts: np.ndarray, periods: np.ndarray) -> np.ndarray:
    """Periods P at radii ``rho`` (array) for the zones of :func:`angle_zones`."""
    idx = np.searchsorted(np.asarray(starts, np.float64), np.asarray(rho, np.float64), side="right") - 1
    return np.asarray(periods)[np.clip(idx, 0, len(periods) - 1)]


def spec_angle_zones(spec: "PatternSpec") -> tuple[np.ndarray, np.ndarray]:
    """The angle code's zones of a pattern (:func:`angle_zones` of its annulus, sector bits and ``angle_period``)."""
    return angle_zones(rho0=spec.rho0, pitch=spec.pitch, bands=spec.n_bands, sector_bits=spec.sector_bits,
                       min_period_px=spec.angle_period)


class GrayRingsLayout(PatternLayout):
    name = "gray-rings"
    parameters = (
        Parameter("bits", int, None, 1, 16, doc="Gray-code bits of the band index"),
        Parameter("sector_bits", int, 0, 0, 12, doc="Gray-code bits of the angular sector; 0 = none"),
    ) + ANGLE_PARAMETERS
    # 9 sector bits let the angle reach P = 256 periods, 8 px ones from rho 326 on, so phi stays sharp out to
    # the annulus's rim (docs/dense.md, "How sharp"; docs/accuracy.md: oblique rig 0.15x -> 0.11x, 2 more frames)
    defaults = {"rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 9, "angle_steps": 4, "angle_period": 8.0}

    def binary_frame_names(self, spec: PatternSpec) -> list[str]:
        names = ["white", "black"]
        for b in range(spec.bits):
            names += [f"gray_{b}", f"gray_{b}_inv"]
        for b in range(spec.sector_bits):
            names += [f"sector_{b}", f"sector_{b}_inv"]
        return names

    def frame_names(self, spec: PatternSpec) -> list[str]:
        return self.binary_frame_names(spec) + angle_frame_names(spec)

    def check_values(self, kw: dict, pitch: float, src) -> None:
        if pitch < 1.0:
            raise FormatError(src, f"patterns.pitch: {pitch} px is below one projector pixel; binary bands cannot be shown")
        check_angle_values(kw, src)


class PhaseRingsLayout(GrayRingsLayout):
    name = "phase-rings"
    dense = True
    parameters = GrayRingsLayout.parameters + (Parameter("steps", int, 4, 3, 64, doc="phase steps"),)
    defaults = {"rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 9, "steps": 8, "angle_steps": 4,
                "angle_period": 8.0}

    def frame_names(self, spec: PatternSpec) -> list[str]:
        # the angle frames last, so every other frame keeps its index with or without them
        return (self.binary_frame_names(spec) + [f"phase_{n}" for n in range(spec.steps)]
                + angle_frame_names(spec))


class RingsLayout(PatternLayout):
    name = "rings"
    parameters = (
        Parameter("count", int, None, 1, 100000, doc="number of rings"),
        Parameter("line_width", float, 2.0, positive=True, doc="width of each ring line (projector px)"),
    )
    defaults = {"count": 9, "pitch": 40.0, "line_width": 3.0}

    def frame_names(self, spec: PatternSpec) -> list[str]:
        return ["rings"]

    def n_bands(self, spec: PatternSpec) -> int:
        return spec.count

    def ring_radii(self, spec: PatternSpec) -> np.ndarray:
        return spec.rho0 + spec.pitch * np.arange(spec.count)

    def rho_max(self, spec: PatternSpec) -> float:
        return spec.rho0 + (spec.count - 1) * spec.pitch + 0.5 * spec.line_width

    def fill_defaults(self, d: dict) -> None:
        # ring 0 one ring spacing across the centre: large enough to be seen as
        # the loop that anchors the labels (docs/single_shot.md)
        if d.get("rho0") is None:
            d["rho0"] = d["pitch"]

    def check_values(self, kw: dict, pitch: float, src) -> None:
        if kw["line_width"] >= pitch:
            raise FormatError(src, f"patterns.line_width: {kw['line_width']} px does not fit in pitch {pitch} px (rings would touch)")

    def check_fits(self, spec: PatternSpec, far: float, src) -> None:
        if spec.ring_radii()[-1] > far:
            n_in = int(np.sum(spec.ring_radii() <= far))
            raise FormatError(src, f"patterns.count: only {n_in} of {spec.count} rings fit on the {spec.width}x{spec.height} projector")


class DecodedLayout(PatternLayout):
    name = "decoded"
    projectable = False
    dense = True
    parameters = (Parameter("sector_bits", int, 8, 0, 12, doc="bits of the polar-angle sector for the root choice"),
                  Parameter("scale", int, DECODED_SCALE, 1, DECODED_SCALE,
                            doc="the maps' fixed-point steps a projector px (decoded_scale: 32 up to 2047 px)"))

    def frame_names(self, spec: PatternSpec) -> list[str]:
        return ["proj_u", "proj_v", "contrast"]


PATTERN_LAYOUTS: dict[str, PatternLayout] = {
    layout.name: layout for layout in (RingsLayout(), GrayRingsLayout(), PhaseRingsLayout(), DecodedLayout())
}
"""codec name -> its data-level description; the behaviour of each is its ``Codec``
in ``pipeline.codecs`` (``codecs.registry``)."""
CODECS = tuple(k for k, layout in PATTERN_LAYOUTS.items() if layout.projectable)
"""The projectable codecs (``ringscan patterns``, ``simulate``, ``capture``)."""
IMPORTED_CODECS = tuple(k for k, layout in PATTERN_LAYOUTS.items() if not layout.projectable)
"""Codecs of imported captures (not projectable): ``decoded`` holds each camera pixel's
decoded projector position (``ringscan import``)."""
CODEC_DEFAULTS: dict[str, dict] = {k: dict(PATTERN_LAYOUTS[k].defaults) for k in CODECS}
"""Default parameters of each projectable codec (``ringscan patterns`` and
``simulate`` use them for every option not given). ``rings`` has no fixed
``rho0``: it defaults to the pitch, so ring 0 is a circle one ring spacing
across the centre, large enough to be seen as the loop that anchors the labels
of the rings wholly on an object (docs/single_shot.md)."""


def pattern_layout(codec: str, *, source=None) -> PatternLayout:
    """The :class:`PatternLayout` of ``codec``.

    Raises:
        FormatError: an unknown codec, naming ``source``.
    """
    layout = PATTERN_LAYOUTS.get(codec) if isinstance(codec, str) else None
    if layout is None:
        raise FormatError(source, f"patterns.codec: unknown codec {codec!r} (known: {', '.join(PATTERN_LAYOUTS)})")
    return layout


def parse_patterns(d: dict, *, source: str | os.PathLike | None = None) -> PatternSpec:
    """Validate a ``patterns`` dictionary and build a :class:`PatternSpec`.

    Raises:
        FormatError: naming ``source`` and the field for every problem.
    """
    src = source
    if not isinstance(d, dict):
        raise FormatError(src, "patterns: expected an object")
    codec = d.get("codec")
    layout = pattern_layout(codec, source=src)

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
    if width * height > MAX_IMAGE_PIXELS:  # every frame is drawn at this size
        raise FormatError(src, f"patterns: {width}x{height} is {width * height / 1e6:.0f} megapixels: larger than "
                               f"the images ringscan reads ({MAX_IMAGE_PIXELS / 1e6:.0f} megapixels)")
    center = d.get("center")
    if not (isinstance(center, (list, tuple)) and len(center) == 2
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in center)):
        raise FormatError(src, f"patterns.center: expected [c_u, c_v], got {center!r}")
    if layout.projectable and not (0 <= center[0] <= width - 1 and 0 <= center[1] <= height - 1):
        raise FormatError(src, f"patterns.center: {list(center)} lies outside the {width}x{height} projector")
    rho0 = num("rho0")
    if rho0 < 0:
        raise FormatError(src, f"patterns.rho0: must be >= 0, got {rho0}")
    pitch = num("pitch", positive=True)
    kw = {p.name: p.parse(d, src) for p in layout.parameters}
    layout.check_values(kw, pitch, src)
    if "precompensated_gamma" in d:
        if not layout.projectable:
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
    if layout.projectable and spec.rho0 >= far:
        raise FormatError(src, f"patterns.rho0: {spec.rho0} px lies outside the projector (farthest corner {far:.1f} px)")
    layout.check_fits(spec, far, src)
    return spec


def default_patterns(codec: str, *, width: int = 1024, height: int = 768, center=None, source=None,
                     **given) -> PatternSpec:
    """A validated :class:`PatternSpec` of ``codec`` from :data:`CODEC_DEFAULTS`,
    each overridden by a keyword in ``given`` that is not None (``rho0``,
    ``pitch``, ``count``, ``line_width``, ``bits``, ``sector_bits``, ``steps``,
    ``angle_steps``, ``angle_period``, ``precompensated_gamma``; keywords another codec uses are ignored). ``center`` defaults to the image
    centre ((W-1)/2, (H-1)/2); ``rings``' ``rho0`` to its pitch.

    Raises:
        FormatError: naming ``source`` and the field, as :func:`parse_patterns` does.
    """
    if codec not in CODEC_DEFAULTS:
        raise FormatError(source, f"patterns.codec: unknown codec {codec!r} (known: {', '.join(CODECS)})")
    layout = PATTERN_LAYOUTS[codec]
    d = dict(CODEC_DEFAULTS[codec])
    keys = set(d) | {"rho0", "pitch", "precompensated_gamma"}
    d.update({k: v for k, v in given.items() if v is not None and k in keys})
    layout.fill_defaults(d)
    if center is None:
        center = [(width - 1) / 2.0, (height - 1) / 2.0]
    return parse_patterns({"codec": codec, "width": width, "height": height, "center": list(center), **d},
                          source=source)


def frame_names(spec: PatternSpec) -> list[str]:
    """The frame names of a codec, in projection order (its :class:`PatternLayout`)."""
    return spec.layout.frame_names(spec)


# ----------------------------------------------------------------------------- command-line options


@dataclass(frozen=True)
class PatternOption:
    """One codec option of ``ringscan patterns`` and ``simulate`` (added by
    ``tools.cmd_patterns``): a keyword of :func:`default_patterns`. Not given, it
    takes its codec's default (:data:`CODEC_DEFAULTS`)."""

    flag: str
    """The option, e.g. ``--sector-bits``."""
    dest: str
    """The :func:`default_patterns` keyword (a :class:`PatternSpec` field)."""
    type: type
    """``int`` or ``float``."""
    help: str
    """Its ``--help`` text (naming the codecs' defaults)."""
    metavar: str | None = None
    """Its ``--help`` placeholder (None: argparse's)."""


def pattern_options() -> tuple[PatternOption, ...]:
    """The codec options of the pattern set, in ``--help`` order: the parameters of
    the projectable codecs' layouts plus ``rho0`` and ``pitch``, each help naming
    the defaults of :data:`CODEC_DEFAULTS` (the one place on the command line that
    names the codecs)."""
    gd, rd, pd = CODEC_DEFAULTS["gray-rings"], CODEC_DEFAULTS["rings"], CODEC_DEFAULTS["phase-rings"]
    return (
        PatternOption("--bits", "bits", int, f"Gray-code bits of the band index (default {gd['bits']})"),
        PatternOption("--pitch", "pitch", float, f"projector px per band (default {gd['pitch']:g}; {rd['pitch']:g} for "
                                                 "rings)"),
        PatternOption("--rho0", "rho0", float,
                      f"inner radius in projector px (default {gd['rho0']:g}; the pitch for rings)"),
        PatternOption("--sector-bits", "sector_bits", int,
                      f"Gray-code bits of the angular sector (default {gd['sector_bits']}; 0 = none; not for rings)"),
        PatternOption("--count", "count", int, f"rings of the single-shot codec (default {rd['count']})"),
        PatternOption("--line-width", "line_width", float,
                      f"ring line width in px, rings codec (default {rd['line_width']:g})"),
        PatternOption("--steps", "steps", int, f"phase steps, phase-rings codec (default {pd['steps']})"),
        PatternOption("--angle-steps", "angle_steps", int,
                      "phase steps of the angle code (angular fringes around the centre, so every point gets "
                      f"both projector coordinates; gray-rings and phase-rings; default {gd['angle_steps']}; "
                      "0 = none (rings alone, the paper's patterns), else >= 3)"),
        PatternOption("--angle-period", "angle_period", float,
                      f"least period of the angular fringes, projector px (default {gd['angle_period']:g})",
                      metavar="PX"),
    )


# ----------------------------------------------------------------------------- rendering


