"""Triangulation against hand-made geometry: known points, projected through the
camera and the light, come back where they were."""

import cv2
import numpy as np
import pytest
import warp as wp

from ringscan.kernels.geometry import make_camera, make_parallel_light, make_perspective_light, polar_angle
from ringscan.kernels.triangulation import (
    NOMINAL_SIGMA_PX,
    PI,
    STATUS_NAMES,
    TriangulateSettings,
    camera_side_sigmas,
    compact_points,
    sector_residual,
    triangulate_rings,
)
from ringscan.pipeline.formats.rig import default_rig

CENTER = (511.5, 383.5)
SB = 6
PROJ_DIST = np.array([0.05, -0.02, 0.001, 0.0005, 0.0])


def _setup(model, n=400, seed=0):
    rig = default_rig(light_model=model)
    c, L = rig.camera, rig.light
    cam = make_camera(c.K, c.dist, c.R, c.t)
    rng = np.random.default_rng(seed)
    P = np.c_[rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), rng.uniform(0, 60, n)]
    if model == "parallel":
        light = make_parallel_light(L.R, L.t, L.pixel_pitch_mm, L.axis_px)
        pu = P[:, 0] / L.pixel_pitch_mm + L.axis_px[0]
        pv = P[:, 1] / L.pixel_pitch_mm + L.axis_px[1]
    else:
        light = make_perspective_light(L.K, PROJ_DIST, L.R, L.t)
        pp = cv2.projectPoints(P, cv2.Rodrigues(L.R)[0], L.t, L.K, PROJ_DIST)[0][:, 0]
        pu, pv = pp[:, 0], pp[:, 1]
    rho = np.hypot(pu - CENTER[0], pv - CENTER[1]).astype(np.float32)
    phi = np.arctan2(pv - CENTER[1], pu - CENTER[0])
    sec = np.floor((phi + np.pi) / (2 * np.pi) * 2 ** SB).astype(np.int32)
    uv = cv2.projectPoints(P, cv2.Rodrigues(c.R)[0], c.t, c.K, c.dist)[0][:, 0].astype(np.float32)
    return rig, cam, light, P, uv, rho, sec


def _run(device, cam, light, uv, rho, sec, sector_bits=SB, vol=(-3, 95, 100), **kw):
    n = len(uv)
    return triangulate_rings(wp.array(uv, dtype=wp.vec2, device=device), wp.array(rho, device=device),
                             wp.array(sec, device=device), wp.ones(n, dtype=wp.float32, device=device),
                             camera=cam, light=light, volume=vol, center=CENTER, sector_bits=sector_bits, **kw)


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_points_come_back_with_sectors(device, model):
    rig, cam, light, P, uv, rho, sec = _setup(model)
    T = _run(device, cam, light, uv, rho, sec)
    st, X = T.status.numpy(), T.points.numpy()
    ok = st == 0
    assert ok.mean() > 0.95  # the rest: both roots in one sector (ambiguous) or a grazing ray
    assert set(np.unique(st[~ok])) <= {3, 5}
    err = np.linalg.norm(X[ok] - P[ok], axis=1)
    assert err.max() < 2e-3  # mm; float32 pixel coordinates limit it
    conf = T.confidence.numpy()[ok]
    assert np.all((conf > 0) & (conf <= 1))


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_without_sectors_nothing_is_guessed(device, model):
    rig, cam, light, P, uv, rho, sec = _setup(model)
    T = _run(device, cam, light, uv, rho, np.full_like(sec, -1))
    st, X = T.status.numpy(), T.points.numpy()
    ok = st == 0
    amb = st == 3
    assert amb.sum() > 50  # many rays meet the cylinder twice inside the volume
    assert ok.sum() + amb.sum() + (st == 5).sum() == len(st)
    # every point placed is the true one: single roots only
    assert np.linalg.norm(X[ok] - P[ok], axis=1).max() < 2e-3


def test_grazing_rays_are_dropped(device):
    rig, cam, light, P, uv, rho, sec = _setup("parallel")
    T = _run(device, cam, light, uv, rho, sec, settings=TriangulateSettings(min_incidence_cos=0.5))
    st, conf = T.status.numpy(), T.confidence.numpy()
    assert np.any(st == 5) and np.any(st == 0)
    assert np.all(conf[st == 5] < 0.5) and np.all(conf[st == 0] >= 0.5)  # sample confidence is 1 here


