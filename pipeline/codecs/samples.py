"""The samples type: what every codec's decode + sampling stages hand to triangulation."""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

__all__ = ["Samples"]


@dataclass
class Samples:
    """Ring samples of one view (Warp arrays of length n, on the frames' device)."""

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

    def __len__(self) -> int:
        return self.uv.shape[0]
