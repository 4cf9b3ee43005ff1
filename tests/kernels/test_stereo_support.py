"""Two cameras' support kernels (kernels.stereo_support) against float64 NumPy geometry."""

import cv2
import numpy as np
import pytest
import warp as wp

from ringscan.kernels.geometry import make_camera
from ringscan.kernels.stereo_support import epipolar_distances, epipolar_slopes
from tests.support.stereo_rig import CAM1, CAM2, project_points, surface_hits


def test_epipolar_distances_match_float64_geometry():
    """The kernel's epipolar distance against the float64 construction (OpenCV's undistortion,
    E = [t]x R): exact matches of a distorting pair lie on their lines (0 up to float32), and
    camera-2 pixels moved by known amounts keep the float64 distance within 1e-3 px (float32
    normalised coordinates: ~1e-7 of a 2600 px focal length, times the lens's stretch)."""

    rng = np.random.default_rng(3)
    uv1 = np.c_[rng.uniform(300, 980, 400), rng.uniform(250, 780, 400)]
    X = surface_hits(CAM1, uv1)
    X = X[np.isfinite(X).all(axis=1)]
    uv1, uv2 = project_points(CAM1, X), project_points(CAM2, X)
    uv2_moved = uv2 + rng.normal(0, 1.5, uv2.shape)
    R = CAM2.R @ CAM1.R.T
    t = CAM2.t - R @ CAM1.t
    t = t / np.linalg.norm(t)
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    cm1 = make_camera(CAM1.K, CAM1.dist, CAM1.R, CAM1.t)
    cm2 = make_camera(CAM2.K, CAM2.dist, CAM2.R, CAM2.t)
    scale = float(np.sqrt(CAM2.K[0, 0] * CAM2.K[1, 1]))

    def kernel(a, b):
        return epipolar_distances(wp.array(a.astype(np.float32), dtype=wp.vec2, device="cpu"),
                                  wp.array(b.astype(np.float32), dtype=wp.vec2, device="cpu"), camera1=cm1,
                                  camera2=cm2, E=E, scale=scale, threads=2).numpy()

    def reference(a, b):
        n1 = cv2.undistortPoints(a.reshape(-1, 1, 2), CAM1.K, CAM1.dist,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))[:, 0]
        n2 = cv2.undistortPoints(b.reshape(-1, 1, 2), CAM2.K, CAM2.dist,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))[:, 0]
        line = np.c_[n1, np.ones(len(n1))] @ E.T
        return np.abs(np.sum(line * np.c_[n2, np.ones(len(n2))], 1)) / np.hypot(line[:, 0], line[:, 1]) * scale

    # the float32 inputs are the reference's too: what is compared is the arithmetic
    uv1, uv2, uv2_moved = (a.astype(np.float32).astype(np.float64) for a in (uv1, uv2, uv2_moved))
    assert len(uv1) > 200
    exact = kernel(uv1, uv2)
    assert np.all(np.isfinite(exact)) and np.max(np.abs(exact - reference(uv1, uv2))) < 1e-3
    assert np.median(exact) < 2e-3
    moved = kernel(uv1, uv2_moved)
    assert np.max(np.abs(moved - reference(uv1, uv2_moved))) < 1e-3
    assert np.median(moved) > 0.3  # the moves are seen: ~N(0, 1.5) across the lines


def test_epipolar_slopes_sign_the_distance_and_measure_how_camera_1_moves_the_line():
    """The signed distance's size is :func:`epipolar_distances`' and its sign the side of the line a move
    puts camera 2's pixel on; the slope is the float64 derivative of the signed distance by camera 1's
    pixel (central differences of OpenCV's undistortion over 1e-3 px: the kernel's own differences over
    0.5 px in float32 keep it within 2 % where the line moves ~1 px a px)."""
    rng = np.random.default_rng(5)
    uv1 = np.c_[rng.uniform(300, 980, 300), rng.uniform(250, 780, 300)]
    X = surface_hits(CAM1, uv1)
    X = X[np.isfinite(X).all(axis=1)]
    uv1, uv2 = project_points(CAM1, X), project_points(CAM2, X)
    R = CAM2.R @ CAM1.R.T
    t = CAM2.t - R @ CAM1.t
    t = t / np.linalg.norm(t)
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    scale = float(np.sqrt(CAM2.K[0, 0] * CAM2.K[1, 1]))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)

    def signed(a, b):
        n1 = cv2.undistortPoints(a.reshape(-1, 1, 2), CAM1.K, CAM1.dist, criteria=crit)[:, 0]
        n2 = cv2.undistortPoints(b.reshape(-1, 1, 2), CAM2.K, CAM2.dist, criteria=crit)[:, 0]
        line = np.c_[n1, np.ones(len(n1))] @ E.T
        return np.sum(line * np.c_[n2, np.ones(len(n2))], 1) / np.hypot(line[:, 0], line[:, 1]) * scale

    # camera 2's pixels moved across their lines by +-0.6 px (each its own side)
    side = np.where(rng.random(len(uv1)) < 0.5, -1.0, 1.0)
    h = 1e-3
    grad = np.stack([(signed(uv1 + [h, 0], uv2) - signed(uv1 - [h, 0], uv2)) / (2 * h),
                     (signed(uv1 + [0, h], uv2) - signed(uv1 - [0, h], uv2)) / (2 * h)], 1)
    n_line = np.stack([(signed(uv1, uv2 + [h, 0]) - signed(uv1, uv2 - [h, 0])) / (2 * h),
                       (signed(uv1, uv2 + [0, h]) - signed(uv1, uv2 - [0, h])) / (2 * h)], 1)
    uv2_moved = (uv2 + 0.6 * side[:, None] * n_line / np.linalg.norm(n_line, axis=1, keepdims=True))
    uv1, uv2_moved = (a.astype(np.float32).astype(np.float64) for a in (uv1, uv2_moved))
    w = lambda a: wp.array(a.astype(np.float32), dtype=wp.vec2, device="cpu")  # noqa: E731
    cams = dict(camera1=make_camera(CAM1.K, CAM1.dist, CAM1.R, CAM1.t),
                camera2=make_camera(CAM2.K, CAM2.dist, CAM2.R, CAM2.t), E=E, scale=scale, threads=2)
    d, g2 = (a.numpy().astype(np.float64) for a in epipolar_slopes(w(uv1), w(uv2_moved), **cams))
    ref = signed(uv1, uv2_moved)
    assert len(d) > 150 and np.all(np.isfinite(d)) and np.all(np.isfinite(g2))
    assert np.max(np.abs(d - ref)) < 1e-3  # float32 arithmetic, as epipolar_distances
    assert np.all(np.sign(d) == np.sign(ref)) and np.median(np.abs(np.abs(d) - 0.6)) < 0.05
    unsigned = epipolar_distances(w(uv1), w(uv2_moved), **cams).numpy()
    assert np.max(np.abs(np.abs(d) - unsigned)) < 1e-5  # one construction
    g2_ref = np.sum(grad ** 2, 1)
    assert 0.3 < np.median(g2_ref) < 3  # the line moves about a pixel a pixel: the check is not vacuous
    assert np.max(np.abs(g2 / g2_ref - 1)) < 0.02