def test_wrong_sector_is_rejected(device):
    rig, cam, light, P, uv, rho, sec = _setup("parallel")
    bad = (sec + 2 ** SB // 2) % 2 ** SB  # opposite side of the pattern
    st = _run(device, cam, light, uv, rho, bad).status.numpy()
    assert np.mean(st == 4) > 0.9


def test_volume_and_no_root(device):
    rig, cam, light, P, uv, rho, sec = _setup("parallel", n=50)
    # a volume that excludes every true point (all have z >= 0): nothing inside
    T = _run(device, cam, light, uv, rho, sec, vol=(-50, -40, 100))
    st = T.status.numpy()
    assert np.all(st != 0)
    assert np.mean(st == 2) > 0.5  # the rest meet it below the plane, in the wrong sector (4)
    # a ring larger than any the rays can reach inside: no real root or outside
    T = _run(device, cam, light, uv, np.full_like(rho, 5000.0), sec)
    assert np.all(np.isin(T.status.numpy(), [1, 2]))


def test_empty_and_compaction(device):
    rig, cam, light, P, uv, rho, sec = _setup("parallel", n=4)
    T = _run(device, cam, light, uv[:0], rho[:0], sec[:0])
    assert T.points.shape == (0,)
    assert compact_points(T.status).shape == (0,)
    st = wp.array(np.array([0, 3, 0, 1, 0], np.int32), device=device)
    assert compact_points(st).numpy().tolist() == [0, 2, 4]


def test_bad_input(device):
    rig, cam, light, P, uv, rho, sec = _setup("parallel", n=4)
    with pytest.raises(ValueError, match="rho"):
        triangulate_rings(wp.array(uv, dtype=wp.vec2, device=device), wp.array(rho[:2], device=device),
                          wp.array(sec, device=device), wp.ones(4, dtype=wp.float32, device=device),
                          camera=cam, light=light, volume=(0, 1, 1), center=CENTER)
    with pytest.raises(ValueError, match="volume"):
        _run(device, cam, light, uv, rho, sec, vol=(5, 1, 10))
    with pytest.raises(ValueError, match="vec2"):
        triangulate_rings(wp.array(rho, device=device), wp.array(rho, device=device), wp.array(sec, device=device),
                          wp.array(rho, device=device), camera=cam, light=light, volume=(0, 1, 1), center=CENTER)


def test_cpu_spans_on_several_threads_match_one_thread():
    """On the CPU the samples are cut into spans launched from a thread pool
    (``launch_spans``): every span must land where one launch puts it."""
    rig, cam, light, P, uv, rho, sec = _setup("parallel", n=30000, seed=3)
    one = _run("cpu", cam, light, uv, rho, sec, threads=1)
    many = _run("cpu", cam, light, uv, rho, sec, threads=2)
    for a, b in ((one.status, many.status), (one.points, many.points), (one.confidence, many.confidence)):
        np.testing.assert_array_equal(a.numpy(), b.numpy())
    ok = one.status.numpy() == 0
    assert np.linalg.norm(one.points.numpy()[ok] - P[ok], axis=1).max() < 2e-3


# ----------------------------------------------------------------------------- lens models that fold or converge slowly

STATUS = {name: i for i, name in enumerate(STATUS_NAMES)}


def test_strongly_distorted_projector_points_are_right_or_dropped(device):
    """A projector lens far from its undistorted cone (k1 = -5, k2 = 20, no fold):
    a fixed 4 Newton steps kept points tens of millimetres off. Every point kept
    is the true one; a root that does not converge drops its sample, counted."""
    dist = np.array([-5.0, 20.0, 0.01, 0.01, 0.0])
    rig = default_rig(light_model="perspective")
    c, L = rig.camera, rig.light
    cam = make_camera(c.K, c.dist, c.R, c.t)
    light = make_perspective_light(L.K, dist, L.R, L.t)
    rng = np.random.default_rng(5)
    n = 6000
    P = np.c_[rng.uniform(-80, 80, n), rng.uniform(-80, 80, n), rng.uniform(0, 60, n)]
    pp = cv2.projectPoints(P, cv2.Rodrigues(L.R)[0], L.t, L.K, dist)[0][:, 0]
    rho = np.hypot(pp[:, 0] - CENTER[0], pp[:, 1] - CENTER[1]).astype(np.float32)
    sec = np.floor((np.arctan2(pp[:, 1] - CENTER[1], pp[:, 0] - CENTER[0]) + np.pi) / (2 * np.pi) * 2 ** SB)
    uv = cv2.projectPoints(P, cv2.Rodrigues(c.R)[0], c.t, c.K, c.dist)[0][:, 0].astype(np.float32)
    T = _run(device, cam, light, uv, rho, sec.astype(np.int32), vol=(-3, 95, 200))
    st, X = T.status.numpy(), T.points.numpy()
    ok = st == 0
    assert ok.mean() > 0.75  # most of the rest: the undistorted cone misses the ray (no_root)
    assert set(np.unique(st)) <= {STATUS[k] for k in ("ok", "no_root", "outside_volume", "ambiguous",
                                                        "sector_mismatch", "grazing", "not_converged")}
    assert np.linalg.norm(X[ok] - P[ok], axis=1).max() < 2e-3
    assert np.all(X[st == STATUS["not_converged"]] == 0)


def test_pixels_without_an_undistorted_ray_are_dropped(device):
    """A wide camera whose barrel lens folds at r = 1.21: pixels beyond the fold's
    image have no ray; their samples are dropped as undistort_failed, never
    triangulated, while the pixels of true points still give them back."""
    rig, _, light, P, _, rho, sec = _setup("parallel", n=400)
    c = rig.camera
    K = np.array([[700.0, 0, 639.5], [0, 700.0, 511.5], [0, 0, 1]])
    dist = np.array([-0.35, 0.05, 0.0, 0.0, 0.0])
    cam = make_camera(K, dist, c.R, c.t)
    uv = cv2.projectPoints(P, cv2.Rodrigues(c.R)[0], c.t, K, dist)[0][:, 0]
    corners = np.array([[5.0, 5.0], [1275.0, 5.0], [5.0, 1019.0], [1275.0, 1019.0], [1270.0, 900.0]])
    # r = 1.1-1.2 in normalised units, past the largest radius (0.72) of the fold-free region's image
    assert np.all(np.hypot(corners[:, 0] - 639.5, corners[:, 1] - 511.5) / 700.0 > 1.0)
    uv_all = np.concatenate([uv, corners]).astype(np.float32)
    rho_all = np.concatenate([rho, np.full(5, 200.0, np.float32)])
    sec_all = np.concatenate([sec, np.zeros(5, np.int32)])
    T = _run(device, cam, light, uv_all, rho_all, sec_all)
    st, X = T.status.numpy(), T.points.numpy()
    assert np.all(st[-5:] == STATUS["undistort_failed"])
    ok = st[:-5] == 0
    assert ok.mean() > 0.95
    assert np.linalg.norm(X[:-5][ok] - P[ok], axis=1).max() < 2e-3


def test_status_names_cover_every_code():
    assert STATUS_NAMES[:7] == ("ok", "no_root", "outside_volume", "ambiguous", "sector_mismatch", "grazing",
                                "isolated")
    assert STATUS["not_converged"] == 7 and STATUS["undistort_failed"] == 8


# ----------------------------------------------------------------------------- both projector coordinates


def _run_full(device, cam, light, uv, rho, phi, s_rho, s_tan, sec=None, vol=(-3, 95, 100), **kw):
    n = len(uv)
    sec = np.full(n, -1, np.int32) if sec is None else sec
    return triangulate_rings(wp.array(uv, dtype=wp.vec2, device=device), wp.array(rho, device=device),
                             wp.array(sec, device=device), wp.ones(n, dtype=wp.float32, device=device),
                             camera=cam, light=light, volume=vol, center=CENTER,
                             phi=wp.array(np.asarray(phi, np.float32), device=device),
                             sigma_rho=wp.array(np.full(n, s_rho, np.float32), device=device),
                             sigma_tan=wp.array(np.full(n, s_tan, np.float32), device=device), **kw)


def _polar(model, P, light_params):
    L = light_params
    if model == "parallel":
        pu = P[:, 0] / L.pixel_pitch_mm + L.axis_px[0]
        pv = P[:, 1] / L.pixel_pitch_mm + L.axis_px[1]
    else:
        pp = cv2.projectPoints(P, cv2.Rodrigues(L.R)[0], L.t, L.K, PROJ_DIST)[0][:, 0]
        pu, pv = pp[:, 0], pp[:, 1]
    return np.arctan2(pv - CENTER[1], pu - CENTER[0]).astype(np.float32)


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_both_coordinates_place_every_point_without_a_sector(device, model):
    """With rho and the polar angle every sample has one answer: no ambiguous
    root, no sector needed, and the points come back where they were (the
    projector's lens distortion included)."""
    rig, cam, light, P, uv, rho, sec = _setup(model)
    phi = _polar(model, P, rig.light)
    T = _run_full(device, cam, light, uv, rho, phi, 0.05, 0.05)
    st, X = T.status.numpy(), T.points.numpy()
    assert np.all(st == 0)
    assert np.linalg.norm(X - P, axis=1).max() < 2e-3
    assert np.all(T.residual.numpy() < 0.01)  # projector px
    # rings alone on the same samples, without a sector: ambiguous roots are dropped
    R = _run(device, cam, light, uv, rho, np.full_like(sec, -1))
    assert np.mean(R.status.numpy() == 3) > 0.1


def test_both_coordinates_where_the_ring_is_blind(device):
    """Rays that run along the ring's cylinder (|cos| < 0.05, where the ring
    alone drops the point as grazing or puts it millimetres off) are placed by
    the angle, with a small predicted sigma; rings-only drops them."""
    rig, cam, light, P, uv, rho, sec = _setup("parallel", n=20000, seed=7)
    R = _run(device, cam, light, uv, rho, sec)
    cos = R.confidence.numpy()
    phi = _polar("parallel", P, rig.light)
    T = _run_full(device, cam, light, uv, rho, phi, 0.05, 0.05)
    st = T.status.numpy()
    blind = (R.status.numpy() == 5)
    assert blind.sum() > 20
    assert np.all(st[blind] == 0)
    assert np.linalg.norm(T.points.numpy()[blind] - P[blind], axis=1).max() < 2e-3
    sig_rings = 0.05 / np.maximum(cos, 1e-9)  # what the ring alone would give (px over |d rho/dt|), in relative terms
    assert np.median(T.sigma.numpy()[blind]) < 0.2  # mm: the angle pins the depth there
    assert np.all(T.confidence.numpy()[blind] > 0.03)
    assert sig_rings[blind].min() > 0  # the ring constraint had (almost) nothing there


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_predicted_sigma_matches_the_scatter(device, model):
    """Noise of known standard deviation on rho and on the tangential position:
    the scatter of the points along the ray matches the predicted sigma."""
    rig, cam, light, P0, uv0, rho0, _ = _setup(model, n=40, seed=11)
    phi0 = _polar(model, P0, rig.light)
    k = 400
    rng = np.random.default_rng(1)
    s_rho, s_tan = 0.05, 0.2
    uv = np.repeat(uv0, k, 0)
    rho = (np.repeat(rho0, k) + rng.normal(0, s_rho, uv.shape[0])).astype(np.float32)
    phi = (np.repeat(phi0, k) + rng.normal(0, s_tan, uv.shape[0]) / np.repeat(rho0, k)).astype(np.float32)
    T = _run_full(device, cam, light, uv, rho, phi, s_rho, s_tan, vol=(-50, 200, 300))
    st = T.status.numpy().reshape(40, k)
    X = T.points.numpy().reshape(40, k, 3)
    sig = T.sigma.numpy().reshape(40, k)
    good = np.all(st == 0, axis=1)
    assert good.sum() >= 30
    spread = np.array([np.linalg.norm(X[i] - X[i].mean(0), axis=1).std() * 0 + np.sqrt(
        np.sum(np.var(X[i], axis=0))) for i in np.flatnonzero(good)])
    pred = np.median(sig[good], axis=1)
    ratio = spread / pred
    assert 0.8 < np.median(ratio) < 1.25


def test_angle_alone_and_inconsistent_angles(device):
    rig, cam, light, P, uv, rho, sec = _setup("parallel")
    phi = _polar("parallel", P, rig.light)
    A = _run_full(device, cam, light, uv, rho, phi, 0.05, 0.05, settings=TriangulateSettings(constraint="angle"))
    ok = A.status.numpy() == 0
    assert ok.mean() > 0.9
    assert np.linalg.norm(A.points.numpy()[ok] - P[ok], axis=1).max() < 5e-3
    # an angle 0.3 rad off disagrees with the ring: dropped as inconsistent, never placed silently
    T = _run_full(device, cam, light, uv, rho, phi + 0.3, 0.05, 0.05)
    st = T.status.numpy()
    assert np.mean(st == STATUS["inconsistent"]) > 0.9
    assert np.all(T.residual.numpy()[st == STATUS["inconsistent"]] > 2.0)


def test_rays_along_the_projector_ray_are_ill_conditioned(device):
    """A camera ray parallel to the light's rays (the camera on the light axis)
    learns nothing of its depth from the projector: dropped as ill_conditioned."""
    rig = default_rig(light_model="parallel")
    L = rig.light
    light = make_parallel_light(L.R, L.t, L.pixel_pitch_mm, L.axis_px)
    K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])
    R = np.diag([1.0, -1.0, -1.0])  # looking down -z, as the light does
    cam = make_camera(K, None, R, -R @ np.array([5.0, 3.0, 500.0]))
    P = np.array([[5.0 + 0.01, 3.0, 10.0], [5.0, 3.0 + 0.01, 30.0]])
    uv = cv2.projectPoints(P, cv2.Rodrigues(R)[0], -R @ np.array([5.0, 3.0, 500.0]), K, None)[0][:, 0]
    pu = P[:, 0] / L.pixel_pitch_mm + L.axis_px[0]
    pv = P[:, 1] / L.pixel_pitch_mm + L.axis_px[1]
    rho = np.hypot(pu - CENTER[0], pv - CENTER[1]).astype(np.float32)
    phi = np.arctan2(pv - CENTER[1], pu - CENTER[0]).astype(np.float32)
    T = _run_full(device, cam, light, uv.astype(np.float32), rho, phi, 0.05, 0.05, vol=(-3, 95, 200))
    assert np.all(np.isin(T.status.numpy(), [STATUS["ill_conditioned"], STATUS["not_converged"]]))


