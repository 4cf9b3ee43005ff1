"""Resolved settings of a run, saved as JSON next to every output."""

from __future__ import annotations

from dataclasses import dataclass, field

from ringscan.kernels.angle import AngleSettings
from ringscan.kernels.phase import PhaseSettings
from ringscan.kernels.point_filter import NeighbourFilterSettings
from ringscan.kernels.ring_labels import DecodeSettings
from ringscan.kernels.ring_sampling import SampleSettings
from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.codecs.single_shot.settings import SingleShotSettings

__all__ = ["ReconstructSettings"]


@dataclass(frozen=True)
class ReconstructSettings:
    """Settings of ``ringscan reconstruct``: one block per stage."""

    decode: DecodeSettings = field(default_factory=DecodeSettings)
    """Per-pixel decoding thresholds."""
    sample: SampleSettings = field(default_factory=SampleSettings)
    """Sub-pixel ring sampling thresholds."""
    triangulate: TriangulateSettings = field(default_factory=TriangulateSettings)
    """Root choice (docs/design.md §4)."""
    filter: NeighbourFilterSettings = field(default_factory=NeighbourFilterSettings)
    """Image-space neighbour filter (mixed pixels, isolated outliers)."""
    phase: PhaseSettings = field(default_factory=PhaseSettings)
    """Phase decoder of the ``phase-rings`` codec (response, modulation, unwrapping)."""
    single_shot: SingleShotSettings = field(default_factory=SingleShotSettings)
    """Line detection and nesting-order labelling of the single-shot ``rings`` codec."""
    angle: AngleSettings = field(default_factory=AngleSettings)
    """The angle code's decoder and the camera noise of the predicted standard deviations."""
    min_confidence: float = 0.0
    """Points below this confidence are not written."""
    threads: int = 0
    """CPU threads for Warp launches on the CPU (0: all cores)."""


