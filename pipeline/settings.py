"""Resolved settings of a run, saved as JSON next to every output."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ringscan.kernels.phase import PhaseSettings
from ringscan.kernels.point_filter import NeighbourFilterSettings
from ringscan.kernels.ring_labels import DecodeSettings
from ringscan.kernels.ring_sampling import SampleSettings
from ringscan.kernels.triangulation import TriangulateSettings

from .single_shot import SingleShotSettings

__all__ = ["ReconstructSettings", "settings_to_dict", "settings_from_dict"]


@dataclass(frozen=True)
class ReconstructSettings:
    """Settings of ``ringscan reconstruct``: one block per stage."""

    decode: DecodeSettings = field(default_factory=DecodeSettings)
    """Per-pixel decoding thresholds."""
    sample: SampleSettings = field(default_factory=SampleSettings)
    """Sub-pixel ring sampling thresholds."""
    triangulate: TriangulateSettings = field(default_factory=TriangulateSettings)
    """Root choice (DESIGN §4)."""
    filter: NeighbourFilterSettings = field(default_factory=NeighbourFilterSettings)
    """Image-space neighbour filter (mixed pixels, isolated outliers)."""
    phase: PhaseSettings = field(default_factory=PhaseSettings)
    """Phase decoder of the ``phase-rings`` codec (response, modulation, unwrapping)."""
    single_shot: SingleShotSettings = field(default_factory=SingleShotSettings)
    """Line detection and nesting-order labelling of the single-shot ``rings`` codec."""
    min_confidence: float = 0.0
    """Points below this confidence are not written."""
    threads: int = 0
    """CPU threads for Warp launches on the CPU (0: all cores)."""


def settings_to_dict(s) -> dict:
    return dataclasses.asdict(s)


def settings_from_dict(cls, d: dict):
    """Build a (nested) settings dataclass from a dict, rejecting unknown keys."""
    if d is None:
        return cls()
    kwargs = {}
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for k, v in d.items():
        if k not in fields:
            raise ValueError(f"{cls.__name__}: unknown setting {k!r} (known: {', '.join(fields)})")
        f = fields[k]
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        kwargs[k] = settings_from_dict(type(sub), v) if dataclasses.is_dataclass(sub) else v
    return cls(**kwargs)