def test_constraint_setting_is_checked(device):
    rig, cam, light, P, uv, rho, sec = _setup("parallel", n=4)
    with pytest.raises(ValueError, match="constraint"):
        _run(device, cam, light, uv, rho, sec, settings=TriangulateSettings(constraint="cones"))
    with pytest.raises(ValueError, match="needs samples with an angle"):
        _run(device, cam, light, uv, rho, sec, settings=TriangulateSettings(constraint="both"))


def test_calibration_floor_discounts_errors_across_the_epipolar_line(device):
    """A calibration that misses by 0.5 px across the epipolar lines (what a
    wrong rig does to a real decode): the floor finds the 0.5 px, and with it the
    miss no longer leaks into depth through the anisotropic decode weights."""
    from ringscan.kernels.calibration_floor import calibration_floor

    rig, cam, light, P, uv, rho, sec = _setup("perspective", n=3000, seed=21)
    L = rig.light
    X = P
    c = rig.camera
    d = X - c.center
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pa = cv2.projectPoints(X + 0.5 * d, cv2.Rodrigues(L.R)[0], L.t, L.K, PROJ_DIST)[0][:, 0]
    pb = cv2.projectPoints(X - 0.5 * d, cv2.Rodrigues(L.R)[0], L.t, L.K, PROJ_DIST)[0][:, 0]
    e = (pa - pb) / np.linalg.norm(pa - pb, axis=1, keepdims=True)
    n = np.c_[-e[:, 1], e[:, 0]]
    p = cv2.projectPoints(P, cv2.Rodrigues(L.R)[0], L.t, L.K, PROJ_DIST)[0][:, 0]
    rng = np.random.default_rng(2)
    q = p + n * rng.normal(0, 0.5, (len(p), 1))
    rho_n = np.hypot(q[:, 0] - CENTER[0], q[:, 1] - CENTER[1]).astype(np.float32)
    phi_n = np.arctan2(q[:, 1] - CENTER[1], q[:, 0] - CENTER[0]).astype(np.float32)
    kw = dict(vol=(-50, 200, 300))
    T1 = _run_full(device, cam, light, uv, rho_n, phi_n, 0.02, 0.2, **kw)
    floor, stats = calibration_floor(T1)
    assert 0.4 < floor < 0.6
    assert stats["chi2_median"] > 3  # the model alone (0.02 px radially) cannot explain it
    T2 = _run_full(device, cam, light, uv, rho_n, phi_n, 0.02, 0.2, floor=floor,
                   settings=TriangulateSettings(max_residual_px=5 * floor), **kw)
    ok1 = T1.status.numpy() == 0
    ok2 = T2.status.numpy() == 0
    assert ok2.mean() > 0.98
    e1 = np.linalg.norm(T1.points.numpy()[ok1] - P[ok1], axis=1)
    e2 = np.linalg.norm(T2.points.numpy()[ok2] - P[ok2], axis=1)
    assert np.median(e2) < 0.5 * np.median(e1)
    # a rig that fits: no floor
    T0 = _run_full(device, cam, light, uv, rho, _polar("perspective", P, rig.light), 0.02, 0.2, **kw)
    assert calibration_floor(T0)[0] == 0.0


