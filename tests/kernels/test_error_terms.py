"""kernels.error_terms: the error model's per-sample work on the device, against its NumPy statements
(pipeline.reconstruct.error_scale) to the bit."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.error_terms import widen_sigmas
from ringscan.pipeline.reconstruct.error_scale import apply_error_model, region_scale


def _f32(a):
    return wp.array(np.asarray(a, np.float32), dtype=wp.float32, device="cpu")


def test_widened_sigmas_are_the_numpy_statements_to_the_bit():
    """k, a floor, the indirect share above its median and a tile's factor: every term and their mix,
    samples inside the factors' tiles and outside them (and at negative positions)."""
    rng = np.random.default_rng(2)
    n = 30000
    s = rng.uniform(0.01, 0.5, n).astype(np.float32)
    b = rng.uniform(0, 0.6, n).astype(np.float32)
    uv = rng.uniform(-40, 700, (n, 2)).astype(np.float32)
    regions = {"tile_px": 32, "scales": [[0, 0, 1.7], [3, 5, 2.25], [-1, 2, 1.3], [12, 1, 4.0]]}
    middle = float(np.median(b.astype(np.float64)))
    for k, f, px, reg in ((1.6, 0.0, 0.0, None), (1.0, 0.12, 0.0, None), (2.3, 0.05, 0.67, None),
                          (1.2, 0.03, 0.9, regions)):
        got = widen_sigmas(_f32(s), k=k, floor=f, indirect=_f32(b), indirect_px=px, indirect_median=middle,
                           uv=wp.array(uv, dtype=wp.vec2), regions=reg, threads=2).numpy()
        w = apply_error_model(s, k, f, indirect_px=px, indirect=np.maximum(b.astype(np.float64) - middle, 0.0))
        if reg is not None:
            w = (w * np.sqrt(region_scale(reg, uv))).astype(np.float32)
            assert np.count_nonzero(region_scale(reg, uv) != 1.0) > 100  # the tiles hold samples
        np.testing.assert_array_equal(got, w)
