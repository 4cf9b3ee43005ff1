"""Line centres, ring roots and gap links of the single-shot ``rings`` codec,
against images and geometry whose answer is known."""

import cv2
import numpy as np
import pytest
import warp as wp

from ringscan.kernels.geometry import make_camera, make_parallel_light, make_perspective_light
from ringscan.kernels.ring_lines import centre_sigmas, detect_ring_lines, smooth_frame
from ringscan.kernels.ring_links import link_lines, ring_roots
from ringscan.kernels.settings import LineSettings
from ringscan.pipeline.formats.rig import default_rig
from tests.support.ring_lines_image import CENTER, RADII, circles_image


def _detect(img, device, **kw):
    return detect_ring_lines(wp.array(img[None], device=device), **kw)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_centres_lie_on_the_circles(device, dtype):
    lines = _detect(circles_image(dtype=dtype, noise=1.0), device)
    d = lines.numpy()
    r = np.hypot(d["uv"][:, 0] - CENTER[0], d["uv"][:, 1] - CENTER[1])
    k = np.argmin(np.abs(r[:, None] - np.array(RADII)[None]), 1)
    err = r - np.array(RADII)[k]
    # every circle is found all round: about 2 pi r centres each (one per pixel)
    counts = np.bincount(k, minlength=len(RADII))
    assert np.all(counts > 0.6 * 2 * np.pi * np.array(RADII)), counts
    assert np.all(counts < 1.6 * 2 * np.pi * np.array(RADII)), counts
    assert np.abs(err).max() < 0.12
    assert np.median(np.abs(err)) < 0.04
    # normals point across the line (radially)
    radial = (d["uv"] - np.array(CENTER)) / r[:, None]
    assert np.all(np.abs(np.sum(radial * d["normal"], 1)) > 0.97)
    # contrast in 8-bit grey levels whatever the depth; confidence in (0, 1]
    assert np.median(d["contrast"]) > 50 and np.all((d["confidence"] > 0) & (d["confidence"] <= 1))
    H, W = 160, 200
    assert np.array_equal(d["pixel"], np.rint(d["uv"][:, 1]).astype(int) * W + np.rint(d["uv"][:, 0]).astype(int))
    assert np.all(np.diff(d["pixel"]) > 0)  # raster order, one centre per pixel
    assert lines.smoothed.shape == (H, W)


def test_line_centre_is_unbiased_by_blur_and_width(device):
    # a straight line at a sub-pixel position: its centre, whatever the blur
    for x0, width, blur in ((60.3, 3.0, 0.5), (60.71, 5.0, 1.5), (61.05, 2.0, 1.0)):
        s = 16
        uu = (np.arange(120 * s) + 0.5) / s - 0.5
        prof = (np.abs(uu - x0) <= width / 2).reshape(120, s).mean(1)
        img = cv2.GaussianBlur(50 + 100 * prof[None, :].repeat(40, 0), (0, 0), blur)
        d = _detect(np.rint(img).astype(np.uint8), device).numpy()
        assert len(d["uv"]) >= 30
        assert np.abs(d["uv"][:, 0] - x0).max() < 0.05, (x0, width, blur)


def _line_image(x0, *, rows=200, cols=64, noise=0.0, shade=0.0, step=0.0, seed=0):
    """A 3 px wide line at column x0, 100 levels on 20, blurred by 1.5 px, as 16-bit (x257: no rounding
    of 8-bit levels); ``shade``: the light's log-gradient at 45 deg to it (as steep along as across);
    ``step``: the background ``step`` levels higher on its right."""
    s = 16
    uu = (np.arange(cols * s) + 0.5) / s - 0.5
    prof = (np.abs(uu - x0) <= 1.5).reshape(cols, s).mean(1)
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    light = np.exp(shade * ((x - x0) + (y - rows / 2)) / np.sqrt(2.0))
    img = cv2.GaussianBlur(100 * prof[None, :] * light + 20 + step * (x > x0), (0, 0), 1.5)
    img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.rint(img * 257), 0, 65535).astype(np.uint16)