def test_samples_without_an_angle_pick_their_root_by_a_coarse_sector(device):
    """In a scan with an angle code, a sample whose angle failed keeps its ring;
    where no root matches its decoded sector it picks the root by the sector code's
    top bits: finest bits read wrong (off by up to 3 sectors of 512) no longer drop
    it as a sector mismatch."""
    rig, cam, light, P, uv, rho, _ = _setup("parallel")
    phi_true = _polar("parallel", P, rig.light)
    fine = np.floor((phi_true + np.pi) / (2 * np.pi) * 2 ** 9).astype(np.int32)
    wrong = fine ^ 3  # the two finest bits of the binary sector flipped: the coarse sector is kept
    nan = np.full(len(uv), np.nan, np.float32)
    kw = dict(sec=wrong, settings=TriangulateSettings(fallback_sector_px=16.0))
    T = _run_full(device, cam, light, uv, rho, nan, 0.05, 0.0, sector_bits=9, **kw)
    st, X = T.status.numpy(), T.points.numpy()
    ok = st == 0
    # the rest: both roots in one coarse sector (ambiguous, 17 here) or a grazing ray
    assert ok.mean() > 0.9 and set(np.unique(st[~ok])) <= {3, 5}
    assert np.linalg.norm(X[ok] - P[ok], axis=1).max() < 2e-3
    # samples whose decoded sector matches a root keep it: the same as without the fallback
    right = [_run_full(device, cam, light, uv, rho, nan, 0.05, 0.0, sector_bits=9, sec=fine,
                       settings=TriangulateSettings(fallback_sector_px=f)).status.numpy() for f in (16.0, 0.0)]
    assert np.array_equal(right[0], right[1])
    # the sector as decoded (the setting off, its default, or rings forced): mismatches
    for s in (TriangulateSettings(), TriangulateSettings(constraint="rings", fallback_sector_px=16.0)):
        st0 = _run_full(device, cam, light, uv, rho, nan, 0.05, 0.0, sector_bits=9, sec=wrong,
                        settings=s).status.numpy()
        assert np.mean(st0 == 4) > 0.5
    with pytest.raises(ValueError, match="fallback_sector_px"):
        TriangulateSettings(fallback_sector_px=-1.0)


