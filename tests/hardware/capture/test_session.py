"""Capture sessions: poses in a row, a key between them, resumed like a single capture."""

import io

import pytest

from ringscan.hardware.capture.sequence import CAPTURE_FORMAT
from ringscan.hardware.capture.session import pose_state, run_session, wait_for_key
from ringscan.hardware.errors import CaptureError
from ringscan.pipeline.formats.atomic import atomic_write_json


def test_run_session_resumes_a_partial_pose_and_stops_without_a_key(tmp_path):
    calls = []

    def capture(i, folder, resume):
        calls.append((i, resume))
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_json(folder / "capture.json", {"format": CAPTURE_FORMAT, "plan": {"angles": [0.0]}, "table": {"deg": 0.0},
                                                     "status": "complete" if i != 1 or resume else "interrupted"})

    keys, said = io.StringIO("\n"), io.StringIO()  # one Enter, then the input ends
    with pytest.raises(CaptureError, match="pose 3: no key pressed"):
        run_session(tmp_path, 3, capture, wait=lambda i, n: wait_for_key(i, n, stream=keys, out=said))
    assert said.getvalue().count("turn the object over") == 2
    assert calls == [(0, False), (1, False)]
    assert pose_state(tmp_path / "pose_1") == "partial"
    run_session(tmp_path, 3, capture, wait=lambda i, n: None)
    assert calls[2:] == [(1, True), (2, False)]  # pose 0 kept, pose 1 resumed, pose 2 captured
    with pytest.raises(ValueError, match="has 3 poses, not 2"):
        run_session(tmp_path, 2, capture)
