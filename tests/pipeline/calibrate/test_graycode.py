"""Gray-code decoding against a synthetic capture with a known camera -> projector map."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import (GrayCodeSettings, decode_graycode, graycode_bits, list_capture,
                                                  natural_key, read_capture, read_capture_files,
                                                  subpixel_map)
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


@pytest.mark.parametrize("case", ["dim", "stray", "dark"])
def test_dim_pixels_decode_where_the_patterns_reach_them(tmp_path, case):
    """A dim capture (white - black 16 grey levels, below ``min_contrast`` 20; camera
    noise 1.5) whose patterns modulate every pixel reads its codes right: a bit away
    from its edge differs from its inverse by the whole contrast, 7.5 noise sigmas.
    The same white - black from stray light, with patterns that hardly change the
    pixel (a real board's black squares beside white ones), gains nothing over
    contrast alone; nor does a pixel at 3 levels."""
    u, v = write_capture(tmp_path / "clean", projector=PROJ, noise=0.0, levels=(20.0, 220.0))
    cap = read_capture(tmp_path / "clean", projector=PROJ)
    rng = np.random.default_rng(7)
    contrast = 3.0 if case == "dark" else 16.0
    depth = 0.15 if case == "stray" else 1.0   # how much of the contrast the patterns carry

    def dim(f, depth=1.0):  # the same lit fractions at the dim contrast, with fresh camera noise, rounded
        lit = 0.5 + depth * ((f - 20.0) / 200.0 - 0.5)
        return np.clip(np.round(20.0 + contrast * lit + rng.normal(0, 1.5, f.shape)), 0, 255)

    cap = dataclasses.replace(cap, white=dim(cap.white), black=dim(cap.black), col_pairs=dim(cap.col_pairs, depth),
                              row_pairs=dim(cap.row_pairs, depth))
    dec = decode_graycode(cap)
    alone = decode_graycode(cap, settings=GrayCodeSettings(dim_contrast=20.0)).valid  # on contrast alone
    assert alone.mean() < 0.1   # noise lifts a few pixels over 20
    if case != "dim":
        assert (dec.valid & ~alone).mean() < 0.002
        return
    assert dec.valid.mean() > 0.99
    inner = (np.abs(u - np.round(u)) < 0.3) & (np.abs(v - np.round(v)) < 0.3) & dec.valid
    assert np.mean(dec.col[inner] == np.round(u[inner])) > 0.999
    assert np.mean(dec.row[inner] == np.round(v[inner])) > 0.999


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


# ----------------------------------------------------------------------------- fine bits that barely modulate


@pytest.fixture(scope="module")
def defocused(tmp_path_factory):
    """The affine scene through a projector defocused by 1.8 projector px (a Gaussian): the finest Gray bit
    (stripes 2 projector px wide) keeps ~4 % of the pixel's white - black, under a noise of 1.5 levels."""
    folder = tmp_path_factory.mktemp("defocus") / "capture"
    u, v = write_capture(folder, cam=(320, 240), projector=(256, 192), blur_px=1.8, noise=1.5, levels=(20, 120))
    return read_capture(folder, projector=(256, 192)), u, v


def test_the_noise_is_measured_from_the_capture(defocused, capture):
    cap, _, _ = defocused
    dec = decode_graycode(cap)
    assert 1.2 < dec.noise < 1.8  # the frames' noise: 1.5 levels (rounded to integers)
    sharp = decode_graycode(read_capture(capture[0], projector=PROJ))
    assert 0.8 < sharp.noise < 1.2 and not sharp.low_modulation.any() and not sharp.coarse.any()


def test_bits_that_barely_modulate_give_way_to_coarser_ones(defocused):
    """The finest bit is read by the noise: every bit trusted, the positions zigzag by up to a projector
    pixel (the old decode: median 0.18 px, 1 % over 1.4 px); trusting only the bits that stand clear of the
    noise, the positions come from the boundaries of the coarser bits, as exact as a sharp projector's."""
    import ringscan.pipeline.calibrate.graycode as gc

    cap, u, v = defocused
    dec = subpixel_map(cap, decode_graycode(cap))
    ok = dec.valid
    assert ok.mean() > 0.9 and (dec.coarse[..., 0][ok] == 1).mean() > 0.95  # the finest bit, not more
    e = np.abs(dec.u - u)[ok]
    assert np.median(e) < 0.05 and np.percentile(e, 99) < 0.2, (np.median(e), np.percentile(e, 99))
    ev = np.abs(dec.v - v)[ok]
    assert np.median(ev) < 0.05 and np.percentile(ev, 99) < 0.2
    assert dec.low_modulation.sum() == (~ok).sum()  # what is not decoded is counted as low_modulation
    # every bit trusted (the thresholds at zero): the finest bit's misreads are whole-pixel errors
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(gc, "CLEAR_NOISE_SIGMAS", 0.0)
        mp.setattr(gc, "CLEAR_CONTRAST_FRACTION", 0.0)
        blind = subpixel_map(cap, decode_graycode(cap))
    eb = np.abs(blind.u - u)[blind.valid]
    assert np.percentile(eb, 99) > 1.0 and np.median(eb) > 2 * np.median(e)


def test_a_pixel_whose_coarser_bits_barely_modulate_is_dropped_as_low_modulation(defocused):
    cap, u, v = defocused
    dark = dataclasses.replace(cap, col_pairs=cap.col_pairs.copy())
    # a patch where the projector's light hardly reaches the 5 finest column bits (one more than MAX_COARSE_BITS)
    b = dark.col_pairs.shape[0]
    patch = (slice(b - 5, b), slice(None), slice(40, 200), slice(40, 280))
    mean = dark.col_pairs[patch].mean(axis=1, keepdims=True)
    dark.col_pairs[patch] = mean + 0.02 * (dark.col_pairs[patch] - mean)
    dec = subpixel_map(dark, decode_graycode(dark))
    inner = (slice(80, 160), slice(80, 240))  # farther than the 5th bit's half stripe (29 camera px) from the rim
    assert dec.low_modulation[inner].all() and not dec.valid[inner].any()
    assert np.isnan(dec.u[inner]).all()
    assert dec.valid[:30].mean() > 0.9  # outside the patch, decoded as before


# ---------------------------------------------------------------------- captures named by the camera, text lists

def _renamed(src, dst, names):
    """The capture's graycode_NN frames copied to ``names`` (in capture order)."""
    import shutil

    dst.mkdir()
    frames = sorted(src.glob("graycode_*.png"))
    for p, n in zip(frames, names):
        shutil.copy(p, dst / n)
    return frames


def test_frames_named_by_the_camera_are_taken_in_natural_name_order(capture, tmp_path):
    # DSC8 .. DSC37: in plain string order DSC10 .. DSC19 would come before DSC8 and the capture be garbled
    folder, u, v = capture
    names = [f"DSC{k}.PNG" for k in range(8, 38)]
    frames = _renamed(folder, tmp_path / "cap", names)
    files = list_capture(tmp_path / "cap", projector=PROJ)
    assert files.kind == "named" and [p.name for p in files.cameras[0]] == names
    assert sorted(names) != names  # (the plain sort would not do)
    a = read_capture_files(files.cameras[0], projector=PROJ)
    b = read_capture_files(frames, projector=PROJ)
    assert np.array_equal(a.col_pairs, b.col_pairs) and np.array_equal(a.white, b.white)
    dec = subpixel_map(a, decode_graycode(a))
    assert np.sqrt(np.mean((dec.u[dec.subpixel] - u[dec.subpixel]) ** 2)) < 0.08  # as the graycode_NN import


def test_natural_order_compares_numbers_as_numbers():
    names = ["DSC10.JPG", "dsc2.jpg", "DSC1.JPG", "img_2_b.png", "img_10_a.png", "img_2_a.png"]
    assert sorted(names, key=natural_key) == ["DSC1.JPG", "dsc2.jpg", "DSC10.JPG", "img_2_a.png", "img_2_b.png",
                                              "img_10_a.png"]


def test_frames_of_other_names_that_do_not_fit_say_what_the_layout_expects(capture, tmp_path):
    folder, _, _ = capture
    names = [f"DSC{k:05d}.png" for k in range(4052, 4052 + 29)]  # one frame short of 30
    _renamed(folder, tmp_path / "cap", names)
    with pytest.raises(CalibrationError) as e:
        list_capture(tmp_path / "cap", projector=PROJ)
    msg = str(e.value)
    assert msg.startswith(f"{tmp_path / 'cap'}: no frames named graycode_NN")
    assert ("found 29 image(s) of other names (DSC04052.png .. DSC04080.png), but a 128x96 projector in layout "
            "opencv-graycode has 30 (7 column and 7 row bits") in msg, msg


def test_a_plain_text_list_reads_as_a_filestorage_list(capture, tmp_path, monkeypatch):
    folder, _, _ = capture
    frames = sorted(folder.glob("graycode_*.png"))
    sub = tmp_path / "lists"
    sub.mkdir()
    # relative paths beside the list, one absolute, blank lines and comments; CRLF line ends
    lines = ["# capture of the target, camera 1", ""]
    for k, p in enumerate(frames):
        lines.append(str(p) if k == 0 else f"../frames/{p.name}" + ("  # white" if k == len(frames) - 2 else ""))
    (tmp_path / "frames").mkdir()
    for p in frames[1:]:
        (tmp_path / "frames" / p.name).write_bytes(p.read_bytes())
    lst = sub / "capture.txt"
    lst.write_text("\r\n".join(lines) + "\r\n")
    with pytest.raises(CalibrationError, match=r"line 31: \.\./frames/graycode_28\.png  # white not found"):
        list_capture(lst, projector=PROJ)  # a comment after a path is part of the path: only whole lines are
    lines[-2] = lines[-2].split("  #")[0]
    lst.write_text("\r\n".join(lines) + "\r\n")
    files = list_capture(lst, projector=PROJ)
    assert files.kind == "text" and [p.name for p in files.cameras[0]] == [p.name for p in frames]
    assert files.cameras[0][0] == frames[0] and files.cameras[0][1] == sub / "../frames" / frames[1].name
    # not beside the list: the current folder
    monkeypatch.chdir(tmp_path)
    lst2 = tmp_path / "elsewhere" / "c.lst"
    lst2.parent.mkdir()
    lst2.write_text("\n".join(str(Path("frames") / p.name) if k else str(p) for k, p in enumerate(frames)))
    assert list_capture(lst2, projector=PROJ).cameras[0][1] == (tmp_path / "frames" / frames[1].name)
    # a count that does not fit, a missing file, a line that is no image: one line each, naming the list
    lst.write_text("\n".join(str(p) for p in frames[:-1]))
    with pytest.raises(CalibrationError, match=r"capture\.txt: lists 29 frames, but a 128x96 projector .* has 30"):
        list_capture(lst, projector=PROJ)
    lst.write_text("\n".join(["nothere.png"] + [str(p) for p in frames[1:]]))
    with pytest.raises(CalibrationError, match=r"capture\.txt: line 1: nothere\.png not found"):
        list_capture(lst, projector=PROJ)
    lst.write_text("\n".join([str(lst)] + [str(p) for p in frames[1:]]))
    with pytest.raises(CalibrationError, match=r"line 1: .*capture\.txt is not a PNG, TIFF, JPEG or BMP file name"):
        list_capture(lst, projector=PROJ)
    lst.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(CalibrationError, match="not a text image list"):
        list_capture(lst, projector=PROJ)


def test_a_capture_kept_as_read_decodes_as_its_float_levels(capture, tmp_path):
    """The frames are kept as read (8-bit here; 16-bit with scale 1 / 257): the decode and the sub-pixel map
    of the capture equal those of the same capture as float32 levels, to the bit."""
    folder, u, v = capture
    cap = read_capture(folder, projector=PROJ)
    assert cap.col_pairs.dtype == np.uint8 and cap.scale == 1.0
    flt = dataclasses.replace(cap, col_pairs=cap.col_pairs.astype(np.float32),
                              row_pairs=cap.row_pairs.astype(np.float32))
    a, b = subpixel_map(cap, decode_graycode(cap)), subpixel_map(flt, decode_graycode(flt))
    for f in ("col", "row", "valid", "contrast", "coarse", "low_modulation", "subpixel"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert a.noise == b.noise
    assert np.array_equal(a.u, b.u, equal_nan=True) and np.array_equal(a.v, b.v, equal_nan=True)
