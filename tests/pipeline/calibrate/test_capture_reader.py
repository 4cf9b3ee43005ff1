"""Reading a Gray-code capture's frames: the layout check, 12-bit frames and --frame-bits
(pipeline/calibrate/capture_reader)."""

from __future__ import annotations

import numpy as np
import pytest

from ringscan.pipeline.calibrate.capture_reader import read_capture
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import decode_graycode
from tests.support.synthetic_captures import SMALL_PROJECTOR

PROJ = SMALL_PROJECTOR  # the capture fixture's projector (tests/pipeline/calibrate/conftest.py)


def test_wrong_layout_is_a_clear_error(capture, tmp_path):
    folder, _, _ = capture
    with pytest.raises(CalibrationError, match="darker than the one read as black.*opencv-graycode-wb-first"):
        read_capture(folder, projector=PROJ, layout="opencv-graycode-wb-first")
    with pytest.raises(CalibrationError, match="30 graycode_NN frames, but a 1024x768 projector .* has 42"):
        read_capture(folder, projector=(1024, 768))
    with pytest.raises(CalibrationError, match="capture folder not found"):
        read_capture(tmp_path / "nothing", projector=PROJ)


def _to_12_bits(src, dst):
    """The 8-bit capture ``src`` as a 12-bit camera records it: 16-bit PNGs holding
    v * 4095 / 255 (v << 4 | v >> 4), 0..4095."""
    import cv2

    dst.mkdir(parents=True)
    for p in sorted(src.glob("graycode_*.png")):
        v = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.uint16)
        cv2.imwrite(str(dst / p.name), (v << 4) | (v >> 4))


def test_frame_bits_reads_a_12_bit_capture_as_its_8_bit_original(capture, tmp_path):
    folder, u, v = capture
    _to_12_bits(folder, tmp_path / "c12")
    ref = read_capture(folder, projector=PROJ)
    cap = read_capture(tmp_path / "c12", projector=PROJ, frame_bits=12)
    # v -> v << 4 | v >> 4 -> replicated to 16 bits: v * 257 give or take 15 of 65536 (the pairs are kept
    # as read: their levels are value * scale, 1 / 257 for 16-bit frames)
    assert cap.col_pairs.dtype == np.uint16 and ref.col_pairs.dtype == np.uint8 and cap.scale == 1 / 257
    for a, b in ((cap.white, ref.white), (cap.black, ref.black),
                 (cap.col_pairs * np.float32(cap.scale), ref.col_pairs.astype(np.float32)),
                 (cap.row_pairs * np.float32(cap.scale), ref.row_pairs.astype(np.float32))):
        assert np.abs(a - b).max() <= 15 / 257 + 1e-4
    d12, d8 = decode_graycode(cap), decode_graycode(ref)
    assert np.mean(d12.valid == d8.valid) > 0.999
    both = d12.valid & d8.valid
    assert np.mean((d12.col == d8.col)[both]) > 0.999 and np.mean((d12.row == d8.row)[both]) > 0.999


def test_a_12_bit_capture_without_frame_bits_says_what_to_give(capture, tmp_path):
    folder, _, _ = capture
    _to_12_bits(folder, tmp_path / "c12")
    with pytest.raises(CalibrationError) as e:
        read_capture(tmp_path / "c12", projector=PROJ)
    msg = str(e.value)
    assert "no projector light in the capture" in msg
    assert "16-bit frames whose brightest value is" in msg and "ringscan import --frame-bits" in msg


def test_frames_that_frame_bits_does_not_fit_are_refused_naming_the_frame(capture, tmp_path):
    import cv2

    folder, _, _ = capture
    _to_12_bits(folder, tmp_path / "c12")
    p = sorted((tmp_path / "c12").glob("graycode_*.png"))[3]
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    img[7, 8] = 5000
    cv2.imwrite(str(p), img)
    with pytest.raises(CalibrationError, match=r"frame holds 5000, above the 12-bit range --frame-bits says \(4095\)") \
            as e:
        read_capture(tmp_path / "c12", projector=PROJ, frame_bits=12)
    assert e.value.path == str(p)
    with pytest.raises(CalibrationError, match="frame is 8-bit, but --frame-bits says 12"):
        read_capture(folder, projector=PROJ, frame_bits=12)
    with pytest.raises(CalibrationError, match="frame is 16-bit, but --frame-bits says 8"):
        read_capture(tmp_path / "c12", projector=PROJ, frame_bits=8)
    with pytest.raises(ValueError, match="frame_bits must be 8 or 9..16"):
        read_capture(folder, projector=PROJ, frame_bits=7)
