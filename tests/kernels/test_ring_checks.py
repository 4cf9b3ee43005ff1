"""kernels.ring_checks: each sample's widest check along its ring, against the NumPy statement
(``neighbour_checks.check_reach``) and against what a ring's shape says it must be."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.ring_checks import sample_reach
from ringscan.pipeline.reconstruct.neighbour_checks import check_reach
from tests.support.ring_views import WIDTH, ring_circle, ring_view

_circle, _view = ring_circle, ring_view


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


def test_ring_lag_nodes_are_the_numpy_statements_to_the_bit(device):
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
    kept, dirs, nodes, place = ring_lag_nodes(uv64, idx.ring, idx.at_pixel, centre, width=WIDTH, lags=(2, 4, 8),
                                              device=device)
    assert np.array_equal(kept, wide) and np.array_equal(dirs, direction) and 0 < kept.size < centre.size
    for li, lag in enumerate(NEIGHBOUR_LAGS[1:]):
        want_nodes, want_place = _lag_nodes(uv64, idx.ring, idx.at_pixel, WIDTH, wide, direction, lag)
        assert np.array_equal(nodes[:, li], want_nodes)
        found = want_nodes >= 0
        assert np.array_equal(place[:, li][found], want_place[found]) and (place[:, li][~found] == 0).all()
        assert 0 < found.all(axis=1).sum() < found.shape[0]  # some centres with all four nodes, some without
    # a run of the lags alone: the same nodes as in the whole run
    _, _, part, _ = ring_lag_nodes(uv64, idx.ring, idx.at_pixel, centre, width=WIDTH, lags=(4, 8), device=device)
    assert np.array_equal(part, nodes[:, 1:])
    for bad in ((2, 8), (8, 4), (3,), ()):
        with pytest.raises(ValueError, match="a run of"):
            ring_lag_nodes(uv64, idx.ring, idx.at_pixel, centre, width=WIDTH, lags=bad)


def test_next_neighbours_are_the_numpy_statements(device):
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
    got = next_neighbours(uv, ring, pixel, idx.key, idx.order, idx.at_pixel, idx.npix, idx.order, width=WIDTH,
                          device=device)
    assert all(np.array_equal(a, b) for a, b in zip(got, want))
    assert 0 < want[0].size < idx.order.size  # some centres with a pair, some without



@pytest.mark.parametrize("held", ["corner", "far"])
def test_the_reach_is_the_numpy_statements_wherever_a_sample_lies_in_its_pixel(held):
    """The node search settles a node from the 3 x 3 pixels around its target when the samples' own offsets in
    their pixels (``pixel_offsets``: each view's) say none of the outer 16 can be nearer: the same reaches as
    the NumPy statement, which reads all 25, with samples held by the pixel at their corner (edge samples:
    0..1 px from it) and by one 1.4 px away (a bound that leaves the 3 x 3 nothing to settle)."""
    from ringscan.kernels.ring_checks import pixel_offsets
    from tests.support.ring_views import WIDTH as W

    rng = np.random.default_rng(7)
    pieces = [_circle(k, 10 + 4.3 * k) for k in range(24)]
    uv, _, ring = _view(pieces)
    shift = 0.0 if held == "corner" else 1.4
    x = np.floor(uv[:, 0] - shift).astype(np.int64)
    y = np.floor(uv[:, 1]).astype(np.int64)
    pixel = y * W + x
    _, first = np.unique(pixel, return_index=True)  # one sample a pixel
    keep = np.zeros(len(pixel), bool)
    keep[first] = True
    keep &= rng.random(len(pixel)) > 0.2
    uv, pixel, ring = uv[keep], pixel[keep].astype(np.int32), ring[keep]
    lo_x, hi_x, lo_y, hi_y = pixel_offsets(uv, pixel, W)
    # (float32 positions of ~200 px: within 1e-4 px of the held offsets)
    assert lo_x > shift - 1e-4 and lo_y > -1e-4 and hi_x < shift + 1.0 + 1e-4 and hi_y < 1.0 + 1e-4
    got, ref = _reach(uv, pixel, ring)
    assert np.array_equal(got, ref)
    assert set(np.unique(got)) >= {0, 1, 8}
