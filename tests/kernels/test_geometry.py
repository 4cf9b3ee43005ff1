"""kernels.geometry: the polar angle, the working volume and the lens model's inverse
(undistortion, fold-free regions), against hand-computed geometry and OpenCV (independent
code). The ring quadric's roots: test_ring_quadric.py."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import warp as wp

from ringscan.kernels import init_warp
from ringscan.kernels.geometry import (
    LENS_MIN_DET,
    R2_UNBOUNDED,
    CameraModel,
    Volume,
    distort,
    fold_free_radius2,
    in_lens_region,
    in_volume,
    locally_unfolded,
    make_camera,
    make_perspective_light,
    make_volume,
    monotonic_radius2,
    pole_radius2,
    polar_angle,
    sqrt_limit32,
    undistort,
)
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.geometry import undistort_normalized
from tests.support.opencv_lenses import STRONG_PROJECTOR, cv_min_det, cv_pixels

init_warp()


@wp.kernel
def _atan2_kernel(y: wp.array(dtype=float), x: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = polar_angle(y[i], x[i])


def test_polar_angle_matches_the_library(device):
    rng = np.random.default_rng(0)
    a = np.concatenate([rng.uniform(-np.pi, np.pi, 20000), np.arange(-4, 5) * np.pi / 4])
    r = np.concatenate([rng.uniform(1e-3, 10.0, 20000), np.ones(9)])
    y, x = (r * np.sin(a)).astype(np.float32), (r * np.cos(a)).astype(np.float32)
    x[-9:] = np.rint(x[-9:])  # exact axes and diagonals
    y[-9:] = np.rint(y[-9:])
    y = np.append(y, 0.0).astype(np.float32)
    x = np.append(x, 0.0).astype(np.float32)
    out = wp.zeros(y.size, dtype=float, device=device)
    wp.launch(_atan2_kernel, y.size, inputs=[wp.array(y, device=device), wp.array(x, device=device)], outputs=[out],
              device=device)
    got = out.numpy()
    err = np.angle(np.exp(1j * (got[:-1] - np.arctan2(y[:-1], x[:-1]))))
    assert np.abs(err).max() < 2e-5
    assert np.all(got > -np.pi - 1e-6) and np.all(got <= np.pi + 1e-6)
    assert got[-1] == 0.0  # atan2(0, 0) is 0 by convention


@pytest.mark.parametrize("bad", [np.zeros((2, 2)), np.eye(4)])
def test_perspective_light_rejects_a_wrong_size_matrix(bad):
    with pytest.raises(ValueError, match="make_camera"):
        make_perspective_light(bad, None, np.eye(3), np.zeros(3))


# ----------------------------------------------------------------------------- strong distortion against OpenCV

WIDE_K = np.array([[700.0, 0, 639.5], [0, 700.0, 511.5], [0, 0, 1]])
"""A wide-angle 1280x1024 camera: image corners at normalised radius 1.17."""
WIDE_LENSES = {
    # barrel that folds at r = 1.21 (OpenCV's own projection turns back there)
    # and rises again beyond r = 1.66: pixels past the fold's image have no
    # true inverse, but Newton can land on the far branch
    "radial": np.array([-0.35, 0.05, 0.0, 0.0, 0.0]),
    "tangential": np.array([-0.35, 0.05, 0.01, -0.01, 0.0]),
}


@wp.kernel
def _undistort_kernel(cam: CameraModel, uv: wp.array(dtype=wp.vec2), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    yd = (uv[i][1] - cam.cy) / cam.fy
    xd = (uv[i][0] - cam.cx - cam.skew * yd) / cam.fx
    out[i] = undistort(cam, xd, yd)


def _undistort(K, dist, uv, device):
    cam = make_camera(K, dist, np.eye(3), np.zeros(3))
    out = wp.zeros(len(uv), dtype=wp.vec3, device=device)
    wp.launch(_undistort_kernel, len(uv), inputs=[cam, wp.array(uv.astype(np.float32), dtype=wp.vec2, device=device)],
              outputs=[out], device=device)
    o = out.numpy().astype(np.float64)
    return o[:, :2], o[:, 2] > 0


@pytest.mark.parametrize("lens", sorted(WIDE_LENSES))
def test_undistort_inverts_opencv_inside_the_fold_free_region(device, lens):
    """Points where the lens is one to one (by OpenCV's projection) come back from
    their OpenCV pixels, flagged good; deep inside, OpenCV's own iterative
    undistortion agrees."""
    dist = WIDE_LENSES[lens]
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1.6, 1.6, (6000, 2))
    xy = xy[cv_min_det(xy, WIDE_K, dist) > 0.05][:2000]
    assert len(xy) > 500
    uv = cv_pixels(xy, WIDE_K, dist)
    got, ok = _undistort(WIDE_K, dist, uv, device)
    assert ok.all(), f"{np.count_nonzero(~ok)} good pixels flagged"
    assert np.abs(cv_pixels(got, WIDE_K, dist) - uv).max() < 0.01
    assert np.abs(got - xy).max() < 2e-4
    inner = cv_min_det(xy, WIDE_K, dist) > 0.5
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    pts = uv[inner].reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x; 5.x takes the criteria in undistortPoints
        ref = cv2.undistortPointsIter(pts, WIDE_K, dist, None, None, crit)[:, 0]
    else:
        ref = cv2.undistortPoints(pts, WIDE_K, dist, None, None, None, crit)[:, 0]
    assert np.abs(got[inner] - ref).max() < 2e-5


@pytest.mark.parametrize("lens", sorted(WIDE_LENSES))
def test_undistort_flags_pixels_without_a_true_inverse(device, lens):
    """Over the whole image of a strongly distorted lens: every pixel is either
    flagged or undistorted to a point that OpenCV projects back onto it *and*
    that lies in the fold-free region (not on the polynomial's far branch, which
    also projects onto the pixel). Past the image of the fold every pixel is
    flagged; well inside it none is."""
    dist = WIDE_LENSES[lens]
    v, u = np.mgrid[0:1024:8, 0:1280:8]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    got, ok = _undistort(WIDE_K, dist, uv, device)
    assert 0.1 < np.mean(~ok) < 0.6  # the scene exercises the fold
    assert np.abs(cv_pixels(got[ok], WIDE_K, dist) - uv[ok]).max() < 0.01
    assert cv_min_det(got[ok], WIDE_K, dist).min() > 0
    if lens == "radial":
        # the largest image radius a point of the fold-free region reaches:
        # where OpenCV's projection of (r, 0) first turns back
        r = np.linspace(0, 2.0, 40001)
        ur = (cv_pixels(np.c_[r, np.zeros_like(r)], WIDE_K, dist)[:, 0] - WIDE_K[0, 2]) / WIDE_K[0, 0]
        reach = ur[np.argmax(np.diff(ur) <= 0)]
        rd = np.hypot(uv[:, 0] - WIDE_K[0, 2], uv[:, 1] - WIDE_K[1, 2]) / WIDE_K[0, 0]
        assert not ok[rd > reach * 1.0001].any()
        assert ok[rd < reach * 0.98].all()


def test_undistort_default_camera_flags_nothing(device):
    """The default rig's mild lens: every pixel of its image has a true inverse."""
    c = default_rig().camera
    v, u = np.mgrid[0:c.height:16, 0:c.width:16]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    got, ok = _undistort(c.K, c.dist, uv, device)
    assert ok.all()
    assert np.abs(cv_pixels(got, c.K, c.dist) - uv).max() < 0.01


def test_monotonic_radius_is_where_opencv_turns_back():
    for dist in ([-0.35, 0.05, 0, 0, 0], [-0.4, 0, 0, 0, 0], [0.3, -0.2, 0, 0, 0.01]):
        r = np.linspace(0, 3.0, 300001)
        u = cv_pixels(np.c_[r, np.zeros_like(r)], np.eye(3), np.array(dist))[:, 0]
        turn = r[np.argmax(np.diff(u) <= 0)]
        assert abs(np.sqrt(monotonic_radius2(dist)) - turn) < 1e-4
    assert monotonic_radius2([0.02, 0.0, 0.0, 0.0, 0.0]) >= 1e29      # pincushion: never folds
    assert monotonic_radius2(None) >= 1e29


# ----------------------------------------------------------------------------- per-launch constants: the same answers, cheaper

REAL_CAMERA = np.array([-0.2223, -0.8661, -7.278e-4, -1.688e-3, 3.125])
"""A real camera's calibration (shared/data/procam): tangential terms, a large k3."""
FOLD_LENSES = {"default": np.array(default_rig().camera.dist, float), "real": REAL_CAMERA,
               **{f"wide-{k}": v for k, v in WIDE_LENSES.items()},
               **{f"projector-{k}": v for k, v in STRONG_PROJECTOR.items()}}


@wp.kernel
def _fold_checks_kernel(cam: CameraModel, xy: wp.array(dtype=wp.vec2), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    x = xy[i][0]
    y = xy[i][1]
    out[i] = wp.vec3(wp.where(in_lens_region(cam, x, y), 1.0, 0.0), wp.where(locally_unfolded(cam, x, y), 1.0, 0.0),
                     0.0)


@pytest.mark.parametrize("lens", sorted(FOLD_LENSES))
def test_fold_free_radius_has_its_margin_by_opencv(lens):
    """Inside fold_free_radius2 every point has a Jacobian determinant (of
    OpenCV's projection: independent code) of at least 2 LENS_MIN_DET, and the
    disc stays inside the monotonic radius; for the default and the real camera
    it covers the whole image (the fast path is the common path)."""
    dist = FOLD_LENSES[lens]
    s = fold_free_radius2(dist)
    assert 0 < s < monotonic_radius2(dist)
    rng = np.random.default_rng(5)
    r = np.sqrt(s) * np.sqrt(rng.uniform(0, 1, 4000))
    r[:400] = np.sqrt(s)  # the rim, where the margin is least
    a = rng.uniform(-np.pi, np.pi, r.size)
    xy = np.c_[r * np.cos(a), r * np.sin(a)]
    assert cv_min_det(xy, np.eye(3), dist, samples=1).min() > 2 * float(LENS_MIN_DET) - 1e-4
    if lens in ("default", "real"):
        assert s > 0.17  # the default camera's corners: r^2 = 0.10; the real one's 1280x1024 at f 3450: 0.05
    assert fold_free_radius2(None) == R2_UNBOUNDED
    assert fold_free_radius2([np.nan, 0, 0, 0, 0]) == 0.0


@pytest.mark.parametrize("lens", sorted(FOLD_LENSES))
def test_fold_checks_answer_as_the_full_test_does(device, lens):
    """The fold checks with the host's fold-free radius give the same answers as
    the full test (r2_safe = 0), inside the radius and out, and undistort gives
    the same bits over a whole image."""
    dist = FOLD_LENSES[lens]
    fast = make_camera(WIDE_K, dist, np.eye(3), np.zeros(3))
    full = make_camera(WIDE_K, dist, np.eye(3), np.zeros(3))
    full.r2_safe = 0.0
    rng = np.random.default_rng(9)
    r = np.r_[np.sqrt(fast.r2_safe) * rng.uniform(0, 2.5, 20000), rng.uniform(0, 3.0, 5000)]
    a = rng.uniform(-np.pi, np.pi, r.size)
    xy = wp.array(np.c_[r * np.cos(a), r * np.sin(a)].astype(np.float32), dtype=wp.vec2, device=device)
    got = []
    for cam in (fast, full):
        out = wp.zeros(r.size, dtype=wp.vec3, device=device)
        wp.launch(_fold_checks_kernel, r.size, inputs=[cam, xy], outputs=[out], device=device)
        got.append(out.numpy())
    np.testing.assert_array_equal(got[0], got[1])
    assert got[0][:, 0].any() and (r * r > fast.r2_safe).mean() > 0.5  # both paths taken
    v, u = np.mgrid[0:1024:4, 0:1280:4]
    uv = wp.array(np.stack([u.ravel(), v.ravel()], 1).astype(np.float32) + 0.25, dtype=wp.vec2, device=device)
    outs = []
    for cam in (fast, full):
        out = wp.zeros(uv.shape[0], dtype=wp.vec3, device=device)
        wp.launch(_undistort_kernel, uv.shape[0], inputs=[cam, uv], outputs=[out], device=device)
        outs.append(out.numpy())
    assert outs[0].tobytes() == outs[1].tobytes()


def test_a_lens_without_distortion_undistorts_to_itself(device):
    """No distortion: every pixel's normalised point comes back exactly, flagged
    good; a NaN pixel is flagged."""
    uv = np.array([[0.0, 0.0], [639.5, 511.5], [1279.0, 1023.0], [1e7, -3e6], [np.nan, 5.0]])
    cam = make_camera(WIDE_K, None, np.eye(3), np.zeros(3))
    out = wp.zeros(len(uv), dtype=wp.vec3, device=device)
    wp.launch(_undistort_kernel, len(uv), inputs=[cam, wp.array(uv.astype(np.float32), dtype=wp.vec2, device=device)],
              outputs=[out], device=device)
    o = out.numpy()
    yd = (uv[:, 1].astype(np.float32) - np.float32(511.5)) / np.float32(700.0)
    xd = (uv[:, 0].astype(np.float32) - np.float32(639.5) - np.float32(0.0) * yd) / np.float32(700.0)
    np.testing.assert_array_equal(o[:4, :2], np.c_[xd, yd][:4])
    assert o[:4, 2].tolist() == [1.0] * 4 and o[4, 2] == 0.0


def test_sqrt_limit_is_the_square_root_test():
    """s <= sqrt_limit32(r) exactly where float32 sqrt(s) <= float32(r)."""
    rng = np.random.default_rng(2)
    rs = np.r_[rng.uniform(0, 5000, 300), 10.0 ** rng.uniform(-30, 18, 100), [0.0, 1.0, 100.0, 3.4e38]]
    up = np.float32(np.inf)
    for r in rs:
        s = sqrt_limit32(r)
        r32 = np.float32(r)
        assert np.sqrt(s) <= r32
        with np.errstate(over="ignore"):
            assert not np.sqrt(np.nextafter(s, up)) <= r32
    assert sqrt_limit32(-1.0) < 0 and sqrt_limit32(np.nan) < 0 and sqrt_limit32(np.inf) == np.inf


@wp.kernel
def _volume_kernel(X: wp.array(dtype=wp.vec3), vol: Volume, out: wp.array(dtype=wp.vec2i)):
    i = wp.tid()
    p = X[i]
    ref = p[2] >= vol.z_min and p[2] <= vol.z_max and wp.sqrt(p[0] * p[0] + p[1] * p[1]) <= vol.r_max
    out[i] = wp.vec2i(wp.where(in_volume(p, vol), 1, 0), wp.where(ref, 1, 0))


def test_volume_radius_test_matches_the_square_root_to_the_bit(device):
    """in_volume (no square root) agrees with sqrt(x^2 + y^2) <= r_max on points
    within a few ulps of the volume's wall."""
    rng = np.random.default_rng(4)
    vol = make_volume(-3.0, 95.0, 100.0)
    n = 40000
    a = rng.uniform(-np.pi, np.pi, n)
    r = np.float32(100.0) * (1 + rng.integers(-40, 40, n) * np.float32(2 ** -24))
    X = np.c_[r * np.cos(a), r * np.sin(a), rng.uniform(0, 90, n)].astype(np.float32)
    out = wp.zeros(n, dtype=wp.vec2i, device=device)
    wp.launch(_volume_kernel, n, inputs=[wp.array(X, dtype=wp.vec3, device=device), vol], outputs=[out],
              device=device)
    o = out.numpy()
    np.testing.assert_array_equal(o[:, 0], o[:, 1])
    assert 0.2 < o[:, 1].mean() < 0.8


# ----------------------------------------------------------------------------- OpenCV's rational and thin-prism models

RATIONAL_LENSES = {
    # a wide-angle lens as CALIB_RATIONAL_MODEL fits them: large k1 and k4 that
    # nearly cancel, barrel of ~-0.3 r^2 over the field, no fold inside r = 1.6
    "rational": np.array([1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15]),
    # + CALIB_THIN_PRISM_MODEL's s1..s4
    "thin-prism": np.array([1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15, 0.002, -0.0005, -0.001, 0.0003]),
}
RATIONAL_FOLDS = {
    # radial (1 - 0.2 r^2) / (1 + 0.3 r^2): folds at r = 1.02, inside WIDE_K's corners (1.17)
    "rational-fold": np.array([-0.2, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0]),
    # the same with thin-prism terms: the fold-free region is no longer a disc
    "prism-fold": np.array([-0.2, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0, 0.02, 0.0, -0.01, 0.005]),
    # 1 / (1 - 0.8 r^2): no fold, but a pole at r = 1.118; past it a point lands on
    # the opposite side of the image, on a pixel a point inside also reaches
    "rational-pole": np.array([0.0, 0.0, 0.0, 0.0, 0.0, -0.8, 0.0, 0.0]),
}


@wp.kernel
def _distort_kernel(cam: CameraModel, xy: wp.array(dtype=wp.vec2), out: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    out[i] = distort(cam, xy[i][0], xy[i][1])


def _field_points(K, dist, n, seed, min_det=0.05):
    """Points of WIDE_K's field (a little beyond its corners) where OpenCV's projection is one to one."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1.2, 1.2, (3 * n, 2))
    return xy[cv_min_det(xy, K, dist) > min_det][:n]


@pytest.mark.parametrize("lens", sorted(RATIONAL_LENSES))
def test_rational_distort_is_opencvs(device, lens):
    """The kernels' distortion of an 8- and a 12-coefficient lens is cv2.projectPoints'
    to float32 precision: |x''| < 1.2 after ~20 float32 operations (relative error
    6e-8 each) is within 1e-6, 0.0007 px at f = 700 px."""
    dist = RATIONAL_LENSES[lens]
    cam = make_camera(np.eye(3), dist, np.eye(3), np.zeros(3))
    assert (cam.rational, cam.prism) == (1, int(dist.size == 12))
    xy = np.random.default_rng(1).uniform(-1.2, 1.2, (4000, 2)).astype(np.float32)
    out = wp.zeros(len(xy), dtype=wp.vec2, device=device)
    wp.launch(_distort_kernel, len(xy), inputs=[cam, wp.array(xy, dtype=wp.vec2, device=device)], outputs=[out],
              device=device)
    ref = cv_pixels(xy.astype(np.float64), np.eye(3), dist)
    assert np.abs(ref - xy).max() > 0.1  # a strong lens: a wrong term would show
    assert np.abs(out.numpy() - ref).max() < 1e-6


@pytest.mark.parametrize("lens", sorted(RATIONAL_LENSES))
def test_rational_undistort_inverts_opencv(device, lens):
    """Points where the lens is one to one come back from their OpenCV pixels,
    flagged good: round trip within 0.01 px (the kernels' own tolerance) and, as
    absolute values, within 2e-6 of the points and of OpenCV's iterative
    undistortion (float32 pixels of ~1000 carry 6e-5 px, 1e-7 normalised; Newton
    stops on a step below 1e-6 after its quadratic step, so what is left is
    float32 rounding, amplified by the inverse Jacobian, |J^-1| < 2 here)."""
    dist = RATIONAL_LENSES[lens]
    xy = _field_points(WIDE_K, dist, 2000, 3)
    assert len(xy) > 1500
    uv = cv_pixels(xy, WIDE_K, dist)
    got, ok = _undistort(WIDE_K, dist, uv, device)
    assert ok.all(), f"{np.count_nonzero(~ok)} good pixels flagged"
    assert np.abs(cv_pixels(got, WIDE_K, dist) - uv).max() < 0.01
    assert np.abs(got - xy).max() < 2e-6
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    pts = uv.reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):
        ref = cv2.undistortPointsIter(pts, WIDE_K, dist, None, None, crit)[:, 0]
    else:
        ref = cv2.undistortPoints(pts, WIDE_K, dist, None, None, None, crit)[:, 0]
    assert np.abs(got - ref).max() < 2e-6


@pytest.mark.parametrize("lens", sorted(RATIONAL_FOLDS))
def test_rational_undistort_drops_pixels_without_a_true_inverse(device, lens):
    """Over the whole image of a rational lens that folds (or has a pole): every
    pixel is either flagged or undistorted to a point that OpenCV projects back
    onto it *and* that lies in the fold-free region (before the pole, not on
    the far branch). Past the image of the fold every pixel is flagged, well
    inside it none is."""
    dist = RATIONAL_FOLDS[lens]
    v, u = np.mgrid[0:1024:8, 0:1280:8]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    got, ok = _undistort(WIDE_K, dist, uv, device)
    assert np.abs(cv_pixels(got[ok], WIDE_K, dist) - uv[ok]).max() < 0.01
    assert cv_min_det(got[ok], WIDE_K, dist).min() > 0
    assert (got[ok] ** 2).sum(1).max() < pole_radius2(dist)
    # every pixel that OpenCV's iterative undistortion inverts inside the region
    # (the host twin, pipeline.geometry) is inverted here too
    x, _y = undistort_normalized(SimpleNamespace(K=WIDE_K, dist=dist), uv[:, 0], uv[:, 1])
    assert np.isfinite(x).sum() > 0.4 * len(x) and not (np.isfinite(x) & ~ok).any()
    rd = np.hypot(uv[:, 0] - WIDE_K[0, 2], uv[:, 1] - WIDE_K[1, 2]) / WIDE_K[0, 0]
    if lens == "rational-pole":
        # the inner branch reaches every radius: every pixel has its inverse there
        assert pole_radius2(dist) == pytest.approx(1.25)
        assert ok.all()
        return
    assert 0.1 < np.mean(~ok) < 0.6  # the scene exercises the fold
    if lens == "rational-fold":
        r = np.linspace(0, 2.0, 40001)
        ur = (cv_pixels(np.c_[r, np.zeros_like(r)], WIDE_K, dist)[:, 0] - WIDE_K[0, 2]) / WIDE_K[0, 0]
        turn = np.argmax(np.diff(ur) <= 0)
        assert abs(np.sqrt(monotonic_radius2(dist)) - r[turn]) < 1e-4
        assert not ok[rd > ur[turn] * 1.0001].any()
        assert ok[rd < ur[turn] * 0.98].all()
    else:
        assert ok[rd < 0.5].all()  # the thin prism brings the fold's image in to r = 0.6 on one side


@pytest.mark.parametrize("lens", sorted({**RATIONAL_LENSES, **RATIONAL_FOLDS}))
def test_rational_fold_free_radius_has_its_margin_by_opencv(lens, monkeypatch):
    """The rational and thin-prism lenses' fold-free radius (their own bound:
    the radial factor's extremes taken exactly, so cancelling k1 and k4 count)
    holds its margin by OpenCV's projection, as the 5-coefficient one does."""
    monkeypatch.setitem(FOLD_LENSES, lens, {**RATIONAL_LENSES, **RATIONAL_FOLDS}[lens])
    test_fold_free_radius_has_its_margin_by_opencv(lens)
    if lens in RATIONAL_LENSES:  # a fitted wide-angle lens: the fast path covers WIDE_K's corners (r^2 = 1.37)
        assert fold_free_radius2(RATIONAL_LENSES[lens]) > 1.37


@pytest.mark.parametrize("lens", sorted({**RATIONAL_LENSES, **RATIONAL_FOLDS}))
def test_rational_fold_checks_answer_as_the_full_test_does(device, lens, monkeypatch):
    monkeypatch.setitem(FOLD_LENSES, lens, {**RATIONAL_LENSES, **RATIONAL_FOLDS}[lens])
    test_fold_checks_answer_as_the_full_test_does(device, lens)


def test_zero_extra_terms_are_the_five_coefficient_lens(device):
    """An 8-, 12- or 14-vector whose extra terms are 0 is the 5-coefficient lens,
    to the bit (its flags 0, its fold-free radius the 5-coefficient one)."""
    five = np.array([-0.35, 0.05, 0.01, -0.01, 0.0])
    v, u = np.mgrid[0:1024:8, 0:1280:8]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    outs = []
    for d in (five, np.r_[five, np.zeros(3)], np.r_[five, np.zeros(7)], np.r_[five, np.zeros(9)]):
        cam = make_camera(WIDE_K, d, np.eye(3), np.zeros(3))
        assert (cam.rational, cam.prism, cam.r2_safe) == (0, 0, fold_free_radius2(five))
        out = wp.zeros(len(uv), dtype=wp.vec3, device=device)
        wp.launch(_undistort_kernel, len(uv), inputs=[cam, wp.array(uv.astype(np.float32), dtype=wp.vec2,
                                                                      device=device)], outputs=[out], device=device)
        outs.append(out.numpy().tobytes())
    assert len(set(outs)) == 1


def test_a_tilted_sensor_is_refused():
    with pytest.raises(ValueError, match="tilted-sensor"):
        make_camera(WIDE_K, np.r_[np.zeros(12), 0.01, 0.0], np.eye(3), np.zeros(3))
    cam = make_camera(WIDE_K, np.r_[0.1, np.zeros(13)], np.eye(3), np.zeros(3))  # zero tilt: the 12-vector
    assert (cam.k1, cam.rational, cam.prism) == (pytest.approx(0.1), 0, 0)
