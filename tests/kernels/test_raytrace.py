"""The ray tracer against analytic geometry: plane and sphere depth, shading, shadows."""

import math

import cv2
import numpy as np
import pytest
import warp as wp

from ringscan.kernels.geometry import make_camera, make_parallel_light, make_perspective_light
from ringscan.kernels.raytrace import make_trace_mesh, shade_frame, trace_geometry
from ringscan.pipeline.formats.rig import look_at
from ringscan.pipeline.simulate.scenes import corner_normals, icosphere, make_chessboard, make_scene

W, H = 160, 128
DIST = np.array([0.02, -0.05, 0.001, -0.001, 0.0])


def _camera(dist=DIST):
    """A small camera like the default rig's: 35 deg off axis, 420 mm from (0, 0, 25)."""
    a = math.radians(35.0)
    target = np.array([0.0, 0.0, 25.0])
    eye = target + 420.0 * np.array([0.0, -math.sin(a), math.cos(a)])
    R, t = look_at(eye, target)
    K = np.array([[325.0, 0, (W - 1) / 2], [0, 325.0, (H - 1) / 2], [0, 0, 1.0]])
    return K, np.asarray(dist, float), R, t


def _light(R=np.eye(3), s=0.6, size=(256, 192)):
    return make_parallel_light(R, np.zeros(3), s, ((size[0] - 1) / 2, (size[1] - 1) / 2)), size


def _trace(device, scene, cam=None, light=None, ss=1, ambient=0.0, albedo=1.0):
    K, d, R, t = cam if cam is not None else _camera()
    li, size = light if light is not None else _light()
    cn = corner_normals(scene.vertices, scene.faces)
    mesh = make_trace_mesh(scene.vertices, scene.faces, cn, device=device)
    geo = trace_geometry(mesh, make_camera(K, d, R, t), li, width=W, height=H, projector_size=size,
                         supersample=ss, albedo=albedo, ambient=ambient)
    return geo, mesh


def test_plane_depth_is_exact(device):
    K, d, R, t = _camera()
    geo, _ = _trace(device, make_scene("plane"))
    depth, pts, lit = geo.depth.numpy(), geo.points.numpy().astype(np.float64), geo.lit.numpy()
    assert np.all(np.isfinite(depth))
    assert np.abs(pts[..., 2]).max() < 1e-4                              # on z = 0
    # The forward OpenCV model maps every centre-ray point back to its pixel centre.
    uv, _ = cv2.projectPoints(pts.reshape(-1, 3), cv2.Rodrigues(R)[0], t, K, d)
    v, u = np.mgrid[0:H, 0:W]
    assert np.abs(uv.reshape(H, W, 2) - np.stack([u, v], -1)).max() < 2e-3
    zc = (pts.reshape(-1, 3) @ R.T + t)[:, 2].reshape(H, W)
    assert np.abs(depth - zc).max() < 1e-3
    # Lit exactly where the point lies on the 256 x 192 px, 0.6 mm projector image.
    inside = (np.abs(pts[..., 0]) < 0.6 * 128 - 0.01) & (np.abs(pts[..., 1]) < 0.6 * 96 - 0.01)
    outside = (np.abs(pts[..., 0]) > 0.6 * 128 + 0.01) | (np.abs(pts[..., 1]) > 0.6 * 96 + 0.01)
    assert lit[inside].all() and not lit[outside].any() and inside.sum() > 1000 and outside.sum() > 1000


