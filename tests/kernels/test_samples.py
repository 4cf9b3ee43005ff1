"""The one Samples type: what every sampler and codec returns."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.samples import Samples


def test_optional_fields_default_to_none_and_numpy_gives_the_set_ones():
    uv = wp.array(np.array([[1.5, 2.0], [3.0, 4.5]], np.float32), dtype=wp.vec2, device="cpu")
    f = wp.array(np.array([10.0, 11.0], np.float32), dtype=wp.float32, device="cpu")
    i = wp.array(np.array([0, 7], np.int32), dtype=wp.int32, device="cpu")
    s = Samples(uv=uv, rho=f, ring=None, sector=i, confidence=f, pixel=i)
    assert len(s) == 2
    assert s.phi is None and s.sigma_rho is None and s.sigma_tan is None
    d = s.numpy()
    assert set(d) == {"uv", "rho", "sector", "confidence", "pixel"}
    np.testing.assert_array_equal(d["uv"], [[1.5, 2.0], [3.0, 4.5]])
    s.phi = wp.array(np.array([0.5, -3.0], np.float32), dtype=wp.float32, device="cpu")
    np.testing.assert_array_equal(s.numpy()["phi"], np.float32([0.5, -3.0]))
