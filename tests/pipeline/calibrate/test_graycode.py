"""Gray-code decoding against a synthetic capture with a known camera -> projector map."""

from __future__ import annotations

import numpy as np
import pytest

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import decode_graycode, graycode_bits, read_capture, subpixel_map
from tests.pipeline.calibrate.synthetic import write_capture

PROJ = (128, 96)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gc") / "capture"
    u, v = write_capture(folder, projector=PROJ)
    return folder, u, v


def test_bits_of_projector_sizes():
    assert graycode_bits((1024, 768)) == (10, 10)
    assert graycode_bits((1920, 1080)) == (11, 11)
    assert graycode_bits((128, 96)) == (7, 7)


def test_integer_decode_matches_the_projected_pixel(capture):
    folder, u, v = capture
    dec = decode_graycode(read_capture(folder, projector=PROJ))
    assert dec.valid.mean() > 0.99
    # away from projector pixel boundaries the code is the projector pixel under the camera pixel centre
    inner = (np.abs(u - np.round(u)) < 0.3) & (np.abs(v - np.round(v)) < 0.3) & dec.valid
    assert np.mean(dec.col[inner] == np.round(u[inner])) > 0.999
    assert np.mean(dec.row[inner] == np.round(v[inner])) > 0.999


def test_subpixel_beats_the_integer_floor(capture):
    folder, u, v = capture
    cap = read_capture(folder, projector=PROJ)
    dec = subpixel_map(cap, decode_graycode(cap))
    sp = dec.subpixel
    assert sp.mean() > 0.8
    e_int = np.sqrt(np.mean((dec.col[sp] - u[sp]) ** 2))
    e_sub = np.sqrt(np.mean((dec.u[sp] - u[sp]) ** 2))
    e_sub_v = np.sqrt(np.mean((dec.v[sp] - v[sp]) ** 2))
    assert 0.25 < e_int < 0.33  # uniform quantisation: 1/sqrt(12)
    assert e_sub < 0.08 and e_sub_v < 0.08, (e_sub, e_sub_v)


def test_both_layouts(tmp_path):
    u, v = write_capture(tmp_path / "wbfirst", projector=PROJ, wb_first=True)
    dec = decode_graycode(read_capture(tmp_path / "wbfirst", projector=PROJ, layout="opencv-graycode-wb-first"))
    inner = (np.abs(u - np.round(u)) < 0.3) & dec.valid
    assert np.mean(dec.col[inner] == np.round(u[inner])) > 0.999


def test_wrong_layout_is_a_clear_error(capture, tmp_path):
    folder, _, _ = capture
    with pytest.raises(CalibrationError, match="darker than the one read as black.*opencv-graycode-wb-first"):
        read_capture(folder, projector=PROJ, layout="opencv-graycode-wb-first")
    with pytest.raises(CalibrationError, match="30 graycode_NN frames, but a 1024x768 projector .* has 42"):
        read_capture(folder, projector=(1024, 768))
    with pytest.raises(CalibrationError, match="capture folder not found"):
        read_capture(tmp_path / "nothing", projector=PROJ)
