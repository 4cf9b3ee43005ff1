"""kernels.ring_checks: each sample's widest check along its ring, against the NumPy statement
(``neighbour_checks.check_reach``) and against what a ring's shape says it must be."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.ring_checks import sample_reach
from ringscan.pipeline.reconstruct.neighbour_checks import check_reach

WIDTH, HEIGHT = 320, 240


def _circle(k, r, cx=160.0, cy=120.0, arc=(0.0, 2 * np.pi)):
    """One sample a camera pixel along a circle of radius r (px), as a ring's crossings are sampled."""
    th = np.linspace(arc[0], arc[1], int((arc[1] - arc[0]) * r * 1.3), endpoint=False)
    u, v = cx + r * np.cos(th), cy + r * np.sin(th)
    p = np.round(v).astype(int) * WIDTH + np.round(u).astype(int)
    _, first = np.unique(p, return_index=True)
    first = np.sort(first)
    return u[first], v[first], p[first], np.full(first.size, k)


def _view(pieces):
    u, v, p, k = (np.concatenate(a) for a in zip(*pieces))
    return np.stack([u, v], 1).astype(np.float32), p.astype(np.int32), k.astype(np.int32)


def _reach(uv, pixel, ring, depth=None):
    depth = np.full(len(pixel), 500.0) if depth is None else depth
    got = sample_reach(wp.array(uv, dtype=wp.vec2), wp.array(ring, dtype=wp.int32), wp.array(pixel, dtype=wp.int32),
                       np.isfinite(depth), width=WIDTH, threads=2)
    return got, check_reach(depth, pixel, ring, uv.astype(np.float64), width=WIDTH)


def test_a_whole_ring_is_checked_8_px_wide_and_a_fragment_only_by_its_next_neighbours():
    whole = _circle(0, 60.0)
    # a short arc of another ring: 3 samples (the middle one has a neighbour on either side)
    u, v, p, k = _circle(1, 90.0)
    frag = (u[:3], v[:3], p[:3], k[:3])
    lone = _circle(2, 100.0)
    lone = tuple(a[:1] for a in lone)
    uv, pixel, ring = _view([whole, frag, lone])
    got, ref = _reach(uv, pixel, ring)
    n = whole[0].size
    assert np.array_equal(got, ref)
    assert np.all(got[:n] == 8)  # a circle 60 px across: four nodes at +-8 and +-16 px everywhere
    assert got[n:n + 3].tolist() == [0, 1, 0] and got[-1] == 0


def test_the_kernel_reads_the_same_reach_as_the_numpy_statement_on_broken_rings():
    rng = np.random.default_rng(5)
    pieces = [_circle(k, 10 + 4.3 * k) for k in range(24)]
    uv, pixel, ring = _view(pieces)
    keep = rng.random(len(pixel)) > 0.25  # a quarter dropped at random: gaps, fragments, lone samples
    depth = np.where(rng.random(keep.sum()) < 0.05, np.nan, 500.0)  # and some without a depth
    got, ref = _reach(uv[keep], pixel[keep], ring[keep], depth)
    assert np.array_equal(got, ref)
    assert np.all(got[np.isnan(depth)] == -1)
    # every class is there (the test sees each branch)
    assert set(np.unique(got)) == {-1, 0, 1, 2, 4, 8}


def test_bad_arguments_are_refused():
    uv = wp.zeros(3, dtype=wp.vec2)
    with pytest.raises(ValueError, match="ring must be"):
        sample_reach(uv, wp.zeros(2, dtype=wp.int32), wp.zeros(3, dtype=wp.int32), np.ones(3, bool), width=8)
    with pytest.raises(ValueError, match="usable must be"):
        sample_reach(uv, wp.zeros(3, dtype=wp.int32), wp.zeros(3, dtype=wp.int32), np.ones(2, bool), width=8)


