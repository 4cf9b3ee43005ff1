"""Two- and three-ray triangulation (kernels.stereo_rays) against a hand-made rig
(tests/support/stereo_rig.py): two cameras and a projector around a known sphere; truth
projected through each lens gives the exact pixels."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.geometry import make_camera, make_perspective_light
from ringscan.kernels.stereo_rays import (RayTriangulation, place_matches, polar_information, triangulate_rays,
                                          widen_by_chi)
from ringscan.kernels.triangulation import STATUS_NAMES
from tests.support.stereo_rig import CAM1, CAM2, CENTER, PROJ, VOLUME, project_points, surface_hits, warp_array as _w


def _tri_inputs(rng, n=2000):
    uv1 = np.c_[rng.uniform(350, 930, n), rng.uniform(250, 770, n)]
    X = surface_hits(CAM1, uv1)
    ok = np.isfinite(X).all(1)
    uv1, X = uv1[ok], X[ok]
    return uv1, X, project_points(CAM2, X), project_points(PROJ, X)


def _models():
    return (make_camera(CAM1.K, CAM1.dist, CAM1.R, CAM1.t), make_camera(CAM2.K, CAM2.dist, CAM2.R, CAM2.t),
            make_perspective_light(PROJ.K, PROJ.dist, PROJ.R, PROJ.t))


def test_two_and_three_rays_place_exact_points(device):
    uv1, X, uv2, p = _tri_inputs(np.random.default_rng(4))
    c1, c2, light = _models()
    n = len(uv1)
    s = _w(np.full(n, 0.1), wp.float32, device)
    sr = _w(np.full(n, 0.05), wp.float32, device)
    pj = _w(p, wp.vec2, device)
    for kw in ({}, {"light": light, "proj": pj, "proj_info": polar_information(pj, sr, sr, center=CENTER)}):
        T = triangulate_rays(_w(uv1, wp.vec2, device), _w(uv2, wp.vec2, device), s, s, camera1=c1, camera2=c2,
                             volume=VOLUME, **kw)
        st = T.status.numpy()
        assert (st == 0).all(), np.bincount(st)
        err = np.linalg.norm(T.points.numpy() - X, axis=1)
        assert err.max() < 2e-3  # mm; float32 pixels limit it
        assert np.median(T.residual.numpy()) < 1e-3
        assert np.all(T.sigma.numpy() > 0)


def test_noise_three_rays_beat_two_and_sigma_and_chi2_are_honest(device):
    rng = np.random.default_rng(5)
    uv1, X, uv2, p = _tri_inputs(rng, 4000)
    c1, c2, light = _models()
    n = len(uv1)
    s1, s2, sp = 0.05, 0.2, 0.05
    uv1n = uv1 + rng.normal(0, s1, uv1.shape)
    uv2n = uv2 + rng.normal(0, s2, uv2.shape)
    pn = p + rng.normal(0, sp, p.shape)
    d1 = (X - CAM1.center) / np.linalg.norm(X - CAM1.center, axis=1, keepdims=True)
    pj = _w(pn, wp.vec2, device)
    spa = _w(np.full(n, sp), wp.float32, device)
    out = {}
    for name, kw, dof in (("two", {}, 1),
                          ("three", {"light": light, "proj": pj,
                                     "proj_info": polar_information(pj, spa, spa, center=CENTER)}, 3)):
        T = triangulate_rays(_w(uv1n, wp.vec2, device), _w(uv2n, wp.vec2, device),
                             _w(np.full(n, s1), wp.float32, device), _w(np.full(n, s2), wp.float32, device),
                             camera1=c1, camera2=c2, volume=VOLUME, **kw)
        st = T.status.numpy()
        assert (st == 0).mean() > 0.99, [STATUS_NAMES[k] for k in np.unique(st)]
        ok = st == 0
        e = T.points.numpy()[ok] - X[ok]
        along = np.sum(e * d1[ok], axis=1)
        sig = T.sigma.numpy()[ok]
        # the predicted sigma along camera 1's ray is the error's scale there
        assert 0.8 < np.std(along / sig) < 1.25
        # chi-square with its degrees of freedom: mean dof
        assert abs(np.mean(T.chi2.numpy()[ok]) / dof - 1) < 0.15
        out[name] = np.median(np.linalg.norm(e, axis=1))
    assert out["three"] < 0.8 * out["two"], out


def test_widen_by_chi_grows_a_point_by_its_own_disagreement(device):
    """The Birge ratio of each placed point's fit: sigma x sqrt(chi2 / dof) where above 1, else as it was (and
    unplaced points as they were). On noisy rays with 5 % of camera 2's pixels 8 sigmas off (a misread
    code), those points' share beyond 3 of their sigmas falls to under a third (two rays 71 -> 17 %, three
    22 -> 0 %), and a typical point keeps its sigma (chi^2 / dof under 1 for most of them)."""
    tri = RayTriangulation(points=wp.zeros(4, dtype=wp.vec3, device=device),
                           status=_w(np.array([0, 0, 0, STATUS_NAMES.index("inconsistent")]), wp.int32, device),
                           residual=_w(np.zeros(4), wp.float32, device),
                           chi2=_w(np.array([0.5, 4.0, 12.0, 50.0]), wp.float32, device),
                           sigma=_w(np.array([1.0, 1.0, 2.0, 1.0]), wp.float32, device))
    np.testing.assert_allclose(widen_by_chi(tri, dof=1).sigma.numpy(), [1.0, 2.0, 2.0 * np.sqrt(12.0), 1.0], rtol=1e-6)
    np.testing.assert_allclose(widen_by_chi(tri, dof=3).sigma.numpy(), [1.0, np.sqrt(4 / 3), 4.0, 1.0], rtol=1e-6)
    with pytest.raises(ValueError, match="dof"):
        widen_by_chi(tri, dof=0)

    rng = np.random.default_rng(21)
    uv1, X, uv2, p = _tri_inputs(rng, 4000)
    c1, c2, light = _models()
    n = len(uv1)
    s1, s2 = 0.05, 0.2
    uv2n = uv2 + rng.normal(0, s2, uv2.shape)
    bad = rng.random(n) < 0.05
    turn = rng.uniform(0, 2 * np.pi, n)
    uv2n[bad] += 8 * s2 * np.c_[np.cos(turn), np.sin(turn)][bad]
    pj = _w(p + rng.normal(0, 0.05, p.shape), wp.vec2, device)
    spa = _w(np.full(n, 0.05), wp.float32, device)
    d1 = (X - CAM1.center) / np.linalg.norm(X - CAM1.center, axis=1, keepdims=True)
    for kw, dof in (({}, 1), ({"light": light, "proj": pj, "proj_info": polar_information(pj, spa, spa, center=CENTER)},
                              3)):
        T = triangulate_rays(_w(uv1 + rng.normal(0, s1, uv1.shape), wp.vec2, device), _w(uv2n, wp.vec2, device),
                             _w(np.full(n, s1), wp.float32, device), _w(np.full(n, s2), wp.float32, device),
                             camera1=c1, camera2=c2, volume=VOLUME, max_residual_px=50.0, **kw)
        W = widen_by_chi(T, dof=dof)
        ok = T.status.numpy() == 0
        z = np.abs(np.sum((T.points.numpy() - X) * d1, axis=1))
        before, after = z / T.sigma.numpy(), z / W.sigma.numpy()
        # two rays: a pixel moved along its epipolar line moves the point with no residual (those stay beyond);
        # three: the projector's ray holds the point (fewer beyond to start with), and the chi sees every one
        assert np.mean(before[ok & bad] > 3) > 0.2 and np.mean(after[ok & bad] > 3) < 0.25, dof
        assert np.mean(after[ok & bad] > 3) < 0.3 * np.mean(before[ok & bad] > 3), dof
        grown = W.sigma.numpy()[ok & ~bad] / T.sigma.numpy()[ok & ~bad]
        assert np.median(grown) < 1.05 and np.all(grown >= 1.0), dof


def _surface_map(p, h=0.5):
    """(n, 2, 2) d uv2 / d p along the sphere: where camera 2 sees the surface point of projector pixel p, moved
    +-h px in u and in v (the map the matcher fits through camera 2's neighbours)."""
    cols = []
    for e in (np.array([h, 0.0]), np.array([0.0, h])):
        cols.append((project_points(CAM2, surface_hits(PROJ, p + e)) - project_points(CAM2, surface_hits(PROJ, p - e)))
                    / (2 * h))
    return np.stack(cols, axis=2)


def _mapped_inputs(rng, n):
    """_tri_inputs' camera-1 pixels, points and projector pixels with the surface's map at each (where the
    projector's moved pixels still meet the sphere)."""
    uv1, X, _, p = _tri_inputs(rng, n)
    A = _surface_map(p)
    ok = np.isfinite(A).all(axis=(1, 2))
    return uv1[ok], X[ok], p[ok], A[ok]


def test_three_rays_through_the_matchers_map_count_the_projector_points_error_once(device):
    """A match as the matcher makes it: camera 1's pixel exact, its projector point p off by e1, and uv2 where
    camera 2 reads p, so off by A (e1 - e2) (A the surface's map from projector to camera-2 px, e2 camera 2's
    code error). Given the map, the three rays take camera 2's residual less A times the projector's: the
    sigma means what it says (std of error / sigma ~1) and the points beat the rays taken as independent
    (camera 1 given the stand-in sigma |A| sigma_p, as two rays take it), which count e1 twice: on this rig
    the two copies pull the point the same way, and the sigma is too narrow (too wide on others: wrong either
    way), the points twice as far off."""
    rng = np.random.default_rng(8)
    uv1, X, p, A = _mapped_inputs(rng, 4000)
    c1, c2, light = _models()
    n = len(uv1)
    sp, s2 = 0.08, 0.05  # projector px: camera 1's code error; camera 2's (through the map)
    e1 = rng.normal(0, sp, p.shape)
    e2 = rng.normal(0, s2, p.shape)
    pn = p + e1
    uv2 = project_points(CAM2, X) + np.einsum("nij,nj->ni", A, e1 - e2)
    gain = np.sqrt(0.5 * (A ** 2).sum(axis=(1, 2)))
    d1 = (X - CAM1.center) / np.linalg.norm(X - CAM1.center, axis=1, keepdims=True)
    pj = _w(pn, wp.vec2, device)
    spa = _w(np.full(n, sp), wp.float32, device)
    common = dict(camera2=c2, volume=VOLUME, light=light, proj=pj,
                  proj_info=polar_information(pj, spa, spa, center=CENTER), camera1=c1)
    out = {}
    for name, sigma1, kw in (
            ("map", np.full(n, 0.01), {"proj_map": _w(A.reshape(n, 4), wp.vec4, device)}),
            ("independent", gain * sp, {})):
        T = triangulate_rays(_w(uv1, wp.vec2, device), _w(uv2, wp.vec2, device), _w(sigma1, wp.float32, device),
                             _w(gain * s2, wp.float32, device), **common, **kw)
        st = T.status.numpy()
        assert (st == 0).mean() > 0.99, [STATUS_NAMES[k] for k in np.unique(st)]
        good = st == 0
        e = T.points.numpy()[good] - X[good]
        z = np.sum(e * d1[good], axis=1) / T.sigma.numpy()[good]
        out[name] = (np.median(np.linalg.norm(e, axis=1)), np.std(z))
    # (4000 draws: the std of a unit Gaussian's sample std is ~1.1 %; the camera-2 sigma |A| s2 is isotropic
    # where A e2 is not: the bounds allow a quarter for it)
    assert 0.75 < out["map"][1] < 1.25, out
    assert not 0.75 < out["independent"][1] < 1.25, out  # e1 counted twice
    assert out["map"][0] < 0.7 * out["independent"][0], out


def test_bad_inputs_raise(device):
    a = wp.zeros(3, dtype=wp.vec2, device=device)
    f = wp.zeros(3, dtype=wp.float32, device=device)
    c1, c2, light = _models()
    with pytest.raises(ValueError, match="go together"):
        triangulate_rays(a, a, f, f, camera1=c1, camera2=c2, volume=VOLUME, light=light)
    with pytest.raises(ValueError, match="needs proj_info"):
        triangulate_rays(a, a, f, f, camera1=c1, camera2=c2, volume=VOLUME, proj_map=wp.zeros(3, dtype=wp.vec4,
                                                                                             device=device))
    with pytest.raises(ValueError, match="needs proj_map"):
        triangulate_rays(a, a, f, f, camera1=c1, camera2=c2, volume=VOLUME, proj_info=wp.zeros(3, dtype=wp.vec3,
                                                                                              device=device))


def test_a_scene_in_metres_is_triangulated_as_in_millimetres(device):
    """The rig and points of test_two_and_three_rays_place_exact_points in metres (a calibration in metres
    imported as mm): the Jacobians' step is at most 0.2 % of the point's distance, so it stays a step the
    scene allows (before: 0.5 'mm', here more than the 0.4 m to the camera, and points off or dropped)."""
    uv1, X, uv2, _ = _tri_inputs(np.random.default_rng(4))
    c1 = make_camera(CAM1.K, CAM1.dist, CAM1.R, CAM1.t / 1000.0)
    c2 = make_camera(CAM2.K, CAM2.dist, CAM2.R, CAM2.t / 1000.0)
    n = len(uv1)
    s = _w(np.full(n, 0.1), wp.float32, device)
    T = triangulate_rays(_w(uv1, wp.vec2, device), _w(uv2, wp.vec2, device), s, s, camera1=c1, camera2=c2,
                         volume=tuple(v / 1000.0 for v in VOLUME))
    st = T.status.numpy()
    assert (st == 0).all(), np.bincount(st)
    err = np.linalg.norm(T.points.numpy() - X / 1000.0, axis=1)
    assert err.max() < 2e-6  # m: the 2e-3 mm of millimetres, float32 pixels limit it alike


def test_place_matches_writes_each_match_at_its_sample_and_leaves_the_others():
    """place_matches scatters the matches' points at their samples: a matched sample gets the match's point,
    status, sigma and residual, and its own confidence only where the point is ok; an unmatched sample keeps
    what the arrays held (the camera-projector fallback, or the defaults)."""
    rng = np.random.default_rng(2)
    n, m = 50, 20
    index = rng.choice(n, m, replace=False).astype(np.int32)
    pts = rng.normal(size=(m, 3)).astype(np.float32)
    st = np.where(rng.random(m) < 0.7, 0, 3).astype(np.int32)
    sig, res = rng.random(m).astype(np.float32), rng.random(m).astype(np.float32)
    conf = rng.random(n).astype(np.float32)
    f32 = lambda a: wp.array(a, dtype=wp.float32, device="cpu")  # noqa: E731
    tri = RayTriangulation(points=wp.array(pts, dtype=wp.vec3, device="cpu"), status=wp.array(st, dtype=wp.int32,
                           device="cpu"), residual=f32(res), chi2=f32(np.zeros(m)), sigma=f32(sig))
    out = dict(points=wp.array(np.full((n, 3), 7.0, np.float32), dtype=wp.vec3, device="cpu"),
               status=wp.array(np.full(n, 11, np.int32), dtype=wp.int32, device="cpu"), sigma=f32(np.full(n, 5.0)),
               residual=f32(np.full(n, -1.0)), placed_confidence=f32(np.full(n, 9.0)))
    place_matches(wp.array(index, dtype=wp.int32, device="cpu"), tri, f32(conf), threads=2, **out)
    got = {k: a.numpy() for k, a in out.items()}
    other = np.setdiff1d(np.arange(n), index)
    assert np.array_equal(got["points"][index], pts) and np.all(got["points"][other] == 7.0)
    assert np.array_equal(got["status"][index], st) and np.all(got["status"][other] == 11)
    assert np.array_equal(got["sigma"][index], sig) and np.array_equal(got["residual"][index], res)
    assert np.array_equal(got["placed_confidence"][index], np.where(st == 0, conf[index], 0.0).astype(np.float32))
    assert np.all(got["placed_confidence"][other] == 9.0) and np.all(got["residual"][other] == -1.0)


def test_polar_information_on_the_device_is_the_numpy_statement():
    """The information matrices by a kernel (float64 inside, float32 out) against NumPy's float64 arithmetic."""
    from ringscan.kernels.stereo_rays import polar_information

    rng = np.random.default_rng(8)
    n = 20000
    p = rng.uniform(0, 1024, (n, 2)).astype(np.float32)
    p[0] = (511.5, 383.5)  # at the centre itself: the radial direction is u
    sr = rng.uniform(0.0, 0.5, n).astype(np.float32)  # below 1e-3 included: floored
    st = rng.uniform(0.0005, 0.8, n).astype(np.float32)
    got = polar_information(wp.array(p, dtype=wp.vec2), wp.array(sr), wp.array(st), center=(511.5, 383.5),
                            threads=2).numpy()
    off = p.astype(np.float64) - (511.5, 383.5)
    r = np.hypot(off[:, 0], off[:, 1])
    c = np.where(r > 0, off[:, 0] / np.where(r > 0, r, 1), 1.0)
    s = np.where(r > 0, off[:, 1] / np.where(r > 0, r, 1), 0.0)
    ir = 1.0 / np.maximum(sr.astype(np.float64), 1e-3) ** 2
    it = 1.0 / np.maximum(st.astype(np.float64), 1e-3) ** 2
    W = np.stack([ir * c * c + it * s * s, (ir - it) * c * s, ir * s * s + it * c * c], axis=1).astype(np.float32)
    # (sqrt(x^2 + y^2) for NumPy's hypot: a float64 last bit apart at most, which float32 hides: equal here)
    np.testing.assert_array_equal(got, W)
    assert got[0].tolist() == pytest.approx([1 / max(sr[0], 1e-3) ** 2, 0.0, 1 / st[0] ** 2], rel=1e-6)


def test_polar_information_adds_an_isotropic_error_over_the_gain():
    """``extra`` (camera px) over ``gain`` (camera px per projector px) adds to both directions in quadrature:
    the covariance's inverse is the information, and with extra 0 nothing changes."""
    rng = np.random.default_rng(9)
    n = 2000
    p = rng.uniform(0, 1024, (n, 2)).astype(np.float32)
    sr = rng.uniform(0.01, 0.5, n).astype(np.float32)
    st = rng.uniform(0.01, 0.8, n).astype(np.float32)
    extra = rng.uniform(0.0, 0.3, n).astype(np.float32)
    extra[:100] = 0.0
    gain = rng.uniform(0.2, 3.0, n).astype(np.float32)
    args = (wp.array(p, dtype=wp.vec2), wp.array(sr), wp.array(st))
    got = polar_information(*args, center=CENTER, extra=wp.array(extra), gain=wp.array(gain), threads=2).numpy()
    plain = polar_information(*args, center=CENTER, threads=2).numpy()
    e = extra.astype(np.float64) / gain
    wider = polar_information(wp.array(p, dtype=wp.vec2), wp.array(np.sqrt(sr.astype(np.float64) ** 2 + e ** 2)
                                                                   .astype(np.float32)),
                              wp.array(np.sqrt(st.astype(np.float64) ** 2 + e ** 2).astype(np.float32)),
                              center=CENTER, threads=2).numpy()
    # (float32 rounding of the widened sigmas, which the off-diagonal's difference of two terms magnifies: to
    # the diagonal's scale)
    assert np.all(np.abs(got - wider) <= 1e-5 * (got[:, :1] + got[:, 2:]))
    np.testing.assert_array_equal(got[:100], plain[:100])
    W = np.stack([np.array([[g[0], g[1]], [g[1], g[2]]]) for g in got.astype(np.float64)])
    cov = np.linalg.inv(W)
    want = sr.astype(np.float64) ** 2 + st ** 2 + 2 * e ** 2
    assert np.allclose(np.trace(cov, axis1=1, axis2=2), want, rtol=1e-3)  # (the float32 information inverted)
    with pytest.raises(ValueError, match="go together"):
        polar_information(*args, center=CENTER, extra=wp.array(extra))


def test_through_map_takes_each_kind_of_map_as_it_is():
    """A full map: camera 1's pixel is its ray, the query's scatter share goes to the projector. A map along a
    line (a ring edge): the ring's radius exact, the edge's error at camera 1 (sigma_rho through the gain, and
    the share). No map (0), or a line of a dense code: sigma1 as it is, nothing added."""
    from ringscan.kernels.stereo_rays import EXACT_RADIUS_PX, PIXEL_RAY_PX, through_map

    f = np.float32
    sigma1 = wp.array(np.array([0.3, 0.4, 0.5], f))
    model = wp.array(np.array([0.05, 0.07, 0.09], f))
    maps = wp.array(np.array([[1.2, 0.1, -0.2, 0.9], [0.6, 0.3, 1.2, 0.6], [0, 0, 0, 0]], f), dtype=wp.vec4)
    sigma_rho = wp.array(np.array([0.02, 0.03, 0.04], f))
    gain = wp.array(np.array([1.1, 2.0, 1.5], f))
    s1, extra, sr = (a.numpy().tolist() for a in through_map(sigma1, model, maps, sigma_rho, gain, ring_edges=True,
                                                             threads=1))
    assert s1 == pytest.approx([PIXEL_RAY_PX, np.hypot(2.0 * 0.03, 0.07), 0.5], rel=1e-6)
    assert extra == pytest.approx([0.05, 0.0, 0.0])
    assert sr == pytest.approx([0.02, EXACT_RADIUS_PX, 0.04], rel=1e-6)
    # a dense code's samples along a line (its radius errs too): independent
    s1, extra, sr = (a.numpy().tolist() for a in through_map(sigma1, model, maps, sigma_rho, gain, ring_edges=False,
                                                             threads=1))
    assert s1[1:] == pytest.approx([0.4, 0.5]) and extra[1:] == [0.0, 0.0] and sr[1:] == pytest.approx([0.03, 0.04])


def test_projector_misses_measure_the_projectors_miss_from_the_cameras_points(device):
    """Two cameras place each point (noise 0.05 px); the projector's pixel against it, along camera 1's ray
    through the projector: a chi-square with one degree of freedom where the projector is right (median 0.455),
    and the miss itself where its pixels are all 0.6 px off along it."""
    from ringscan.kernels.stereo_rays import projector_misses

    rng = np.random.default_rng(12)
    uv1, X, uv2, p = _tri_inputs(rng, 4000)
    c1, c2, light = _models()
    n = len(uv1)
    s, sp = 0.05, 0.05
    two = triangulate_rays(_w(uv1 + rng.normal(0, s, uv1.shape), wp.vec2, device),
                           _w(uv2 + rng.normal(0, s, uv2.shape), wp.vec2, device),
                           _w(np.full(n, s), wp.float32, device),
                           _w(np.full(n, s), wp.float32, device), camera1=c1, camera2=c2, volume=VOLUME)
    spa = _w(np.full(n, sp), wp.float32, device)
    pn = p + rng.normal(0, sp, p.shape)
    # (camera 1's rays run through this projector along its v axis: the miss along v)
    for off, check in ((np.zeros(2), "honest"), (np.array([0.0, 0.6]), "miss")):
        pj = _w(pn + off, wp.vec2, device)
        r, v = projector_misses(two, pj, polar_information(pj, spa, spa, center=CENTER), camera1=c1, light=light)
        r, v = r.numpy(), v.numpy()
        ok = v > 0
        assert ok.mean() > 0.99
        if check == "honest":
            # (4000 draws: the median's standard error is ~3 %; the cameras' point's error across camera 1's
            # ray is not in the variance, which leaves it ~1.4 times above here, where the cameras' noise is the
            # projector's: the view applies a floor above twice it, PROJECTOR_FLOOR_CHI2)
            assert 0.9 < np.median(r[ok] ** 2 / v[ok]) / 0.455 < 1.7
        else:
            assert 0.4 < np.median(r[ok]) < 0.65  # the 0.6 px, through each ray's direction


def test_a_projector_floor_conditions_the_map_on_the_projectors_miss(device):
    """The matcher's three rays (as in the map test above) with the projector's pixels all 0.5 px off: taken
    as the code's error alone the map carries the miss into camera 2's residual and the points follow it;
    given the miss as a floor they keep to the cameras, within the noise."""
    rng = np.random.default_rng(13)
    uv1, X, p, A = _mapped_inputs(rng, 3000)
    c1, c2, light = _models()
    n = len(uv1)
    sp, s2 = 0.05, 0.05
    e1, e2 = rng.normal(0, sp, p.shape), rng.normal(0, s2, p.shape)
    uv2 = project_points(CAM2, X) + np.einsum("nij,nj->ni", A, e1 - e2)
    pj = _w(p + e1 + np.array([0.5, 0.0]), wp.vec2, device)  # the projector's calibration 0.5 px off
    gain = np.sqrt(0.5 * (A ** 2).sum(axis=(1, 2)))
    spa = _w(np.full(n, sp), wp.float32, device)
    d1 = (X - CAM1.center) / np.linalg.norm(X - CAM1.center, axis=1, keepdims=True)
    out = {}
    for floor in (0.0, 0.5):
        T = triangulate_rays(_w(uv1, wp.vec2, device), _w(uv2, wp.vec2, device), _w(np.full(n, 0.01), wp.float32,
                                                                                    device),
                             _w(gain * s2, wp.float32, device), camera1=c1, camera2=c2, volume=VOLUME, light=light,
                             proj=pj, proj_info=polar_information(pj, spa, spa, center=CENTER),
                             proj_map=_w(A.reshape(n, 4), wp.vec4, device), projector_floor_px=floor)
        good = T.status.numpy() == 0
        e = np.sum((T.points.numpy()[good] - X[good]) * d1[good], axis=1)
        out[floor] = (np.median(np.abs(e)), np.mean(np.abs(e / T.sigma.numpy()[good]) > 3))
    assert out[0.5][0] < 0.5 * out[0.0][0], out
    assert out[0.5][1] < 0.05 < out[0.0][1], out
    with pytest.raises(ValueError, match="needs the light"):
        triangulate_rays(pj, pj, spa, spa, camera1=c1, camera2=c2, volume=VOLUME, projector_floor_px=0.5)


def test_widen_along_rays_adds_the_projector_miss_as_depth():
    """A miss of f projector px along camera 1's ray's course through the projector is f over the px a mm
    there, along the ray (OpenCV's projection of the points moved +-0.5 mm); points without status ok keep
    their sigma."""
    from ringscan.kernels.stereo_rays import widen_along_rays

    uv1, X, _, _ = _tri_inputs(np.random.default_rng(14), 500)
    c1, _, light = _models()
    n = len(X)
    status = np.zeros(n, np.int32)
    status[:10] = 3
    sig = np.full(n, 0.01, np.float32)
    tri = RayTriangulation(points=wp.array(X.astype(np.float32), dtype=wp.vec3), status=wp.array(status),
                           residual=wp.zeros(n, dtype=wp.float32), chi2=wp.zeros(n, dtype=wp.float32),
                           sigma=wp.array(sig))
    got = widen_along_rays(tri, 0.3, camera1=c1, light=light, threads=2).numpy()
    d = (X - CAM1.center) / np.linalg.norm(X - CAM1.center, axis=1, keepdims=True)
    gl = np.linalg.norm(project_points(PROJ, X + 0.5 * d) - project_points(PROJ, X - 0.5 * d), axis=1) / 1.0
    want = np.sqrt(0.01 ** 2 + (0.3 / gl) ** 2)
    np.testing.assert_allclose(got[10:], want[10:], rtol=1e-3)  # (float32 points, central differences)
    assert np.all(got[:10] == sig[:10])


def test_two_rays_through_the_map_take_an_anisotropic_code_error_along_the_epipolar_lines(device):
    """Two rays of a match as the matcher makes it, the query's code error anisotropic (0.02 projector px
    along u, 0.2 along v: as a ring edge's radius against its angle): camera 1's pixel its ray, uv2 off by
    A (e1 - e2). Through the map camera 2's covariance takes A S A^T and the sigma means what it says; the
    isotropic stand-in on camera 1 (|A| times the mean of the two) cannot tell which part runs along the
    epipolar lines, and misses it."""
    rng = np.random.default_rng(15)
    uv1, X, p, A = _mapped_inputs(rng, 4000)
    c1, c2, _ = _models()
    n = len(uv1)
    su, sv, s2 = 0.02, 0.2, 0.01
    e1 = np.c_[rng.normal(0, su, n), rng.normal(0, sv, n)]
    uv2 = project_points(CAM2, X) + np.einsum("nij,nj->ni", A, e1 - rng.normal(0, s2, p.shape))
    gain = np.sqrt(0.5 * (A ** 2).sum(axis=(1, 2)))
    # the query's information in u, v: a polar frame whose "radius" is u (the point at the centre's right)
    info = np.tile([1 / su ** 2, 0.0, 1 / sv ** 2], (n, 1))
    d1 = (X - CAM1.center) / np.linalg.norm(X - CAM1.center, axis=1, keepdims=True)
    out = {}
    for name, sigma1, kw in (
            ("map", np.full(n, 0.01), {"proj_map": _w(A.reshape(n, 4), wp.vec4, device),
                                       "proj_info": _w(info, wp.vec3, device)}),
            ("stand-in", gain * np.sqrt(0.5 * (su ** 2 + sv ** 2)), {})):
        T = triangulate_rays(_w(uv1, wp.vec2, device), _w(uv2, wp.vec2, device), _w(sigma1, wp.float32, device),
                             _w(gain * s2, wp.float32, device), camera1=c1, camera2=c2, volume=VOLUME, **kw)
        good = T.status.numpy() == 0
        assert good.mean() > 0.99
        z = np.sum((T.points.numpy()[good] - X[good]) * d1[good], axis=1) / T.sigma.numpy()[good]
        out[name] = np.std(z)
    assert 0.8 < out["map"] < 1.25 and not 0.8 < out["stand-in"] < 1.25, out
