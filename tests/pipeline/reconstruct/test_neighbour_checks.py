"""The neighbour model (pipeline.reconstruct.neighbour_checks): a ring-only sample's errors checked against
its neighbours along its ring, planted terms recovered, and the samples no check along a ring reaches."""

import numpy as np
import pytest
import warp as wp

def _ring_samples(rng, *, k_rho=1.0, f_rho=0.0, width=400, height=300):
    """Edge samples of 30 concentric camera circles (one a pixel, as a ring's crossings
    are sampled) on a gently curved depth, each sample's error drawn from the model
    sqrt(k^2 s^2 + (f g)^2) with g its depth per projector px."""
    u, v, pix, ring = [], [], [], []
    for k in range(30):
        r = 12 + 4.3 * k
        th = np.linspace(0, 2 * np.pi, int(2 * np.pi * r * 1.3), endpoint=False)
        uu, vv = 200 + r * np.cos(th), 150 + r * np.sin(th)
        p = np.round(vv).astype(int) * width + np.round(uu).astype(int)
        _, first = np.unique(p, return_index=True)
        u.append(uu[first]), v.append(vv[first]), pix.append(p[first]), ring.append(np.full(first.size, k))
    u, v, pix, ring = (np.concatenate(a) for a in (u, v, pix, ring))
    sigma_px = rng.uniform(0.02, 0.08, u.size)
    g = rng.uniform(0.5, 2.0, u.size)
    s = sigma_px * g
    truth = 500 + 0.05 * u + 0.02 * v + 1e-4 * (u - 200) ** 2  # curvature ~2e-4 mm a px^2: far below the noise
    err = np.sqrt((k_rho * s) ** 2 + (f_rho * g) ** 2) * rng.standard_normal(u.size)
    return dict(depth=truth + err, s=s, sigma_px=sigma_px, pixel=pix, ring=ring, uv=np.stack([u, v], 1), width=width)


@pytest.mark.parametrize("k_rho,f_rho", [(1.0, 0.0), (2.5, 0.0), (1.0, 0.05), (3.0, 0.1)])
def test_neighbours_recover_planted_terms(k_rho, f_rho):
    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model, widen_depth_sigma

    d = _ring_samples(np.random.default_rng(7), k_rho=k_rho, f_rho=f_rho)
    m = fit_neighbour_model(d["depth"], d["s"], d["sigma_px"], d["pixel"], d["ring"], d["uv"], width=d["width"])
    assert m["measured_by"] == "neighbours" and m["pairs"] > 4000
    # the two terms trade against each other a little (s / g, the rho sigma, spans 4x here): what must
    # hold is each sample's widened sigma, within 10 % of the planted one (~4800 residuals fix a
    # standard deviation to ~1.5 %), and a Gaussian's median |z| of 0.674 against the truth
    planted = np.sqrt((k_rho * d["s"]) ** 2 + (f_rho * d["s"] / d["sigma_px"]) ** 2)
    fitted = widen_depth_sigma(d["s"], d["sigma_px"], m)
    assert np.median(fitted / planted) == pytest.approx(1.0, abs=0.1)
    # (a floor of 0.04 px beside k s ~ 0.1-0.4 px adds under 5 % to any sigma)
    assert m["k_rho"] == pytest.approx(k_rho, rel=0.15) and m["floor_rho_px"] == pytest.approx(f_rho, abs=0.04)
    truth = 500 + 0.05 * d["uv"][:, 0] + 0.02 * d["uv"][:, 1] + 1e-4 * (d["uv"][:, 0] - 200) ** 2
    assert 0.6 <= np.median(np.abs(d["depth"] - truth) / fitted) <= 0.75


def test_a_small_view_checks_every_row_rather_than_none():
    """A view whose every third row gives fewer than MIN_PAIRS checks (here the inner 7 rings, ~860
    samples, ~290 such checks) has each sample checked instead: k measured, not the decode's sigma
    kept as it is (the identity model: on a small view of Mitsuba's corner, 4x too confident)."""
    from ringscan.pipeline.reconstruct.error_scale import MIN_PAIRS
    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model

    d = _ring_samples(np.random.default_rng(5), k_rho=3.0)
    keep = d["ring"] < 7
    args = [d[k][keep] for k in ("depth", "s", "sigma_px", "pixel", "ring", "uv")]
    y = d["pixel"][keep] // d["width"]
    assert np.count_nonzero(y % 3 == 1) < MIN_PAIRS < keep.sum()  # the case: every third row too few
    m = fit_neighbour_model(*args, width=d["width"])
    assert m["measured_by"] == "neighbours" and m["pairs"] >= MIN_PAIRS
    # ~800 residuals that share samples: k to ~15 %
    assert m["k_rho"] == pytest.approx(3.0, rel=0.15)


