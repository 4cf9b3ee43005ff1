"""The dense Gray-code map's sub-pixel kernels against the NumPy construction they replaced, and each other."""

import numpy as np
import pytest

from ringscan.kernels.graycode_map import subpixel_lines, subpixel_points


def _reference_along_x(code, valid, pairs, max_span):
    """The NumPy construction subpixel_lines replaced (graycode._along_axis before issue 33), along x."""
    H, W = code.shape
    bits = pairs.shape[0]
    c0, c1 = code[:, :-1].astype(np.int64), code[:, 1:].astype(np.int64)
    trans = valid[:, :-1] & valid[:, 1:] & (np.abs(c1 - c0) == 1)
    yy, xx = np.nonzero(trans)
    a, b_ = c0[yy, xx], c1[yy, xx]
    x = np.maximum((a ^ (a >> 1)) ^ (b_ ^ (b_ >> 1)), 1)
    b = bits - 1 - np.floor(np.log2(x)).astype(np.int64)
    d0 = pairs[b, 0, yy, xx] - pairs[b, 1, yy, xx]
    d1 = pairs[b, 0, yy, xx + 1] - pairs[b, 1, yy, xx + 1]
    den = d0 - d1
    frac = np.where(np.abs(den) > 1e-6, d0 / np.where(den == 0, 1, den), 0.5)
    pos = np.full((H, W - 1), np.nan)
    val = np.full((H, W - 1), np.nan)
    pos[yy, xx] = xx + np.clip(frac, 0.0, 1.0)
    val[yy, xx] = 0.5 * (c0[yy, xx] + c1[yy, xx])
    left = np.maximum.accumulate(np.where(trans, np.arange(W - 1)[None, :], -1), axis=1)
    right = np.minimum.accumulate(np.where(trans, np.arange(W - 1)[None, :], W)[:, ::-1], axis=1)[:, ::-1]
    lk = np.concatenate([np.full((H, 1), -1), left], axis=1)
    rk = np.concatenate([right, np.full((H, 1), W)], axis=1)
    has = (lk >= 0) & (rk < W - 1)
    rows = np.arange(H)[:, None]
    pl, vl = pos[rows, np.clip(lk, 0, W - 2)], val[rows, np.clip(lk, 0, W - 2)]
    pr, vr = pos[rows, np.clip(rk, 0, W - 2)], val[rows, np.clip(rk, 0, W - 2)]
    span = pr - pl
    ok = has & valid & (np.abs(vr - vl) == 1) & (span > 0) & (span <= max_span)
    ok &= np.abs(code - 0.5 * (vl + vr)) < 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        res = vl + (np.arange(W)[None, :] - pl) / span * (vr - vl)
    return np.where(ok, res, code.astype(np.float64)), ok


@pytest.mark.parametrize("axis", [1, 0])
def test_subpixel_lines_equal_the_numpy_construction(axis):
    """A Gray-coded ramp (2.3 camera px per code, a few misread and undecoded pixels, a depth step that
    jumps codes) with noisy pattern/inverse levels: the kernel's walk gives the NumPy construction's
    numbers to the bit, along rows and (transposed) along columns; most pixels are interpolated, and
    a pixel's interpolated code lies within half a code of its integer one (the boundaries around code c
    lie at c -+ 1/2)."""
    rng = np.random.default_rng(5)
    H, W, bits = 40, 300, 7
    xs = np.arange(W) / 2.3 + 0.4 * np.sin(np.arange(H))[:, None]
    xs[:, 200:] += 9.0  # a depth step: codes jump
    code = np.floor(xs).astype(np.int32)
    valid = rng.random((H, W)) > 0.03
    code[rng.random((H, W)) < 0.01] += 3  # misreads
    c = np.clip(code, 0, 2 ** bits - 1).astype(np.int64)
    g = c ^ (c >> 1)  # the reflected Gray code
    pairs = np.empty((bits, 2, H, W), np.float32)
    for b in range(bits):
        on = ((g >> (bits - 1 - b)) & 1).astype(np.float32)
        level = 40 + 160 * on + rng.normal(0, 3, (H, W))
        pairs[b, 0], pairs[b, 1] = level, 240 - level
    if axis == 0:
        code, valid, pairs = code.T.copy(), valid.T.copy(), pairs.transpose(0, 1, 3, 2).copy()
    out, ok = subpixel_lines(code, valid, pairs, bits=bits, axis=axis, max_span=12.0)
    t = (lambda a: a.T) if axis == 0 else (lambda a: a)
    want, want_ok = _reference_along_x(t(code), t(valid), pairs if axis == 1 else pairs.transpose(0, 1, 3, 2), 12.0)
    assert np.array_equal(t(ok), want_ok) and np.array_equal(t(out), want)
    assert want_ok.mean() > 0.6
    assert np.all(np.abs(out[ok] - code[ok]) <= 0.5 + 1e-12)  # between the boundaries c -+ 1/2
    # some lines alone (a coarser level's walk, where few pixels are left to place): those lines'
    # numbers as the whole walk gives them, nothing on the others
    some = np.array([0, 3, 17, code.shape[0 if axis == 1 else 1] - 1])
    part, part_ok = subpixel_lines(code, valid, pairs, bits=bits, axis=axis, max_span=12.0, lines=some)
    on = np.zeros(code.shape, bool)
    if axis == 1:
        on[some] = True
    else:
        on[:, some] = True
    assert np.array_equal(part[on], out[on]) and np.array_equal(part_ok[on], ok[on])
    assert np.isnan(part[~on]).all() and not part_ok[~on].any()


