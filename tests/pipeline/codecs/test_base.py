"""The codec interface's shared messages (``codecs/base.py``): the hint that dark 16-bit
frames may be a 10- or 12-bit camera's, wanting scan.json's ``frame_bits``."""

import numpy as np
import pytest

from ringscan.pipeline.codecs.base import frame_bits_hint
from ringscan.pipeline.codecs.registry import codec_for
from ringscan.pipeline.formats.patterns import default_patterns, frame_names
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.formats.scan import Scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

HINT = ("; 16-bit frames whose brightest value is 3317: a 10- or 12-bit camera's frames? set frame_bits in "
        "scan.json (docs/formats.md)")


def test_the_hint_is_for_dark_16_bit_frames_of_a_scan_without_frame_bits():
    assert frame_bits_hint(3317, np.uint16, None) == HINT
    assert frame_bits_hint(16383, np.uint16, None) != ""
    assert frame_bits_hint(16384, np.uint16, None) == ""  # a quarter of the range: not a few-bit camera's
    assert frame_bits_hint(3317, np.uint16, 12) == ""  # frame_bits set: it was heard
    assert frame_bits_hint(200, np.uint8, None) == ""


@pytest.mark.parametrize("frame_bits,hinted", [(None, True), (16, False)])
def test_a_dark_16_bit_rings_frame_gets_the_hint(frame_bits, hinted):
    spec = default_patterns("rings")
    scan = Scan(folder=None, rig=default_rig(), patterns=spec, views=(), frame_bits=frame_bits)
    codec = codec_for("rings")
    frames = np.full((len(frame_names(spec)), 48, 64), 1000, np.uint16)
    frames[:, ::4] = 1200  # lines at 12-bit levels: 200 of 65535 (0.8 8-bit levels) of contrast
    why = codec.explain_no_points(frames, scan, {}, codec.settings_from(ReconstructSettings()))
    assert why.startswith("no ring found: the rings frame has no contrast")
    assert why.endswith(HINT.replace("3317", "1200")) == hinted
