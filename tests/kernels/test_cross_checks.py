"""kernels.cross_checks: the neighbour model's checks across rings against their NumPy statement
(pipeline.reconstruct.neighbour_checks._cross_ring_checks)."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.cross_checks import MAT66D, condition_below, cross_ring_checks
from tests.support.ring_views import WIDTH, ring_circle, ring_view


def test_cross_ring_checks_are_the_numpy_statements():
    """The checks across rings (kernels.cross_checks.cross_ring_checks) against the NumPy statement
    (neighbour_checks._cross_ring_checks) on rings 4.3 px apart over a curved depth with noise, some
    samples far off (refitted without them) and holes (centres without neighbours on both sides, gated
    neighbourhoods): the same checked samples, r to 1e-6 of its scale and the variances to 1e-10."""
    from ringscan.pipeline.reconstruct.neighbour_checks import CROSS_GATE, CROSS_REJECT, _cross_ring_checks, _ring_index

    rng = np.random.default_rng(21)
    uv, pixel, ring = ring_view([ring_circle(k, 10 + 4.3 * k) for k in range(24)])
    keep = rng.random(len(pixel)) > 0.2
    uv, pixel, ring = uv[keep].astype(np.float64), pixel[keep], ring[keep]
    n = len(pixel)
    var = rng.uniform(0.5, 2.0, n) * 1e-4
    depth = 500 + 0.03 * uv[:, 0] + 2e-4 * (uv[:, 1] - 120) ** 2 + np.sqrt(var) * rng.standard_normal(n)
    depth[rng.random(n) < 0.03] += 0.5  # far off their neighbours' fit
    depth[rng.random(n) < 0.02] = np.nan  # not placed
    ok = np.flatnonzero(np.isfinite(depth))
    idx = _ring_index(ring.astype(np.int64), pixel.astype(np.int64), ok, WIDTH)
    view = dict(depth=wp.array(depth, dtype=wp.float64), var=wp.array(var, dtype=wp.float64),
                uv=wp.array(uv, dtype=wp.vec2d), ring=wp.array(ring, dtype=wp.int32),
                pixel=wp.array(pixel, dtype=wp.int32), at_pixel=wp.array(idx.at_pixel.astype(np.int32), dtype=wp.int32))
    centre = ok[rng.random(ok.size) < 0.4]
    for radius in (8, 12):
        want = _cross_ring_checks(depth, var, uv, idx, centre, radius)
        got = cross_ring_checks(**view, centre=centre, radius=radius, width=WIDTH, reject=CROSS_REJECT,
                                gate=CROSS_GATE, threads=2)
        assert np.array_equal(got[0], want[0]) and 0.2 * centre.size < want[0].size < centre.size
        # r: depth (~500 mm) less a fit of it, so rounding of ~1e-13 of the depth shows as ~1e-9 mm
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-6 * np.std(want[1]))
        np.testing.assert_allclose(got[2], want[2], rtol=1e-10)
    with pytest.raises(ValueError, match="centre"):
        cross_ring_checks(**view, centre=np.array([n + 3]), radius=8, width=WIDTH, reject=CROSS_REJECT, gate=CROSS_GATE)


@wp.kernel
def _condition_below_kernel(N: wp.array(dtype=MAT66D), limit: wp.float64, below: wp.array(dtype=wp.int32)):
    i = wp.tid()
    below[i] = wp.where(condition_below(N[i], limit), 1, 0)


def test_condition_below_decides_as_the_condition_number():
    """condition_below (the fits' test, cheap bounds and the Jacobi eigenvalues where they do not
    settle it) against NumPy's 2-norm condition number for 6x6 symmetric matrices of known spectra:
    far below and above the limit (the bounds decide), within 3 % of it on either side (the bounds
    are 36x apart: Jacobi decides), beyond what a Cholesky factor survives, and singular."""
    rng = np.random.default_rng(5)
    limit = 1e12
    conds = [1e2, 1e8, 3e10, 0.97e12, 0.99e12 * 0.98, 1.03e12, 3e12, 1e14, 1e17]
    mats = []
    for cond in conds:
        q, _ = np.linalg.qr(rng.standard_normal((6, 6)))
        lam = np.geomspace(1.0, cond, 6) * 50.0
        mats.append((q * lam) @ q.T)
    singular = rng.standard_normal((6, 5))
    mats.append(singular @ singular.T)
    mats = [0.5 * (m + m.T) for m in mats]
    want = [np.linalg.cond(m) < limit for m in mats]
    assert want == [True] * 5 + [False] * 5  # the spectra as built
    below = wp.zeros(len(mats), dtype=wp.int32)
    wp.launch(_condition_below_kernel, dim=len(mats), inputs=[wp.array(np.array(mats), dtype=MAT66D), limit],
              outputs=[below])
    assert below.numpy().astype(bool).tolist() == want