def test_centre_sigma_is_the_scatter_of_the_centres(device):
    """centre_sigmas: the noise of the smoothed gradient over the curvature, against how far ~3800
    centres of a line at sub-pixel positions across a pixel move in 1.5 and 3 levels of noise (each
    against the same pixel's centre without noise: the estimator's own sub-pixel bias, ~0.02 px RMS
    for this line, is the same in both and left out)."""
    for noise in (1.5, 3.0):
        moved, pred = [], []
        for i, x0 in enumerate(np.linspace(30.0, 31.0, 21)):
            clean = _detect(_line_image(x0), device).numpy()
            d = _detect(_line_image(x0, noise=noise, seed=i), device).numpy()
            at = dict(zip(clean["pixel"], clean["uv"][:, 0]))
            m = (d["uv"][:, 1] > 10) & (d["uv"][:, 1] < 190) & np.isin(d["pixel"], clean["pixel"])
            moved.append(d["uv"][m, 0] - np.array([at[p] for p in d["pixel"][m]]))
            pred.append(centre_sigmas(d["curvature"][m], sigma=LineSettings().sigma, noise=noise))
        moved, pred = np.concatenate(moved), np.concatenate(pred)
        assert moved.size > 3000
        # 10 %: the model leaves out the curvature's own noise (~5 % at |t| = 0.5 px); a std of ~3000
        # centres is known to ~2 %
        assert np.std(moved) == pytest.approx(np.median(pred), rel=0.1), noise
        assert np.median(pred) == pytest.approx(0.0104 * noise, rel=0.1)  # hundredths of a px a level


def test_shading_bounds_a_light_gradient_and_a_tilted_background(device):
    """``shading``: ~0 on an evenly lit line; under a gradient of the light it grows with it and is no
    less than the shift it causes (a bound: all blur counted before the surface); a background
    higher on one side shows too."""
    def centre(img):
        d = _detect(img, device).numpy()
        m = (d["uv"][:, 1] > 80) & (d["uv"][:, 1] < 120)
        return float(np.median(d["uv"][m, 0])), float(np.median(d["shading"][m]))

    x0 = 30.3
    _, flat = centre(_line_image(x0))
    assert flat < 0.02
    (u1, s1), (u2, s2) = centre(_line_image(x0, shade=0.05)), centre(_line_image(x0, shade=0.1))
    assert s1 >= abs(u1 - x0) > 0.01 and s2 >= abs(u2 - x0)
    assert s2 / s1 == pytest.approx(2.0, rel=0.1)  # linear in the gradient
    (_, t1), (_, t2) = centre(_line_image(x0, step=5.0)), centre(_line_image(x0, step=10.0))
    assert t1 > 0.02 and t2 / t1 == pytest.approx(2.0, rel=0.25)


def test_shading_reads_no_gradient_into_evenly_lit_lines_across_the_pixels(device):
    """``shading`` on evenly lit circles (every slope of the line against the pixel grid, no noise): the
    crest read 2 px either side along the line by a quadratic about the nearest pixel shows no light
    gradient; read bilinearly it showed ~0.011 px (a bilinear read of a crest errs by up to an eighth
    of its curvature, differently at each sub-pixel place): on a bare plane that made the single-shot
    codec's sigmas 2.6x its errors. 0.006: what is left (the circles' own curvature and the 16-bit
    levels) is ~0.004."""
    for blur in (0.8, 1.5):
        d = _detect(circles_image(blur=blur, dtype=np.uint16), device).numpy()
        assert d["shading"].size > 1000 and np.median(d["shading"]) < 0.006, blur


def test_flat_and_empty_frames_give_no_centres(device):
    for img in (np.full((60, 80), 77, np.uint8), np.zeros((60, 80), np.uint16), np.zeros((0, 0), np.uint8)):
        lines = _detect(img, device)
        assert len(lines) == 0 and lines.uv.shape == (0,) and lines.pixel.shape == (0,)


def test_weak_lines_and_noise_are_rejected(device):
    img = circles_image(level=4.0, noise=1.5)  # lines 4 grey levels high: below min_contrast
    assert len(_detect(img, device)) == 0
    noise = np.clip(np.random.default_rng(1).normal(60, 2.0, (120, 160)), 0, 255).astype(np.uint8)
    assert len(_detect(noise, device)) < 20


