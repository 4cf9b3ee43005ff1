"""kernels.error_terms: the error model's per-sample work on the device, against its NumPy statements
(pipeline.reconstruct.error_scale) to the bit."""

import numpy as np
import warp as wp

from ringscan.kernels.error_terms import widen_for_slope, widen_sigmas
from ringscan.pipeline.reconstruct.error_scale import apply_error_model, region_scale


def _f32(a):
    return wp.array(np.asarray(a, np.float32), dtype=wp.float32, device="cpu")


def test_widened_sigmas_are_the_numpy_statements_to_the_bit():
    """k, a floor, the indirect share above its median, the light's gradient and a tile's factor: every
    term and their mix, samples inside the factors' tiles and outside them (and at negative positions)."""
    rng = np.random.default_rng(2)
    n = 30000
    s = rng.uniform(0.01, 0.5, n).astype(np.float32)
    b = rng.uniform(0, 0.6, n).astype(np.float32)
    g = rng.lognormal(np.log(0.05), 1.0, n).astype(np.float32)
    uv = rng.uniform(-40, 700, (n, 2)).astype(np.float32)
    regions = {"tile_px": 32, "scales": [[0, 0, 1.7], [3, 5, 2.25], [-1, 2, 1.3], [12, 1, 4.0]]}
    middle = float(np.median(b.astype(np.float64)))
    for k, f, px, gpx, reg in ((1.6, 0.0, 0.0, 0.0, None), (1.0, 0.12, 0.0, 0.0, None), (2.3, 0.05, 0.67, 0.0, None),
                               (1.0, 0.0, 0.0, 0.8, None), (1.2, 0.03, 0.9, 0.5, regions)):
        got = widen_sigmas(_f32(s), k=k, floor=f, indirect=_f32(b), indirect_px=px, indirect_median=middle,
                           shading=_f32(g), shading_px=gpx, uv=wp.array(uv, dtype=wp.vec2), regions=reg,
                           threads=2).numpy()
        w = apply_error_model(s, k, f, indirect_px=px, indirect=np.maximum(b.astype(np.float64) - middle, 0.0),
                              shading_px=gpx, shading=g)
        if reg is not None:
            w = (w * np.sqrt(region_scale(reg, uv))).astype(np.float32)
            assert np.count_nonzero(region_scale(reg, uv) != 1.0) > 100  # the tiles hold samples
        np.testing.assert_array_equal(got, w)


def _rings_on_a_plane(gu, gv, *, width=200, height=160, spacing=3.0, d0=400.0):
    """Samples along rings spacing px apart (one a pixel, as a ring's edge crossings are) whose depths
    along their rays lie on the plane d0 + gu u + gv v over the image (the camera at the origin, each
    point straight along +z at that depth: the kernel reads depths and image positions only)."""
    uv = []
    for r in np.arange(10.0, 70.0, spacing):
        th = np.linspace(0, 2 * np.pi, int(2 * np.pi * r), endpoint=False)
        uv.append(np.stack([100 + r * np.cos(th), 80 + r * np.sin(th)], 1))
    uv = np.concatenate(uv)
    pixel = (np.round(uv[:, 1]).astype(np.int64) * width + np.round(uv[:, 0]).astype(np.int64)).astype(np.int32)
    depth = d0 + gu * uv[:, 0] + gv * uv[:, 1]
    points = np.stack([np.zeros_like(depth), np.zeros_like(depth), depth], 1)
    return uv.astype(np.float32), pixel, points.astype(np.float32), width, height


