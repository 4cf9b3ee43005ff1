"""Resolved settings of a run, saved as JSON next to every output."""

from __future__ import annotations

from dataclasses import dataclass, field

from ringscan.kernels.angle import AngleSettings
from ringscan.kernels.phase import PhaseSettings
from ringscan.kernels.point_filter import NeighbourFilterSettings
from ringscan.kernels.ring_labels import DecodeSettings
from ringscan.kernels.ring_sampling import SampleSettings
from ringscan.kernels.stereo import MatchSettings
from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.codecs.single_shot.settings import SingleShotSettings

__all__ = ["ReconstructSettings", "StereoSettings", "RAYS"]

RAYS = ("auto", "camera-projector", "camera-camera", "all")
"""``StereoSettings.rays`` values."""


@dataclass(frozen=True)
class StereoSettings:
    """Two-camera views: which rays place a point, and how cameras are matched
    (docs/reconstruction.md "Two cameras")."""

    rays: str = "auto"
    """Which rays place each point: ``camera-projector`` (camera 1 and the
    projector, as for one camera: camera 2 unused), ``camera-camera`` (camera 1
    and camera 2, matched by equal projector coordinate; the projector needs no
    calibration), ``all`` (both cameras and the calibrated projector, weighted
    least squares), or ``auto`` (``all`` where the projector is calibrated, else
    ``camera-camera``; camera 1's samples camera 2 does not see fall back to
    camera-projector where the projector is calibrated; one-camera views:
    ``camera-projector``)."""
    match: MatchSettings = field(default_factory=MatchSettings)
    """Matching camera 1's samples to camera 2 by projector coordinate."""
    min_ray_sin: float = 0.03
    """Least sine of the widest angle between camera 1's ray and another ray
    (about 2 degrees): below it the point is ``ill_conditioned``."""
    max_residual_px: float = 2.0
    """Largest RMS reprojection error (px) of a point's rays: above it the point
    is ``inconsistent`` (a wrong match, a rig that does not fit)."""

    def __post_init__(self):
        if self.rays not in RAYS:
            raise ValueError(f"stereo.rays: must be one of {', '.join(RAYS)}, not {self.rays!r}")
        if not (0 <= self.min_ray_sin < 1):
            raise ValueError(f"stereo.min_ray_sin: must be in [0, 1), got {self.min_ray_sin}")
        if not (self.max_residual_px > 0):
            raise ValueError(f"stereo.max_residual_px: must be > 0, got {self.max_residual_px}")


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
    stereo: StereoSettings = field(default_factory=StereoSettings)
    """Two-camera views: the rays (``--rays``) and the matching."""
    min_confidence: float = 0.0
    """Points below this confidence are not written."""
    threads: int = 0
    """CPU threads for Warp launches on the CPU (0: all cores)."""