def test_threads_do_not_change_the_result():
    fr = wp.array(circles_image(noise=1.0)[None], device="cpu")
    a = detect_ring_lines(fr, threads=1).numpy()
    b = detect_ring_lines(fr, threads=3).numpy()
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_bad_input():
    with pytest.raises(ValueError, match="3D Warp array"):
        detect_ring_lines(np.zeros((1, 10, 10), np.uint8))
    with pytest.raises(ValueError, match="uint8 or uint16"):
        detect_ring_lines(wp.zeros((1, 10, 10), dtype=wp.float32, device="cpu"))
    with pytest.raises(ValueError, match="frame 2"):
        detect_ring_lines(wp.zeros((1, 10, 10), dtype=wp.uint8, device="cpu"), frame=2)
    with pytest.raises(ValueError, match="sigma"):
        LineSettings(sigma=0.0)
    with pytest.raises(ValueError, match="min_contrast"):
        LineSettings(min_contrast=-1.0)
    with pytest.raises(ValueError, match="LineSettings"):
        detect_ring_lines(wp.zeros((1, 10, 10), dtype=wp.uint8, device="cpu"), settings={"sigma": 1})


def test_smoothing_keeps_the_mean_and_scales_16_bit(device):
    img = circles_image()
    s8 = smooth_frame(wp.array(img[None], device=device), sigma=1.5).numpy()
    s16 = smooth_frame(wp.array(img[None].astype(np.uint16) * 257, device=device), sigma=1.5).numpy()
    assert abs(s8.mean() - img.mean()) < 0.5
    assert np.allclose(s8, s16, atol=1e-3)
    ref = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.5, borderType=cv2.BORDER_REPLICATE)
    assert np.abs(s8 - ref)[5:-5, 5:-5].max() < 0.05


# ----------------------------------------------------------------------------- ring roots


@pytest.mark.parametrize("model", ["parallel", "perspective"])
def test_ring_roots_find_the_point(device, model):
    rig = default_rig(light_model=model)
    c, L = rig.camera, rig.light
    cam = make_camera(c.K, c.dist, c.R, c.t)
    rng = np.random.default_rng(3)
    n = 300
    P = np.c_[rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), rng.uniform(0, 60, n)]
    if model == "parallel":
        light = make_parallel_light(L.R, L.t, L.pixel_pitch_mm, L.axis_px)
        pp = P[:, :2] / L.pixel_pitch_mm + L.axis_px
    else:
        light = make_perspective_light(L.K, L.dist, L.R, L.t)
        pp = cv2.projectPoints(P, cv2.Rodrigues(L.R)[0], L.t, L.K, L.dist)[0][:, 0]
    center = (511.5, 383.5)
    rho = np.hypot(pp[:, 0] - center[0], pp[:, 1] - center[1])
    uv = cv2.projectPoints(P, cv2.Rodrigues(c.R)[0], c.t, c.K, c.dist)[0][:, 0].astype(np.float32)
    radii = np.array([rho[0], rho[1], 50.0])
    R = ring_roots(wp.array(uv, dtype=wp.vec2, device=device), np.concatenate([rho, radii]), camera=cam,
                   light=light, volume=(-3.0, 95.0, 100.0), center=center)
    X, off, val = R.points.numpy(), R.offset.numpy(), R.valid.numpy()
    assert X.shape == (n, n + 3, 2, 3) and val.shape == (n, n + 3)
    own = np.arange(n)
    Xo, vo = X[own, own], val[own, own]
    d = np.linalg.norm(Xo - P[:, None, :], axis=2)
    d[~np.stack([(vo & 1) > 0, (vo & 2) > 0], 1)] = np.inf
    assert np.all(d.min(1) < 1e-2), d.min(1).max()  # each point is one of its ring's roots
    k = np.argmin(d, 1)
    # the offset of a root is its place on the pattern: radius rho, polar angle of p - c
    o = off[own, own, k]
    assert np.allclose(np.hypot(o[:, 0], o[:, 1]), rho, atol=1e-2)
    assert np.abs(o - (pp - np.array(center))).max() < 0.1
    # roots outside the volume are invalid (and zero): every point lies below z = 60
    R2 = ring_roots(wp.array(uv, dtype=wp.vec2, device=device), np.concatenate([rho, radii]), camera=cam,
                    light=light, volume=(70.0, 95.0, 100.0), center=center)
    X2, v2 = R2.points.numpy()[own, own], R2.valid.numpy()[own, own]
    ok2 = np.stack([(v2 & 1) > 0, (v2 & 2) > 0], 1)
    assert np.all((X2[..., 2] >= 70) & (X2[..., 2] <= 95) | ~ok2)
    assert np.all(X2[~ok2] == 0)
    assert np.all(np.linalg.norm(X2 - P[:, None, :], axis=2)[ok2] > 5)