def test_ring_lag_nodes_are_the_numpy_statements_to_the_bit():
    """The nodes the neighbour model's wide checks use (its centres' ring directions, their four same-ring
    nodes at 2, 4 and 8 px and the nodes' places) are _ring_directions' and _lag_nodes' to the bit, on
    broken rings whose centres have every outcome (no direction; some nodes missing; all four)."""
    from ringscan.kernels.ring_checks import LAGS, ring_lag_nodes
    from ringscan.pipeline.reconstruct.neighbour_checks import NEIGHBOUR_LAGS, _lag_nodes, _ring_directions, _ring_index

    assert tuple(int(x) for x in LAGS) == NEIGHBOUR_LAGS[1:]  # the kernel's lags are the model's
    rng = np.random.default_rng(12)
    uv, pixel, ring = _view([_circle(k, 10 + 4.3 * k) for k in range(24)])
    keep = rng.random(len(pixel)) > 0.3
    uv, pixel, ring = uv[keep], pixel[keep], ring[keep]
    uv64 = uv.astype(np.float64)
    idx = _ring_index(ring.astype(np.int64), pixel.astype(np.int64), np.arange(len(pixel)), WIDTH)
    centre = idx.order[rng.random(idx.order.size) < 0.5]
    wide, direction = _ring_directions(uv64, idx.ring, idx.at_pixel, WIDTH, centre)
    kept, dirs, nodes, place = ring_lag_nodes(uv64, idx.ring, idx.at_pixel, centre, width=WIDTH, lags=3)
    assert np.array_equal(kept, wide) and np.array_equal(dirs, direction) and 0 < kept.size < centre.size
    for li, lag in enumerate(NEIGHBOUR_LAGS[1:]):
        want_nodes, want_place = _lag_nodes(uv64, idx.ring, idx.at_pixel, WIDTH, wide, direction, lag)
        assert np.array_equal(nodes[:, li], want_nodes)
        found = want_nodes >= 0
        assert np.array_equal(place[:, li][found], want_place[found]) and (place[:, li][~found] == 0).all()
        assert 0 < found.all(axis=1).sum() < found.shape[0]  # some centres with all four nodes, some without


def test_next_neighbours_are_the_numpy_statements():
    """The 1 px check's pairs (two same-ring samples among a centre's 8 neighbouring pixels, at least 120
    degrees apart, the most nearly opposite first) are _next_neighbours' to the sample, on broken rings."""
    from ringscan.kernels.ring_checks import next_neighbours
    from ringscan.pipeline.reconstruct.neighbour_checks import _next_neighbours, _ring_index

    rng = np.random.default_rng(13)
    uv, pixel, ring = _view([_circle(k, 10 + 4.3 * k) for k in range(24)])
    keep = rng.random(len(pixel)) > 0.3
    uv, pixel, ring = uv[keep], pixel[keep].astype(np.int64), ring[keep].astype(np.int64)
    idx = _ring_index(ring, pixel, np.arange(len(pixel)), WIDTH)
    want = _next_neighbours(uv.astype(np.float64), idx, idx.order)
    got = next_neighbours(uv, ring, pixel, idx.key, idx.order, idx.npix, idx.order, width=WIDTH)
    assert all(np.array_equal(a, b) for a, b in zip(got, want))
    assert 0 < want[0].size < idx.order.size  # some centres with a pair, some without


def test_cross_ring_checks_are_the_numpy_statements():
    """The checks across rings (kernels.ring_checks.cross_ring_checks) against the NumPy statement
    (neighbour_checks._cross_ring_checks) on rings 4.3 px apart over a curved depth with noise, some
    samples far off (refitted without them) and holes (centres without neighbours on both sides, gated
    neighbourhoods): the same checked samples, r to 1e-6 of its scale and the variances to 1e-10."""
    from ringscan.kernels.ring_checks import cross_ring_checks
    from ringscan.pipeline.reconstruct.neighbour_checks import CROSS_GATE, CROSS_REJECT, _cross_ring_checks, _ring_index

    rng = np.random.default_rng(21)
    uv, pixel, ring = _view([_circle(k, 10 + 4.3 * k) for k in range(24)])
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