def test_a_few_bad_samples_do_not_widen_every_sigma():
    """4 % of the samples off by 30-100 sigma (a fringe's order, a pixel across an edge): each spoils
    the checks it is one of five in (~20 % of them), which read k ~2x the planted one under the
    Student-t alone (CLIP_ROUNDS = 0); the core fitted without the checks beyond CLIP_Z keeps it."""
    from ringscan.pipeline.reconstruct import neighbour_checks as nc

    rng = np.random.default_rng(11)
    d = _ring_samples(rng, k_rho=2.0)
    bad = rng.random(d["s"].size) < 0.04
    d["depth"] = d["depth"] + np.where(bad, rng.choice([-1, 1], bad.size) * rng.uniform(30, 100, bad.size)
                                       * 2.0 * d["s"], 0.0)
    args = (d["depth"], d["s"], d["sigma_px"], d["pixel"], d["ring"], d["uv"])
    m = nc.fit_neighbour_model(*args, width=d["width"])
    # ~4600 residuals, a fifth spoilt: 15 % on k
    assert m["k_rho"] == pytest.approx(2.0, rel=0.15) and m["floor_rho_px"] < 0.03
    unclipped = nc.CLIP_ROUNDS
    try:
        nc.CLIP_ROUNDS = 0
        assert nc.fit_neighbour_model(*args, width=d["width"])["k_rho"] > 1.3 * m["k_rho"]
    finally:
        nc.CLIP_ROUNDS = unclipped


def test_neighbours_of_a_dense_code_are_the_pixel_grid():
    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model, widen_depth_sigma

    rng = np.random.default_rng(3)
    w, h = 120, 90
    y, x = np.mgrid[0:h, 0:w]
    pix = (y * w + x).ravel()
    s = np.full(pix.size, 0.01)
    depth = 400 + 0.03 * x.ravel() + 2.0 * 0.01 * rng.standard_normal(pix.size)
    sigma_px = rng.uniform(0.02, 0.08, pix.size)
    m = fit_neighbour_model(depth, s, sigma_px, pix, None, np.stack([x.ravel(), y.ravel()], 1), width=w)
    assert m["pairs"] > 3000  # every third row's pixels, each against its two neighbours
    # the errors' sigma is 2 s: widened sigmas within 10 % of it (~3600 residuals: ~1.2 % on a sigma)
    assert np.median(widen_depth_sigma(s, sigma_px, m) / (2 * s)) == pytest.approx(1.0, abs=0.1)


def test_too_few_neighbours_change_nothing():
    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model

    d = _ring_samples(np.random.default_rng(1))
    keep = np.arange(0, d["depth"].size, 3)  # every third sample: no two on opposite sides of one
    m = fit_neighbour_model(d["depth"][keep], d["s"][keep], d["sigma_px"][keep], d["pixel"][keep], d["ring"][keep],
                            d["uv"][keep], width=d["width"])
    assert m["measured_by"] is None and m["k_rho"] == 1.0 and m["floor_rho_px"] == 0.0


def test_a_smoothed_dense_code_is_checked_with_its_window():
    """Errors averaged over 3x3 pixels (phase-rings' default window) are partly shared by
    neighbouring pixels: their 1 px difference hides that share (taken as independent they
    look ~1.5x smaller than they are). With the window's overlap taken into account they are
    what they are; without it, the wider checks (4 px apart and more: no shared pixel) see them."""
    from scipy.ndimage import uniform_filter

    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model, widen_depth_sigma

    rng = np.random.default_rng(5)
    w, h = 150, 120
    y, x = np.mgrid[0:h, 0:w]
    noise = uniform_filter(rng.standard_normal((h, w)), size=3, mode="reflect") * 3.0  # sd 1 after a 3x3 mean
    s = np.full(w * h, 0.01)
    sigma_px = rng.uniform(0.02, 0.08, w * h)
    depth = (400 + 0.03 * x + 3.0 * 0.01 * noise).ravel()  # error sd 3 s
    args = (depth, s, sigma_px, (y * w + x).ravel(), None, np.stack([x.ravel(), y.ravel()], 1))
    blind_model = fit_neighbour_model(*args, width=w)
    blind = np.median(widen_depth_sigma(s, sigma_px, blind_model) / (3 * s))
    known = np.median(widen_depth_sigma(s, sigma_px, fit_neighbour_model(*args, width=w, window=3)) / (3 * s))
    assert known == pytest.approx(1.0, abs=0.1)  # ~6000 residuals: ~1 % on a sigma
    # the 1 px check alone saw ~0.65 of it (the shared part cancels); a wider one was kept
    assert blind_model["lag_px"] >= 2 and blind == pytest.approx(1.0, abs=0.1)