def _integer_view(rng, w=96, h=72, share=1.0):
    """A dense map of projector codes over a tilted plane with noise, ``share`` of them rounded to whole
    projector pixels (an imported Gray code without sub-pixel refinement), the rest sub-pixel; a hole."""
    y, x = np.mgrid[0:h, 0:w]
    u = 100 + 0.83 * x + 0.11 * y + rng.normal(0, 0.05, x.shape)
    v = 40 + 0.07 * x + 0.91 * y + rng.normal(0, 0.05, x.shape)
    keep = ~((x > 30) & (x < 40) & (y > 20) & (y < 28))
    pix = (y * w + x)[keep].astype(np.int32)
    p = np.stack([u[keep], v[keep]], 1)
    whole = rng.random(len(p)) < share
    frac = p - np.round(p)  # the sub-pixel codes kept clear of whole pixels (no accidental integer code)
    p = np.where(np.abs(frac) < 0.1, np.round(p) + np.copysign(0.1, frac), p)
    p[whole] = np.round(p[whole])
    sr = np.where(whole, 0.29, 0.05).astype(np.float32)
    st = np.where(whole, 0.29, 0.06).astype(np.float32)
    return p.astype(np.float32), sr, st, pix, w, h


@pytest.mark.parametrize("share", [0.01, 1.0])
def test_integer_codes_refined_on_the_device_are_the_numpy_statement(share):
    """A few integer codes: the NumPy statement sums their windows the same way (equal to the bit); every
    code integer: it sums them by the image's filters, in another order (float64 sums ~1e-16 apart; the
    plane's sigma, from the normal equations' inverse, ~1e-10: 1e-9 relative)."""
    from ringscan.kernels.stereo_support import RefineSettings, polar_sigmas, refine_codes
    from ringscan.pipeline.reconstruct.stereo import (INTEGER_TOLERANCE_PX, QUERY_FIT_CHI2, QUERY_MIN_PIXELS,
                                                      QUERY_WINDOW_PX, _polar_to_uv, refine_integer_codes)

    p, sr, st, pix, w, h = _integer_view(np.random.default_rng(3), share=share)
    center = (512.0, 384.0)
    settings = RefineSettings()
    settings.radius, settings.min_pixels = QUERY_WINDOW_PX, QUERY_MIN_PIXELS
    settings.max_chi2, settings.tolerance = QUERY_FIT_CHI2, INTEGER_TOLERANCE_PX
    got = refine_codes(wp.array(p, dtype=wp.vec2), wp.array(sr), wp.array(st), wp.array(pix), center=center, width=w,
                       height=h, settings=settings, threads=2)
    p64 = p.astype(np.float64)
    ref_p, ref_s, refined = refine_integer_codes(pix, p64, _polar_to_uv(p64, sr.astype(np.float64),
                                                                         st.astype(np.float64), center), width=w, height=h)
    bits = got["refined"].numpy()
    np.testing.assert_array_equal(bits, refined[:, 0] * 1 + refined[:, 1] * 2)
    assert got["count"] == int(refined.any(axis=1).sum()) > 0
    exact = share < 0.5
    check = np.testing.assert_array_equal if exact else (lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-9))
    check(got["proj64"].numpy(), ref_p)
    ref_sr, ref_st = polar_sigmas(wp.array(ref_p, dtype=wp.vec2d), wp.array(ref_s, dtype=wp.vec2d), center=center)
    check(got["sigma_rho64"].numpy(), ref_sr.numpy())
    check(got["sigma_tan64"].numpy(), ref_st.numpy())
    # float32 for the match, and the isotropic sigma
    np.testing.assert_array_equal(got["proj"].numpy(), got["proj64"].numpy().astype(np.float32))
    s64 = np.sqrt(0.5 * (got["sigma_rho64"].numpy() ** 2 + got["sigma_tan64"].numpy() ** 2))
    np.testing.assert_array_equal(got["sigma"].numpy(), s64.astype(np.float32))
    # a plane through 25 whole-pixel codes: a few times better than one code's 0.29 px
    if not exact:
        assert np.median(got["sigma_rho64"].numpy()[bits == 3]) < 0.15