@pytest.mark.parametrize("dtype, scale", [(np.uint8, 1.0), (np.uint16, 1.0 / 257.0)])
def test_subpixel_lines_read_frames_as_stored(dtype, scale):
    """A frame stack kept as read (8-bit, or 16-bit with levels value / 257: ringscan import keeps a
    capture so, a quarter of float32's memory) gives the numbers its float32 levels give, to the bit."""
    rng = np.random.default_rng(9)
    H, W, bits = 24, 200, 6
    xs = np.arange(W) / 1.7 + 0.5 * np.cos(np.arange(H))[:, None]
    code = np.floor(xs).astype(np.int32)
    valid = rng.random((H, W)) > 0.02
    c = np.clip(code, 0, 2 ** bits - 1).astype(np.int64)
    g = c ^ (c >> 1)
    top = 255 if dtype == np.uint8 else 65535
    raw = np.empty((bits, 2, H, W), dtype)
    for b in range(bits):
        on = ((g >> (bits - 1 - b)) & 1).astype(np.float64)
        level = np.clip((0.15 + 0.7 * on) * top + rng.normal(0, 0.02 * top, (H, W)), 0, top)
        raw[b, 0], raw[b, 1] = np.round(level), np.round(top - level)
    levels = raw.astype(np.float32) * np.float32(scale)
    out, ok = subpixel_lines(code, valid, raw, bits=bits, axis=1, max_span=12.0, scale=scale)
    want, want_ok = subpixel_lines(code, valid, levels, bits=bits, axis=1, max_span=12.0)
    assert np.array_equal(ok, want_ok) and np.array_equal(out, want)
    assert ok.mean() > 0.6


def _ramp(rng, H, W, bits, per_code, misread=0.01):
    """A Gray-coded ramp along x (0.6 to 1.4 times ``per_code`` camera px a code from the first row to the
    last, a depth step, misreads, undecoded pixels) and its noisy float32 pattern/inverse levels:
    (code, valid, pairs)."""
    rate = per_code * (0.6 + 0.8 * np.arange(H) / H)[:, None]
    xs = np.arange(W) / rate + 0.4 * np.sin(np.arange(H))[:, None]
    xs[:, W // 2:] += 9.0
    code = np.floor(xs).astype(np.int32)
    valid = rng.random((H, W)) > 0.05
    code[rng.random((H, W)) < misread] += 3
    g = np.clip(code, 0, 2 ** bits - 1).astype(np.int64)
    g = g ^ (g >> 1)
    pairs = np.empty((bits, 2, H, W), np.float32)
    for b in range(bits):
        on = ((g >> (bits - 1 - b)) & 1).astype(np.float32)
        level = 40 + 160 * on + rng.normal(0, 3, (H, W))
        pairs[b, 0], pairs[b, 1] = level, 240 - level
    return code, valid, pairs


@pytest.mark.parametrize("axis", [1, 0])
@pytest.mark.parametrize("per_code, max_span", [(2.3, 12.0), (4.0, 4.0), (9.0, 30.5)])
def test_subpixel_points_give_the_walks_numbers(axis, per_code, max_span):
    """At any pixels (a coarser level's few left to place, and every pixel), the bounded search around each
    gives what the whole line's walk gives there, to the bit: spans longer than max_span (codes wider than
    it) rejected as the walk rejects them, undecoded pixels and misreads alike."""
    rng = np.random.default_rng(11)
    code, valid, pairs = _ramp(rng, 30, 160, 7, per_code)
    if axis == 0:  # the ramp down the columns
        code, valid, pairs = code.T.copy(), valid.T.copy(), pairs.transpose(0, 1, 3, 2).copy()
    out, ok = subpixel_lines(code, valid, pairs, bits=7, axis=axis, max_span=max_span)
    assert 0.2 < ok.mean() and (~ok & valid).any()  # some placed, some not: both outcomes compared
    every = np.arange(code.size)
    some = rng.choice(code.size, 500, replace=False)
    for px in (every, some):
        res, good = subpixel_points(code, valid, pairs, px, bits=7, axis=axis, max_span=max_span)
        assert np.array_equal(good, ok.flat[px])
        assert np.array_equal(res[good], out.flat[px[good]])
        assert np.array_equal(res[~good & valid.flat[px]], code.flat[px[~good & valid.flat[px]]])
    # fewer bits read (a coarser level: code >> k with the first bits - k pairs) agree likewise
    res, good = subpixel_points(code >> 1, valid, pairs, every, bits=6, axis=axis, max_span=2 * max_span)
    want, want_ok = subpixel_lines(code >> 1, valid, pairs[:6], bits=6, axis=axis, max_span=2 * max_span)
    assert np.array_equal(good, want_ok.ravel()) and np.array_equal(res[good], want.ravel()[good])


def test_subpixel_points_check_their_pixels():
    code, valid, pairs = _ramp(np.random.default_rng(1), 8, 20, 5, 2.0)
    with pytest.raises(ValueError, match="indices below 160"):
        subpixel_points(code, valid, pairs, np.array([160]), bits=5, axis=1, max_span=8.0)
    res, good = subpixel_points(code, valid, pairs, np.zeros(0, np.int64), bits=5, axis=1, max_span=8.0)
    assert res.shape == (0,) and good.shape == (0,)
    # spans without a bound (inf: the line's length bounds the search) and none passing (NaN), as the walk
    every = np.arange(code.size)
    for span in (np.inf, np.nan):
        want, want_ok = subpixel_lines(code, valid, pairs, bits=5, axis=1, max_span=span)
        res, good = subpixel_points(code, valid, pairs, every, bits=5, axis=1, max_span=span)
        assert np.array_equal(good, want_ok.ravel()) and np.array_equal(res[good], want.ravel()[good])
        assert good.any() == (span == np.inf)
