"""The Mitsuba 3 renderer (an independent virtual rig) against analytic geometry, and end to end.

The analytic predictions here are plain NumPy from the rig's numbers (K, R, t, the
radial distortion written out), never ringscan's ray or projection code."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import Camera, ParallelLight, PerspectiveLight, default_rig, look_at
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.mitsuba_render import MitsubaRig, MitsubaSettings, choose_variant
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.truth import load_truth
from ringscan.pipeline.simulate.virtual_rig import RenderSettings

from tests.support.benchmark_scripts import load_benchmark

W, H, PW, PH = 160, 128, 256, 192     # camera and projector of the small rigs (the default rig's field of view)
F_CAM = 325.0                          # the default rig's 2600 px focal length at 1/8 the size
F_PROJ = 575.0 / 0.6                   # a perspective projector 600 mm up, 0.6 mm pixels at z = 25 mm
CAM_DIST = np.array([0.02, -0.05, 0.0, 0.0, 0.0])   # the default rig's lens: k1, k2


def small_rig(*, light="perspective", cam_dist=CAM_DIST, proj_k1=0.0, proj_offset=(0.0, 0.0), gamma=2.2):
    """The default rig's pose with a 160x128 camera and a 256x192 projector, perspective (600 mm above
    the plane, looking down) or parallel (0.6 mm pixels)."""
    rig = default_rig(light_model="perspective")
    c = rig.camera
    K = np.array([[F_CAM, 0, 79.5], [0, F_CAM, 63.5], [0, 0, 1.0]])
    cam = Camera(width=W, height=H, K=K, dist=np.asarray(cam_dist, float), R=c.R, t=c.t, gamma=gamma)
    if light == "parallel":
        li = ParallelLight(R=np.eye(3), t=np.zeros(3), pixel_pitch_mm=0.6, axis_px=np.array([127.5, 95.5]),
                           width=PW, height=PH)
    else:
        Kp = np.array([[F_PROJ, 0, 127.5 + proj_offset[0]], [0, F_PROJ, 95.5 + proj_offset[1]], [0, 0, 1.0]])
        Rp, tp = look_at([0.0, 0.0, 600.0], [0.0, 0.0, 0.0])
        li = PerspectiveLight(width=PW, height=PH, K=Kp, dist=np.array([proj_k1, 0, 0, 0, 0.0]), R=Rp, t=tp)
    return dataclasses.replace(rig, camera=cam, light=li)


def _undistort(xd, yd, k1, k2, iterations=8):
    """Ideal normalized coordinates of distorted ones under radial k1, k2 (fixed point: in this field of
    view, |r| < 0.3, each step shrinks the error ~100-fold, so 8 steps reach float64's rounding)."""
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        f = 1.0 + k1 * r2 + k2 * r2 * r2
        x, y = xd / f, yd / f
    return x, y


def _plane_points(rig, u, v):
    """World points on z = 0 seen at camera pixel positions (u, v) (pinhole plus radial k1, k2)."""
    c = rig.camera
    xd = (u - c.K[0, 2]) / c.K[0, 0]
    yd = (v - c.K[1, 2]) / c.K[1, 1]
    x, y = _undistort(xd, yd, c.dist[0], c.dist[1])
    d = np.stack([x, y, np.ones_like(x)], -1) @ c.R            # world directions (rows: R^T d)
    C = -c.R.T @ c.t
    s = -C[2] / d[..., 2]
    return C + s[..., None] * d


def _projector_uv(rig, X):
    """Projector pixel (u_p, v_p) of world points (pinhole plus radial k1), or the parallel light's."""
    li = rig.light
    XL = X @ li.R.T + li.t
    if isinstance(li, ParallelLight):
        return XL[..., 0] / li.pixel_pitch_mm + li.axis_px[0], XL[..., 1] / li.pixel_pitch_mm + li.axis_px[1]
    x, y = XL[..., 0] / XL[..., 2], XL[..., 1] / XL[..., 2]
    f = 1.0 + li.dist[0] * (x * x + y * y)
    return li.K[0, 0] * x * f + li.K[0, 2], li.K[1, 1] * y * f + li.K[1, 2]


LINEAR = RenderSettings(supersample=2, ambient=0.0, albedo=0.8, defocus_px=0.0, noise=0.0)


@pytest.mark.parametrize("case", ["perspective", "parallel"])
def test_a_lit_projector_column_lands_where_the_pinhole_model_puts_it(case):
    """One lit projector column on the plane z = 0: each camera row's stripe has the analytic
    brightness (albedo x the pixel's area that sees the column) and centroid.

    Perspective: an off-centre principal point (+13.3, -7.6 px), a projector lens (k1 = 0.5: the column,
    near the image's side, bends by 0.9 px between its middle and its ends) and the
    default camera lens (k1 0.02, k2 -0.05), all through Mitsuba's texture mapping and OpenCV's
    resampling; parallel: the light as a projector 100 km away. The projector looks straight down at
    the plane, so the light falls on it at the angle it leaves the projector, at the depth its
    brightness is scaled for: full white is the albedo, exactly."""
    if case == "perspective":
        rig = small_rig(proj_k1=0.5, proj_offset=(13.3, -7.6))
    else:
        rig = small_rig(light="parallel", cam_dist=np.zeros(5))
    mr = MitsubaRig(rig, "plane", settings=LINEAR, mitsuba=MitsubaSettings(spp=32, max_depth=2))
    col = 230
    frame = np.zeros((PH, PW), np.uint8)
    frame[:, col] = 255
    got = mr.render_linear(frame, seed=7)
    # analytic: 16 x 16 points a pixel, the share whose plane point lies in the column's square (only
    # pixels whose centre maps within 8 projector columns: a camera pixel spans ~2.2 of them)
    V0, U0 = np.meshgrid(np.arange(H, dtype=float), np.arange(W, dtype=float), indexing="ij")
    up0, _ = _projector_uv(rig, _plane_points(rig, U0, V0))
    near = np.abs(up0 - col) < 8
    n = 16
    off = (np.arange(n) + 0.5) / n - 0.5
    du, dv = np.meshgrid(off, off)
    U = U0[near][:, None] + du.ravel()[None, :]
    V = V0[near][:, None] + dv.ravel()[None, :]
    up, vp = _projector_uv(rig, _plane_points(rig, U, V))
    inside = (up >= col - 0.5) & (up < col + 0.5) & (vp >= -0.5) & (vp < PH - 0.5)
    want = np.zeros((H, W))
    want[near] = 0.8 * inside.mean(1)
    assert not np.any(want[near & ~(np.abs(up0 - col) < 7)])   # the band holds the whole stripe
    rows = np.nonzero(want.sum(1) > 0.3)[0][2:-2]   # not the rows where the column's ends cross
    assert len(rows) > 60, len(rows)
    # nothing lit more than a pixel and a half away from the analytic stripe (the plane only: no
    # bounce; Mitsuba's samples are exact there, not noisy)
    cols = np.arange(W)
    for r in rows:
        lo, hi = np.nonzero(want[r] > 0)[0][[0, -1]]
        far = (cols < lo - 1) | (cols > hi + 1)
        assert np.all(got[r, far] == 0.0), r
    c_got = (got[rows] * cols).sum(1) / got[rows].sum(1)
    c_want = (want[rows] * cols).sum(1) / want[rows].sum(1)
    # 128 random samples a pixel (4 texels x 32 spp): a stripe half a pixel wide has each edge pixel's
    # share known to ~0.045 (binomial), so a row's centroid to ~0.05 px (5 sigma: 0.25) and the mean of
    # ~70-100 rows to ~0.006 px (3 sigma: 0.02); a wrong principal point, distortion, parallel-light
    # distance or texel alignment moves the mean by 0.1 px or more
    assert np.abs(c_got - c_want).max() < 0.25
    assert abs(np.mean(c_got - c_want)) < 0.02, np.mean(c_got - c_want)
    # a row's light: the stripe's area. Each edge pixel's share is a binomial estimate from its samples
    # (~0.04 of 0.2-0.5), so a row's sum is known to ~10 % and the mean of the rows to ~1.5 %; a stripe
    # of the wrong width (a texel off: +-25 %) or brightness fails
    s_got, s_want = got[rows].sum(1), want[rows].sum(1)
    assert np.abs(s_got / s_want - 1).max() < 0.4 and abs(np.mean(s_got / s_want) - 1) < 0.05
    # full white: the albedo wherever the whole pixel sees the lit image (direct light only)
    white = mr.render_linear(np.full((PH, PW), 255, np.uint8), seed=8)
    up_c, vp_c = _projector_uv(rig, _plane_points(rig, U0, V0))
    well_inside = (up_c > 3) & (up_c < PW - 4) & (vp_c > 3) & (vp_c < PH - 4)
    assert well_inside.sum() > 5000
    assert np.allclose(white[well_inside], 0.8, atol=2e-4)   # float32 radiance, rounding only


def test_sphere_silhouette_and_depth_in_the_truth():
    """The truth depth of a 40 mm sphere standing on the plane: its pixels are those whose centre ray
    passes within the radius of the centre (analytic, through the camera's lens), and their depth is
    the ray's first meeting with the sphere."""
    rig = small_rig()
    mr = MitsubaRig(rig, "sphere", settings=LINEAR, mitsuba=MitsubaSettings(spp=1, ambient_spp=1),
                    projector_size=(PW, PH))
    # size 80 mm by default: radius 40 mm, centre (0, 0, 40)
    truth = mr.truth()
    depth, lit = truth["depth"], truth["lit"]
    c = rig.camera
    U, V = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    xd, yd = (U - c.K[0, 2]) / c.K[0, 0], (V - c.K[1, 2]) / c.K[1, 1]
    x, y = _undistort(xd, yd, c.dist[0], c.dist[1])
    dc = np.stack([x, y, np.ones_like(x)], -1)
    dw = dc / np.linalg.norm(dc, axis=-1, keepdims=True) @ c.R
    C = -c.R.T @ c.t
    centre, r = np.array([0.0, 0.0, 40.0]), 40.0
    oc = C - centre
    b = (dw * oc).sum(-1)
    miss = np.linalg.norm(np.cross(oc, dw), axis=-1)             # the ray's distance from the centre
    t_sphere = -b - np.sqrt(np.maximum(b * b - (oc @ oc - r * r), 0.0))
    z_sphere = t_sphere * (dw @ c.R.T)[..., 2]
    z_plane = _plane_points(rig, U, V) @ c.R.T + c.t
    on_sphere = np.isfinite(depth) & (depth < z_plane[..., 2] - 0.05)
    # the icosphere's facets lie within 2.9 µm inside the true sphere: a pixel may differ only where its
    # ray grazes the silhouette that closely (a few float32 ulps at 400 mm added)
    differ = on_sphere != (miss < r)
    assert on_sphere.sum() > 1500
    assert np.all(np.abs(miss[differ] - r) < 0.01), np.abs(miss[differ] - r).max()
    # the silhouette's radius in pixels, along the image row through the sphere's centre (~28 px)
    inner = on_sphere & (miss < r - 0.5)
    # depth: the ray meets the polyhedron at most sagitta / cos(incidence) beyond the true sphere;
    # away from the rim (cos > 0.1) that is < 0.03 mm
    assert np.abs(depth[inner] - z_sphere[inner]).max() < 0.03
    # the plane's pixels: the plane's own depth (float32 at ~450 mm)
    plane = np.isfinite(depth) & (miss > r + 0.5)
    assert np.abs(depth[plane] - z_plane[..., 2][plane]).max() < 2e-3
    # lit: the projector, 560 mm above the sphere's centre on its axis, lights the cap where the normal's
    # z exceeds r / 560: above z = 40 + 40 * 40 / 560 = 42.86 mm (1 mm either side: pixels a facet off)
    pts = truth["points"]
    z_terminator = 40.0 + 40.0 * 40.0 / 560.0
    lower = on_sphere & (pts[..., 2] < z_terminator - 1.0)
    upper = on_sphere & (pts[..., 2] > z_terminator + 1.0)
    assert lower.sum() > 50 and upper.sum() > 1000
    assert not lit[lower].any() and lit[upper].all()


def _camera_pixel(rig, X):
    """Camera pixel (u, v) of a world point (pinhole plus radial k1, k2)."""
    c = rig.camera
    x = c.R @ X + c.t
    xn, yn = x[0] / x[2], x[1] / x[2]
    r2 = xn * xn + yn * yn
    f = 1.0 + c.dist[0] * r2 + c.dist[1] * r2 * r2
    return c.K[0, 0] * xn * f + c.K[0, 2], c.K[1, 1] * yn * f + c.K[1, 2]


def test_glossy_sphere_shows_the_projector_where_the_mirror_law_puts_it():
    """A glossy 40 mm sphere (``coat_roughness`` 0.1) under full white: the highlight (glossy less matte
    radiance) is centred where the sphere's normal bisects the directions to the projector and to the
    camera (found here by bisection in the plane x = 0 that holds both, then projected through the lens),
    and off it the coat only takes light from the diffuse base."""
    rig = small_rig()
    white = np.full((PH, PW), 255, np.uint8)
    img = {}
    for name, coat in (("matte", None), ("glossy", 0.1)):
        mr = MitsubaRig(rig, "sphere", settings=dataclasses.replace(LINEAR, seed=1), projector_size=(PW, PH),
                        mitsuba=MitsubaSettings(spp=4, max_depth=2, coat_roughness=coat))
        img[name] = mr.render_linear(white, seed=1)
    d = img["glossy"] - img["matte"]
    c = rig.camera
    C, P = -c.R.T @ c.t, np.array([0.0, 0.0, 600.0])
    centre, r = np.array([0.0, 0.0, 40.0]), 40.0

    def off_bisector(th):
        n = np.array([0.0, -math.sin(th), math.cos(th)])
        X = centre + r * n
        h = (P - X) / np.linalg.norm(P - X) + (C - X) / np.linalg.norm(C - X)
        return n[1] * h[2] - n[2] * h[1], X

    lo, hi = 0.0, math.radians(40.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.sign(off_bisector(mid)[0]) == np.sign(off_bisector(lo)[0]) else (lo, mid)
    u0, v0 = _camera_pixel(rig, off_bisector(lo)[1])
    # GGX alpha 0.1 at normal incidence-ish: the lobe's peak adds ~0.35 pi of full white (measured 0.74)
    assert d.max() > 0.4, d.max()
    top = d > 0.5 * d.max()
    vv, uu = np.nonzero(top)
    wt = d[top]
    # the centroid of the brightest pixels: within half a camera pixel (facets 1 degree across, S = 2)
    assert math.hypot((uu * wt).sum() / wt.sum() - u0, (vv * wt).sum() / wt.sum() - v0) < 0.5
    U, V = np.meshgrid(np.arange(W), np.arange(H))
    far = (np.hypot(U - u0, V - v0) > 8) & (img["matte"] > 0.3)
    assert far.sum() > 300 and np.all(d[far] < 0.02)   # no second highlight; Monte Carlo noise of the lobe


def test_concave_corner_bounces_light_as_its_view_factor_says():
    """Inter-reflection in the ``corner`` scene's 90-degree groove: with one bounce (max_depth 3) a point
    on one face gets, beyond its direct light E_A, albedo x the integral over the other face of
    E_B cos1 cos2 / (pi r^2) (Lambertian radiosity; E from a pinhole 600 mm above, E ~ cos / (cos_axis z^2)),
    summed here by quadrature on a 100 x 200 grid: the ratio to the direct render (max_depth 2) is
    1 + 0.8 F (predicted 1.183 on this patch of the 80 mm block; measured 1.179 and 1.180 on its two faces)."""
    rig = small_rig()
    img = {}
    for depth in (2, 3):
        mr = MitsubaRig(rig, "corner", settings=LINEAR, projector_size=(PW, PH),
                        mitsuba=MitsubaSettings(spp=4, max_depth=depth))
        img[depth] = mr.render_linear(np.full((PH, PW), 255, np.uint8), seed=3)
    truth = mr.truth()
    pts, lit = truth["points"], truth["lit"]
    S, b, r = 80.0, 10.0, 1.0 / math.sqrt(2.0)        # the default 80 mm block, base 10 mm
    P = np.array([0.0, 0.0, 600.0])

    def irradiance(X, n):
        dv = P - X
        dist = np.linalg.norm(dv, axis=-1)
        zp = P[2] - X[..., 2]
        return np.maximum((dv * n).sum(-1) / dist, 0.0) / ((zp / dist) * zp ** 2)

    for side in (1.0, -1.0):
        nA, nB = np.array([side * r, 0.0, r]), np.array([-side * r, 0.0, r])
        with np.errstate(invalid="ignore"):
            onA = (lit & (np.abs(pts[..., 2] - (b - side * pts[..., 0])) < 0.05) & (np.abs(pts[..., 1]) < 10)
                   & (-side * pts[..., 0] > 6) & (-side * pts[..., 0] < 34))
        X = pts[onA].astype(float)
        u = (np.arange(100) + 0.5) / 100 * S / 2
        y = (np.arange(200) + 0.5) / 200 * S - S / 2
        Uu, Yy = np.meshgrid(u, y)
        Y = np.stack([side * Uu, Yy, b + Uu], -1).reshape(-1, 3)      # face B: (side u, y, b + u)
        dA = (S / 2 / 100 * math.sqrt(2.0)) * (S / 200)
        dv = Y[None] - X[:, None]
        d2 = (dv ** 2).sum(-1)
        dn = dv / np.sqrt(d2)[..., None]
        k = np.maximum(dn @ nA, 0) * np.maximum(-(dn @ nB), 0) / (math.pi * d2)
        F = (k * irradiance(Y, nB)[None]).sum(1) * dA / irradiance(X, nA)
        bounce = img[3][onA].mean() / img[2][onA].mean() - 1.0
        assert onA.sum() > 150
        # 5 %: the plane seen past the block's ends, the quadrature, 16 samples a pixel
        assert bounce == pytest.approx(0.8 * F.mean(), rel=0.05), (bounce, 0.8 * F.mean())


def test_choose_variant_is_one_mitsuba_has():
    import mitsuba as mi

    v = choose_variant()
    assert v in ("llvm_ad_rgb", "scalar_rgb") and mi.variant() == v
    with pytest.raises(ValueError, match="not available"):
        choose_variant("no_such_variant")
    choose_variant(v)


def test_settings_are_checked():
    for bad in ({"spp": 0}, {"max_depth": 1}, {"ambient_spp": True}, {"variant": "gpu"}, {"coat_roughness": 0.0},
                {"coat_roughness": "glossy"}):
        with pytest.raises(ValueError, match=f"MitsubaSettings.{next(iter(bad))}"):
            MitsubaSettings(**bad)


def test_scan_rendered_by_mitsuba_reconstructs_end_to_end(tmp_path):
    """A Mitsuba scan of a 40 mm sphere under the perspective projector, reconstructed by ringscan and
    measured against Mitsuba's own truth.

    ringscan's renderer gives this scan (160x128, gray-rings 3 bits, 16 frames, S = 2) a median error of
    0.062 mm (p95 0.28 mm, coverage 0.99). Mitsuba's differs in what ringscan's reconstruction does not
    model: inverse-square fall-off (the sphere's top 8 % brighter than the plane), light bounced
    between sphere and plane, occluded ambient light, flat facets, and Monte Carlo noise (measured:
    median 0.073 mm, p95 0.33 mm with 4 spp; with 16 unstratified samples a pixel, S = 1, the noise
    raises the median to 0.10 mm, with 4 to 0.16 mm). The bound, 0.15 mm (an eighth of a 1.3 mm camera
    pixel), lets those shift the decoded boundaries by a little, but fails a wrong geometry (a ring
    misplaced by a projector pixel moves points by ~0.6 mm) or a wrong truth."""
    rig = small_rig()
    spec = parse_patterns({"codec": "gray-rings", "width": PW, "height": PH, "center": [127.5, 95.5], "rho0": 4.0,
                           "pitch": 3.0, "bits": 3, "sector_bits": 4})
    scan = simulate_scan(tmp_path / "scan", scene="sphere", size_mm=40.0, rig=rig, patterns=spec, progress=False,
                         renderer="mitsuba", mitsuba=MitsubaSettings(spp=4))
    t = load_truth(scan)
    assert t.settings == RenderSettings().to_dict() and t.faces.shape[0] > 10000
    rend = scan.extra["truth"]["renderer"]
    assert rend["name"] == "mitsuba" and rend["spp"] == 4 and rend["max_depth"] == 3
    reconstruct_scan(scan, tmp_path / "rec", device="cpu", progress=False)
    ev = evaluate_recon(tmp_path / "rec", scan)["views"]["view_000"]
    assert ev["points"] > 150 and ev["coverage"] > 0.9
    assert ev["median_mm"] < 0.15 and ev["frac_over_1mm"] < 0.02, ev
    assert math.isfinite(ev["p95_mm"]) and ev["p95_mm"] < 0.6, ev


def test_sigma_honesty_refuses_mitsuba_only_conditions_on_ringscans_renderer(tmp_path, capsys):
    """benchmarks/sigma_honesty.py: the conditions only Mitsuba renders (a corner's inter-reflection, a glossy
    coat) are refused for ringscan's renderer with one line, before anything is rendered; each names a
    scene or Mitsuba settings that exist."""
    sh = load_benchmark("sigma_honesty")
    only = [n for n in sh.CONDITIONS if sh.condition_extras(n).get("mitsuba_only")]
    assert {"corner-interreflection", "glossy-coat-0.1"} <= set(only)
    for n in sh.CONDITIONS:
        ex = sh.condition_extras(n)
        MitsubaSettings(**ex.get("mitsuba", {}))                     # valid settings
        if "scene" in ex:
            from ringscan.pipeline.simulate.scenes import make_scene

            make_scene(ex["scene"])
    for n in only:
        with pytest.raises(ValueError, match=f"condition {n}: needs --renderer mitsuba"):
            sh.run_condition(n, tmp_path, renderer="warp")
    assert sh.main(["--only", "glossy-coat-0.1", "--out", str(tmp_path)]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert out == ["error: condition glossy-coat-0.1 needs --renderer mitsuba: ringscan's own renderer cannot render "
                   "a glossy coat's specular lobe (it renders Lambertian surfaces only)"]
    assert not any(tmp_path.iterdir())