def test_sphere_depth_matches_ray_sphere(device):
    r, c = 40.0, np.array([0.0, 0.0, 40.0])
    scene = make_scene("sphere", size_mm=2 * r)
    K, _, R, t = _camera(dist=np.zeros(5))
    geo, _ = _trace(device, scene, cam=(K, np.zeros(5), R, t))
    depth = geo.depth.numpy()
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    dc = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    dw = dc @ R                                    # R^T d for each pixel (world, not unit)
    C = -R.T @ t
    # |C + s dw - c|^2 = r^2, s = camera depth since dc has z = 1.
    a = np.einsum("...i,...i", dw, dw)
    b = 2 * np.einsum("...i,...i", dw, C - c)
    cc = np.dot(C - c, C - c) - r * r
    disc = b * b - 4 * a * cc
    hit = disc > 0
    s = (-b - np.sqrt(np.where(hit, disc, 0))) / (2 * a)
    # The icosphere's facets lie inside the sphere by at most their sagitta.
    vv, ff = icosphere(6)
    sag = r * (1 - np.linalg.norm(vv[ff].mean(1), axis=1).min())
    X = C + s[..., None] * dw
    cos_inc = np.abs(np.einsum("...i,...i", (X - c) / r, dw)) / np.sqrt(a)
    sure = hit & (cos_inc > 0.2)                   # away from the silhouette
    assert sure.sum() > 2000 and sag < 3e-3
    # A ray meets a facet behind the sphere by at most sag / cos(incidence) along the ray.
    err = depth[sure] - s[sure]
    assert err.min() > -2e-4
    assert np.all(err < sag / cos_inc[sure] + 2e-4)
    assert np.median(err) < 3e-3
    # Pixels that miss the sphere see the plane.
    pts = geo.points.numpy()
    assert np.abs(pts[~hit][:, 2]).max() < 1e-4


def test_white_on_plane_is_exposure_times_albedo(device):
    geo, _ = _trace(device, make_scene("plane"), albedo=0.5, ambient=0.0)
    e = wp.array(np.ones((192, 256), np.float32), device=device)
    img = shade_frame(geo, e, full_irradiance=1.0 / 0.9, gamma=1.0, full_scale=65535).numpy()
    lit = geo.lit.numpy().astype(bool)
    assert np.abs(img[lit] / 65535.0 - 0.9 * 0.5).max() < 1e-4


@pytest.mark.parametrize("k,interp", [(1, "linear"), (3, "linear"), (1, "nearest")])
def test_brightness_follows_projector_frame(device, k, interp):
    """Parallel light: a pixel that sees (x, y, 0) records E at (x/s + a_u, y/s + a_v).

    E is given k times finer than the projector pixels: projector position u is
    fine position (u + 0.5) k - 0.5.
    """
    geo, _ = _trace(device, make_scene("plane"), albedo=1.0, ambient=0.0)
    vf, uf = np.mgrid[0:192 * k, 0:256 * k].astype(np.float32)
    E = 0.5 + 0.4 * np.sin(uf / (7.0 * k)) * np.cos(vf / (5.0 * k))
    img = shade_frame(geo, wp.array(E, device=device), upsample=k, interpolation=interp, full_irradiance=1.0,
                      gamma=1.0, full_scale=65535).numpy()
    pts = geo.points.numpy().astype(np.float64)
    u_p = (pts[..., 0] / 0.6 + 127.5 + 0.5) * k - 0.5
    v_p = (pts[..., 1] / 0.6 + 95.5 + 0.5) * k - 0.5
    inside = (u_p > 0) & (u_p < 256 * k - 1) & (v_p > 0) & (v_p < 192 * k - 1)
    if interp == "linear":
        expect = cv2.remap(E, u_p.astype(np.float32), v_p.astype(np.float32), cv2.INTER_LINEAR)
    else:
        expect = E[np.clip(np.rint(v_p), 0, 191).astype(int), np.clip(np.rint(u_p), 0, 255).astype(int)]
    assert inside.sum() > 1000
    assert np.abs(img[inside] / 65535.0 - expect[inside]).max() < 2e-3
    assert np.all(img[~geo.lit.numpy().astype(bool)] == 0)       # no ambient: unlit pixels are black


