"""The paper's single-shot ``rings`` codec: one frame of ``count`` antialiased ring
lines; line detection + nesting-order labelling (:mod:`.single_shot`)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels.samples import Samples
from ringscan.pipeline.codecs.base import Codec, RigNeeds, StageSettings, describe_lighting, frame_bits_hint
from ringscan.pipeline.codecs.drawing import draw_frame
from ringscan.pipeline.codecs.single_shot.extract import extract_rings
from ringscan.pipeline.codecs.single_shot.settings import SingleShotSettings
from ringscan.pipeline.formats.patterns import PATTERN_LAYOUTS, PatternSpec, frame_names
from ringscan.pipeline.formats.scan import Scan

__all__ = ["NAME", "RingsCodec"]

NAME = "rings"
"""The codec's name (scan.json ``patterns.codec``): what code outside the codec spells it by."""


class RingsCodec(Codec[SingleShotSettings]):
    """One frame ``rings``: lines ``line_width`` px wide at rho_j = rho0 + j * pitch,
    j = 0..count-1. The labeller reads the rig's geometry to order the rings."""

    layout = PATTERN_LAYOUTS[NAME]
    settings_type = SingleShotSettings
    rig_needs = RigNeeds(geometry_to_decode=True)

    def render_frame(self, spec: PatternSpec, name: str) -> np.ndarray:
        return draw_frame(spec, name)

    def settings_from(self, stages: StageSettings) -> SingleShotSettings:
        return stages.single_shot

    def extract(self, frames: wp.array, scan: Scan, settings: SingleShotSettings, *,
                threads: int) -> tuple[Samples, dict]:
        return extract_rings(frames, scan, settings, threads)

    def explain_no_points(self, frames: np.ndarray, scan: Scan, stats: dict,
                          settings: SingleShotSettings) -> str | None:
        frames = np.asarray(frames)
        full = 65535.0 if frames.dtype == np.uint16 else 255.0
        f = frames[frame_names(scan.patterns).index("rings")].astype(np.float32)
        lo, hi = (float(x) for x in np.percentile(f, [1.0, 99.0]))
        if hi - lo < settings.lines.min_contrast * full / 255.0:
            return (f"no ring found: the rings frame has no contrast (grey levels {lo:.0f} to {hi:.0f} between the "
                    f"1st and 99th percentile): {describe_lighting(lo, hi, full)}"
                    f"{frame_bits_hint(int(f.max()), frames.dtype, scan.frame_bits)}")
        if stats.get("samples", 0) == 0:
            return (f"no ring found: {stats.get('line_samples', 0)} line centres in {stats.get('pieces', 0)} "
                    f"pieces, none labelled with a ring (see the labelling counts in the report)")
        return None
