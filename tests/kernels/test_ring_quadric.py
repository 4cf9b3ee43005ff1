"""kernels.ring_quadric: the ring quadric solve and its root rules against hand-computed
geometry and OpenCV (independent code), distorted projector roots converged or flagged."""

import cv2
import numpy as np
import pytest
import warp as wp

from ringscan.kernels.geometry import LightModel, Volume, make_parallel_light, make_perspective_light, make_volume
from ringscan.kernels.ring_quadric import ray_ring_roots, root_usable
from ringscan.pipeline.formats.rig import default_rig
from tests.support.opencv_lenses import RATIONAL_PROJECTOR, STRONG_PROJECTOR, cv_min_det


@wp.kernel
def _roots_kernel(C: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float),
                  light: LightModel, center: wp.vec2, vol: Volume,
                  roots: wp.array(dtype=wp.vec3), usable: wp.array(dtype=wp.vec2i), failed: wp.array(dtype=int)):
    i = wp.tid()
    r, f = ray_ring_roots(light, C[i], d[i], rho[i], center)
    roots[i] = r
    failed[i] = f
    u0 = int(0)
    u1 = int(0)
    if r[2] != 0.0:
        if root_usable(light, C[i] + d[i] * r[0], r[0], vol):
            u0 = 1
        if root_usable(light, C[i] + d[i] * r[1], r[1], vol):
            u1 = 1
    usable[i] = wp.vec2i(u0, u1)


def _roots(light, C, d, rho, center, vol, device, with_failed=False):
    n = len(rho)
    roots = wp.zeros(n, dtype=wp.vec3, device=device)
    usable = wp.zeros(n, dtype=wp.vec2i, device=device)
    failed = wp.zeros(n, dtype=int, device=device)
    wp.launch(_roots_kernel, n, inputs=[wp.array(C, dtype=wp.vec3, device=device),
                                        wp.array(d, dtype=wp.vec3, device=device),
                                        wp.array(rho, dtype=float, device=device), light, wp.vec2(*center), vol],
              outputs=[roots, usable, failed], device=device)
    if with_failed:
        return roots.numpy(), usable.numpy(), failed.numpy()
    return roots.numpy(), usable.numpy()


def test_parallel_light_roots_match_the_cylinder_by_hand(device):
    """Parallel light along z, pitch s, axis pixel a = c: ring rho is the cylinder
    x^2 + y^2 = (s rho)^2. A ray C + t d with d in the x-z plane through C = (x0, 0, z0)
    meets it where (x0 + t dx)^2 = (s rho)^2: t = (+-s rho - x0) / dx."""
    s = 0.25
    light = make_parallel_light(np.eye(3), np.zeros(3), s, (400.0, 300.0))
    C = np.array([[-100.0, 0.0, 300.0]] * 3, np.float32)
    d = np.array([[0.8, 0.0, -0.6], [0.6, 0.0, -0.8], [0.0, 1.0, 0.0]], np.float32)
    rho = np.array([40.0, 100.0, 40.0], np.float32)  # the third ray (x = -100 forever) misses ring 40 (10 mm)
    roots, usable = _roots(light, C, d, rho, (400.0, 300.0), make_volume(0, 500, 200), device)
    for i in range(2):
        r = s * rho[i]
        want = sorted([(r - C[i, 0]) / d[i, 0], (-r - C[i, 0]) / d[i, 0]])
        assert roots[i, 2] == 1.0
        np.testing.assert_allclose(roots[i, :2], want, rtol=1e-5)
        assert usable[i].tolist() == [1, 1]
    assert roots[2].tolist() == [0.0, 0.0, 0.0]


def test_root_rules_drop_roots_behind_the_camera_and_outside_the_volume(device):
    light = make_parallel_light(np.eye(3), np.zeros(3), 0.25, (0.0, 0.0))
    # from x = -5 inside the cylinder of radius 10: one root behind (t < 0), one ahead
    C = np.array([[-5.0, 0.0, 50.0], [-100.0, 0.0, 300.0]], np.float32)
    d = np.array([[1.0, 0.0, 0.0], [0.8, 0.0, -0.6]], np.float32)
    rho = np.array([40.0, 40.0], np.float32)
    roots, usable = _roots(light, C, d, rho, (0.0, 0.0), make_volume(0, 100, 200), device)
    assert roots[0, 0] < 0 < roots[0, 1] and usable[0].tolist() == [0, 1]
    # second ray: both meetings have z > 100 (the volume's top): none usable
    z = C[1, 2] + d[1, 2] * roots[1, :2]
    assert np.all(z > 100) and usable[1].tolist() == [0, 0]


