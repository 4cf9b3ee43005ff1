"""Resolved settings of a run, saved as JSON next to every output."""

from __future__ import annotations

from dataclasses import dataclass, field

from ringscan.kernels.angle import AngleSettings
from ringscan.kernels.phase import PhaseSettings
from ringscan.kernels.point_filter import NeighbourFilterSettings
from ringscan.kernels.ring_labels import DecodeSettings
from ringscan.kernels.ring_sampling import SampleSettings
from ringscan.kernels.stereo_match import MatchSettings
from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.codecs.single_shot.settings import SingleShotSettings

__all__ = ["ReconstructSettings", "StereoSettings", "RAYS", "SETTING_RANGES", "check_setting_ranges"]

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




@dataclass(frozen=True)
class Bound:
    """The range a numeric setting may take, and why (``check_setting_ranges``)."""

    lo: float
    hi: float
    why: str
    lo_open: bool = False
    """True: ``lo`` itself is outside (``> lo``)."""

    def holds(self, v: float) -> bool:
        return (v > self.lo if self.lo_open else v >= self.lo) and v <= self.hi

    def text(self) -> str:
        lo = f"> {self.lo:g}" if self.lo_open else f"{self.lo:g}"
        return f"{lo} .. {self.hi:g}" if not self.lo_open else f"{lo} and <= {self.hi:g}"


_GREY = "8-bit grey levels of white - black (x257 for 16-bit frames): below 1 an unlit pixel counts as lit; " \
        "above 200 only a white - black step of nearly the camera's whole range (255) passes"
_MARGIN = "a fraction of white - black: 0 trusts a bit at the noise level, and |frame - inverse| never exceeds " \
          "white - black, so at 1 no bit is strong"
_MODULATION = "a fringe modulation (1 for a perfect fringe): at 1 or more no pixel passes"
_FRACTION = "a fraction of the pairs or samples: at most all of them (1)"
_DEG = "degrees between two directions: at most 180"
_ARC = "degrees of a circle: at most 360"
_CAM_PX = "camera px: at most the largest camera side ringscan reads (65536)"
_PROJ_PX = "projector px: at most the largest projector side a rig may have (65536)"
_MM = "mm: at most the rig's sane length range (100 m)"
_LEVELS = "8-bit grey levels: a frame holds at most 255"

