"""The decoded codec: fixed-point frames, rho and sector by hand."""

from __future__ import annotations

import math

import numpy as np

from ringscan.pipeline.calibrate.importer import encode_decoded
from ringscan.pipeline.codecs.decoded import decoded_samples
from ringscan.pipeline.formats.patterns import DECODED_SCALE, frame_names, parse_patterns


def test_samples_by_hand():
    u = np.array([[100.0, np.nan], [50.0, 10.0]])
    v = np.array([[200.0, 5.0], [200.0, 300.0]])
    c = np.full((2, 2), 128.0)
    d = decoded_samples(u, v, c, center=(100.0, 300.0), sector_bits=2)
    assert d["pixel"].tolist() == [0, 2, 3]
    assert d["uv"].tolist() == [[0, 0], [0, 1], [1, 1]]
    np.testing.assert_allclose(d["rho"], [100.0, math.hypot(50, 100), 90.0], rtol=1e-6)
    # phi = atan2(dv, du): (0, -100) -> -pi/2 -> sector 1 of 4; (-50, -100) -> sector 0; (-90, 0) -> pi -> 3
    np.testing.assert_allclose(d["phi"], [-np.pi / 2, math.atan2(-100, -50), np.pi], rtol=1e-6)
    assert d["sector"].tolist() == [1, 0, 3]
    assert np.all(d["confidence"] == 1.0)
    # integer codes: uniform over a pixel, in both directions
    np.testing.assert_allclose(d["sigma_rho"], 1 / math.sqrt(12), rtol=1e-6)
    np.testing.assert_allclose(d["sigma_tan"], 1 / math.sqrt(12), rtol=1e-6)


def test_sigma_follows_contrast_and_direction():
    # u sub-pixel (sharp), v integer (coarse); phi = 0 puts u radial, phi = pi/2 tangential
    u = np.array([[110.25, 100.25]])
    v = np.array([[300.0, 320.0]])
    d = decoded_samples(u, v, np.full((1, 2), 64.0), center=(100.0, 300.0), sector_bits=0)
    assert d["sigma_rho"][0] < 0.06 and abs(d["sigma_tan"][0] - 1 / math.sqrt(12)) < 1e-6
    assert d["sigma_tan"][1] < 0.06 + 1e-3 and abs(d["sigma_rho"][1] - 1 / math.sqrt(12)) < 1e-3
    low = decoded_samples(u, v, np.full((1, 2), 16.0), center=(100.0, 300.0), sector_bits=0)
    np.testing.assert_allclose(low["sigma_rho"][0], 4 * d["sigma_rho"][0], rtol=1e-5)


def test_fixed_point_round_trip():
    u = np.array([[0.0, 1023.0, 511.37, np.nan]])
    v = np.array([[767.0, 0.0, 200.01, 3.0]])
    fu, fv, fc = encode_decoded(u, v, np.full(u.shape, 10.0))
    assert fu.dtype == np.uint16 and fu[0, 3] == 0 and fv[0, 3] == 0  # a pixel needs both coordinates
    back = fu[0, :3] / DECODED_SCALE - 1
    assert np.max(np.abs(back - u[0, :3])) <= 0.5 / DECODED_SCALE


def test_patterns_block():
    spec = parse_patterns({"codec": "decoded", "width": 1024, "height": 768, "center": [457.5, 857.4],
                           "rho0": 0.0, "pitch": 1.0, "sector_bits": 8})
    assert frame_names(spec) == ["proj_u", "proj_v", "contrast"]
    assert spec.to_dict()["sector_bits"] == 8 and "bits" not in spec.to_dict()

