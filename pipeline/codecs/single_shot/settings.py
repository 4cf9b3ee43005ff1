"""Settings and results of the single-shot ``rings`` labeller."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, fields
from typing import ClassVar

import numpy as np

from ringscan.kernels.settings import LineSettings
from ringscan.pipeline.formats.settings import WHY_CAM_PX, WHY_LEVELS, WHY_MM, Bound

log = logging.getLogger(__name__)

__all__ = ["SECTOR_BITS", "PHI_BINS", "SingleShotSettings", "SETTING_RANGES", "LabelTuning", "TUNING", "RingLabelling"]


SECTOR_BITS = 8


PHI_BINS = 720


@dataclass(frozen=True)
class LabelTuning:
    """The labeller's fixed thresholds: how centres join pieces, where pieces are cut,
    how a label is anchored and spread (``TUNING``). Not settings: no test, document or
    benchmark has needed another value, and a user cannot judge them from a scan; they
    were ``single_shot.*`` settings until 0.1 (a settings file that names one with its
    old default still loads)."""

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
    plane_tolerance_px: float = 0.5
    """Plane anchor: largest distance (projector px) between a sample's ray's
    meeting with z = 0 and its ring's circle."""
    plane_min_arc_deg: float = 45.0
    """Plane anchor: the samples on the plane must cover a contiguous arc of at
    least this many degrees of the ring."""
    closed_max_gap_deg: float = 20.0
    """A piece counts as a closed loop when its centres leave no angular gap wider
    than this around the piece's centroid."""
    max_bump_fraction: float = 0.05
    """A link whose pairs cross a faint ring more often than this is not used."""
    min_link_pairs: int = 8
    """Least number of sample pairs linking two pieces for a label to spread."""
    min_pass_fraction: float = 0.8
    """Least fraction of a link's pairs that must pass the 3D test."""
    min_root_fraction: float = 0.8
    """Least fraction of a piece's samples that must have their root (the one
    whose orientation matches the piece's outward side) under its label."""
    max_step_pitches: float = 3.0
    """Longest 3D step between two linked samples, in ring pitches at the object
    (a continuous surface between two neighbouring rings up to ~71 degrees steep).
    A steeper step may hide a ring on a face the light does not reach (a block's
    front face): with 8 pitches the corner scene's V-groove was labelled one ring
    off (10-30 mm); a piece reached only across such a step is left unlabelled."""
    min_root_separation_mm: float = 3.0
    """Where a sample's two meetings with its ring lie closer than this (the ray
    nearly grazes the ring's quadric), the orientation does not choose between
    them: the sample's root is left undecided (sector -1)."""


TUNING = LabelTuning()
"""The values the labeller uses."""


@dataclass(frozen=True)
class SingleShotSettings:
    """Settings of the single-shot ``rings`` stage (line detection and labelling)."""

    RETIRED: ClassVar[dict] = {f.name: f.default for f in fields(LabelTuning)}
    """Former fields, now the labeller's fixed :data:`TUNING`: a settings file that
    names one with this value loads (``formats.settings``)."""

    lines: LineSettings = field(default_factory=LineSettings)
    """Line (ridge) detector thresholds."""
    min_piece_samples: int = 12
    """Pieces with fewer line centres are dropped (noise, scraps at occlusions)."""
    loop_fit_px: float = 0.35
    """A chain of centres that closes on itself, alone (no other centre within
    ``TUNING.junction_px``, none inside) and bends more tightly than
    ``TUNING.min_curvature_radius_px`` allows is still one ring's image when all of its
    centres lie within this distance (camera px) of one fitted ellipse: its bends
    are not taken for junctions, so it can serve as the centre anchor."""
    max_gap_px: float = 0.0
    """How far across the dark gap to look for the next ring (camera px);
    0: three times the widest ring spacing on the reference plane."""
    bump_contrast: float = 2.0
    """A gap between two linked rings must be one clean valley: a rise and fall of
    this many grey levels inside it (a faint ring left undetected between them)
    marks the pair as crossing a hidden ring."""
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
        v = self.min_piece_samples
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"SingleShotSettings.min_piece_samples: expected an integer >= 1, got {v!r}")
        for name in ("loop_fit_px", "off_plane_mm", "bump_contrast"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"SingleShotSettings.{name}: must be a finite number > 0, got {v!r}")
        for name in ("min_view_cos", "min_light_cos"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 <= v <= 1):
                raise ValueError(f"SingleShotSettings.{name}: must be in [0, 1], got {v!r}")
        if not (isinstance(self.max_gap_px, (int, float)) and math.isfinite(self.max_gap_px) and self.max_gap_px >= 0):
            raise ValueError(f"SingleShotSettings.max_gap_px: must be >= 0, got {self.max_gap_px!r}")


SETTING_RANGES: dict[str, Bound] = {
    "lines.sigma": Bound(0, 20, "camera px: a larger Gaussian merges neighbouring rings",
                         lo_open=True),
    "lines.min_contrast": Bound(0, 200, WHY_LEVELS + "; above 200 only a nearly full-range line passes"),
    "lines.min_curvature": Bound(0, 1020, "grey levels per px^2: a second difference of 8-bit "
                                          "values is at most 4 x 255"),
    "lines.max_eigen_ratio": Bound(0, 1, "a ratio of eigenvalues: above 1 a blob passes as a line"),
    "lines.max_tangent_slope": Bound(0, 100, "px times -lambda per px: beyond 100 every flank "
                                             "passes as a centre"),
    "lines.background_px": Bound(0, 64, "camera px: beyond 64 the background is read on the next "
                                        "rings", lo_open=True),
    "min_piece_samples": Bound(1, 200000, "line centres: the longest ring on the largest camera "
                                          "(2 pi 32768 px) has fewer"),
    "loop_fit_px": Bound(0, 65536, WHY_CAM_PX, lo_open=True),
    "max_gap_px": Bound(0, 65536, WHY_CAM_PX + "; 0: three ring spacings"),
    "bump_contrast": Bound(0, 255, WHY_LEVELS, lo_open=True),
    "off_plane_mm": Bound(0, 1e5, WHY_MM, lo_open=True),
    "min_view_cos": Bound(0, 1, "a cosine: at most 1 (facing straight on)"),
    "min_light_cos": Bound(0, 1, "a cosine: at most 1 (facing straight on)"),
}
"""Each numeric field's range, and why, by its path in :class:`SingleShotSettings`
(``reconstruct.SETTING_RANGES`` holds them under ``single_shot.``)."""


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
    gap: np.ndarray | None = None
    """(n, 2) float32 distance (camera px) along +normal and -normal to the next line met across
    the sample's (``kernels.ring_links.link_lines``), 0 where none; None where no line was linked."""
    across: np.ndarray | None = None
    """(n, 2) int32 the line sample met there (-1: none); None where no line was linked."""
    normal: np.ndarray | None = None
    """(n, 2) float32 the normals ``gap`` and ``across`` are along (each curve's oriented one)."""
