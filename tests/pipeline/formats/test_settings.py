"""Settings checks of pipeline/formats/settings.py: only what a caller changed is checked, and it is checked."""

import dataclasses

import pytest

from ringscan.pipeline.formats.settings import check_settings_types, settings_from_dict
from ringscan.pipeline.reconstruct.settings import ReconstructSettings


def test_defaults_pass_and_build_the_defaults():
    check_settings_types(ReconstructSettings())
    assert settings_from_dict(ReconstructSettings, {}) == ReconstructSettings()


@pytest.mark.parametrize("change, message", [
    (lambda s: dataclasses.replace(s, min_confidence="high"),
     r"ReconstructSettings\.min_confidence: expected a number, got 'high'"),
    # equal to the default by value (False == 0) but not by type: still refused
    (lambda s: dataclasses.replace(s, threads=False), r"ReconstructSettings\.threads: expected a whole number"),
    (lambda s: dataclasses.replace(s, phase=dataclasses.replace(s.phase, smooth_radius=True)),
     r"ReconstructSettings\.phase\.smooth_radius: expected a whole number"),
    (lambda s: dataclasses.replace(s, triangulate=dataclasses.replace(s.triangulate, sector_margin="1")),
     r"ReconstructSettings\.triangulate\.sector_margin: expected a number, got '1'"),
])
def test_a_changed_value_of_the_wrong_type_is_named(change, message):
    with pytest.raises(ValueError, match=message):
        check_settings_types(change(ReconstructSettings()))


def test_a_changed_value_of_the_right_type_passes():
    s = ReconstructSettings()
    check_settings_types(dataclasses.replace(s, min_confidence=0.5,
                                             triangulate=dataclasses.replace(s.triangulate, constraint="rings")))


@pytest.mark.parametrize("t", [float, int, bool, str])
def test_scalars_are_checked_as_pydantic_checks_them(t):
    """A scalar setting is checked without pydantic (its import alone is ~0.05 s of a command): the same verdict
    and the same message as pydantic's strict JSON check of the field's type, for every kind of value."""
    import json
    import math

    import numpy as np

    from ringscan.pipeline.formats import settings as fs

    @dataclasses.dataclass(frozen=True)
    class One:
        x: t = t()

    values = [0, 1, -3, 1.0, 1.5, math.nan, math.inf, True, False, "1", "high", "", None, [1], (1.0,), {"a": 1},
              np.float32(2.5), np.float64(1.0), np.int64(3), np.bool_(True), object()]
    for v in values:
        text = json.dumps(v, allow_nan=True, default=lambda o: o.item() if hasattr(o, "item") else str(o))
        try:
            fs._validate_with_pydantic(t, text, "One.x")
            want = None
        except ValueError as e:
            want = str(e)
        try:
            fs._validate(One, {"x": v}, "One.")
            got = None
        except ValueError as e:
            got = str(e)
        assert got == want, (t, v)
