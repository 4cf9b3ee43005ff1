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
    uv, rho, sector, conf, pix = decoded_samples(u, v, c, center=(100.0, 300.0), sector_bits=2)
    assert pix.tolist() == [0, 2, 3]
    assert uv.tolist() == [[0, 0], [0, 1], [1, 1]]
    np.testing.assert_allclose(rho, [100.0, math.hypot(50, 100), 90.0], rtol=1e-6)
    # phi = atan2(dv, du): (0, -100) -> -pi/2 -> sector 1 of 4; (-50, -100) -> sector 0; (-90, 0) -> pi -> 3
    assert sector.tolist() == [1, 0, 3]
    assert np.all(conf == 1.0)


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
