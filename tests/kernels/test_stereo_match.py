"""Two-camera matching (kernels.stereo_match) against a hand-made rig (tests/support/stereo_rig.py):
two cameras and a projector around a known sphere (or a step); truth projected through each lens
gives the exact projector coordinates and pixels."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.stereo_match import (
    MATCH_STATUS_NAMES,
    MatchSettings,
    match_by_projector,
    projector_coordinates,
)
from tests.support.stereo_rig import (
    CAM1,
    CAM2,
    CENTER,
    PH,
    PROJ,
    PW,
    from_projector,
    project_points,
    ring_samples,
    surface_hits,
    warp_array as _w,
)


def _match(device, q, qs, p2, uv2, s2, **kw):
    return match_by_projector(_w(q, wp.vec2, device), _w(qs, wp.float32, device), _w(p2, wp.vec2, device),
                              _w(uv2, wp.vec2, device), _w(s2, wp.float32, device), projector_size=(PW, PH), **kw)


def test_dense_map_matches_to_hundredths_of_a_pixel(device):
    # camera 2's coordinates at every pixel of a window (the imported Gray code's kind)
    uu, vv = np.meshgrid(np.arange(380.0, 640.0), np.arange(500.0, 780.0))
    g = np.c_[uu.ravel(), vv.ravel()]
    X2 = surface_hits(CAM2, g)
    p2 = project_points(PROJ, X2)
    # queries: camera-1 pixels whose points camera 2 sees inside that window
    rng = np.random.default_rng(1)
    X = surface_hits(CAM1, np.c_[rng.uniform(300, 980, 3000), rng.uniform(250, 800, 3000)])
    uv2_true = project_points(CAM2, X)
    inside = (np.isfinite(X).all(1) & (uv2_true[:, 0] > 390) & (uv2_true[:, 0] < 630)
              & (uv2_true[:, 1] > 510) & (uv2_true[:, 1] < 770))
    X, uv2_true = X[inside], uv2_true[inside]
    q = project_points(PROJ, X)
    M = _match(device, q, np.full(len(q), 0.05), p2, g, np.full(len(g), 0.05))
    st = M.status.numpy()
    assert len(q) > 200 and (st == 0).mean() > 0.98, np.bincount(st)  # the rest: at the window's edge
    err = np.linalg.norm(M.uv2.numpy()[st == 0] - uv2_true[st == 0], axis=1)
    # the affine map's curvature error: sub-hundredth where the sphere faces the
    # camera, a tenth of a pixel at most near its silhouette
    assert np.median(err) < 0.005 and np.percentile(err, 99) < 0.03 and err.max() < 0.15
    # the map's linear part is the surface's d uv2 / d p (what three rays decorrelate by): the truth by
    # central differences of +-0.5 projector px through the sphere
    ok = st == 0
    cols = [(project_points(CAM2, surface_hits(PROJ, q[ok] + e)) - project_points(CAM2, surface_hits(PROJ, q[ok] - e)))
            for e in (np.array([0.5, 0.0]), np.array([0.0, 0.5]))]
    A_true = np.stack(cols, axis=2)  # (m, 2, 2): per 1 projector px
    A = M.proj_map.numpy()[ok].reshape(-1, 2, 2)
    rel = np.linalg.norm(A - A_true, axis=(1, 2)) / np.linalg.norm(A_true, axis=(1, 2))
    assert np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.05, np.percentile(rel, [50, 95])
    # without maps the same matches, and one-element placeholders
    M0 = _match(device, q, np.full(len(q), 0.05), p2, g, np.full(len(g), 0.05), maps=False)
    assert np.array_equal(M0.uv2.numpy(), M.uv2.numpy()) and M0.proj_map.shape == (1,)
    # outside the map: no neighbours, never a guess
    far = _match(device, np.array([[5.0, 5.0], [np.nan, 1.0]]), np.full(2, 0.05), p2, g, np.full(len(g), 0.05))
    assert [MATCH_STATUS_NAMES[s] for s in far.status.numpy()] == ["too_few_neighbours", "no_coordinate"]


def test_ring_samples_match_along_their_ring_with_predicted_sigma(device):
    rng = np.random.default_rng(2)
    radii = np.arange(20.0, 240.0, 8.0)
    p2_true = ring_samples(rng, radii)
    X2, ok2 = from_projector(p2_true)
    p2_true, X2 = p2_true[ok2], X2[ok2]
    uv2 = project_points(CAM2, X2)
    # the angle code's noise: tangential, 0.1 projector px
    sig = 0.1
    off = p2_true - CENTER
    tang = np.c_[-off[:, 1], off[:, 0]] / np.linalg.norm(off, axis=1, keepdims=True)
    p2 = p2_true + tang * rng.normal(0, sig, (len(off), 1))
    # queries: camera 1's samples on the same rings (exact coordinates)
    q = ring_samples(rng, radii, step=3.0)
    Xq, okq = from_projector(q)
    q, Xq = q[okq], Xq[okq]
    truth = project_points(CAM2, Xq)
    M = _match(device, q, np.full(len(q), 0.0), p2, uv2, np.full(len(p2), sig))
    st = M.status.numpy()
    assert (st == 0).mean() > 0.97, np.bincount(st)
    e = M.uv2.numpy()[st == 0] - truth[st == 0]
    err = np.linalg.norm(e, axis=1)
    s2 = M.sigma2.numpy()[st == 0]
    assert np.median(err) < 0.05  # camera px; a single sample is off by gain * 0.1 ~ 0.1 px
    # the predicted sigma (per axis) is the error's own scale
    ratio = np.sqrt(np.mean(np.sum(e ** 2, axis=1) / 2) / np.mean(s2 ** 2))
    assert 0.6 < ratio < 1.6, ratio
    gain = M.gain.numpy()[st == 0]
    assert 0.7 < np.median(gain) < 1.5  # ~1 camera px per projector px on this rig
    # neighbours along a ring: the map across it is unknown; it is rank one, along the ring (three rays take
    # it so: kernels.stereo_rays.through_map)
    A = M.proj_map.numpy()[st == 0].astype(np.float64)
    det = np.abs(A[:, 0] * A[:, 3] - A[:, 1] * A[:, 2])
    n2 = 0.5 * (A ** 2).sum(axis=1)
    assert (det < 1e-4 * n2).mean() > 0.9
    tang_q = np.c_[-(q - CENTER)[:, 1], (q - CENTER)[:, 0]][st == 0]
    tang_q /= np.linalg.norm(tang_q, axis=1, keepdims=True)
    along = np.abs(np.einsum("nij,nj->ni", A.reshape(-1, 2, 2), tang_q)).sum(axis=1)
    across = np.abs(np.einsum("nij,nj->ni", A.reshape(-1, 2, 2), np.c_[tang_q[:, 1], -tang_q[:, 0]])).sum(axis=1)
    assert np.median(across / along) < 0.05  # what a radial step does: (next to) nothing


def test_a_depth_step_is_dropped_not_blended(device):
    rng = np.random.default_rng(3)
    p2 = np.c_[rng.uniform(300, 720, 40000), rng.uniform(200, 560, 40000)]
    X2, ok2 = from_projector(p2, "step")
    p2, uv2 = p2[ok2], project_points(CAM2, X2[ok2])
    q = np.c_[rng.uniform(320, 700, 4000), rng.uniform(220, 540, 4000)]
    Xq, okq = from_projector(q, "step")
    q, truth = q[okq], project_points(CAM2, Xq[okq])
    M = _match(device, q, np.zeros(len(q)), p2, uv2, np.full(len(p2), 0.02))
    st = M.status.numpy()
    err = np.linalg.norm(M.uv2.numpy() - truth, axis=1)
    assert np.any(st == MATCH_STATUS_NAMES.index("discontinuity"))
    assert (st == 0).mean() > 0.9
    assert err[st == 0].max() < 0.1  # nothing blended across the edge (a blend is ~100 px off)


def test_bad_inputs_raise(device):
    a = wp.zeros(3, dtype=wp.vec2, device=device)
    f = wp.zeros(3, dtype=wp.float32, device=device)
    with pytest.raises(ValueError, match="query_sigma"):
        match_by_projector(a, wp.zeros(2, dtype=wp.float32, device=device), a, a, f, projector_size=(PW, PH))
    with pytest.raises(ValueError, match="neighbours"):
        MatchSettings(neighbours=40)
    p, s = projector_coordinates(wp.array(np.array([10.0, 5.0], np.float32), device=device),
                                 wp.array(np.array([0.0, np.nan], np.float32), device=device),
                                 wp.array(np.array([0.3, 0.3], np.float32), device=device),
                                 wp.array(np.array([0.4, 0.4], np.float32), device=device), center=CENTER)
    pn = p.numpy()
    assert np.allclose(pn[0], [CENTER[0] + 10, CENTER[1]]) and np.isnan(pn[1]).all()
    assert np.allclose(s.numpy(), np.sqrt((0.09 + 0.16) / 2))


def test_predicted_sigmas_take_in_the_samples_scatter_beyond_their_noise(device):
    """Samples whose positions scatter more than their stated noise (a decode's model error: the ring edges'
    sub-pixel bias, the pattern's rasterization): the neighbours' excess scatter about the fitted map goes
    into sigma1 and sigma2 (half each), so sqrt(sigma1^2 + sigma2^2) predicts the actual match errors (camera
    2's scatter and the query's own) within a factor 1.5, where the stated noise alone predicts under a third. The
    term is made for a decode's errors, correlated over neighbouring samples, which the fit does not average
    out (on the virtual rig's scan it is honest to 10 %: benchmarks/stereo_rays.py); this scatter is
    independent per sample, which the fit partly averages out, so here it predicts up to 1.5x too much."""
    rng = np.random.default_rng(4)
    radii = np.arange(20.0, 240.0, 8.0)
    p2 = ring_samples(rng, radii)
    X2, ok2 = from_projector(p2)
    p2, X2 = p2[ok2], X2[ok2]
    scatter = 0.05  # camera px per axis, beyond the stated 0.01 projector px
    uv2 = project_points(CAM2, X2) + rng.normal(0, scatter, (len(X2), 2))
    q_true = ring_samples(rng, radii, step=3.0)
    Xq, okq = from_projector(q_true)
    q_true, Xq = q_true[okq], Xq[okq]
    off = q_true - CENTER
    tang = np.c_[-off[:, 1], off[:, 0]] / np.linalg.norm(off, axis=1, keepdims=True)
    q = q_true + tang * rng.normal(0, scatter, (len(q_true), 1))  # the query's own (along its ring; gain ~1)
    M = _match(device, q, np.full(len(q), 0.01), p2, uv2, np.full(len(p2), 0.01))
    st = M.status.numpy()
    assert (st == 0).mean() > 0.9, np.bincount(st)
    ok = st == 0
    e = M.uv2.numpy()[ok] - project_points(CAM2, Xq[ok])
    s1, s2, gain = M.sigma1.numpy()[ok], M.sigma2.numpy()[ok], M.gain.numpy()[ok]
    z = e / np.hypot(s1, s2)[:, None]
    mad = 1.4826 * np.median(np.abs(z - np.median(z, axis=0)), axis=0)
    assert np.all((0.5 < mad) & (mad < 1.5)), mad
    assert np.median(np.hypot(s1, s2)) > 3 * np.median(gain) * 0.01 * np.sqrt(2)  # the stated noise alone


# ---------------------------------------------------------------------- about one camera pixel per projector pixel

_A = np.array([[1.1, 0.15], [-0.1, 1.05]])  # projector px per camera-2 px: about one, turned a little
_B = np.array([150.0, 140.0])


def _lattice(rng, n_query=3000, A=_A):
    """Camera 2's pixels over a 240 x 240 window, their exact projector coordinates p = A x + b, and
    queries: exact projector points well inside, with where camera 2 truly sees them."""
    xx, yy = np.meshgrid(np.arange(240.0), np.arange(240.0))
    uv2 = np.c_[xx.ravel(), yy.ravel()]
    p2 = uv2 @ A.T + _B
    truth = np.c_[rng.uniform(20, 220, n_query), rng.uniform(20, 220, n_query)]
    return uv2, p2, truth @ A.T + _B, truth


def _plain_error(q, p2_int, uv2, truth):
    """The plain decode's camera-2 position of each query: the mean of camera 2's pixels of its
    rounded code (NaN where camera 2 has none), and its distance from the truth."""
    key = lambda p: np.round(p[:, 0]).astype(np.int64) * 100000 + np.round(p[:, 1]).astype(np.int64)  # noqa: E731
    k2, kq = key(p2_int), key(q)
    order = np.argsort(k2)
    ks, first = np.unique(k2[order], return_index=True)
    sums = np.add.reduceat(uv2[order], first)
    cnt = np.diff(np.r_[first, len(order)])
    at = np.searchsorted(ks, kq)
    hit = (at < len(ks)) & (ks[np.minimum(at, len(ks) - 1)] == kq)
    pos = np.full(q.shape, np.nan)
    pos[hit] = sums[at[hit]] / cnt[at[hit], None]
    return np.linalg.norm(pos - truth, axis=1)


def test_integer_codes_at_one_pixel_per_projector_pixel_are_matched_between_the_codes(device):
    """Integer codes one camera pixel per projector pixel apart scatter ~0.4 camera px about any map (a
    projector pixel's quantisation, uniform): the fit's limit scales with the codes' own sigma
    (1 / sqrt 12), so they are matched, not dropped as a discontinuity as under the fixed 0.5 px,
    and the fit through eight of them lands closer than the plain decode's mean of one code's pixels."""
    rng = np.random.default_rng(11)
    A = 0.7 * _A  # 1.3 camera px per projector px: the codes scatter 0.45 px about their map
    uv2, p2, q, truth = _lattice(rng, A=A)
    p2_int = np.round(p2)
    q_int = np.round(q)  # camera 1's codes are integers too
    s_int = 1.0 / np.sqrt(12.0)
    M = _match(device, q_int, np.full(len(q), s_int), p2_int, uv2, np.full(len(p2), s_int))
    st = M.status.numpy()
    assert (st == 0).mean() > 0.99, np.bincount(st)  # before: half lost as discontinuity
    # the query's own code is as far off as the plain decode's: compare at camera 2's side, where the
    # exact code of the query's rounded point lies
    truth_int = (q_int - _B) @ np.linalg.inv(A).T
    err = np.linalg.norm(M.uv2.numpy() - truth_int, axis=1)[st == 0]
    plain = _plain_error(q_int, p2_int, uv2, truth_int)
    # the fit through eight codes lands closer than the plain mean of one code's pixels (measured 0.09
    # against 0.21 px median; at about one pixel per code the rounding errors of neighbours are alike,
    # a slow beat, so eight average them less than independent errors would: 0.8 leaves room for it)
    assert np.median(err) < 0.8 * np.nanmedian(plain), (np.median(err), np.nanmedian(plain))


def test_sub_pixel_positions_among_integer_codes_are_not_taken_for_extrapolation(device):
    """An import that interpolated some pixels (sigma 0.02 px) and left their neighbours integer codes
    (0.29 px) weighs them 200 to 1: judged on the weighted spread, a query amid its neighbours looked
    extrapolated, or its neighbours a line (before: 30-40 % of such queries lost). The neighbourhood's
    shape is its plain spread; the fit stays weighted."""
    rng = np.random.default_rng(12)
    uv2, p2, q, truth = _lattice(rng)
    sub = rng.random(len(p2)) < 0.3
    p2m = np.where(sub[:, None], p2, np.round(p2))
    s2 = np.where(sub, 0.02, 1.0 / np.sqrt(12.0))
    M = _match(device, q, np.full(len(q), 0.02), p2m, uv2, s2)
    st = M.status.numpy()
    assert (st == 0).mean() > 0.99, [MATCH_STATUS_NAMES[k] for k in np.unique(st)]
    err = np.linalg.norm(M.uv2.numpy() - truth, axis=1)[st == 0]
    # the precise neighbours lead the fit: well under the integer codes' 0.1-0.2 px
    assert np.median(err) < 0.05, np.median(err)


def test_one_misread_neighbour_is_left_out_two_surfaces_still_are_a_discontinuity(device):
    """A code misread by a few projector pixels (a weak bit) ruins the fit of every query that has it
    among its eight neighbours: it is left out and the map fitted again, so 5 % of misread codes no
    longer cost ~35 % of the matches; the query lands where the others say, not between."""
    rng = np.random.default_rng(13)
    uv2, p2, q, truth = _lattice(rng)
    s2 = np.full(len(p2), 0.02)
    bad = rng.random(len(p2)) < 0.05
    p2b = p2.copy()
    p2b[bad] += rng.choice([-1.0, 1.0], (bad.sum(), 2)) * rng.uniform(3, 6, (bad.sum(), 2))
    M = _match(device, q, np.full(len(q), 0.02), p2b, uv2, s2)
    st = M.status.numpy()
    assert (st == 0).mean() > 0.95, np.bincount(st)
    err = np.linalg.norm(M.uv2.numpy() - truth, axis=1)[st == 0]
    assert np.percentile(err, 99) < 0.1, np.percentile(err, 99)  # camera px: nothing pulled toward a misread


def test_dense_map_binned_finer_finds_the_same_matches(monkeypatch):
    """A dense camera-2 map (~80 samples a 4 px cell) is binned in cells of 1 px (MAX_GRID_SPLIT):
    the same neighbours, so the same matches to the bit as the 4 px grid, the radius unchanged."""
    import ringscan.kernels.stereo_match as ks

    rng = np.random.default_rng(11)
    H, W = 200, 300
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    pu = 0.42 * x + 0.03 * y + 2e-4 * x * y + rng.normal(0, 0.02, x.shape)
    pv = 0.45 * y - 0.02 * x + rng.normal(0, 0.02, x.shape)
    keep = rng.random(x.shape) > 0.05
    proj2 = np.stack([pu[keep], pv[keep]], 1).astype(np.float32)
    uv2 = np.stack([x[keep], y[keep]], 1).astype(np.float32)
    q = np.stack([rng.uniform(-2, 130, 3000), rng.uniform(-2, 95, 3000)], 1).astype(np.float32)
    q[::50] = np.nan

    def run():
        v2 = lambda a: wp.array(a, dtype=wp.vec2, device="cpu")  # noqa: E731
        f32 = lambda a: wp.array(a, dtype=wp.float32, device="cpu")  # noqa: E731
        M = match_by_projector(v2(q), f32(np.full(len(q), 0.05, np.float32)), v2(proj2), v2(uv2),
                               f32(np.full(len(proj2), 0.05, np.float32)), projector_size=(128, 96), threads=2)
        return {k: getattr(M, k).numpy() for k in ("uv2", "sigma2", "sigma1", "gain", "fit_px", "status")}

    fine = run()
    monkeypatch.setattr(ks, "MAX_GRID_SPLIT", 0)
    coarse = run()
    for k in fine:
        assert np.array_equal(fine[k], coarse[k], equal_nan=True), k
    assert (fine["status"] == 0).mean() > 0.8  # most queries inside the map matched


def test_neighbour_search_skipping_empty_cells_finds_the_k_nearest():
    """The search skips what its summed-area table and each cell's nearest point say holds no
    neighbour (gaps in camera 2's view, far corners of a ring): its matches are those of the exact
    k nearest (a brute-force search here) fitted by least squares, and a query with fewer than
    ``min_neighbours`` samples within the radius is ``too_few_neighbours``, exactly."""
    rng = np.random.default_rng(5)
    # camera 2's samples in three patches with gaps between them (a view with occlusions)
    pts = np.concatenate([rng.uniform((10, 10), (60, 40), (2500, 2)), rng.uniform((75, 12), (120, 60), (2500, 2)),
                          rng.uniform((20, 55), (50, 90), (1500, 2))])
    uv = np.stack([2.1 * pts[:, 0] + 0.2 * pts[:, 1] + 3e-3 * pts[:, 0] ** 2,
                   1.9 * pts[:, 1] - 0.1 * pts[:, 0] + 2e-3 * pts[:, 0] * pts[:, 1]], 1)
    uv += rng.normal(0, 0.05, uv.shape)  # another neighbour set would move a match by ~0.01 px
    q = rng.uniform((0, 0), (128, 96), (1500, 2))
    s = MatchSettings()
    M = match_by_projector(wp.array(q.astype(np.float32), dtype=wp.vec2, device="cpu"),
                           wp.array(np.full(len(q), 0.05, np.float32), dtype=wp.float32, device="cpu"),
                           wp.array(pts.astype(np.float32), dtype=wp.vec2, device="cpu"),
                           wp.array(uv.astype(np.float32), dtype=wp.vec2, device="cpu"),
                           wp.array(np.full(len(pts), 0.05, np.float32), dtype=wp.float32, device="cpu"),
                           projector_size=(128, 96), settings=s, threads=2)
    st, got = M.status.numpy(), M.uv2.numpy()
    p32 = pts.astype(np.float32).astype(np.float64)
    d2 = ((q.astype(np.float32).astype(np.float64)[:, None, :] - p32[None]) ** 2).sum(-1)
    within = (d2 <= s.radius_px ** 2).sum(1)
    assert np.array_equal(st == 2, within < s.min_neighbours)
    ok = np.flatnonzero(st == 0)
    assert 0.3 * len(q) < ok.size < 0.9 * len(q)  # queries in the gaps and beyond the patches are not matched
    worst = 0.0
    for i in ok:
        nn = np.argsort(d2[i], kind="stable")[:s.neighbours]
        Aff = np.c_[p32[nn], np.ones(len(nn))]
        coef, *_ = np.linalg.lstsq(Aff, uv.astype(np.float32)[nn].astype(np.float64), rcond=None)
        worst = max(worst, np.abs(np.r_[q[i].astype(np.float32), 1.0] @ coef - got[i]).max())
    # float32 arithmetic on coordinates of ~300 px: 1e-3 px; a neighbour missed or taken wrongly: ~1e-2
    assert worst < 2e-3


def test_neighbours_at_equal_distance_are_taken_by_sample_index():
    """Queries at the centres of a grid of camera-2 samples have their neighbours at equal distances (4 at
    0.5 px^2, 8 at 2.5 px^2): of the 8 at 2.5 the search keeps the 4 of lowest sample index, whatever the
    cells' order (the samples are given shuffled), as a brute-force search sorted by (distance, index)."""
    rng = np.random.default_rng(8)
    gx, gy = np.meshgrid(np.arange(4.0, 44.0), np.arange(4.0, 36.0))
    pts = np.c_[gx.ravel(), gy.ravel()][rng.permutation(gx.size)]
    uv = pts @ np.array([[2.0, 0.1], [-0.2, 1.8]]) + rng.normal(0, 0.2, pts.shape)  # a set's choice: ~0.05 px
    q = np.c_[rng.integers(8, 38, 300) + 0.5, rng.integers(8, 30, 300) + 0.5]
    s = MatchSettings()
    f32 = lambda a: wp.array(np.asarray(a, np.float32), dtype=wp.float32, device="cpu")  # noqa: E731
    v2 = lambda a: wp.array(np.asarray(a, np.float32), dtype=wp.vec2, device="cpu")  # noqa: E731
    M = match_by_projector(v2(q), f32(np.full(len(q), 0.05)), v2(pts), v2(uv), f32(np.full(len(pts), 0.05)),
                           projector_size=(48, 40), settings=s, threads=2)
    st, got = M.status.numpy(), M.uv2.numpy()
    assert (st == 0).all(), np.bincount(st)
    d2 = ((q[:, None, :] - pts[None]) ** 2).sum(-1)  # (exact: halves and integers)
    worst = 0.0
    for i in range(len(q)):
        nn = np.lexsort((np.arange(len(pts)), d2[i]))[:s.neighbours]
        assert d2[i, nn[-1]] == 2.5 and (d2[i] == 2.5).sum() == 8  # the choice among ties is the test
        Aff = np.c_[pts[nn], np.ones(len(nn))]
        coef, *_ = np.linalg.lstsq(Aff, uv.astype(np.float32)[nn].astype(np.float64), rcond=None)
        worst = max(worst, np.abs(np.r_[q[i], 1.0] @ coef - got[i]).max())
    assert worst < 2e-3  # float32 on coordinates of ~80 px; another set of 4 among the ties: ~0.05 px