def test_errors_that_neighbouring_samples_share_are_seen_by_the_wider_checks():
    """Errors smoothed along each ring over ~3 samples (a blur spreading a pixel's noise over
    its neighbours): the 1 px check sees ~half of them; the kept check sees them all."""
    from scipy.ndimage import gaussian_filter1d

    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model, widen_depth_sigma

    rng = np.random.default_rng(11)
    d = _ring_samples(rng)
    truth = 500 + 0.05 * d["uv"][:, 0] + 0.02 * d["uv"][:, 1] + 1e-4 * (d["uv"][:, 0] - 200) ** 2
    err = np.empty_like(truth)
    for k in np.unique(d["ring"]):  # samples of a ring are in order around it (_ring_samples)
        m = np.flatnonzero(d["ring"] == k)
        e = gaussian_filter1d(rng.standard_normal(m.size), 1.5, mode="wrap")
        err[m] = e / e.std()
    sd = 3.0 * d["s"]
    d["depth"] = truth + sd * err
    m = fit_neighbour_model(d["depth"], d["s"], d["sigma_px"], d["pixel"], d["ring"], d["uv"], width=d["width"])
    assert m["lag_px"] >= 2
    fitted = widen_depth_sigma(d["s"], d["sigma_px"], m)
    # within 15 % of the planted sigma (the floor term trades against k a little, as above)
    assert np.median(fitted / sd) == pytest.approx(1.0, abs=0.15)
    assert 0.55 <= np.median(np.abs(d["depth"] - truth) / fitted) <= 0.8


def test_a_part_of_a_ring_only_view_whose_neighbours_disagree_more_gets_its_own_scale():
    """The neighbours' model is one for the view; a part of it that errs 2x more (an object's
    facets beside a plane) gets its tiles' variance factor, as the angle's model does."""
    from ringscan.pipeline.reconstruct.error_scale import region_scale
    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model, widen_depth_sigma

    rng = np.random.default_rng(12)
    d = _ring_samples(rng, k_rho=1.0)
    truth = 500 + 0.05 * d["uv"][:, 0] + 0.02 * d["uv"][:, 1] + 1e-4 * (d["uv"][:, 0] - 200) ** 2
    hot = (d["uv"][:, 0] > 224) & (d["uv"][:, 1] > 160)  # one quarter-ish corner, in whole 32 px tiles
    d["depth"] = truth + np.where(hot, 2.0, 1.0) * (d["depth"] - truth)
    m = fit_neighbour_model(d["depth"], d["s"], d["sigma_px"], d["pixel"], d["ring"], d["uv"], width=d["width"])
    sig = widen_depth_sigma(d["s"], d["sigma_px"], m) * np.sqrt(region_scale(m["regions"], d["uv"]))
    z = np.abs(d["depth"] - truth) / sig
    # the corner's tiles: a variance factor ~4 (2x the errors); its sigmas hold (a Gaussian: 0.67)
    assert np.median(region_scale(m["regions"], d["uv"][hot])) == pytest.approx(4.0, rel=0.35)
    assert 0.55 <= np.median(z[hot]) <= 0.8 and 0.55 <= np.median(z[~hot]) <= 0.8


