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


def test_16_bit_frames_of_a_camera_with_a_gamma():
    """The contrast test is in linear grey levels (8-bit ones x257 for 16-bit frames): 16-bit frames of a camera
    with gamma 2 were refused as having no contrast (its threshold was raised to the camera's gamma too)."""
    fr, lv = ramp(2.2, gamma_cam=2.0)
    est8 = estimate_light_gamma(fr, lv, camera_gamma=2.0)[0]
    est16 = estimate_light_gamma(fr.astype(np.uint16) * np.uint16(257), lv, camera_gamma=2.0)[0]
    assert abs(est16 - est8) < 1e-9 and abs(est16 - 2.2) < 0.05


def test_camera_gamma_is_undone_first():
    fr, lv = ramp(2.2, gamma_cam=2.0)
    assert abs(estimate_light_gamma(fr, lv, camera_gamma=2.0)[0] - 2.2) < 0.05
    assert abs(estimate_light_gamma(fr, lv)[0] - 2.2) > 0.5  # ignoring it is wrong


def test_binary_levels_only_are_refused():
    fr, lv = ramp(2.2, levels=(0, 1))
    with pytest.raises(CalibrationError, match="at least two grey levels"):
        estimate_light_gamma(fr, lv)


def test_a_ramp_has_no_problems_a_repeated_frame_does():
    from ringscan.pipeline.calibrate.response import repeated_frames, response_problems
    fr, lv = ramp(2.2)
    g, curve = estimate_light_gamma(fr, lv)
    assert repeated_frames(fr, lv) == [] and response_problems(curve, g) == []
    # the 0.5 frame given for 0.25, 0.5 and 0.75: a flat curve, still a gamma (0.91 in the issue)
    fr2 = fr[[0, 2, 2, 2, 4]]
    assert repeated_frames(fr2, lv) == [(1, 2), (1, 3)]
    g2, curve2 = estimate_light_gamma(fr2, lv)
    probs = response_problems(curve2, g2)
    assert any("does not rise" in p for p in probs) and any("not a gamma curve" in p for p in probs)


def test_non_finite_levels_are_refused_not_dropped():
    fr, lv = ramp(2.2)
    lv = lv.astype(float).copy()
    lv[1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        estimate_light_gamma(fr, lv)
