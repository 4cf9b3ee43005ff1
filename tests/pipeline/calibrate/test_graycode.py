"""Gray-code decoding against a synthetic capture with a known camera -> projector map."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from ringscan.pipeline.calibrate.capture_reader import read_capture
from ringscan.pipeline.calibrate.graycode import GrayCodeSettings, decode_graycode, graycode_bits, subpixel_map
from tests.support.synthetic_captures import SMALL_PROJECTOR, write_capture

PROJ = SMALL_PROJECTOR  # the capture fixture's projector (tests/pipeline/calibrate/conftest.py)


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


def test_the_plain_decode_needs_no_warp_the_subpixel_map_loads_it(defocused, tmp_path):
    """`ringscan import` reads its frames before Warp is imported (the import loads the sub-pixel kernels on a
    thread meanwhile): neither the command (its process policy, its modules, its checks) nor the plain decode
    import Warp; the sub-pixel map does."""
    probe = (
        "import sys\n"
        "from ringscan.tools.cli import main\n"  # (the command's process policy, its checks: no Warp)
        "assert main(['import', 'nowhere.yml', '--rig', 'none.yml', '--projector', '256x192', '--out', 'x']) == 1\n"
        "import ringscan.tools.cmd_import\n"
        "from ringscan.pipeline.calibrate.capture_reader import read_capture\n"
        "from ringscan.pipeline.calibrate.graycode import decode_graycode, subpixel_map\n"
        f"cap = read_capture({str(defocused[0].folder)!r}, projector=(256, 192))\n"
        "dec = decode_graycode(cap, threads=2)\n"  # (240 rows: two bands on two threads)
        "print('warp' in sys.modules, int(dec.valid.sum()))\n"
        "subpixel_map(cap, dec)\n"
        "print('warp' in sys.modules, int(dec.subpixel.sum()))\n"
    )
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    (before, decoded), (after, subpixel) = (line.split() for line in r.stdout.split("\n")[:2])
    assert (before, after) == ("False", "True")
    assert int(decoded) > 0 and int(subpixel) > 0


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


@pytest.mark.parametrize("which", ["sharp", "defocused"])
def test_a_capture_kept_as_read_decodes_as_its_float_levels(which, capture, defocused):
    """The frames are kept as read (8-bit here, whose bits and modulations are then compared as integer
    levels; 16-bit with scale 1 / 257): the decode and the sub-pixel map of the capture equal those of the
    same capture as float32 levels, to the bit, on a sharp projector and on a defocused one whose pixels
    take their positions from coarser bits."""
    cap = read_capture(capture[0], projector=PROJ) if which == "sharp" else defocused[0]
    assert cap.col_pairs.dtype == np.uint8 and cap.scale == 1.0
    flt = dataclasses.replace(cap, col_pairs=cap.col_pairs.astype(np.float32),
                              row_pairs=cap.row_pairs.astype(np.float32))
    a, b = subpixel_map(cap, decode_graycode(cap)), subpixel_map(flt, decode_graycode(flt))
    for f in ("col", "row", "valid", "contrast", "coarse", "low_modulation", "subpixel"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert a.noise == b.noise
    assert np.array_equal(a.u, b.u, equal_nan=True) and np.array_equal(a.v, b.v, equal_nan=True)
    if which == "defocused":
        assert (a.coarse[a.valid] > 0).mean() > 0.9 and a.subpixel.mean() > 0.5  # the coarser levels placed them


def test_threads_share_out_rows_and_lines_with_the_same_numbers(defocused):
    """The decode's row bands and the walk's lines shared out among threads (a one-camera import's two
    cores) give the one-thread decode and maps to the bit, coarser levels included."""
    cap, _, _ = defocused
    one = subpixel_map(cap, decode_graycode(cap))
    two = subpixel_map(cap, decode_graycode(cap, threads=2), threads=2)
    assert cap.white.shape[0] >= 128  # two bands of at least 64 rows: the threaded path runs
    for f in ("col", "row", "valid", "contrast", "coarse", "low_modulation", "subpixel"):
        assert np.array_equal(getattr(one, f), getattr(two, f)), f
    assert one.noise == two.noise
    assert np.array_equal(one.u, two.u, equal_nan=True) and np.array_equal(one.v, two.v, equal_nan=True)


@pytest.mark.parametrize("per", [1, 2])
@pytest.mark.parametrize("n", [1, 2, 3, 1000, 1001])
def test_the_counted_median_is_numpys(n, per):
    """frame_noise's medians of whole (per 1) and half (per 2) levels, counted by value: np.median's to
    the bit, for odd and even counts (the mean of the two middle ones), at the range's ends too."""
    from ringscan.pipeline.calibrate.graycode import _whole_median

    rng = np.random.default_rng(n * per)
    x = rng.integers(-1024 * per, 1024 * per + 1, n) / per
    assert _whole_median(x, per) == np.median(x)
    x = np.full(n, 1024.0)
    assert _whole_median(x, per) == 1024.0


# ----------------------------------------------------------------------------- a projector finer than the camera


