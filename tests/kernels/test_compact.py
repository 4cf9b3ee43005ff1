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
        gather(wp.zeros(3, dtype=wp.float64), wp.zeros(2, dtype=wp.int32))