def test_perspective_light_roots_lie_on_their_cone_by_opencv(device):
    """A projector (skewless K, no distortion, turned and moved): every root the
    solve returns projects, by cv2.projectPoints, onto the circle |p - c| = rho."""
    K = np.array([[1400.0, 0, 512], [0, 1400.0, 384], [0, 0, 1]])
    rvec = np.array([0.3, -0.2, 0.1])
    R = cv2.Rodrigues(rvec)[0]
    t = np.array([20.0, -10.0, 600.0])
    light = make_perspective_light(K, None, R, t)
    center = (520.0, 390.0)
    rng = np.random.default_rng(1)
    n = 200
    C = np.tile(np.array([[250.0, -150.0, 500.0]]), (n, 1))
    target = rng.uniform([-60, -60, 0], [60, 60, 80], size=(n, 3))
    d = target - C
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rho = rng.uniform(20, 300, n)
    roots, usable = _roots(light, C.astype(np.float32), d.astype(np.float32), rho.astype(np.float32), center,
                           make_volume(-1000, 1000, 1000), device)
    real = roots[:, 2] == 1.0
    assert real.sum() > n // 2
    for m in range(2):
        ok = real & (usable[:, m] == 1)
        X = C[ok] + d[ok] * roots[ok, m:m + 1]
        p = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, t, K, None)[0].reshape(-1, 2)
        np.testing.assert_allclose(np.hypot(p[:, 0] - center[0], p[:, 1] - center[1]), rho[ok], atol=0.05)


def test_empty_input_launches_nothing(device):
    light = make_parallel_light(np.eye(3), np.zeros(3), 0.25, (0.0, 0.0))
    z = np.zeros((0, 3), np.float32)
    roots, usable = _roots(light, z, z, np.zeros(0, np.float32), (0.0, 0.0), make_volume(0, 1, 1), device)
    assert roots.shape == (0, 3) and usable.shape == (0, 2)


@pytest.mark.parametrize("lens", sorted({**STRONG_PROJECTOR, **RATIONAL_PROJECTOR}))
def test_distorted_projector_roots_are_on_their_ring_or_flagged(device, lens):
    """Every root of a strongly distorted projector's ring that is not flagged as
    failed lies, by cv2.projectPoints, on its ring within 0.01 px, and in the
    lens's fold-free region (5-, 8- and 12-coefficient lenses)."""
    rig = default_rig(light_model="perspective")
    L = rig.light
    dist = {**STRONG_PROJECTOR, **RATIONAL_PROJECTOR}[lens]
    light = make_perspective_light(L.K, dist, L.R, L.t)
    center = (511.5, 383.5)
    rng = np.random.default_rng(7)
    n = 3000
    C = np.tile(rig.camera.center, (n, 1))
    target = rng.uniform([-80, -80, 0], [80, 80, 60], size=(n, 3))
    d = target - C
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rho = rng.uniform(20, 450, n)
    roots, usable, failed = _roots(light, C.astype(np.float32), d.astype(np.float32), rho.astype(np.float32), center,
                                   make_volume(-1000, 1000, 1000), device, with_failed=True)
    real = roots[:, 2] == 1.0
    rvec = cv2.Rodrigues(L.R)[0]
    kept = 0
    for m in range(2):
        good = real & (usable[:, m] == 1) & ((failed & (1 << m)) == 0)
        X = C[good] + d[good] * roots[good, m:m + 1]
        p = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, L.t, L.K, dist)[0].reshape(-1, 2)
        np.testing.assert_allclose(np.hypot(p[:, 0] - center[0], p[:, 1] - center[1]), rho[good], atol=0.01)
        Xp = X @ L.R.T + L.t
        assert cv_min_det(Xp[:, :2] / Xp[:, 2:], np.eye(3), dist).min() > 0
        kept += good.sum()
    assert kept > n // 2