def test_sphere_shading_is_lambertian(device):
    """Interpolated normals: white light on the sphere records albedo * n.l of the true normal."""
    r = 40.0
    scene = make_scene("sphere", size_mm=2 * r)
    geo, _ = _trace(device, scene, albedo=1.0)
    img = shade_frame(geo, wp.array(np.ones((192, 256), np.float32), device=device), full_irradiance=1.0,
                      gamma=1.0, full_scale=65535).numpy() / 65535.0
    pts = geo.points.numpy()
    on_sphere = pts[..., 2] > 1.0
    n = (pts - [0, 0, r]) / r
    lit = geo.lit.numpy().astype(bool) & on_sphere & (n[..., 2] > 0.05)
    assert lit.sum() > 1000
    assert np.abs(img[lit] - n[..., 2][lit]).max() < 3e-3
    # The lower half faces away from the light: unlit, black without ambient.
    low = on_sphere & (n[..., 2] < -0.05)
    assert low.sum() > 50 and not geo.lit.numpy()[low].any() and np.all(img[low] == 0)


def test_cube_casts_shadow_of_tilted_light(device):
    """A light tilted 30 deg: plane points whose path to the light crosses the cube are unlit."""
    cube = make_scene("cube", size_mm=30.0)
    a = math.radians(30.0)
    RL = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    geo, _ = _trace(device, cube, light=_light(R=RL), ambient=0.1)
    pts = geo.points.numpy().astype(np.float64)
    lit = geo.lit.numpy().astype(bool)
    L = RL.T @ [0.0, 0.0, 1.0]                        # toward the light
    on_plane = np.abs(pts[..., 2]) < 1e-3
    # Slab test in the cube's frame (turned 30 deg about z, edge 30, from z = 0 to 30).
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    o = pts[on_plane] @ Rz
    dl = Rz.T @ L
    lo, hi = np.array([-15, -15, 0.0]), np.array([15, 15, 30.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / dl, (hi - o) / dl
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    shadow = (tmax > np.maximum(tmin, 0)) & (tmax - np.maximum(tmin, 0) > 0.5)   # clearly inside
    clear = (tmax < np.maximum(tmin, 0) - 0.5) | (tmax < 0)
    xy_in = (np.abs(pts[on_plane][:, 0]) < 70) & (np.abs(pts[on_plane][:, 1]) < 50)
    assert (shadow & xy_in).sum() > 100
    assert not lit[on_plane][shadow].any()
    assert lit[on_plane][clear & xy_in].all()
    # Shadowed plane pixels record ambient light only.
    img = shade_frame(geo, wp.array(np.ones((192, 256), np.float32), device=device), full_irradiance=1.1,
                      gamma=1.0, full_scale=65535).numpy() / 65535.0
    assert np.abs(img[on_plane][shadow] - 0.1 / 1.1).max() < 1e-4
    assert np.abs(img[on_plane][clear & xy_in] - (math.cos(a) + 0.1) / 1.1).max() < 1e-4   # n.l = cos 30


def test_perspective_light_smoke(device):
    f = 575.0 / 0.6
    Kp = np.array([[f, 0, 127.5], [0, f, 95.5], [0, 0, 1.0]])
    Rp, tp = look_at([0.0, 0.0, 600.0], [0.0, 0.0, 0.0])
    li = make_perspective_light(Kp, np.zeros(5), Rp, tp)
    scene = make_scene("cube", size_mm=30.0)
    geo, _ = _trace(device, scene, light=(li, (256, 192)))
    lit = geo.lit.numpy().astype(bool)
    pts = geo.points.numpy()
    assert lit.mean() > 0.2
    top = lit & (pts[..., 2] > 29.9)
    assert top.sum() > 50                                    # the cube's top is lit
    uv, _ = cv2.projectPoints(pts[lit].astype(np.float64), cv2.Rodrigues(Rp)[0], tp, Kp, np.zeros(5))
    uv = uv.reshape(-1, 2)
    assert np.all((uv > -0.5 - 1e-3) & (uv < np.array([255.5, 191.5]) + 1e-3))


def test_noise_is_seeded_and_has_sigma(device):
    geo, _ = _trace(device, make_scene("plane"), ambient=0.0, albedo=1.0)
    e = wp.array(np.full((192, 256), 0.5, np.float32), device=device)
    kw = dict(full_irradiance=1.0, gamma=1.0, full_scale=65535)
    clean = shade_frame(geo, e, **kw).numpy().astype(np.float64)
    a = shade_frame(geo, e, noise_sigma=300.0, seed=7, **kw).numpy().astype(np.float64)
    b = shade_frame(geo, e, noise_sigma=300.0, seed=7, **kw).numpy().astype(np.float64)
    c = shade_frame(geo, e, noise_sigma=300.0, seed=8, **kw).numpy().astype(np.float64)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    lit = geo.lit.numpy().astype(bool)
    assert abs(np.std(a[lit] - clean[lit]) / 300.0 - 1.0) < 0.05
    assert abs(np.mean(a[lit] - clean[lit])) < 15.0


def test_supersampling_antialiases_an_edge(device):
    """Half a pixel's sub-samples on a lit half-plane gives the pixel half the light."""
    geo1, _ = _trace(device, make_scene("plane"), ss=1)
    geo4, _ = _trace(device, make_scene("plane"), ss=4)
    E = np.zeros((192, 256), np.float32)
    E[:, 128:] = 1.0                                        # a vertical edge at u_p = 127.5
    e = wp.array(E, device=device)
    kw = dict(full_irradiance=1.0, gamma=1.0, full_scale=65535)
    i1 = shade_frame(geo1, e, **kw).numpy()
    i4 = shade_frame(geo4, e, **kw).numpy()
    grey1 = np.count_nonzero((i1 > 2000) & (i1 < 63000))
    grey4 = np.count_nonzero((i4 > 2000) & (i4 < 63000))
    assert grey4 > grey1                                    # more partly lit pixels at the edge
    # Total light is conserved (to the sampling error of the edge).
    assert abs(i4.astype(np.float64).sum() / i1.astype(np.float64).sum() - 1) < 0.01


def test_empty_scene_and_bad_input(device):
    geo, mesh = _trace(device, make_scene("plane"))
    assert mesh.mesh is None and geo.depth.shape == (H, W)
    with pytest.raises(ValueError, match="vertices"):
        make_trace_mesh(np.zeros((3, 2)), np.zeros((1, 3), np.int32), np.zeros((1, 3, 3)), device=device)
    with pytest.raises(ValueError, match="faces"):
        make_trace_mesh(np.zeros((3, 3)), np.array([[0, 1, 5]]), np.zeros((1, 3, 3)), device=device)
    with pytest.raises(ValueError, match="corner_normals"):
        make_trace_mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros((2, 3, 3)), device=device)
    with pytest.raises(ValueError, match="emitted"):
        shade_frame(geo, wp.zeros((4, 4), dtype=wp.uint8, device=device), full_irradiance=1.0)
    with pytest.raises(ValueError, match="upsample"):
        shade_frame(geo, wp.zeros((6, 6), dtype=float, device=device), full_irradiance=1.0, upsample=4)
    with pytest.raises(ValueError, match="interpolation"):
        shade_frame(geo, wp.zeros((6, 6), dtype=float, device=device), full_irradiance=1.0, interpolation="cubic")
    with pytest.raises(ValueError, match="supersample"):
        trace_geometry(mesh, make_camera(*_camera()), _light()[0], width=W, height=H, projector_size=(8, 8),
                       supersample=0)


def test_pixels_past_the_lens_fold_see_nothing(device):
    """A wide barrel lens that folds (k1 = -0.35, k2 = 0.05: OpenCV's projection of
    (r, 0, 1) turns back at r = 1.21): the renderer shares the reconstruction's
    undistortion, so a pixel without a true inverse must render as nothing (NaN
    truth, unlit, black) rather than as the far branch's point, which OpenCV also
    projects onto the pixel."""
    K, _, R, t = _camera()
    Kw = np.array([[87.5, 0, (W - 1) / 2], [0, 87.5, (H - 1) / 2], [0, 0, 1.0]])  # 700 px at 1280 wide, scaled
    dist = np.array([-0.35, 0.05, 0.0, 0.0, 0.0])
    geo, _ = _trace(device, make_scene("plane"), cam=(Kw, dist, R, t), ambient=0.3)
    depth, pts, lit = geo.depth.numpy(), geo.points.numpy().astype(np.float64), geo.lit.numpy()
    r = np.linspace(0, 2.0, 20001)
    ur = cv2.projectPoints(np.c_[r, 0 * r, 1 + 0 * r], np.zeros(3), np.zeros(3), np.eye(3), dist)[0][:, 0, 0]
    turn = np.argmax(np.diff(ur) <= 0)
    r_fold, reach = r[turn], ur[turn]
    v, u = np.mgrid[0:H, 0:W]
    rd = np.hypot(u - Kw[0, 2], v - Kw[1, 2]) / Kw[0, 0]
    past = rd > reach * 1.001
    assert past.sum() > 1000 and (~past).sum() > 1000
    assert np.all(np.isnan(depth[past])) and not lit[past].any()
    hit = np.isfinite(depth)
    assert hit[rd < reach * 0.99].all()
    # every point drawn is the true one: OpenCV maps it back to its pixel, from
    # inside the fold
    Xc = pts[hit] @ R.T + t
    assert np.hypot(Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]).max() < r_fold
    uv, _ = cv2.projectPoints(pts[hit], cv2.Rodrigues(R)[0], t, Kw, dist)
    assert np.abs(uv[:, 0] - np.stack([u[hit], v[hit]], -1)).max() < 0.01
    # and the frame shows nothing there: no ambient light either
    img = shade_frame(geo, wp.full((192, 256), 1.0, dtype=float, device=device), full_irradiance=1.3)
    assert np.all(img.numpy()[past] == 0) and np.all(img.numpy()[rd < reach * 0.99] > 0)


