"""Triangulation against hand-made geometry: known points, projected through the
camera and the light, come back where they were."""

import cv2
import numpy as np
import pytest
import warp as wp

from ringscan.kernels.geometry import make_camera, make_parallel_light, make_perspective_light
from ringscan.kernels.triangulation import STATUS_NAMES, TriangulateSettings, compact_points, triangulate_rings
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
