"""TODO docstring (ringscan.pipeline.codecs.samples, split from ringscan.pipeline.reconstruct.scan)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import warp as wp

log = logging.getLogger(__name__)


@dataclass
class Samples:
    """What a codec's decode + sampling stages hand to triangulation (Warp arrays, length n)."""

    uv: wp.array
    """vec2 camera pixel coordinates."""
    rho: wp.array
    """float32 ring radius (projector px)."""
    ring: wp.array | None
    """int32 ring / band-boundary index, or None for dense codecs."""
    sector: wp.array
    """int32 decoded sector (-1 unknown)."""
    confidence: wp.array
    """float32 sample confidence."""
    pixel: wp.array
    """int32 linear camera pixel index of each sample."""
