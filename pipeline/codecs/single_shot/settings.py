"""Settings and results of the single-shot ``rings`` labeller."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ringscan.kernels.ring_lines import LineSettings

log = logging.getLogger(__name__)

__all__ = ["SECTOR_BITS", "PHI_BINS", "SingleShotSettings", "RingLabelling"]


SECTOR_BITS = 8


PHI_BINS = 720


@dataclass(frozen=True)
class SingleShotSettings:
    """Settings of the single-shot ``rings`` stage (line detection and labelling)."""

    lines: LineSettings = field(default_factory=LineSettings)
    """Line (ridge) detector thresholds."""
    min_piece_samples: int = 12
    """Pieces with fewer line centres are dropped (noise, scraps at occlusions)."""
    max_normal_turn_deg: float = 30.0
    """Neighbouring centres join the same piece only if their normals turn less."""
    max_piece_step_px: float = 0.8
    """... and if they lie within this distance of each other across the line."""
    fork_px: float = 0.9
    """A centre with two neighbours on one side that lie this far apart across the
    line is a fork (two rings merging where they crowd together): the centres
    within 2 px of it are left out, so that no piece holds two rings."""
    junction_px: float = 3.0
    """Centres up to this far apart are compared for junctions: where their normals
    turn by more than ``junction_deg`` + d / ``min_curvature_radius_px`` (radians)
    over their distance d, two rings' images meet (a ring ending on another where
    the object hides it, a kink): the centres within 2 px are left out, so that no
    piece holds two rings."""
    junction_deg: float = 12.0
    """See ``junction_px``: the turn allowed for noise in the normals."""
    min_curvature_radius_px: float = 8.0
    """See ``junction_px``: the tightest curve (camera px) a ring's own image may
    make. A ring whose whole image is one small clean loop (ring 0 of a pattern
    with a small ``rho0``) may bend more tightly: see ``loop_fit_px``."""
    loop_fit_px: float = 0.35
    """A chain of centres that closes on itself, alone (no other centre within
    ``junction_px``, none inside) and bends more tightly than
    ``min_curvature_radius_px`` allows is still one ring's image when all of its
    centres lie within this distance (camera px) of one fitted ellipse: its bends
    are not taken for junctions, so it can serve as the centre anchor."""
    segment_deg: float = 6.0
    """Curves are cut into pieces (the units that get labels) where two centres
    up to ``junction_px`` apart turn by more than this + d /
    ``segment_curvature_radius_px``, or by more than this while their contrast
    steps by ``segment_contrast_ratio``: where two rings' images might meet
    gently. A label never passes along a curve through such a cut, only across
    gaps from neighbouring rings."""
    segment_curvature_radius_px: float = 30.0
    """See ``segment_deg``."""
    segment_contrast_ratio: float = 1.5
    """See ``segment_deg``."""
    max_gap_px: float = 0.0
    """How far across the dark gap to look for the next ring (camera px);
    0: three times the widest ring spacing on the reference plane."""
    plane_tolerance_px: float = 0.5
    """Plane anchor: largest distance (projector px) between a sample's ray's
    meeting with z = 0 and its ring's circle."""
    plane_min_arc_deg: float = 45.0
    """Plane anchor: the samples on the plane must cover a contiguous arc of at
    least this many degrees of the ring."""
    closed_max_gap_deg: float = 20.0
    """A piece counts as a closed loop when its centres leave no angular gap wider
    than this around the piece's centroid."""
    bump_contrast: float = 2.0
    """A gap between two linked rings must be one clean valley: a rise and fall of
    this many grey levels inside it (a faint ring left undetected between them)
    marks the pair as crossing a hidden ring."""
    max_bump_fraction: float = 0.05
    """A link whose pairs cross a faint ring more often than this is not used."""
    min_link_pairs: int = 8
    """Least number of sample pairs linking two pieces for a label to spread."""
    min_pass_fraction: float = 0.8
    """Least fraction of a link's pairs that must pass the 3D test."""
    min_root_fraction: float = 0.8
    """Least fraction of a piece's samples that must have their root (the one
    whose orientation matches the piece's outward side) under its label."""
    max_step_pitches: float = 8.0
    """Longest 3D step between two linked samples, in ring pitches at the object
    (a continuous surface between two neighbouring rings up to ~83 degrees steep)."""
    min_root_separation_mm: float = 3.0
    """Where a sample's two meetings with its ring lie closer than this (the ray
    nearly grazes the ring's quadric), the orientation does not choose between
    them: the sample's root is left undecided (sector -1)."""
    off_plane_mm: float = 1.0
    """A labelled sample whose root lies more than this above the reference plane
    counts as on the object (report: ``samples_labelled_off_plane``; none of them
    while pieces off the plane were dropped: ``object_unlabelled``)."""
    min_view_cos: float = 0.05
    """The patch between two linked rings must face the camera at least this much
    (cosine of the angle between its normal and the view direction)."""
    min_light_cos: float = 0.05
    """... and the light at least this much."""

    def __post_init__(self):
        if not isinstance(self.lines, LineSettings):
            raise ValueError(f"SingleShotSettings.lines: expected LineSettings, got {type(self.lines).__name__}")
        for name in ("min_piece_samples", "min_link_pairs"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"SingleShotSettings.{name}: expected an integer >= 1, got {v!r}")
        for name in ("max_normal_turn_deg", "max_piece_step_px", "fork_px", "junction_px", "junction_deg",
                     "min_curvature_radius_px", "loop_fit_px", "segment_deg", "segment_curvature_radius_px",
                     "segment_contrast_ratio", "min_root_separation_mm", "off_plane_mm",
                     "plane_tolerance_px", "bump_contrast",
                     "plane_min_arc_deg", "closed_max_gap_deg", "max_step_pitches"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"SingleShotSettings.{name}: must be a finite number > 0, got {v!r}")
        for name in ("min_pass_fraction", "min_root_fraction", "min_view_cos", "min_light_cos", "max_bump_fraction"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 <= v <= 1):
                raise ValueError(f"SingleShotSettings.{name}: must be in [0, 1], got {v!r}")
        if not (isinstance(self.max_gap_px, (int, float)) and math.isfinite(self.max_gap_px) and self.max_gap_px >= 0):
            raise ValueError(f"SingleShotSettings.max_gap_px: must be >= 0, got {self.max_gap_px!r}")


@dataclass
class RingLabelling:
    """Labels of the line samples of one frame (NumPy, one entry per sample)."""

    ring: np.ndarray
    """(n,) int32 ring index j, -1 where the sample's piece was dropped."""
    root: np.ndarray
    """(n,) int8 which meeting of the ray with ring j is the surface (0 nearer,
    1 farther), -1 where the orientation does not decide (or no label)."""
    phi: np.ndarray
    """(n,) float32 polar angle (radians, on the pattern) of the chosen root; NaN
    where ``root`` is -1."""
    piece: np.ndarray
    """(n,) int32 piece of each sample (-1: in no piece)."""
    curve: np.ndarray
    """(n,) int32 curve of each sample (-1: in no curve)."""
    stats: dict
    """Counts: pieces, labelled pieces, anchors, links, conflicts, dropped samples."""