SETTING_RANGES: dict[str, Bound] = {
    "decode.min_contrast": Bound(1, 200, _GREY),
    "decode.bit_margin": Bound(0, 0.99, _MARGIN, lo_open=True),
    "sample.min_contrast": Bound(1, 200, _GREY),
    "sample.min_slope": Bound(0, 1.99, "|d_p - d_q| / contrast across an edge: d lies in +-contrast, so the "
                                       "slope is below 2, and at 2 no edge is sampled"),
    "triangulate.sector_tolerance": Bound(0, 4, "sector widths: beyond 4 a root far outside its decoded sector "
                                                "still matches it (the sector check is off)"),
    "triangulate.sector_margin": Bound(0, 4, "sector widths: beyond 4 nearly every point with two roots in "
                                             "the volume is dropped as ambiguous"),
    "triangulate.fallback_sector_px": Bound(0, 65536, _PROJ_PX),
    "triangulate.min_incidence_cos": Bound(0, 0.99, "a cosine: at 1 only rays exactly along the surface's "
                                                    "normal pass"),
    "triangulate.max_residual_px": Bound(0, 65536, _PROJ_PX + "; 0 drops every point", lo_open=True),
    "filter.radius": Bound(0, 8, "pixels: 0 turns the filter off; above 8 the window (17x17) reaches past a "
                                 "ring's neighbours and costs (2r+1)^2 tests a point"),
    "filter.min_neighbours": Bound(0, 288, "neighbours: the largest window (radius 8) holds 288"),
    "filter.tolerance": Bound(0, 100, "footprints per pixel of distance: 100 admits surfaces tilted 89.4 "
                                      "degrees; beyond it every neighbour agrees (the filter checks nothing)",
                              lo_open=True),
    "filter.floor_mm": Bound(0, 100, "mm: beyond 100 every neighbour of a table-top object agrees (the "
                                     "filter checks nothing)"),
    "phase.min_contrast": Bound(1, 200, _GREY),
    "phase.min_modulation": Bound(0, 0.99, _MODULATION),
    "phase.edge_ratio": Bound(0, 0.99, _MARGIN, lo_open=True),
    "phase.slip_tolerance": Bound(0, 1, "bands: beyond one band a pixel may slip past a whole edge"),
    "phase.smooth_radius": Bound(0, 4, "pixels: the smoothing window's largest half-size"),
    "phase.smooth_tolerance": Bound(0, 1, "bands: beyond one band pixels across an edge join the average"),
    "phase.min_pairs": Bound(0, 40, "pairs: the largest window (radius 4, 9x9) holds 40"),
    "single_shot.lines.sigma": Bound(0, 20, "camera px: a larger Gaussian merges neighbouring rings",
                                     lo_open=True),
    "single_shot.lines.min_contrast": Bound(0, 200, _LEVELS + "; above 200 only a nearly full-range line passes"),
    "single_shot.lines.min_curvature": Bound(0, 1020, "grey levels per px^2: a second difference of 8-bit "
                                                      "values is at most 4 x 255"),
    "single_shot.lines.max_eigen_ratio": Bound(0, 1, "a ratio of eigenvalues: above 1 a blob passes as a line"),
    "single_shot.lines.max_tangent_slope": Bound(0, 100, "px times -lambda per px: beyond 100 every flank "
                                                         "passes as a centre"),
    "single_shot.lines.background_px": Bound(0, 64, "camera px: beyond 64 the background is read on the next "
                                                    "rings", lo_open=True),
    "single_shot.lines.confidence_contrast": Bound(0, 255, _LEVELS, lo_open=True),
    "single_shot.min_piece_samples": Bound(1, 200000, "line centres: the longest ring on the largest camera "
                                                      "(2 pi 32768 px) has fewer"),
    "single_shot.max_normal_turn_deg": Bound(0, 180, _DEG, lo_open=True),
    "single_shot.max_piece_step_px": Bound(0, 65536, _CAM_PX, lo_open=True),
    "single_shot.fork_px": Bound(0, 65536, _CAM_PX, lo_open=True),
    "single_shot.junction_px": Bound(0, 65536, _CAM_PX, lo_open=True),
    "single_shot.junction_deg": Bound(0, 180, _DEG, lo_open=True),
    "single_shot.min_curvature_radius_px": Bound(0, 65536, _CAM_PX, lo_open=True),
    "single_shot.loop_fit_px": Bound(0, 65536, _CAM_PX, lo_open=True),
    "single_shot.segment_deg": Bound(0, 180, _DEG, lo_open=True),
    "single_shot.segment_curvature_radius_px": Bound(0, 65536, _CAM_PX, lo_open=True),
    "single_shot.segment_contrast_ratio": Bound(0, 255, "a ratio of 8-bit contrasts: at most 255 / 1",
                                                lo_open=True),
    "single_shot.max_gap_px": Bound(0, 65536, _CAM_PX + "; 0: three ring spacings"),
    "single_shot.plane_tolerance_px": Bound(0, 65536, _PROJ_PX, lo_open=True),
    "single_shot.plane_min_arc_deg": Bound(0, 360, _ARC, lo_open=True),
    "single_shot.closed_max_gap_deg": Bound(0, 360, _ARC, lo_open=True),
    "single_shot.bump_contrast": Bound(0, 255, _LEVELS, lo_open=True),
    "single_shot.max_bump_fraction": Bound(0, 1, _FRACTION),
    "single_shot.min_link_pairs": Bound(1, 200000, "sample pairs: the longest ring on the largest camera "
                                                   "(2 pi 32768 px) has fewer"),
    "single_shot.min_pass_fraction": Bound(0, 1, _FRACTION),
    "single_shot.min_root_fraction": Bound(0, 1, _FRACTION),
    "single_shot.max_step_pitches": Bound(0, 1000, "ring pitches: beyond 1000 any two rings link", lo_open=True),
    "single_shot.min_root_separation_mm": Bound(0, 1e5, _MM, lo_open=True),
    "single_shot.off_plane_mm": Bound(0, 1e5, _MM, lo_open=True),
    "single_shot.min_view_cos": Bound(0, 1, "a cosine: at most 1 (facing straight on)"),
    "single_shot.min_light_cos": Bound(0, 1, "a cosine: at most 1 (facing straight on)"),
    "angle.min_contrast": Bound(1, 200, _GREY),
    "angle.bit_margin": Bound(0, 0.99, _MARGIN, lo_open=True),
    "angle.min_modulation": Bound(0, 0.99, _MODULATION),
    "angle.noise": Bound(0, 64, "8-bit grey levels: 0 makes every angle exact (infinite weight); beyond 64 "
                                "the noise fills a quarter of the camera's range", lo_open=True),
    "stereo.match.cell_px": Bound(1, 1024, "projector px: the grid holds (projector size / cell)^2 cells, 64 "
                                           "million at 1 px on an 8192-px projector; below 1 px it grows as "
                                           "1/cell^2"),
    "stereo.match.radius_px": Bound(1, 1024, "projector px: a camera pixel spans a few projector px; the "
                                             "search grows as radius^2"),
    "stereo.match.neighbours": Bound(2, 64, "neighbours of a local fit"),
    "stereo.match.min_neighbours": Bound(2, 64, "neighbours of a local fit (a line needs 2)"),
    "stereo.match.line_ratio": Bound(0, 1, "a ratio of variances: at 1 every neighbourhood is a line",
                                     lo_open=True),
    "stereo.match.max_offset_px": Bound(0, 65536, _PROJ_PX, lo_open=True),
    "stereo.match.max_extrapolation": Bound(0, 1000, "standard deviations: beyond 1000 the fit is used far "
                                                     "outside its neighbours", lo_open=True),
    "stereo.match.max_fit_px": Bound(0, 65536, _CAM_PX, lo_open=True),
    "stereo.match.max_gain": Bound(0, 65536, "camera px per projector px: at most a camera's side",
                                   lo_open=True),
    "stereo.min_ray_sin": Bound(0, 0.99, "a sine: at 1 only perpendicular rays pass"),
    "stereo.max_residual_px": Bound(0, 65536, _CAM_PX, lo_open=True),
    "min_confidence": Bound(0, 1, "a confidence: 0..1"),
    "threads": Bound(0, 4096, "CPU threads: 0 uses every core; more than 4096 is more than any machine has"),
}
"""Every numeric setting's range, and why (docs/reconstruction.md, "Settings"): a value outside is refused
before anything is read, so that a typo (``1e308``, ``-1``) cannot run a scan with a stage silently off."""


