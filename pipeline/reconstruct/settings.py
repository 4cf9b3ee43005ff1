"""Resolved settings of a run, saved as JSON next to every output."""

from __future__ import annotations

from dataclasses import dataclass, field

from ringscan.kernels.point_filter import NeighbourFilterSettings
from ringscan.kernels.settings import MatchSettings
from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.codecs.base import STAGE_SETTING_RANGES, StageSettings
from ringscan.pipeline.formats.settings import WHY_CAM_PX, WHY_PROJ_PX, Bound, check_ranges

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
class ReconstructSettings(StageSettings):
    """Settings of ``ringscan reconstruct``: one block per stage, the codecs'
    decoding blocks first, then the geometry's."""

    triangulate: TriangulateSettings = field(default_factory=TriangulateSettings)
    """Root choice (docs/design.md §4)."""
    filter: NeighbourFilterSettings = field(default_factory=NeighbourFilterSettings)
    """Image-space neighbour filter (mixed pixels, isolated outliers)."""
    stereo: StereoSettings = field(default_factory=StereoSettings)
    """Two-camera views: the rays (``--rays``) and the matching."""
    min_confidence: float = 0.0
    """Points below this confidence are not written."""
    threads: int = 0
    """CPU threads for Warp launches on the CPU (0: all cores)."""


SETTING_RANGES: dict[str, Bound] = {
    **STAGE_SETTING_RANGES,
    "triangulate.sector_tolerance": Bound(0, 4, "sector widths: beyond 4 a root far outside its decoded sector "
                                                "still matches it (the sector check is off)"),
    "triangulate.sector_margin": Bound(0, 4, "sector widths: beyond 4 nearly every point with two roots in "
                                             "the volume is dropped as ambiguous"),
    "triangulate.fallback_sector_px": Bound(0, 65536, WHY_PROJ_PX),
    "triangulate.min_incidence_cos": Bound(0, 0.99, "a cosine: at 1 only rays exactly along the surface's "
                                                    "normal pass"),
    "triangulate.max_residual_px": Bound(0, 65536, WHY_PROJ_PX + "; 0 drops every point", lo_open=True),
    "filter.radius": Bound(0, 8, "pixels: 0 turns the filter off; above 8 the window (17x17) reaches past a "
                                 "ring's neighbours and costs (2r+1)^2 tests a point"),
    "filter.min_neighbours": Bound(0, 288, "neighbours: the largest window (radius 8) holds 288"),
    "filter.tolerance": Bound(0, 100, "footprints per pixel of distance: 100 admits surfaces tilted 89.4 "
                                      "degrees; beyond it every neighbour agrees (the filter checks nothing)",
                              lo_open=True),
    "filter.floor_mm": Bound(0, 100, "mm: beyond 100 every neighbour of a table-top object agrees (the "
                                     "filter checks nothing)"),
    "stereo.match.cell_px": Bound(1, 1024, "projector px: the grid holds (projector size / cell)^2 cells, 64 "
                                           "million at 1 px on an 8192-px projector; below 1 px it grows as "
                                           "1/cell^2"),
    "stereo.match.radius_px": Bound(1, 1024, "projector px: a camera pixel spans a few projector px; the "
                                             "search grows as radius^2"),
    "stereo.match.neighbours": Bound(2, 64, "neighbours of a local fit"),
    "stereo.match.min_neighbours": Bound(2, 64, "neighbours of a local fit (a line needs 2)"),
    "stereo.match.max_offset_px": Bound(0, 65536, WHY_PROJ_PX, lo_open=True),
    "stereo.match.max_extrapolation": Bound(0, 1000, "standard deviations: beyond 1000 the fit is used far "
                                                     "outside its neighbours", lo_open=True),
    "stereo.match.max_fit_px": Bound(0, 65536, WHY_CAM_PX, lo_open=True),
    "stereo.match.max_gain": Bound(0, 65536, "camera px per projector px: at most a camera's side",
                                   lo_open=True),
    "stereo.min_ray_sin": Bound(0, 0.99, "a sine: at 1 only perpendicular rays pass"),
    "stereo.max_residual_px": Bound(0, 65536, WHY_CAM_PX, lo_open=True),
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
    check_ranges(s, SETTING_RANGES)
    m = s.stereo.match
    if m.radius_px < m.cell_px or m.radius_px > 64 * m.cell_px:
        raise ValueError(f"stereo.match.radius_px: {m.radius_px:g} must lie between cell_px ({m.cell_px:g}) and "
                         f"64 x cell_px (the search goes ring by ring of cells: at most 64 rings)")
    if s.filter.radius > 0 and s.filter.min_neighbours > (2 * s.filter.radius + 1) ** 2 - 1:
        raise ValueError(f"filter.min_neighbours: {s.filter.min_neighbours} is more than the window of radius "
                         f"{s.filter.radius} holds ({(2 * s.filter.radius + 1) ** 2 - 1}): every point dropped")
