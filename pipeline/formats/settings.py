"""Settings dataclasses <-> JSON: every stage's frozen dataclass is written next to
its outputs and read back with unknown keys refused.
"""

from __future__ import annotations

import dataclasses
import math

__all__ = ["settings_to_dict", "settings_from_dict", "check_finite_settings"]


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


def check_finite_settings(s, *, where: str | None = None) -> None:
    """Refuse a settings dataclass (nested ones too) with a NaN or infinite number.

    Raises:
        ValueError: naming the field, e.g. ``FuseSettings.voxel_mm must be a finite number, got nan``.
    """
    where = where or type(s).__name__
    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        if dataclasses.is_dataclass(v):
            check_finite_settings(v, where=f"{where}.{f.name}")
        elif isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{where}.{f.name} must be a finite number, got {v}")