def test_a_steep_surface_widens_sigma_by_its_depth_gradient():
    """widen_for_slope: a plane's depth gradient across the image read back from the points around each
    sample (exact for a plane, to float32 rounding of the depths: 1e-3 relative), and sigma grown to
    sqrt(s^2 + (position_px gradient)^2); points not placed and samples on one ring alone (a line: no
    gradient across it) keep theirs."""
    for gu, gv in ((0.0, 0.0), (0.3, -0.4), (2.0, 0.5)):
        uv, pixel, points, w, h = _rings_on_a_plane(gu, gv)
        n = len(uv)
        status = np.zeros(n, np.int32)
        status[::17] = 3  # not placed: neither widened nor used by their neighbours
        s = np.full(n, 0.01, np.float32)
        out, grad = widen_for_slope(wp.array(points, dtype=wp.vec3), wp.array(status, dtype=wp.int32), _f32(s),
                                    wp.array(uv, dtype=wp.vec2), wp.array(pixel, dtype=wp.int32), center=(0, 0, 0),
                                    width=w, height=h, position_px=0.04, threads=2)
        out, grad = out.numpy(), grad.numpy()
        placed = status == 0
        assert np.allclose(grad[placed], np.hypot(gu, gv), rtol=1e-3, atol=2e-4), (gu, gv)
        assert np.allclose(out[placed], np.sqrt(0.01 ** 2 + (0.04 * np.hypot(gu, gv)) ** 2), rtol=1e-4)
        assert np.array_equal(out[~placed], s[~placed]) and np.all(grad[~placed] == 0)
    # a dense code (a sample a pixel) reads its plane from its 3 x 3 pixels
    y, x = np.mgrid[0:40, 0:50].astype(np.float64)
    uv = np.stack([x.ravel(), y.ravel()], 1).astype(np.float32)
    pixel = (y.ravel() * 50 + x.ravel()).astype(np.int32)
    depth = 400 + 0.7 * x.ravel() - 0.2 * y.ravel()
    points = np.stack([0 * depth, 0 * depth, depth], 1).astype(np.float32)
    n = len(uv)
    out, grad = widen_for_slope(wp.array(points, dtype=wp.vec3), wp.zeros(n, dtype=wp.int32),
                                _f32(np.full(n, 0.01)), wp.array(uv, dtype=wp.vec2), wp.array(pixel, dtype=wp.int32),
                                center=(0, 0, 0), width=50, height=40, position_px=0.04, radius=1)
    corner = ((x == 0) | (x == 49)).ravel() & ((y == 0) | (y == 39)).ravel()  # 4 points: fewer than 6
    g = grad.numpy()
    assert np.allclose(g[~corner], np.hypot(0.7, 0.2), rtol=1e-3) and np.all(g[corner] == 0)
    # samples along one straight line (a ring's edge seen edge-on): no gradient across it, sigma kept
    u = np.arange(20.0, 180.0, 1.0)
    uv = np.stack([u, 0.3 * u + 20.0], 1).astype(np.float32)
    pixel = (np.round(uv[:, 1]).astype(np.int64) * 200 + np.round(uv[:, 0]).astype(np.int64)).astype(np.int32)
    points = np.stack([0 * u, 0 * u, 400 + 0.5 * u], 1).astype(np.float32)
    n = len(u)
    out, grad = widen_for_slope(wp.array(points, dtype=wp.vec3), wp.zeros(n, dtype=wp.int32),
                                _f32(np.full(n, 0.01)), wp.array(uv, dtype=wp.vec2), wp.array(pixel, dtype=wp.int32),
                                center=(0, 0, 0), width=200, height=160, position_px=0.04)
    assert np.all(grad.numpy() == 0) and np.all(out.numpy() == np.float32(0.01))


def _slope_numpy(uv, pixel, depth, placed, width, height, radius):
    """The plane fit of widen_for_slope stated in NumPy: for each placed sample, the placed points (the
    first at each pixel) in the (2 radius + 1)^2 pixels around its rounded position, the centred sums'
    2x2 solve; 0 with fewer than 6 points or a degenerate spread."""
    first = np.full(width * height, -1)
    for i in np.flatnonzero(placed)[::-1]:
        first[pixel[i]] = i
    g = np.zeros(len(uv))
    for i in np.flatnonzero(placed):
        x, y = (int(np.floor(c + 0.5)) for c in uv[i])
        js = [first[yy * width + xx] for yy in range(max(y - radius, 0), min(y + radius, height - 1) + 1)
              for xx in range(max(x - radius, 0), min(x + radius, width - 1) + 1) if first[yy * width + xx] >= 0]
        if len(js) < 6:
            continue
        du, dv = (uv[js] - uv[i]).astype(np.float64).T
        dd = depth[js] - depth[i]
        cuu, cuv, cvv = np.cov(np.stack([du, dv]), bias=True).ravel()[[0, 1, 3]] * len(js)
        bu, bv = len(js) * np.mean((du - du.mean()) * (dd - dd.mean())), len(js) * np.mean((dv - dv.mean()) * (dd - dd.mean()))
        det = cuu * cvv - cuv * cuv
        if det <= 0.05 * (0.5 * (cuu + cvv)) ** 2:
            continue
        g[i] = np.hypot((cvv * bu - cuv * bv) / det, (cuu * bv - cuv * bu) / det)
    return g


def test_the_slope_reads_every_point_in_its_square_on_a_rough_surface():
    """widen_for_slope on scattered samples over a rough surface (no plane: every point of the square
    moves the fit), some pixels holding two samples (the first counts), some not placed, the image's
    edges in reach: the gradients of the NumPy statement of the square's fit, to rounding."""
    rng = np.random.default_rng(3)
    w, h, n = 60, 45, 1500
    uv = np.stack([rng.uniform(-0.4, w - 0.6, n), rng.uniform(-0.4, h - 0.6, n)], 1).astype(np.float32)
    uv[1::50] = uv[::50][: len(uv[1::50])] + np.float32(0.1)  # a second sample at some pixels
    pixel = (np.floor(uv[:, 1] + 0.5).astype(np.int64) * w + np.floor(uv[:, 0] + 0.5).astype(np.int64)).astype(np.int32)
    depth = 400.0 + 0.3 * uv[:, 0] - 0.1 * uv[:, 1] + rng.normal(0, 0.5, n)
    points = np.stack([0 * depth, 0 * depth, depth], 1).astype(np.float32)
    status = np.where(rng.random(n) < 0.1, 3, 0).astype(np.int32)
    out, grad = widen_for_slope(wp.array(points, dtype=wp.vec3), wp.array(status, dtype=wp.int32),
                                _f32(np.full(n, 0.01)), wp.array(uv, dtype=wp.vec2), wp.array(pixel, dtype=wp.int32),
                                center=(0, 0, 0), width=w, height=h, position_px=0.04, radius=3, threads=2)
    want = _slope_numpy(uv, pixel, np.linalg.norm(points.astype(np.float64), axis=1), status == 0, w, h, 3)
    got = grad.numpy()
    assert (want > 0).mean() > 0.8
    # float32 out; the sums in another order (NumPy's means): 1e-5 relative
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