def test_face_albedo_prints_a_chessboard(device):
    """A mesh whose faces carry their own albedo (the chessboard scene): each camera
    pixel on the board records its square's albedo; the plane keeps the one albedo."""
    board = make_chessboard(5, 4, 12.0, thickness_mm=1.0, dark=0.1, light=0.7)
    cn = corner_normals(board.vertices, board.faces)
    mesh = make_trace_mesh(board.vertices, board.faces, cn, device=device, face_albedo=board.face_albedo)
    geo = trace_geometry(mesh, make_camera(*_camera()), _light()[0], width=W, height=H, projector_size=(256, 192),
                         supersample=1, albedo=0.5, ambient=0.0)
    img = shade_frame(geo, wp.array(np.ones((192, 256), np.float32), device=device), full_irradiance=1.0,
                      gamma=1.0, full_scale=65535).numpy() / 65535.0
    pts = geo.points.numpy().astype(np.float64)
    lit = geo.lit.numpy().astype(bool)
    top = lit & (np.abs(pts[..., 2] - 1.0) < 1e-3)
    # Square (i, j) of the 6 x 5 squares, i along x, j along y; black where i + j is even.
    i = np.floor(pts[..., 0] / 12.0 + 3.0)
    j = np.floor(pts[..., 1] / 12.0 + 2.5)
    fx, fy = pts[..., 0] / 12.0 + 3.0 - i, pts[..., 1] / 12.0 + 2.5 - j
    clear = top & (np.minimum(fx, 1 - fx) > 0.05) & (np.minimum(fy, 1 - fy) > 0.05)   # not on an edge
    on_board = clear & (i >= 0) & (i <= 5) & (j >= 0) & (j <= 4)
    dark = on_board & ((i + j) % 2 == 0)
    assert dark.sum() > 300 and (on_board & ~dark).sum() > 300
    assert np.abs(img[dark] - 0.1).max() < 1e-3 and np.abs(img[on_board & ~dark] - 0.7).max() < 1e-3
    assert np.abs(img[clear & ~on_board] - 0.7).max() < 1e-3                  # the white margin
    plane = lit & (np.abs(pts[..., 2]) < 1e-3)
    assert plane.sum() > 300 and np.abs(img[plane] - 0.5).max() < 1e-3
    with pytest.raises(ValueError, match="face_albedo"):
        make_trace_mesh(board.vertices, board.faces, cn, device=device, face_albedo=board.face_albedo[:-1])
    with pytest.raises(ValueError, match="face_albedo"):
        make_trace_mesh(board.vertices, board.faces, cn, device=device, face_albedo=board.face_albedo + 1.0)
