"""Host-side rig geometry (pipeline/geometry.py): OpenCV's undistortion is kept only
where it is a true inverse, the same pixels the kernels' undistortion accepts."""

import dataclasses

import cv2
import numpy as np
import pytest
import warp as wp

from ringscan.kernels import init_warp
from ringscan.kernels.geometry import CameraModel, make_camera, undistort
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.geometry import camera_rays, in_lens_region, undistort_normalized

init_warp()

WIDE_K = np.array([[700.0, 0, 639.5], [0, 700.0, 511.5], [0, 0, 1]])


@wp.kernel
def _undistort_kernel(cam: CameraModel, uv: wp.array(dtype=wp.vec2), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    yd = (uv[i][1] - cam.cy) / cam.fy
    xd = (uv[i][0] - cam.cx - cam.skew * yd) / cam.fx
    out[i] = undistort(cam, xd, yd)


def _grid(step=8):
    v, u = np.mgrid[0:1024:step, 0:1280:step]
    return np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)


@pytest.mark.parametrize("dist", [[-0.35, 0.05, 0.0, 0.0, 0.0], [-0.35, 0.05, 0.01, -0.01, 0.0],
                                  [-0.2, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0],  # OpenCV's rational model
                                  [-0.2, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0, 0.02, 0.0, -0.01, 0.005]])  # + thin prism
def test_host_undistortion_drops_what_has_no_true_inverse(dist):
    """A strongly distorted lens (it folds inside its image): every pixel the host
    keeps maps back onto itself through cv2.projectPoints from the fold-free
    region, past the fold the host gives NaN, and it drops the same pixels the
    kernels' undistortion flags (up to a few on the edge of the rule)."""
    dist = np.array(dist)
    cam = dataclasses.replace(default_rig().camera, K=WIDE_K, dist=dist)
    uv = _grid()
    x, y = undistort_normalized(cam, uv[:, 0], uv[:, 1])
    ok = np.isfinite(x)
    assert 0.1 < np.mean(~ok) < 0.6 and np.all(np.isnan(y[~ok]))
    back = cv2.projectPoints(np.c_[x[ok], y[ok], np.ones(ok.sum())], np.zeros(3), np.zeros(3), WIDE_K, dist)[0][:, 0]
    assert np.abs(back - uv[ok]).max() < 0.01
    assert in_lens_region(dist, x[ok], y[ok]).all()
    out = wp.zeros(len(uv), dtype=wp.vec3, device="cpu")
    wp.launch(_undistort_kernel, len(uv), inputs=[make_camera(WIDE_K, dist, np.eye(3), np.zeros(3)),
                                                  wp.array(uv.astype(np.float32), dtype=wp.vec2)], outputs=[out])
    k_ok = out.numpy()[:, 2] > 0
    assert np.count_nonzero(k_ok != ok) <= 0.002 * len(uv)
    # the rays of such pixels are NaN too, so nothing downstream can use them
    _, d = camera_rays(dataclasses.replace(default_rig(), camera=cam), uv)
    assert np.all(np.isnan(d[~ok])) and np.all(np.isfinite(d[ok]))


def test_host_undistortion_of_the_default_camera_keeps_every_pixel():
    cam = default_rig().camera
    uv = _grid(16)
    x, y = undistort_normalized(cam, uv[:, 0], uv[:, 1])
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(y))


def test_lens_region_of_a_radial_lens_is_its_monotonic_radius():
    dist = [-0.4, 0.0, 0.0, 0.0, 0.0]  # r (1 - 0.4 r^2) turns back at r = 1 / sqrt(1.2)
    r = np.array([0.0, 0.5, 0.9, 0.92, 1.5])
    assert in_lens_region(dist, r, 0 * r).tolist() == [True, True, True, False, False]
    assert not in_lens_region(dist, np.array([np.nan]), np.array([0.0]))[0]


def test_lens_region_of_a_rational_lens_ends_at_its_fold_or_pole():
    # (1 - 0.2 r^2) / (1 + 0.3 r^2): r times it turns back where 1 - 0.3 s - 0.06 s^2 = 0 (r = 1.0194)
    r = np.array([0.0, 0.5, 1.01, 1.03, 1.5])
    assert in_lens_region([-0.2, 0, 0, 0, 0, 0.3, 0, 0], r, 0 * r).tolist() == [True, True, True, False, False]
    # 1 / (1 - 0.8 r^2) never turns back, but has a pole at r = sqrt(1.25) = 1.118; with a tangential
    # term (the sampled test) the pole still ends the region
    r = np.array([0.0, 1.1, 1.117, 1.119, 2.0])
    for dist in ([0, 0, 0, 0, 0, -0.8, 0, 0], [0, 0, 1e-4, 0, 0, -0.8, 0, 0]):
        assert in_lens_region(dist, r, 0 * r).tolist() == [True, True, True, False, False]
