"""The light's gamma from a synthetic grey ramp with a known response."""

from __future__ import annotations

import numpy as np
import pytest

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.response import estimate_light_gamma


def ramp(gamma_light, gamma_cam=1.0, levels=(0, 0.25, 0.5, 0.75, 1.0), seed=0):
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.3, 0.9, (40, 50))
    frames = []
    for x in levels:
        irr = 0.05 + albedo * x ** gamma_light  # ambient + projector
        rec = 255 * (irr / 1.0) ** (1 / gamma_cam) + rng.normal(0, 0.5, irr.shape)
        frames.append(np.clip(np.round(rec), 0, 255).astype(np.uint8))
    return np.stack(frames), np.asarray(levels)


@pytest.mark.parametrize("g", [1.0, 1.8, 2.2])
def test_recovers_the_light_gamma(g):
    fr, lv = ramp(g)
    est, curve = estimate_light_gamma(fr, lv)
    assert abs(est - g) < 0.03
    assert abs(curve[0.5] - 0.5 ** g) < 0.01


def test_camera_gamma_is_undone_first():
    fr, lv = ramp(2.2, gamma_cam=2.0)
    assert abs(estimate_light_gamma(fr, lv, camera_gamma=2.0)[0] - 2.2) < 0.05
    assert abs(estimate_light_gamma(fr, lv)[0] - 2.2) > 0.5  # ignoring it is wrong


def test_binary_levels_only_are_refused():
    fr, lv = ramp(2.2, levels=(0, 1))
    with pytest.raises(CalibrationError, match="at least two grey levels"):
        estimate_light_gamma(fr, lv)