def check_setting_ranges(s: ReconstructSettings) -> None:
    """Refuse a numeric setting outside its range (:data:`SETTING_RANGES`).

    Raises:
        ValueError: naming the setting, e.g. ``decode.min_contrast: 1e+308 is outside 1 .. 200 (8-bit grey
            levels ...)``.
    """
    for path, bound in SETTING_RANGES.items():
        v = s
        for part in path.split("."):
            v = getattr(v, part)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue  # a value of the wrong type is check_settings_types's to name
        if not bound.holds(v):
            raise ValueError(f"{path}: {v:g} is outside {bound.text()} ({bound.why})")
    m = s.stereo.match
    if m.radius_px < m.cell_px or m.radius_px > 64 * m.cell_px:
        raise ValueError(f"stereo.match.radius_px: {m.radius_px:g} must lie between cell_px ({m.cell_px:g}) and "
                         f"64 x cell_px (the search goes ring by ring of cells: at most 64 rings)")
    if s.filter.radius > 0 and s.filter.min_neighbours > (2 * s.filter.radius + 1) ** 2 - 1:
        raise ValueError(f"filter.min_neighbours: {s.filter.min_neighbours} is more than the window of radius "
                         f"{s.filter.radius} holds ({(2 * s.filter.radius + 1) ** 2 - 1}): every point dropped")
