"""kernels.compact: finite items, gathers and small histograms on the device, against NumPy."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.compact import count_values, finite_flags, finite_indices, gather


def _f32(a):
    return wp.array(np.asarray(a, np.float32), dtype=wp.float32, device="cpu")


def test_finite_indices_and_gather_are_flatnonzero_and_take():
    rng = np.random.default_rng(1)
    a = rng.normal(size=20000).astype(np.float32)
    a[rng.random(a.size) < 0.3] = np.nan
    a[:3] = [np.inf, -np.inf, np.nan]
    np.testing.assert_array_equal(finite_flags(_f32(a)).numpy(), np.isfinite(a).astype(np.int32))
    idx = finite_indices(_f32(a), threads=2)
    np.testing.assert_array_equal(idx.numpy(), np.flatnonzero(np.isfinite(a)))
    uv = rng.uniform(0, 100, (a.size, 2)).astype(np.float32)
    np.testing.assert_array_equal(gather(wp.array(uv, dtype=wp.vec2), idx).numpy(), uv[np.isfinite(a)])
    pts = rng.normal(size=(a.size, 3)).astype(np.float32)
    np.testing.assert_array_equal(gather(wp.array(pts, dtype=wp.vec3), idx).numpy(), pts[np.isfinite(a)])
    assert finite_indices(_f32(np.full(5, np.nan))).shape == (0,)


@pytest.mark.parametrize("n", [0, 1, 4095, 4096, 50001])
def test_count_values_is_bincount(n):
    v = np.random.default_rng(n).integers(0, 12, n).astype(np.int32)
    np.testing.assert_array_equal(count_values(wp.array(v, dtype=wp.int32), 12, threads=2),
                                  np.bincount(v, minlength=12))


def test_gather_refuses_other_types():
    with pytest.raises(ValueError, match="gather: src must be"):
        gather(wp.zeros(3, dtype=wp.uint8), wp.zeros(2, dtype=wp.int32))


@pytest.mark.parametrize("host", [True, False], ids=["numpy-in-place", "device-sort"])
@pytest.mark.parametrize("n", [1, 2, 3, 20, 9999, 10000])
def test_median_and_percentiles_are_numpys(n, host, monkeypatch):
    """On the CPU NumPy selects in place; the device's radix sort (CUDA's path, forced here on the CPU)
    reads the same values to the bit."""
    import ringscan.kernels.compact as compact
    from ringscan.kernels.compact import median, median64, percentile32, percentiles

    monkeypatch.setattr(compact, "_host_order_stats", lambda dev: host)
    rng = np.random.default_rng(n)
    a = (rng.gamma(2.0, 0.3, n) * 3).astype(np.float32)
    if n > 3:
        a[rng.random(n) < 0.1] = np.nan  # left out, as the callers filter them
    fin = a[np.isfinite(a)]
    assert median(_f32(a)) == np.median(fin.astype(np.float64))
    assert median(_f32(a), dtype=np.float32) == float(np.median(fin))
    got, count = percentiles(_f32(a), [50, 95, 5, 100])
    assert count == fin.size and got == [float(x) for x in np.percentile(fin.astype(np.float64), [50, 95, 5, 100])]
    assert np.isnan(median(_f32(np.full(4, np.nan)))) and percentiles(_f32(np.full(4, np.nan)), [50])[1] == 0
    assert percentile32(_f32(a), 95) == float(np.percentile(fin, 95))
    pos = np.abs(rng.normal(size=n))
    assert median64(wp.array(pos, dtype=wp.float64)) == float(np.median(pos))


def test_set_at_writes_the_value_at_the_indices_only():
    from ringscan.kernels.compact import set_at

    a = wp.zeros(10, dtype=wp.int32)
    set_at(a, wp.array(np.array([1, 4, 9], np.int32)), 1)
    assert a.numpy().tolist() == [0, 1, 0, 0, 1, 0, 0, 0, 0, 1]


@pytest.mark.parametrize("way", ["pixel_rows", "_pixel_rows_launched"])
def test_pixel_rows_list_a_maps_items_row_by_row(way):
    """pixel_rows: the occupied pixels before each pixel (a 0..n-1 index: occupied; -1 or >= n: not) and
    their items in pixel order, so a row's items between two columns are one slice of the list; on the
    CPU by NumPy, on a GPU by kernels (run here on the CPU too)."""
    import ringscan.kernels.compact as compact

    pixel_rows = getattr(compact, way)
    rng = np.random.default_rng(5)
    width, height, n = 37, 23, 300
    at = np.where(rng.random(width * height) < 0.5, -1, n + 4).astype(np.int32)  # none: -1 or >= n
    occ = rng.choice(width * height, n, replace=False)
    at[occ] = rng.permutation(n)
    rank, listed = (a.numpy() for a in pixel_rows(wp.array(at, dtype=wp.int32), n))
    have = (at >= 0) & (at < n)
    assert np.array_equal(rank, np.concatenate([[0], np.cumsum(have)]))
    assert np.array_equal(listed, at[have])  # n items, each at one pixel
    y, x0, x1 = 11, 5, 30
    row = at[y * width + x0: y * width + x1 + 1]
    assert np.array_equal(listed[rank[y * width + x0]: rank[y * width + x1 + 1]], row[(row >= 0) & (row < n)])
