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
    # u sub-pixel (sharp), v integer (coarse); phi = 0 puts u radial, phi = pi/2 tangential (two lone pixels:
    # no decoded neighbour, no slope of the map)
    u = np.array([[110.25, np.nan, 100.25]])
    v = np.array([[300.0, np.nan, 320.0]])
    d = decoded_samples(u, v, np.full((1, 3), 64.0), center=(100.0, 300.0), sector_bits=0)
    assert d["sigma_rho"][0] < 0.06 and abs(d["sigma_tan"][0] - 1 / math.sqrt(12)) < 1e-6
    assert d["sigma_tan"][1] < 0.06 + 1e-3 and abs(d["sigma_rho"][1] - 1 / math.sqrt(12)) < 1e-3
    low = decoded_samples(u, v, np.full((1, 3), 16.0), center=(100.0, 300.0), sector_bits=0)
    np.testing.assert_allclose(low["sigma_rho"][0], 4 * d["sigma_rho"][0], rtol=1e-5)


def test_a_sub_pixel_sigma_grows_with_the_projector_px_a_camera_px_spans():
    """A map whose u runs 4 projector px a camera px (a camera coarser than the projector): a sub-pixel u's sigma
    is 4x a lone pixel's (its crossing's error in the camera, times 4); v, 0.5 px a camera px, keeps its own; an
    integer code keeps 1 / sqrt 12; a depth edge beside a pixel (a jump of 200 px) is not the map's slope."""
    from ringscan.pipeline.codecs.decoded import coordinate_sigma, map_rate

    y, x = np.mgrid[0:5, 0:9].astype(np.float64)
    u = 100.3 + 4.0 * x
    v = 50.1 + 0.5 * y
    u[:, 6:] += 200.0  # a depth edge between columns 5 and 6
    u[4, 4] = 116.0  # an integer code
    c = np.full(u.shape, 64.0)
    d = decoded_samples(u, v, c, center=(100.0, 50.0), sector_bits=0)
    rate = map_rate(u)
    assert np.allclose(rate[1:4, 1:8], 4.0)  # the edge's sides too (their other side is the map's own)
    su = coordinate_sigma(u, c).ravel()
    sv = coordinate_sigma(v, c).ravel()
    f = np.arctan2(v - 50.0, u - 100.0).ravel()
    want_su = np.where(np.abs(u - np.round(u)).ravel() < 0.5 / 32, su, su * np.maximum(map_rate(u).ravel(), 1.0))
    want_sv = sv * np.maximum(map_rate(v).ravel(), 1.0)  # (0.5: no change)
    assert np.allclose(want_sv, sv)
    want = np.sqrt(want_su ** 2 * np.cos(f) ** 2 + want_sv ** 2 * np.sin(f) ** 2)
    np.testing.assert_allclose(d["sigma_rho"], want.astype(np.float32), rtol=1e-6)
    k = 4 * 9 + 4  # the integer code
    assert abs(want_su[k] - 1 / math.sqrt(12)) < 1e-12 and abs(want_su[2 * 9 + 2] - 4 * su[2 * 9 + 2]) < 1e-12


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

