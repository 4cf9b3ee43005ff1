"""Each kernel stage's settings (frozen dataclasses, one a stage, a docstring a field), in a module with
no kernels of its own: Warp parses every kernel of a module as it is imported (~1-3 ms a kernel), so a
command that only reads settings (a codec's, a run's settings.json) loads no kernel, and a run loads the
kernel modules of the stages it runs (an imported capture's reconstruct, not the phase, ring or line
decoders'). Each kernel module takes its stage's class from here."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

__all__ = ["AngleSettings", "DecodeSettings", "LineSettings", "MatchSettings", "PhaseSettings", "SampleSettings",
           "CONFIDENCE_CONTRAST", "LINE_RATIO", "MAX_NEIGHBOURS"]

CONFIDENCE_CONTRAST = 40.0
"""Contrast (grey levels) at which a line sample's confidence reaches 1 (was the setting
``single_shot.lines.confidence_contrast``: no test, document or benchmark moved it)."""


@dataclass(frozen=True)
class DecodeSettings:
    """Thresholds of the per-pixel decoder."""

    min_contrast: float = 12.0
    """Least white - black difference, in 8-bit grey levels (scaled by 257 for
    16-bit frames), for a pixel to be decoded at all. Shadowed and unlit pixels
    fall below it."""
    bit_margin: float = 0.12
    """A bit is strong when |frame - inverse| >= bit_margin * (white - black). A weak
    bit is not trusted: the pixel keeps no band label (edge sampling still uses it
    as the one bit that flips between two strong neighbours)."""


@dataclass(frozen=True)
class SampleSettings:
    """Settings of the edge sampler."""

    min_contrast: float = 12.0
    """Least white - black (8-bit grey levels; x257 for 16-bit) at both pixels."""
    min_slope: float = 0.3
    """Least |d_p - d_q| / contrast across the edge: flatter crossings (blurred,
    noisy or mixed pixels) are dropped. At 0.15 a projector blur of more than a
    band width (pitch 2 px, sigma 2.5 px) still let through samples whose sub-pixel
    position was off by more than half a band; 0.3 drops them (docs/dense.md). Where
    a projector px spans more than 1.5 camera px (a camera finer than the projector),
    this over that span: the step per projector px (docs/reconstruction.md, "Sample")."""
    ring_curvature: bool = False
    """Remove the inward shift of blurred ring edges: the crossing of a circle of
    radius rho and its inverse, both blurred by a Gaussian of sigma (projector px
    along the radius: projector pixel and defocus, camera pixel and defocus), lies
    inward by sigma^2 / (2 rho), so the sample's rho (its ring's nominal radius)
    reads too large by that much. Each sample's sigma comes from its own edge: the
    slope of frame - inverse at the crossing is 2 C / (sqrt(2 pi) sigma) camera px
    (C: white - black), scaled to projector px by the camera distance to the
    neighbouring band edges (one pitch each); sigma^2 is then the median over the
    samples of each ring (the bias is smooth; single edges are noisy) and rho
    = rho0 + k pitch - sigma^2 / (2 rho) (docs/reconstruction.md, "Sample").
    Off by default: on the virtual rigs the shift is small (0.05 px at rho < 50
    on the two-camera test rig, 0.015 px on the default rig) and, where the camera
    resolves the projector's pixels (the default rig), the estimate reads the
    blur ~2x too large and over-corrects (demo mesh 0.0100 -> 0.0112 mm); where
    camera pixels are coarse (~3 projector px: the two-camera rig) it removes the
    shift and projector-from-scan's position error falls by ~20 % (``ringscan
    calibrate refine`` and ``projector-from-scan`` turn it on by default).
    Off: rho = rho0 + k pitch."""


@dataclass(frozen=True)
class AngleSettings:
    """Settings of the angle decoder."""

    min_contrast: float = 12.0
    """Least white - black difference at the sample, in 8-bit grey levels (x257 for 16-bit)."""
    bit_margin: float = 0.12
    """A sector bit re-read at a sample's own position (where its pixels' sector
    did not decode) is weak when |frame - inverse| < bit_margin x (white - black),
    as the band decode's ``bit_margin``."""
    min_modulation: float = 0.3
    """Least fringe modulation q (linear units, 1 for a perfect fringe): mixed
    pixels, blur finer than the fringe and zone edges fall below it, and the
    sample keeps its ring alone."""
    noise: float = 1.0
    """Camera noise sigma in 8-bit grey levels, for the predicted standard
    deviation of the angle (only its ratio to the ring's matters for the
    weighting; its size sets the reported sigma in mm)."""

    def __post_init__(self):
        for k in ("min_contrast", "bit_margin", "min_modulation", "noise"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"AngleSettings.{k}: must be a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class PhaseSettings:
    """Settings of the phase decoder (``phase-rings``)."""

    response: str = "rig"
    """How recorded values are linearised: ``rig`` uses the rig's camera and light
    gammas; ``estimate`` estimates the camera gamma from the view's own frames
    (light gamma from the rig); ``linear`` takes the frames as they are."""
    weighted: bool = True
    """Weight each phase sample by the inverse of its noise variance after
    linearisation (weighted least squares). Off: the classic N-step formula."""
    min_contrast: float = 12.0
    """Least white - black difference, in 8-bit grey levels (x257 for 16-bit)."""
    min_modulation: float = 0.3
    """Least fringe modulation q = 2 B / (white - black), linear units: a clean
    fringe at the default pitch gives 0.8 - 1; mixed, blurred or grazing pixels
    fall below 0.3."""
    edge_ratio: float = 0.5
    """A pixel is in an edge's transition zone where that edge's bit has
    |frame - inverse| < edge_ratio * (white - black): the band code may name
    either side there, so the edge itself anchors the unwrapping."""
    slip_tolerance: float = 0.05
    """How far (bands) the phase may put a pixel across an edge against a strong
    edge bit before the pixel is dropped as a slip."""
    smooth_radius: int = 1
    """Half-size of the smoothing window in pixels (0: no smoothing)."""
    smooth_tolerance: float = 0.05
    """A neighbour pair joins the average when its mean t is within this many
    bands of the pixel's own t."""
    min_pairs: int = 1
    """With smoothing, pixels with valid neighbours but fewer agreeing pairs than
    this are dropped as lonely (0: keep them)."""
    ring_curvature: bool = True
    """Remove the outward bias of averaged rings: any averaging across a ring (the
    projector's pixel and defocus, the camera pixel, the smoothing window) reads
    rho too large by (tangential variance) / (2 rho), since rho = |p - c| is
    convex. The light's and the camera pixel's variance comes from the lost
    fringe modulation, the window's from its pairs and the gradient of t
    (docs/dense.md, "Ring curvature"). Off: rho as averaged."""

    def __post_init__(self):
        if self.response not in ("rig", "estimate", "linear"):
            raise ValueError(f"PhaseSettings.response: expected rig, estimate or linear, got {self.response!r}")
        if not 0 <= self.smooth_radius <= 4:
            raise ValueError(f"PhaseSettings.smooth_radius: must be in 0..4, got {self.smooth_radius}")
        if not 0 < self.edge_ratio < 1:
            raise ValueError(f"PhaseSettings.edge_ratio: must be in (0, 1), got {self.edge_ratio}")
        if self.min_modulation < 0 or self.slip_tolerance < 0 or self.smooth_tolerance < 0 or self.min_pairs < 0:
            raise ValueError("PhaseSettings: min_modulation, slip_tolerance, smooth_tolerance and min_pairs must be >= 0")


@dataclass(frozen=True)
class LineSettings:
    """Settings of the line (ridge) detector."""

    sigma: float = 1.2
    """Gaussian smoothing in camera pixels before differentiation. A line of width
    w camera pixels needs sigma >= w / (2 sqrt 3) for one clean maximum across it;
    a larger sigma merges rings that lie close together in the image."""
    min_contrast: float = 6.0
    """Least height of the line's peak above the local background on both of its
    sides, in 8-bit grey levels (of the smoothed image)."""
    min_curvature: float = 0.4
    """Least -lambda (grey levels per px^2 of the smoothed image): the profile
    across the line must bend down at least this much at its centre."""
    max_eigen_ratio: float = 0.6
    """The eigenvalue along the line may be at most this fraction of |lambda|:
    blobs and crossings (both eigenvalues alike) are not lines."""
    max_tangent_slope: float = 1.0
    """Along the line the image may climb at most this many px times -lambda per
    px: the flanks of a tightly curved line (where the profile along the line's
    tangent also bends down) are not line centres."""
    background_px: float = 3.0
    """Distance (camera px) from the centre, along the normal, where the local
    background is read on each side."""

    RETIRED: ClassVar[dict] = {"confidence_contrast": CONFIDENCE_CONTRAST}
    """Former fields, now fixed (``formats.settings``: a settings file that names one
    with this value loads)."""

    def __post_init__(self):
        for name in ("sigma", "background_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"LineSettings.{name}: must be a finite number > 0, got {v!r}")
        for name in ("min_contrast", "min_curvature", "max_eigen_ratio", "max_tangent_slope"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"LineSettings.{name}: must be a finite number >= 0, got {v!r}")
        if self.sigma > 20:
            raise ValueError(f"LineSettings.sigma: {self.sigma} px is too large (at most 20)")


MAX_NEIGHBOURS = 16
"""Largest ``MatchSettings.neighbours`` (the match kernel's fixed local arrays)."""
LINE_RATIO = 0.02
"""Where a match's neighbours' spread across their main direction (variance) is below this
fraction of the spread along it, they lie on a line (a ring edge) and the map is fitted along
the line only (was the setting ``stereo.match.line_ratio``: no test, document or benchmark
moved it)."""


@dataclass(frozen=True)
class MatchSettings:
    """How a camera-1 sample finds its camera-2 position."""

    RETIRED: ClassVar[dict] = {"line_ratio": LINE_RATIO}
    """Former fields, now fixed (``formats.settings``: a settings file that names one
    with this value loads)."""

    cell_px: float = 4.0
    """The grid's cell size in projector pixels: the search grows ring of cells
    by ring of cells until it has found the nearest ``neighbours``."""
    radius_px: float = 16.0
    """Largest search radius in projector pixels: wide enough for the samples'
    spacing (a camera pixel is ~4 projector pixels on a coarse camera)."""
    neighbours: int = 8
    """How many nearest camera-2 samples (in projector space) the local affine
    fit uses, at most ``MAX_NEIGHBOURS``."""
    min_neighbours: int = 4
    """Fewest neighbours a fit needs (a line fit needs 2, an affine map 3; more
    gives the residual that detects a discontinuity)."""
    max_offset_px: float = 0.1
    """On a line fit: the farthest (projector px) the query may lie off the
    neighbours' curve (a quadratic through them: a ring edge's arc); the map
    across it is unknown, so each 0.1 px off costs ~0.1 camera px."""
    max_extrapolation: float = 2.0
    """The farthest the query may lie from the neighbours' weighted mean, in
    their standard deviations along each fitted direction."""
    max_fit_px: float = 0.5
    """Largest RMS residual (camera-2 px) of the affine fit: above it the
    neighbours straddle a depth discontinuity (or a decode error)."""
    max_gain: float = 20.0
    """Largest camera-2 px per projector px of the fitted map (Frobenius norm /
    sqrt 2): beyond it neighbours close in projector space are far apart in the
    image (a discontinuity)."""

    def __post_init__(self):
        if not (self.cell_px > 0 and self.radius_px >= self.cell_px):
            raise ValueError(f"match: need 0 < cell_px <= radius_px, got {self.cell_px}, {self.radius_px}")
        if not (2 <= self.min_neighbours <= self.neighbours <= MAX_NEIGHBOURS):
            raise ValueError(f"match: need 2 <= min_neighbours <= neighbours <= {MAX_NEIGHBOURS}, "
                             f"got {self.min_neighbours}, {self.neighbours}")
        for name in ("max_offset_px", "max_extrapolation", "max_fit_px", "max_gain"):
            if not (getattr(self, name) > 0):
                raise ValueError(f"match.{name}: must be > 0, got {getattr(self, name)}")
