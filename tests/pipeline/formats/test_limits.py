"""Bounded reads (pipeline/formats/limits.py): only regular files, bounded sizes, image
headers checked before decoding."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.limits import check_image_header, image_header_size, read_bounded_text
from tests.support.header_only import png_header_only, tiff_header_only
from tests.support.threads import in_thread


def test_a_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "rig.json"
    os.mkfifo(fifo)
    got = in_thread(lambda: read_json(fifo))
    if got == "hung":  # unblock the thread so the test run can end
        with open(fifo, "wb") as f:
            f.write(b"{}")
    assert isinstance(got, FormatError), got
    assert str(got) == f"{fifo}: is a pipe (FIFO), not a regular file: ringscan reads regular files only"


def test_a_device_is_refused_before_reading():
    got = in_thread(lambda: read_json("/dev/zero"))
    assert isinstance(got, FormatError) and "/dev/zero: is a device, not a regular file" in str(got), got


def test_size_bound(tmp_path):
    p = tmp_path / "s.json"
    p.write_text('{"a": "' + "x" * 100 + '"}')
    assert read_json(p, max_bytes=200) == {"a": "x" * 100}
    with pytest.raises(FormatError, match=r"s.json: 109 bytes: larger than the 50 bytes a file may have"):
        read_json(p, max_bytes=50)
    assert read_bounded_text(p, 109) == p.read_text()
    with pytest.raises(FormatError, match="larger than the 108 bytes"):
        read_bounded_text(p, 108)


def test_a_5000_digit_number_names_the_file(tmp_path):
    p = tmp_path / "rig.json"
    p.write_text('{"camera": {"width": ' + "9" * 5000 + "}}")
    with pytest.raises(FormatError, match=r"rig.json: not valid JSON \(Exceeds the limit"):
        read_json(p)


@pytest.mark.parametrize("w,h,bits", [(60000, 60000, 8), (30000, 30000, 8), (30000, 30000, 16), (70000, 10, 8)])
def test_huge_png_refused_before_decoding(tmp_path, w, h, bits):
    p = png_header_only(tmp_path / "f.png", w, h, bits)
    assert p.stat().st_size < 200
    assert image_header_size(p) == (w, h)
    with pytest.raises(FormatError, match=rf"f.png: image is {w}x{h} \(\d+ megapixels\): larger than ringscan reads "
                                          r"\(at most 65536 px a side, 200 megapixels\)"):
        read_image(p)


@pytest.mark.parametrize("big_endian", [False, True])
def test_huge_tiff_refused_before_decoding(tmp_path, big_endian):
    p = tiff_header_only(tmp_path / "f.tiff", 40000, 40000, big_endian)
    assert image_header_size(p) == (40000, 40000)
    with pytest.raises(FormatError, match=r"image is 40000x40000"):
        read_image(p)


@pytest.mark.parametrize("ext", [".png", ".tiff", ".jpg", ".bmp"])
def test_real_images_pass_with_their_size(tmp_path, ext):
    img = (np.arange(37 * 23) % 251).astype(np.uint8).reshape(23, 37)
    p = tmp_path / f"f{ext}"
    assert cv2.imwrite(str(p), img)
    assert check_image_header(p) == (37, 23)
    assert read_image(p).shape == (23, 37)


def test_16bit_tiff_and_float_tiff_headers(tmp_path):
    p = tmp_path / "d.tiff"
    cv2.imwrite(str(p), np.zeros((9, 13), np.float32))
    assert image_header_size(p) == (13, 9)
    cv2.imwrite(str(p), np.zeros((9, 13), np.uint16))
    assert image_header_size(p) == (13, 9)


def test_not_an_image_and_not_a_regular_file(tmp_path):
    p = tmp_path / "f.png"
    p.write_bytes(b"P5\n30000 30000\n255\n")  # a PGM: a header this does not read
    with pytest.raises(FormatError, match="f.png: not a readable image"):
        read_image(p)
    with pytest.raises(FormatError, match="is a folder, not a regular file"):
        read_image(tmp_path)
    fifo = tmp_path / "frame.png"
    p.unlink()
    os.mkfifo(fifo)
    got = in_thread(lambda: read_image(fifo))
    if got == "hung":
        with open(fifo, "wb"):
            pass
    assert isinstance(got, FormatError) and "is a pipe (FIFO)" in str(got), got


def test_a_rig_or_patterns_larger_than_the_images_ringscan_reads_are_refused(tmp_path):
    """A 456 KB packed scan whose rig declared a 30000x30000 camera was decoded before any check (22 GB); the
    rig, the projector and the patterns are now bounded as an image is (200 megapixels)."""
    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.formats.rig import default_rig, parse_rig, rig_to_dict

    d = rig_to_dict(default_rig())
    d["camera"].update(width=30000, height=30000)
    with pytest.raises(FormatError) as e:
        parse_rig(d, source="rig.json")
    assert str(e.value) == ("rig.json: camera: 30000x30000 is 900 megapixels: larger than the images ringscan reads "
                            "(200 megapixels)")
    d = rig_to_dict(default_rig(light_model="perspective"))
    d["light"].update(width=20000, height=20000)
    with pytest.raises(FormatError, match=r"^rig.json: light: 20000x20000 is 400 megapixels"):
        parse_rig(d, source="rig.json")
    d["light"].update(width=16000, height=12500)  # 200 megapixels: the most
    assert parse_rig(d, source="rig.json").light.width == 16000
    spec = {"codec": "gray-rings", "width": 30000, "height": 30000, "center": [15000, 15000], "rho0": 8.0,
            "pitch": 4.0, "bits": 3, "sector_bits": 2}
    with pytest.raises(FormatError, match=r"patterns: 30000x30000 is 900 megapixels: larger than the images"):
        parse_patterns(spec, source="scan.json")
