"""Projector frames of every projectable codec (drawn in :mod:`.drawing`, NumPy
alone: ``ringscan capture`` and the display projector show patterns without
loading the kernels; each ``Codec.render_frame`` draws through the same functions).

With ``spec.precompensated_gamma`` g != 1 each value v (0..1, the light the
pattern means) is written as round(255 * v**(1/g)): a light whose response is
emitted = (value / 255)**g then emits v. 0 and 1 stay 0 and 255, so white, black
and the binary bands away from their edges are unchanged.
"""

from __future__ import annotations

import numpy as np

from ringscan.pipeline.codecs.drawing import FRAME_KINDS, draw_frame
from ringscan.pipeline.formats.patterns import PatternSpec, frame_names

__all__ = ["render_frame", "render_frames"]


def render_frame(spec: PatternSpec, name: str) -> np.ndarray:
    """Render one projector frame as a (height, width) uint8 image."""
    if name.split("_")[0] in FRAME_KINDS:
        return draw_frame(spec, name)
    # A frame of another kind belongs to a codec registered later (its own
    # render_frame); only then is the registry, and with it the kernels, loaded.
    from ringscan.pipeline.codecs.registry import codec_for

    if name not in frame_names(spec):
        raise ValueError(f"frame {name!r} is not part of the {spec.codec} codec")
    return codec_for(spec.codec).render_frame(spec, name)


def render_frames(spec: PatternSpec) -> dict[str, np.ndarray]:
    """All frames of a codec, in projection order."""
    return {name: render_frame(spec, name) for name in frame_names(spec)}