def test_ring_roots_bad_input():
    rig = default_rig()
    c, L = rig.camera, rig.light
    cam = make_camera(c.K, c.dist, c.R, c.t)
    light = make_parallel_light(L.R, L.t, L.pixel_pitch_mm, L.axis_px)
    uv = wp.zeros(3, dtype=wp.vec2, device="cpu")
    with pytest.raises(ValueError, match="uv"):
        ring_roots(np.zeros((3, 2)), [10.0], camera=cam, light=light, volume=(0, 1, 1), center=(0, 0))
    with pytest.raises(ValueError, match="radii"):
        ring_roots(uv, [np.nan], camera=cam, light=light, volume=(0, 1, 1), center=(0, 0))
    with pytest.raises(ValueError, match="volume"):
        ring_roots(uv, [10.0], camera=cam, light=light, volume=(1, 0, 1), center=(0, 0))
    R = ring_roots(wp.zeros(0, dtype=wp.vec2, device="cpu"), [10.0], camera=cam, light=light, volume=(0, 1, 1),
                   center=(0, 0))
    assert R.points.shape == (0, 1, 2)


# ----------------------------------------------------------------------------- links across the gaps


def _parallel_lines(xs, faint=None, h=60, w=200):
    img = np.full((h, w), 50.0)
    for x in xs:
        img[:, x - 1:x + 2] += 100.0
    if faint is not None:
        img[:, faint] += 10.0
    return np.rint(cv2.GaussianBlur(img, (0, 0), 0.8)).astype(np.uint8)


def _links(img, device, max_gap=40.0):
    lines = _detect(img, device)
    d = lines.numpy()
    piece = np.rint(d["uv"][:, 0] / 10).astype(np.int32)  # one piece per line
    n = wp.array(np.abs(d["normal"]).astype(np.float32), dtype=wp.vec2, device=device)  # +x is side 0
    nb, gap, bump = link_lines(lines.uv, n, wp.array(piece, device=device), image=lines.smoothed, pixel=lines.pixel,
                               max_gap=max_gap)
    return d, nb.numpy(), gap.numpy(), bump.numpy()


def test_links_meet_the_next_line_across_a_clean_gap(device):
    d, nb, gap, bump = _links(_parallel_lines([40, 60, 85, 130]), device)
    x = d["uv"][:, 0]
    inner = (d["uv"][:, 1] > 5) & (d["uv"][:, 1] < 54)
    for x0, right, left in ((40, 60, None), (60, 85, 40), (85, None, 60), (130, None, None)):
        m = inner & (np.abs(x - x0) < 0.5)
        assert m.sum() > 40
        if right is None:
            assert np.all(nb[m, 0] == -1)  # 130 - 85 = 45 > max_gap
        else:
            assert np.all(np.abs(x[nb[m, 0]] - right) < 0.5)
            assert np.allclose(gap[m, 0], right - x0, atol=0.6)
        if left is None:
            assert np.all(nb[m, 1] == -1)
        else:
            assert np.all(np.abs(x[nb[m, 1]] - left) < 0.5)
    assert not bump[inner].any()


def test_a_faint_line_in_the_gap_is_a_bump(device):
    d, nb, gap, bump = _links(_parallel_lines([40, 70], faint=55), device)
    x = d["uv"][:, 0]
    inner = (d["uv"][:, 1] > 5) & (d["uv"][:, 1] < 54)
    m = inner & (np.abs(x - 40) < 0.5)
    assert np.all(np.abs(x[nb[m, 0]] - 70) < 0.5)  # the faint line is no centre ...
    assert np.all(bump[m, 0] == 1)                   # ... but the gap is not clean


def test_link_lines_bad_input(device):
    lines = _detect(_parallel_lines([40, 60]), device)
    n = lines.uv.shape[0]
    with pytest.raises(ValueError, match="piece"):
        link_lines(lines.uv, lines.normal, wp.zeros(n + 1, dtype=wp.int32, device=device), image=lines.smoothed,
                   pixel=lines.pixel, max_gap=10.0)
    with pytest.raises(ValueError, match="image"):
        link_lines(lines.uv, lines.normal, wp.zeros(n, dtype=wp.int32, device=device), image=lines.pixel,
                   pixel=lines.pixel, max_gap=10.0)
    with pytest.raises(ValueError, match="max_gap"):
        link_lines(lines.uv, lines.normal, wp.zeros(n, dtype=wp.int32, device=device), image=lines.smoothed,
                   pixel=lines.pixel, max_gap=0.0)
