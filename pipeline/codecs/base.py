"""The codec interface: one :class:`Codec` subclass per pattern codec, one module each.

A codec pairs the data-level description of its patterns (a
:class:`~ringscan.pipeline.formats.patterns.PatternLayout`: parameters, defaults
and ranges, frame names; it lives in ``formats`` because reading a scan folder
needs the frame names) with its behaviour: render a projector frame, extract the
samples of one view with typed settings of its own, explain an empty view, and
say what it needs from the rig. ``codecs.registry`` maps a codec name to its
instance; nothing outside ``pipeline.codecs`` branches on a codec's name.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import ClassVar, Generic, TypeVar

import numpy as np
import warp as wp

from ringscan.kernels.samples import Samples
from ringscan.kernels.settings import AngleSettings, DecodeSettings, PhaseSettings, SampleSettings
from ringscan.pipeline.codecs.single_shot.settings import SETTING_RANGES as SINGLE_SHOT_RANGES
from ringscan.pipeline.codecs.single_shot.settings import SingleShotSettings
from ringscan.pipeline.formats.images import few_bits_hint
from ringscan.pipeline.formats.patterns import PatternLayout, PatternSpec
from ringscan.pipeline.formats.scan import Scan
from ringscan.pipeline.formats.settings import WHY_GREY, WHY_MARGIN, WHY_MODULATION, Bound

__all__ = ["Codec", "RigNeeds", "StageSettings", "STAGE_SETTING_RANGES", "describe_lighting", "frame_bits_hint"]

S = TypeVar("S")


@dataclass(frozen=True)
class StageSettings:
    """The settings blocks the codecs decode and sample with, one per stage or codec
    (``reconstruct.ReconstructSettings`` holds them first, then the geometry's); each
    codec picks the blocks it uses into its own typed settings
    (:meth:`Codec.settings_from`). A codec with settings of its own adds its block
    here and its ranges to :data:`STAGE_SETTING_RANGES`."""

    decode: DecodeSettings = field(default_factory=DecodeSettings)
    """Per-pixel decoding thresholds."""
    sample: SampleSettings = field(default_factory=SampleSettings)
    """Sub-pixel ring sampling thresholds."""
    phase: PhaseSettings = field(default_factory=PhaseSettings)
    """Phase decoder of the ``phase-rings`` codec (response, modulation, unwrapping)."""
    single_shot: SingleShotSettings = field(default_factory=SingleShotSettings)
    """Line detection and nesting-order labelling of the single-shot ``rings`` codec."""
    angle: AngleSettings = field(default_factory=AngleSettings)
    """The angle code's decoder and the camera noise of the predicted standard deviations."""


STAGE_SETTING_RANGES: dict[str, Bound] = {
    "decode.min_contrast": Bound(1, 200, WHY_GREY),
    "decode.bit_margin": Bound(0, 0.99, WHY_MARGIN, lo_open=True),
    "sample.min_contrast": Bound(1, 200, WHY_GREY),
    "sample.min_slope": Bound(0, 1.99, "|d_p - d_q| / contrast across an edge: d lies in +-contrast, so the "
                                       "slope is below 2, and at 2 no edge is sampled"),
    "phase.min_contrast": Bound(1, 200, WHY_GREY),
    "phase.min_modulation": Bound(0, 0.99, WHY_MODULATION),
    "phase.edge_ratio": Bound(0, 0.99, WHY_MARGIN, lo_open=True),
    "phase.slip_tolerance": Bound(0, 1, "bands: beyond one band a pixel may slip past a whole edge"),
    "phase.smooth_radius": Bound(0, 4, "pixels: the smoothing window's largest half-size"),
    "phase.smooth_tolerance": Bound(0, 1, "bands: beyond one band pixels across an edge join the average"),
    "phase.min_pairs": Bound(0, 40, "pairs: the largest window (radius 4, 9x9) holds 40"),
    "angle.min_contrast": Bound(1, 200, WHY_GREY),
    "angle.bit_margin": Bound(0, 0.99, WHY_MARGIN, lo_open=True),
    "angle.min_modulation": Bound(0, 0.99, WHY_MODULATION),
    "angle.noise": Bound(0, 64, "8-bit grey levels: 0 makes every angle exact (infinite weight); beyond 64 "
                                "the noise fills a quarter of the camera's range", lo_open=True),
    **{f"single_shot.{k}": b for k, b in SINGLE_SHOT_RANGES.items()},
}
"""The range of every numeric field of :class:`StageSettings`, and why, by its path
(``decode.min_contrast``); ``reconstruct.SETTING_RANGES`` holds them with the rest."""


@dataclass(frozen=True)
class RigNeeds:
    """What a codec needs from the rig beyond the triangulation (which always needs
    the camera, the light and the working volume)."""

    geometry_to_decode: bool = False
    """Decoding itself reads the rig's geometry (camera and light poses): its samples
    depend on the calibration, so they cannot calibrate the light."""
    response: bool = False
    """Decoding reads the camera's and the light's response gammas (``rig.camera.gamma``,
    ``rig.light.gamma``)."""


class Codec(ABC, Generic[S]):
    """One pattern codec (the model: OpenCV structured_light's ``StructuredLightPattern``).

    Subclasses set :attr:`layout`, :attr:`settings_type` and :attr:`rig_needs` and
    implement :meth:`settings_from` and :meth:`extract`; a projectable codec also
    implements :meth:`render_frame`.
    """

    layout: ClassVar[PatternLayout]
    """Parameters (defaults, ranges) and frame names (``formats.patterns``)."""
    settings_type: ClassVar[type]
    """The frozen dataclass of this codec's settings (``S``)."""
    rig_needs: ClassVar[RigNeeds] = RigNeeds()
    """What decoding needs from the rig."""

    @property
    def name(self) -> str:
        """The codec name (scan.json ``patterns.codec``)."""
        return self.layout.name

    @property
    def calibrates_light(self) -> bool:
        """Its samples can calibrate the light (projected, decoded without the rig's geometry)."""
        return self.layout.projectable and not self.rig_needs.geometry_to_decode

    @property
    def has_angle_code(self) -> bool:
        """Its patterns can carry the angle code (:mod:`.angle_code`: a layout parameter
        ``angle_steps``), which gives every sample the full projector coordinate."""
        return any(p.name == "angle_steps" for p in self.layout.parameters)

    def full_coordinate(self, spec: PatternSpec) -> bool:
        """Its samples of ``spec`` carry the full projector coordinate (both u_p and
        v_p: the ring radius and the polar angle with their standard deviations), so
        two cameras can be matched by equal projector coordinate
        (docs/reconstruction.md, "Two cameras"). False here; a codec that decodes
        both says when."""
        return False

    @property
    def isotropic_code_error(self) -> bool:
        """Its samples' projector coordinate errs about alike in every direction (a decoded u, v map: its
        radius's and angle's sigmas are both made of the same u and v sigmas), so that camera 1's code error,
        matched camera to camera, is stood in for isotropically on camera 1 and the matcher's map is not read
        (docs/design.md §19). False here: a ring's radius and its angle err by far different amounts, and
        only the map says which part of that runs along the epipolar lines."""
        return False

    def pixel_window(self, settings) -> int | None:
        """For a dense codec (one sample a camera pixel, ``Samples.ring`` None) whose
        samples' errors neighbouring pixels can check: the side (px) of the square each
        sample is averaged over (1: none), which neighbours share part of
        (:func:`~ringscan.pipeline.reconstruct.neighbour_checks.fit_neighbour_model`); None
        where they cannot be checked that way (here). ``settings``: this codec's."""
        return None

    def error_groups(self, spec: PatternSpec, ring: np.ndarray) -> np.ndarray | None:
        """(n,) int: groups of samples whose errors differ by a factor the decode's
        model does not know (the pattern whose edges place them, one modulating less
        than another), each given its own factor where neighbours check the samples
        (:func:`~ringscan.pipeline.reconstruct.neighbour_checks.fit_neighbour_model`); -1: no
        group. None (here): one group. ``ring``: the samples' ring indices."""
        return None

    def frame_names(self, spec: PatternSpec) -> list[str]:
        """The frame names, in projection order (may depend on any pattern parameter)."""
        return self.layout.frame_names(spec)

    def render_frame(self, spec: PatternSpec, name: str) -> np.ndarray:
        """One projector frame ``name`` as a (height, width) uint8 image.

        Raises:
            ValueError: the codec is not projectable.
        """
        raise ValueError(f"the {self.name} codec is not projectable: it has no frames to render")

    @abstractmethod
    def settings_from(self, stages: StageSettings) -> S:
        """This codec's settings, picked from a run's stage blocks."""

    @abstractmethod
    def extract(self, frames: wp.array, scan: Scan, settings: S, *, threads: int) -> tuple[Samples, dict]:
        """Decode + sampling of one view.

        Args:
            frames: (F, H, W) uint8/uint16 Warp array in :meth:`frame_names` order (read only).
            scan: the scan (patterns, rig).
            settings: this codec's settings (:attr:`settings_type`).
            threads: CPU threads for the row-run kernels.

        Returns:
            (samples, stats): stats holds at least ``pixels_decoded``, ``samples`` and
            ``times_s`` (stage -> seconds), and ``sector_bits`` where the codec decides
            sectors of its own.
        """

    def extract_for_matching(self, frames: wp.array, scan: Scan, settings: S, *, threads: int) -> tuple[Samples, dict]:
        """:meth:`extract` for a two-camera match (camera 2 of a view, ``pipeline.reconstruct.stereo``): the
        samples matching reads (their positions, projector coordinates and sigmas); a codec may leave out
        what only a point's own error model reads (``Samples.shading``). By default :meth:`extract`."""
        return self.extract(frames, scan, settings, threads=threads)

    def explain_no_points(self, frames: np.ndarray, scan: Scan, stats: dict, settings: S) -> str | None:
        """Why a view gave no point, where the codec can tell from its frames (one
        sentence for the user), else None (``reconstruct`` then says what the counts say).

        Args:
            frames: the view's (F, H, W) frames in :meth:`frame_names` order.
            stats: the view's counts (``pixels_decoded``, ``samples``, ...).
        """
        return None


def frame_bits_hint(brightest: int, dtype, frame_bits: int | None) -> str:
    """``"; <hint>"`` where 16-bit frames of a scan without ``frame_bits`` are so dark
    that they may hold a 10- to 14-bit camera's values (``brightest``: the brightest
    value of the view's brightest frame), else ``""``."""
    if np.dtype(dtype) != np.uint16 or frame_bits is not None:
        return ""
    return few_bits_hint(brightest, "set frame_bits in scan.json (docs/formats.md)")


def describe_lighting(lo_mean: float, hi_mean: float, full: float) -> str:
    """Why a view has no contrast, from the mean grey level of its darkest and
    brightest frames (``full``: 255 or 65535)."""
    if hi_mean < 0.05 * full:
        return "everything is dark: the projector's light did not reach the camera (projector off, lens cap, " \
               "exposure too short)"
    if lo_mean > 0.95 * full:
        return "everything is saturated: the exposure is too long or the ambient light too strong"
    return "the projector's light does not change the image (projector off or aimed elsewhere, or the " \
           "frames are all alike)"
