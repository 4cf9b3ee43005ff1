"""benchmarks/pixel_ratio.py's rigs: the ratio of projector to camera pixels each is said to have."""

import json

import numpy as np
import pytest

from ringscan.pipeline.formats.rig import load_rig
from ringscan.pipeline.geometry import camera_pixels, projector_pixels
from tests.support.benchmark_scripts import load_benchmark


@pytest.mark.parametrize("r", [1 / 15, 1.25, 5.0])
def test_an_import_rig_spans_r_projector_px_a_camera_px(tmp_path, r):
    """Two points 0.5 mm apart on the plane near its middle: r projector px for each camera px between them
    (to 3 %: the plane is seen at 14 degrees, the projector from straight above)."""
    pr = load_benchmark("pixel_ratio")
    rig_dict, size = pr.import_rig(r)
    assert size == ((512, 384) if r <= 1.25 else (1920, 1080))
    (tmp_path / "rig.json").write_text(json.dumps(rig_dict))
    rig = load_rig(tmp_path / "rig.json")
    X = np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0]])  # (along y: the camera's baseline is along x)
    dp = np.linalg.norm(np.diff(projector_pixels(rig, X), axis=0))
    dc = np.linalg.norm(np.diff(camera_pixels(rig, X), axis=0))
    assert abs(dp / dc / r - 1) < 0.03, dp / dc
