"""The plan of a capture run, before any device opens (hardware/capture/plan)."""

from __future__ import annotations

import math

import pytest

from ringscan.hardware.capture.plan import CapturePlan, check_angles, plan_capture
from ringscan.pipeline.formats.errors import FormatError


def test_angles_in_range_pass_and_others_are_named():
    check_angles(table_at=-3600.0, start=3600.0, step=-360.0)
    check_angles()
    with pytest.raises(ValueError, match=r"--table-at: expected degrees from -3600 to 3600, got 1e\+300"):
        check_angles(table_at=1e300)
    with pytest.raises(ValueError, match="--start: expected degrees from -3600 to 3600, got nan"):
        check_angles(start=math.nan)
    with pytest.raises(ValueError, match="--step: expected degrees from -360 to 360, got 361"):
        check_angles(step=361.0)


def test_a_new_capture_is_planned_as_given_and_a_resume_needs_a_scan(tmp_path):
    rig, patterns = object(), object()
    assert plan_capture(tmp_path / "new", rig=rig, patterns=patterns, views=3) == CapturePlan(rig, patterns, 3, 0.0,
                                                                                              None)
    with pytest.raises(FormatError, match=r"scan\.json: nothing to resume \(no scan\.json\)"):
        plan_capture(tmp_path, rig=None, patterns=None, views=None, resume=True)