def test_a_codecs_group_of_samples_that_errs_more_gets_its_own_factor():
    """Gray-rings' finest pattern washes out first: the edges it places err more than the
    others (Codec.error_groups). Planted: every odd ring's errors 2x; with the rings' parity as
    groups their variance factors come out ~4 apart and each group's sigmas hold; without,
    one factor for both leaves the odd rings over-confident."""
    from ringscan.pipeline.codecs.registry import codec_for
    from ringscan.pipeline.reconstruct.error_scale import group_scale
    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model, widen_depth_sigma

    rng = np.random.default_rng(5)
    d = _ring_samples(rng, k_rho=1.0)
    truth = 500 + 0.05 * d["uv"][:, 0] + 0.02 * d["uv"][:, 1] + 1e-4 * (d["uv"][:, 0] - 200) ** 2
    odd = d["ring"] % 2 == 1
    d["depth"] = truth + np.where(odd, 2.0, 1.0) * (d["depth"] - truth)
    args = (d["depth"], d["s"], d["sigma_px"], d["pixel"], d["ring"], d["uv"])
    m = fit_neighbour_model(*args, width=d["width"], group=odd.astype(np.int64))
    factor = dict(m["groups"])
    assert factor[1] / factor[0] == pytest.approx(4.0, rel=0.2)  # ~2000 checks a group: ~5 % on a variance
    sig = widen_depth_sigma(d["s"], d["sigma_px"], m) * np.sqrt(group_scale(m["groups"], odd.astype(np.int64)))
    z = np.abs(d["depth"] - truth) / sig
    assert 0.55 <= np.median(z[odd]) <= 0.8 and 0.55 <= np.median(z[~odd]) <= 0.8
    one = fit_neighbour_model(*args, width=d["width"])
    z1 = np.abs(d["depth"] - truth) / widen_depth_sigma(d["s"], d["sigma_px"], one)
    assert np.median(z1[odd]) > 0.85 and np.mean(z1[odd] > 3) > 0.01
    # gray-rings' groups: the bit that flips at boundary k (the lowest set bit of k)
    groups = codec_for("gray-rings").error_groups(None, np.array([0, 1, 2, 3, 4, 5, 6, 8, 12, 16]))
    assert groups.tolist() == [-1, 0, 1, 0, 2, 0, 1, 2, 2, 2]


def test_bounced_light_widens_a_ring_only_sigma_by_its_share_above_the_views():
    """Without an angle no neighbour sees an edge shift smooth along the ring (light bounced into
    a groove): each sample's measured share above the view's median widens its sigma by
    INDIRECT_PRIOR_PX per unit share, in quadrature; at or below the median, nothing."""
    from ringscan.pipeline.reconstruct.neighbour_checks import widen_for_indirect
    from ringscan.pipeline.reconstruct.view import INDIRECT_PRIOR_PX

    widened = np.array([0.01, 0.01, 0.01, 0.01], np.float32)  # mm
    s = np.array([0.005, 0.005, 0.005, 0.005])  # the decode's depth sigma (mm) ...
    sigma_px = np.array([0.05, 0.05, 0.05, 0.05])  # ... for 0.05 projector px: 0.1 mm a projector px
    indirect = np.array([0.10, 0.10, 0.10, 0.40])  # shares: the view's median 0.10, one sample 0.3 above
    out = widen_for_indirect(widened, s, sigma_px, indirect, INDIRECT_PRIOR_PX)
    np.testing.assert_array_equal(out[:3], widened[:3])
    expect = np.hypot(0.01, 0.3 * INDIRECT_PRIOR_PX * 0.1)  # 0.3 share x px per share x mm per px
    assert out[3] == pytest.approx(expect, rel=1e-6)  # float32 rounding only


def test_a_steep_light_widens_a_ring_only_sigma_by_its_gradient():
    """The camera's blur moves an edge where the light changes fast across the image: each sample's
    gradient (per camera px) widens its sigma by SHADING_PRIOR_PX per unit, in quadrature; a flat
    light adds nothing."""
    from ringscan.pipeline.reconstruct.neighbour_checks import widen_for_shading
    from ringscan.pipeline.reconstruct.view import SHADING_PRIOR_PX

    widened = np.array([0.01, 0.01, 0.02], np.float32)  # mm
    s = np.array([0.005, 0.005, 0.004])  # the decode's depth sigma (mm) ...
    sigma_px = np.array([0.05, 0.05, 0.02])  # ... for these projector px: 0.1 and 0.2 mm a projector px
    shading = np.array([0.0, 0.4, 1.5])
    out = widen_for_shading(widened, s, sigma_px, shading, SHADING_PRIOR_PX)
    assert out[0] == widened[0]
    expect = np.hypot(widened[1:].astype(np.float64), shading[1:] * SHADING_PRIOR_PX * np.array([0.1, 0.2]))
    np.testing.assert_allclose(out[1:], expect, rtol=1e-6)  # float32 rounding only