@pytest.fixture(scope="module")
def coarse_camera(tmp_path_factory):
    """The affine scene at 3.3 projector px per camera px (a 512 x 384 projector seen by a 128 x 96 camera: each
    camera pixel averages every projector pixel it spans): the finest two bits' stripes (2 and 4 projector px)
    are narrower than a camera pixel."""
    folder = tmp_path_factory.mktemp("coarse") / "capture"
    u, v = write_capture(folder, cam=(128, 96), projector=(512, 384), slope=6.0, noise=1.0, blur_px=0.7)
    return read_capture(folder, projector=(512, 384)), u, v


def test_bits_finer_than_the_camera_resolves_give_way_to_coarser_ones(coarse_camera):
    """Neighbouring pixels' codes step by ~3, so no boundary between two of them is one projector pixel's: the
    walk finds none and the decode kept the integer codes (each the projector pixel under the camera pixel's
    middle: +-0.5 px, uniform). Each pixel now takes its position from the boundaries of the blocks of 2**2
    projector px that the camera resolves: sub-pixel."""
    cap, u, v = coarse_camera
    dec = decode_graycode(cap)
    ok = dec.valid
    assert ok.mean() > 0.99
    assert (dec.unresolved[..., 0][ok] == 2).mean() > 0.9 and (dec.unresolved[..., 1][ok] == 2).mean() > 0.9
    assert dec.coarse.sum() < 0.01 * ok.sum()  # (the finest bits are not counted as barely modulating)
    # the decode before: no level left unresolved, so the walk looks for one-pixel boundaries
    before = subpixel_map(cap, dataclasses.replace(dec, unresolved=None, u=None, v=None))
    assert before.subpixel[ok].mean() < 0.05
    e_int = np.abs(before.u - u)[before.valid & ~before.subpixel]
    assert 0.25 < np.median(e_int) < 0.35 and np.percentile(e_int, 95) > 0.45  # uniform over a projector px
    dec = subpixel_map(cap, dec)
    assert dec.subpixel[dec.valid].mean() > 0.9
    sp = dec.valid & dec.subpixel
    for got, want in ((dec.u, u), (dec.v, v)):
        e = np.abs(got - want)[sp]
        assert np.median(e) < 0.2 and np.percentile(e, 95) < 0.3, (np.median(e), np.percentile(e, 95))


def test_the_resolution_level_is_a_regions_own(capture):
    """resolution_levels reads each region's own code slope: 0 where a camera pixel spans 0.5 projector px,
    2 where it spans 3, 1 where 1.5; a depth edge (a code that jumps once) and codes that jump about (an unlit
    wall's noise read as a code) stay at 0; a capture whose camera resolves every bit gets None."""
    from ringscan.pipeline.calibrate.graycode import resolution_levels

    h, w = 120, 300
    y, x = np.mgrid[0:h, 0:w]
    code = np.where(x < 100, 0.5 * x, np.where(x < 200, 50 + 3.0 * (x - 100), 350 + 1.5 * (x - 200)))
    code = np.floor(code + np.random.default_rng(1).integers(-1, 2, (h, w))).astype(np.int32)  # misreads of +-1
    code[60:, :100] += 500 * (x[60:, :100] >= 50)  # a depth edge in the left region's lower half
    noise = (slice(0, 40), slice(205, 260))
    code[noise] = np.random.default_rng(2).integers(0, 1024, (40, 55))
    valid = np.ones((h, w), bool)
    lv, rate = resolution_levels(code, valid, 1, bits=11)
    assert (lv[:, 10:90] == 0).all()  # the edge at x = 50 included
    assert (lv[10:-10, 120:180] == 2).all()
    assert (lv[60:-10, 220:280] == 1).all()
    assert (lv[5:35, 215:250] == 0).all()  # the noise
    assert 1.0 < rate < 3.5  # the median of the slopes over the decoded pixels
    cap = read_capture(capture[0], projector=PROJ)
    dec = decode_graycode(cap)
    assert resolution_levels(dec.col, dec.valid, 1, bits=7) == (None, 0.0) and not dec.unresolved.any()


def test_a_camera_far_finer_than_the_projector_places_its_pixels_between_boundaries(tmp_path):
    """At 15 camera px a projector px (a 20-megapixel camera on a small projector's pixels, close up) the
    boundaries lie 15 px apart, beyond ``max_span_px`` (12), and a stripe's middle beyond the clearance window
    of the codes' steps (1 px): the decode kept every pixel's integer code (a staircase of whole projector
    px) and left the pixels beside each boundary out as barely modulating. Now the span and the window follow
    the projector px: nearly every pixel sub-pixel, to ~a hundredth of a projector px."""
    folder = tmp_path / "capture"
    u, v = write_capture(folder, cam=(320, 240), projector=PROJ, slope=0.12, noise=1.0, blur_px=0.3)
    cap = read_capture(folder, projector=PROJ)
    dec = decode_graycode(cap)
    assert dec.spacing[0] > 12 and dec.spacing[1] > 12  # 1 / (0.12 x 0.55)
    assert dec.low_modulation.mean() < 0.01
    dec = subpixel_map(cap, dec)
    ok = dec.valid
    # (the pixels before the first boundary or after the last, ~15 px at each edge, keep their integer codes)
    assert ok.mean() > 0.95 and dec.subpixel[ok].mean() > 0.8
    for got, want in ((dec.u, u), (dec.v, v)):
        e = np.abs(got - want)[ok & dec.subpixel]
        assert np.median(e) < 0.03 and np.percentile(e, 95) < 0.1, (np.median(e), np.percentile(e, 95))