@wp.kernel
def _sector_residual_kernel(off: wp.array(dtype=wp.vec2), sector: wp.array(dtype=int), n_sectors: int,
                            out: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    o = off[i]
    # the reference: the wrap by floor, as the residual was first written
    phi = polar_angle(o[1], o[0])
    width = 2.0 * PI / float(n_sectors)
    mid = (float(sector[i]) + 0.5) * width - PI
    dphi = phi - mid
    dphi = dphi - 2.0 * PI * wp.floor((dphi + PI) / (2.0 * PI))
    out[i] = wp.vec2(sector_residual(o, sector[i], n_sectors), wp.max(wp.abs(dphi) / width - 0.5, 0.0))


@pytest.mark.parametrize("n_sectors", [2, 64, 512])
def test_sector_residual_wraps_as_the_floor_formula_to_the_bit(device, n_sectors):
    """The sector residual's wrap without a division gives the floor formula's
    bits for every angle and sector, also on the angles where the wrap turns
    (half a turn from the sector's middle)."""
    rng = np.random.default_rng(11)
    sec = rng.integers(0, n_sectors, 30000)
    mid = (sec + 0.5) * 2 * np.pi / n_sectors - np.pi
    ang = np.r_[rng.uniform(-np.pi, np.pi, 15000), mid[15000:] + np.pi * rng.choice([-1, 1], 15000)
                + rng.normal(0, 1e-6, 15000)]
    rad = rng.uniform(5, 600, ang.size)
    off = np.c_[rad * np.cos(ang), rad * np.sin(ang)].astype(np.float32)
    out = wp.zeros(ang.size, dtype=wp.vec2, device=device)
    wp.launch(_sector_residual_kernel, ang.size,
              inputs=[wp.array(off, dtype=wp.vec2, device=device), wp.array(sec.astype(np.int32), device=device),
                      n_sectors], outputs=[out], device=device)
    o = out.numpy()
    assert o[:, 0].tobytes() == o[:, 1].tobytes()
    assert (o[:, 0] == 0).any() and (o[:, 0] > n_sectors / 2 - 0.6).any()


def test_parallel_light_sigma_is_the_float64_central_difference(device):
    """Parallel light: each point's sigma is sigma_rho over the central difference
    of rho along its ray (h = 0.01 mm), computed in float64 from the point itself:
    to float32's precision, also where the ray nearly grazes the ring (a float32
    difference of the two lengths misses by up to 1e-2 there)."""
    rig, cam, light, P, uv, rho, sec = _setup("parallel", n=3000, seed=3)
    T = _run(device, cam, light, uv, rho, sec)
    st = T.status.numpy()
    m = (st == 0) | (st == 5)
    assert m.mean() > 0.9
    X = T.points.numpy().astype(np.float64)[m]
    L = rig.light
    C = -np.asarray(rig.camera.R).T @ np.asarray(rig.camera.t)
    d = (X - C) / np.linalg.norm(X - C, axis=1, keepdims=True)
    o = (X @ np.asarray(L.R).T + L.t)[:, :2] / L.pixel_pitch_mm + np.asarray(L.axis_px) - CENTER
    v = (d @ np.asarray(L.R).T)[:, :2] / L.pixel_pitch_mm
    h = 0.01
    slope = np.abs(np.linalg.norm(o + h * v, axis=1) - np.linalg.norm(o - h * v, axis=1)) / (2 * h)
    rel = np.abs(T.sigma.numpy()[m] / (NOMINAL_SIGMA_PX / slope) - 1)
    assert np.median(rel) < 1e-6 and rel.max() < 1e-4, (np.median(rel), rel.max())


def _floor_numpy(res, var):
    """The calibration floor as NumPy states it (the function's former body): its medians by sorts."""
    from ringscan.kernels.calibration_floor import CHI2_1_MEDIAN

    m = (var > 0) & (res >= 0) & np.isfinite(res)
    if np.count_nonzero(m) < 20:
        return 0.0, {}
    r2 = res[m].astype(np.float64) ** 2
    v = var[m].astype(np.float64)
    stats = {"samples": int(m.sum()), "residual_px_median": float(np.median(res[m])),
             "residual_px_p95": float(np.percentile(res[m], 95)), "chi2_median": float(np.median(r2 / v))}
    if stats["chi2_median"] <= CHI2_1_MEDIAN:
        return 0.0, stats
    lo, hi = 0.0, float(np.sqrt(r2.max())) + 1e-9
    for _ in range(60):
        c = 0.5 * (lo + hi)
        if np.median(r2 / (v + c * c)) > CHI2_1_MEDIAN:
            lo = c
        else:
            hi = c
    return hi, stats


@pytest.mark.parametrize("n,miss", [(5001, 0.3), (5000, 0.3), (4096 * 3 + 17, 0.05), (3000, 0.0), (19, 0.3)])
def test_calibration_floor_on_the_device_is_the_numpy_statement(n, miss):
    """Residuals of a decode whose sigma is right, plus a miss of ``miss`` px across the epipolar line
    (0: none, no floor), some samples without a residual: the floor and its stats to the bit, odd and
    even counts (an even count's median is the mean of its two middle values), more than one row."""
    from types import SimpleNamespace

    from ringscan.kernels.calibration_floor import calibration_floor

    rng = np.random.default_rng(n)
    sd = rng.uniform(0.05, 0.4, n)
    res = np.abs(rng.normal(0, np.sqrt(sd ** 2 + miss ** 2))).astype(np.float32)
    var = (sd ** 2).astype(np.float32)
    res[rng.random(n) < 0.05] = -1.0  # no residual
    var[rng.random(n) < 0.02] = 0.0
    res[:2] = np.nan
    tri = SimpleNamespace(residual=wp.array(res), residual_var=wp.array(var))
    got = calibration_floor(tri, threads=2)
    want = _floor_numpy(res, var)
    assert got == want
    if miss and n >= 20:
        assert got[0] == pytest.approx(miss, rel=0.2)  # the planted miss, to its sampling noise


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_an_angle_alone_point_is_no_better_known_than_its_coordinates_agree(device, model):
    """The angle alone places the point (the ring's rho does not move it); where rho disagrees with it by
    k times their joint sigma across the epipolar line, the point's sigma grows by k (k > 1), and stays as
    the decode's where they agree. widen_angle=False (the error model's fit): the decode's sigma always."""
    from ringscan.pipeline.reconstruct.settings import TriangulateSettings

    rig, cam, light, P, uv, rho, sec = _setup(model)
    phi = _polar(model, P, rig.light)
    angle = TriangulateSettings(constraint="angle")
    agree = _run_full(device, cam, light, uv, rho, phi, 0.05, 0.05, settings=angle)
    off = rho + np.float32(1.0)  # 1 projector px off along the radius: 20 sigmas of rho
    far = _run_full(device, cam, light, uv, off, phi, 0.05, 0.05, settings=angle)
    plain = _run_full(device, cam, light, uv, off, phi, 0.05, 0.05, settings=angle, widen_angle=False)
    ok = (agree.status.numpy() == 0) & (far.status.numpy() == 0) & (plain.status.numpy() == 0)
    assert ok.mean() > 0.9
    # the points are the angle's: rho moves none of them (but for where the Gauss-Newton starts: it stops
    # within 2 % of a sigma, a few 1e-4 mm here)
    np.testing.assert_allclose(far.points.numpy()[ok], agree.points.numpy()[ok], atol=1e-3)
    s0, s1, s2 = (t.sigma.numpy()[ok] for t in (agree, far, plain))
    np.testing.assert_allclose(s2, s0, rtol=1e-3)  # no widening asked: the decode's sigma (same point, to 2 %
    # of a sigma); agreeing coordinates (chi well below 1) widen nothing
    plain_agree = _run_full(device, cam, light, uv, rho, phi, 0.05, 0.05, settings=angle, widen_angle=False)
    np.testing.assert_array_equal(agree.sigma.numpy()[ok], plain_agree.sigma.numpy()[ok])
    # the chi of a 1 px radial offset across the epipolar line: its residual there over the joint sigma in that
    # direction (cos^2 0.05^2 + sin^2 0.05^2: 0.05, equal sigmas); the line lies in no fixed direction to the
    # radius, so the factor spreads
    ratio = s1 / s2  # the same samples and points, with and without the widening
    chi = far.residual.numpy()[ok] / 0.05
    np.testing.assert_allclose(ratio[chi > 1.0], chi[chi > 1.0], rtol=2e-3)
    assert np.all(ratio[chi <= 1.0] == 1.0) and np.mean(chi > 1.0) > 0.5


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_a_point_of_both_coordinates_is_no_better_known_than_they_agree(device, model):
    """With both coordinates (the default), a point whose ring and angle disagree across the epipolar line by
    chi times their joint sigma there has its sigma grown by chi where chi > 1, and the decode's where they
    agree; the widening moves no point. widen_angle=False (the error model's fit): the decode's sigma."""
    from ringscan.pipeline.reconstruct.settings import TriangulateSettings

    rig, cam, light, P, uv, rho, sec = _setup(model)
    phi = _polar(model, P, rig.light)
    both = TriangulateSettings(constraint="both")
    off = rho + np.float32(0.1)  # 0.1 projector px off along the radius: 2 sigmas of rho
    wide = _run_full(device, cam, light, uv, off, phi, 0.05, 0.05, settings=both)
    plain = _run_full(device, cam, light, uv, off, phi, 0.05, 0.05, settings=both, widen_angle=False)
    ok = (wide.status.numpy() == 0) & (plain.status.numpy() == 0)
    assert ok.mean() > 0.9
    np.testing.assert_array_equal(wide.points.numpy()[ok], plain.points.numpy()[ok])
    chi = plain.residual.numpy()[ok] / np.sqrt(plain.residual_var.numpy()[ok])
    ratio = wide.sigma.numpy()[ok] / plain.sigma.numpy()[ok]
    assert 0.2 < np.mean(chi > 1.0) < 0.9  # the offset's share across the line spreads chi over both sides of 1
    np.testing.assert_allclose(ratio[chi > 1.0], chi[chi > 1.0], rtol=2e-3)  # float32 sigma and residual
    assert np.all(ratio[chi <= 1.0] == 1.0)


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_a_ring_alone_point_is_no_better_known_than_its_coordinates_agree(device, model):
    """The ring alone places the point (``constraint`` rings) on a sample whose angle was read too: where the two
    disagree across the epipolar line by chi times their joint sigma there (the chi the default's fit of both
    reads), its sigma grows by chi (chi > 1) and stays the ring's own where they agree; the point is the
    ring's, the angle moves none. widen_angle=False: the ring's sigma always."""
    from ringscan.pipeline.reconstruct.settings import TriangulateSettings

    rig, cam, light, P, uv, rho, sec = _setup(model)
    phi = _polar(model, P, rig.light)
    rings = TriangulateSettings(constraint="rings")
    off = rho + np.float32(0.1)  # 0.1 projector px off along the radius: 2 sigmas of rho
    kw = dict(sec=sec, sector_bits=SB, settings=rings)  # the ring's root chosen by its sector
    wide = _run_full(device, cam, light, uv, off, phi, 0.05, 0.05, **kw)
    plain = _run_full(device, cam, light, uv, off, phi, 0.05, 0.05, widen_angle=False, **kw)
    no_angle = np.full(len(uv), np.nan, np.float32)  # no angle read: the ring's point and sigma
    alone = _run_full(device, cam, light, uv, off, no_angle, 0.05, 0.05, **kw)
    both = _run_full(device, cam, light, uv, off, phi, 0.05, 0.05, settings=TriangulateSettings(constraint="both"),
                     widen_angle=False)
    ok = (wide.status.numpy() == 0) & (plain.status.numpy() == 0) & (alone.status.numpy() == 0)
    ok &= both.status.numpy() == 0
    assert ok.mean() > 0.9
    np.testing.assert_array_equal(wide.points.numpy()[ok], alone.points.numpy()[ok])
    np.testing.assert_array_equal(plain.sigma.numpy()[ok], alone.sigma.numpy()[ok])
    chi = both.residual.numpy()[ok] / np.sqrt(both.residual_var.numpy()[ok])
    ratio = wide.sigma.numpy()[ok] / plain.sigma.numpy()[ok]
    assert 0.2 < np.mean(chi > 1.0) < 0.9
    np.testing.assert_allclose(ratio[chi > 1.0], chi[chi > 1.0], rtol=2e-3)  # float32 sigma and residual
    assert np.all(ratio[chi <= 1.0] == 1.0)


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_a_camera_side_error_moves_the_depth_as_the_ray_moved_would(model):
    """camera_side_sigmas: the rho sigma whose depth sigma (over the ring's slope, as triangulation
    divides) is the depth change of the same ring met by the camera ray moved along sigma_uv: the
    implicit function against a finite difference of two triangulations."""
    rig, cam, light, P, uv, rho, sec = _setup(model, n=300, seed=4)
    rng = np.random.default_rng(5)
    ang = rng.uniform(0, 2 * np.pi, len(uv))
    s = rng.uniform(0.05, 0.3, len(uv))
    n = np.c_[np.cos(ang), np.sin(ang)]
    first = _run("cpu", cam, light, uv, rho, sec)
    ok = first.status.numpy() == 0
    assert ok.mean() > 0.9
    sr = camera_side_sigmas(wp.array(uv, dtype=wp.vec2), wp.array((n * s[:, None]).astype(np.float32), dtype=wp.vec2),
                            first.points, first.status, camera=cam, light=light, center=CENTER, threads=2).numpy()
    # the depth sigma triangulation gives that rho sigma (nominal sigma scaled: points do not move)
    depth_sigma = first.sigma.numpy() * sr / NOMINAL_SIGMA_PX
    C = np.asarray(rig.camera.R).T @ -np.asarray(rig.camera.t)
    h = 0.1  # px each way (the kernel differences rho over +-0.5 px: both linear to ~1 % here)
    moved = [_run("cpu", cam, light, (uv + sgn * h * n).astype(np.float32), rho, sec) for sgn in (1, -1)]
    ok &= (moved[0].status.numpy() == 0) & (moved[1].status.numpy() == 0)
    dist = [np.linalg.norm(m.points.numpy().astype(np.float64) - C, axis=1) for m in moved]
    fd = np.abs(dist[0] - dist[1]) / (2 * h) * s
    # 2 %: both linear to ~1 % over their steps; atol: float32 points (~3e-5 mm at ~500 mm) differenced
    # over 0.2 px and scaled by s <= 0.3 px
    np.testing.assert_allclose(depth_sigma[ok], fd[ok], rtol=0.02, atol=1e-4)
    # an unplaced sample keeps its camera-side length
    gone = ~(first.status.numpy() == 0) & ~(first.status.numpy() == 5)
    np.testing.assert_allclose(sr[gone], s[gone], rtol=1e-6)