def _fragmented(d, region):
    """The samples of ``d`` (a :func:`_ring_samples` view) less most of those in ``region`` (a mask):
    there a ring keeps pieces 6 px long, 14 px apart (a far, faint surface's broken rings; an
    object's edge), which checks 4 and 8 px wide along the ring do not reach."""
    uv = d["uv"]
    arc = np.arctan2(uv[:, 1] - 150, uv[:, 0] - 200) * (12 + 4.3 * d["ring"])  # px along the ring
    keep = ~region | (np.mod(arc, 20.0) < 6.0)
    return {k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in d.items()}, keep


def test_samples_no_check_along_their_ring_reaches_get_the_factor_their_cross_ring_checks_fit(device):
    """The fit sees the samples its checks reach; fragments of rings err more (they are where a
    pattern barely modulates) and no check along a ring reaches them. Planted: 2x errors on a
    region's fragments. Their reach classes get variance factors ~4 from the cross-ring checks and
    their sigmas hold; the checked samples' stay as they were. The model's kernels on each device."""
    from ringscan.kernels.ring_checks import sample_reach
    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model, reach_scale, widen_depth_sigma

    rng = np.random.default_rng(21)
    d = _ring_samples(rng, k_rho=1.0)
    truth = 500 + 0.05 * d["uv"][:, 0] + 0.02 * d["uv"][:, 1] + 1e-4 * (d["uv"][:, 0] - 200) ** 2
    region = d["uv"][:, 0] < 170  # the left part of every ring
    d["depth"] = truth + np.where(region, 2.0, 1.0) * (d["depth"] - truth)
    d, keep = _fragmented(d, region)
    truth, region = truth[keep], region[keep]
    reach = sample_reach(wp.array(d["uv"].astype(np.float32), dtype=wp.vec2), wp.array(d["ring"].astype(np.int32)),
                         wp.array(d["pixel"].astype(np.int32)), np.isfinite(d["depth"]), width=d["width"])
    args = (d["depth"], d["s"], d["sigma_px"], d["pixel"], d["ring"], d["uv"])
    m = fit_neighbour_model(*args, width=d["width"], reach=reach, device=device)
    factor = {k: f for k, f, _ in m["reach"]}
    unreached = reach < m["lag_px"]
    assert np.mean(unreached[region]) > 0.9 and np.mean(region[reach <= 1]) > 0.9  # the fragments are the region's
    # ~1000 cross-ring checks each: a variance factor to ~10 %; the neighbours' own 2x errors add a little
    for k in (0, 1):
        assert factor[k] == pytest.approx(4.0, rel=0.35), m["reach"]
    sig = widen_depth_sigma(d["s"], d["sigma_px"], m) * np.sqrt(reach_scale(m["reach"], reach))
    z = np.abs(d["depth"] - truth) / sig
    assert 0.55 <= np.median(z[unreached]) <= 0.85 and np.mean(z[unreached] > 3) <= 0.03
    assert 0.55 <= np.median(z[~unreached]) <= 0.8
    # without the reach factors the fragments are over-confident
    z0 = np.abs(d["depth"] - truth) / widen_depth_sigma(d["s"], d["sigma_px"], m)
    assert np.median(z0[region]) > 1.1


def test_an_edge_between_two_surfaces_is_no_error_to_the_cross_ring_checks():
    """Samples by a step in depth (an object's silhouette over the plane behind it) are the
    ones no check along their ring reaches, and their neighbours of other rings lie on two
    surfaces. Errors planted alike everywhere: no factor beyond the checks' own noise (a
    quadratic across the step read factors of thousands; those neighbourhoods are not checked)."""
    from ringscan.kernels.ring_checks import sample_reach
    from ringscan.pipeline.reconstruct.neighbour_checks import fit_neighbour_model

    rng = np.random.default_rng(22)
    d = _ring_samples(rng, k_rho=1.0)
    step = np.where(d["uv"][:, 0] > 200, 20.0, 0.0)  # 20 mm: ~1000 sigmas
    d["depth"] = d["depth"] + step
    d, keep = _fragmented(d, np.abs(d["uv"][:, 0] - 200) < 12)
    reach = sample_reach(wp.array(d["uv"].astype(np.float32), dtype=wp.vec2), wp.array(d["ring"].astype(np.int32)),
                         wp.array(d["pixel"].astype(np.int32)), np.isfinite(d["depth"]), width=d["width"])
    m = fit_neighbour_model(d["depth"], d["s"], d["sigma_px"], d["pixel"], d["ring"], d["uv"], width=d["width"],
                            reach=reach)
    assert all(f <= 1.6 for _, f, _ in m["reach"]), m["reach"]
