"""Fixtures shared by the calibrate tests."""

import pytest

from tests.support.synthetic_captures import write_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A synthetic Gray-code capture of the default small projector, once per test module: (folder, u, v),
    u and v the true projector coordinates of every camera pixel."""
    folder = tmp_path_factory.mktemp("gc") / "capture"
    u, v = write_capture(folder)
    return folder, u, v
