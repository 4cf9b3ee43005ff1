"""Two cameras that see about one projector pixel per camera pixel (issue 34): OpenCV's Gray code
rendered on a scaled-down copy of a public capture's rig (tests/support/one_to_one.py:
two cameras 40 mm apart, a plane 1 m away, 1.1 projector px per camera px), imported as it comes
(about half the pixels sub-pixel, the rest integer codes) and with ``--integer``, reconstructed
camera to camera and measured against the plain way (integer codes matched by equal code,
``cv2.triangulatePoints``): as many points, and a flatter plane. Before, the default import kept
0.75 of the plain points (a third of camera 1's samples dropped as ``extrapolated``)."""

import logging

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.importer import ImportSettings, import_captures

from ringscan.pipeline.calibrate.opencv_files import read_stereo_calibration
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings, StereoSettings
from ringscan.pipeline.reconstruct.stereo import refine_integer_codes
from ringscan.pipeline.simulate.opencv_graycode import render_graycode_captures
from ringscan.kernels.stereo_match import MatchSettings
from tests.support.one_to_one import one_to_one_rig, plain_camera_camera, plane_rms

CAMERA_CAMERA = ReconstructSettings(stereo=StereoSettings(rays="camera-camera"))


@pytest.fixture(scope="module")
def one_to_one(tmp_path_factory):
    """The rendering (128x93 cameras, a 120x67 projector), its two imports and the plain points."""
    work = tmp_path_factory.mktemp("one_to_one")
    rig = one_to_one_rig(scale=16, ratio=0.9)
    render_graycode_captures(work / "render", rig=rig, scene="plane", progress=False)
    proj = (rig.light.width, rig.light.height)
    stereo = read_stereo_calibration(work / "render" / "calibrationParameters.yml")
    scans = {}
    for name, integer in (("default", False), ("integer", True)):
        scans[name], _ = import_captures([work / "render" / "capture_0.yml"], out=work / name, stereo=stereo,
                                         projector=proj, settings=ImportSettings(integer_only=integer))
    plain, _ = plain_camera_camera(work / "render" / "capture_0.yml", work / "render" / "calibrationParameters.yml",
                                   proj)
    return work, scans, plain


def _points(work, scan, name, settings=CAMERA_CAMERA):
    rep = reconstruct_scan(scan, work / f"rec_{name}", settings=settings, progress=False)
    ply = read_ply(work / f"rec_{name}" / f"{scan.views[0].name}.ply")
    return np.c_[ply["x"], ply["y"], ply["z"]].astype(np.float64), rep["views"][0]


def test_camera_camera_keeps_the_plain_points_and_a_flatter_plane(one_to_one):
    work, scans, plain = one_to_one
    rms_plain = plane_rms(plain)
    for name, rms_bar in (("default", 0.3), ("integer", 0.8)):
        P, v = _points(work, scans[name], name)
        # the bar: at least 0.9 of the plain points (measured 1.21: the plain way loses camera-1
        # pixels whose code camera 2 does not see, the local fit does not)
        assert len(P) >= 0.9 * len(plain), (name, len(P), len(plain), v["stereo"]["unmatched"])
        # and at most 0.9 of its plane RMS; measured 0.16 (default: the sub-pixel half leads) and 0.63
        # (integer codes, each read from its 5 x 5 neighbours); the bars leave ~25 % for the noise
        assert plane_rms(P) <= rms_bar * rms_plain, (name, plane_rms(P), rms_plain)


def test_a_view_that_keeps_few_of_its_samples_warns_with_the_main_reason(one_to_one, caplog):
    work, scans, _ = one_to_one
    # queries allowed 0.05 of their neighbours' spread from their middle: almost all are extrapolated
    tight = ReconstructSettings(stereo=StereoSettings(rays="camera-camera",
                                                      match=MatchSettings(max_extrapolation=0.05)))
    with caplog.at_level(logging.WARNING):
        _, v = _points(work, scans["default"], "tight", tight)
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "keeps" in r.getMessage()]
    assert len(lines) == 1, caplog.text
    assert v["points"] < 0.25 * v["samples"]
    assert f"keeps {v['points']} of its {v['samples']} decoded samples" in lines[0]
    assert f"unmatched in camera 2 {v['dropped']['unmatched']} (extrapolated" in lines[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _points(work, scans["default"], "default_again")
    assert "keeps" not in caplog.text  # a view that keeps most of its samples says nothing


def test_integer_codes_are_read_from_their_neighbourhood():
    """A smooth map of projector coordinates at 1.3 projector px per camera px, rounded to integer codes
    (errors uniform over a pixel: 0.29 px RMS): the plane through each pixel's 5 x 5 neighbours reads it
    to a fraction of that; sub-pixel coordinates are left as they are, and a window across a depth step
    (codes jumping by 40) keeps its codes."""
    W, H = 80, 60
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    u = 100 + 1.3 * xx + 0.2 * yy + 0.002 * (xx - 40) ** 2
    v = 50 + 0.15 * xx + 1.25 * yy
    u = np.where(xx >= 50, u + 40, u)  # a depth step at x = 50
    truth = np.c_[u.ravel(), v.ravel()]
    codes = np.round(truth)
    sub = np.zeros(len(codes), bool)
    sub[::7] = True  # every seventh pixel interpolated by the import (exact here; an exact value that is
    sub &= np.all(np.abs(truth - np.round(truth)) > 0.05, axis=1)  # an integer reads as an integer code)
    codes[sub] = truth[sub]
    sigma = np.where(sub[:, None], 0.02, 1 / np.sqrt(12)) * np.ones((1, 2))
    pixel = np.arange(W * H)
    out, s, refined = refine_integer_codes(pixel, codes, sigma, width=W, height=H)
    assert not refined[sub].any() and np.array_equal(out[sub], codes[sub])
    x = pixel % W
    inner = (x >= 2) & (x < 47) & (pixel // W >= 2) & (pixel // W < H - 2) & ~sub
    err = np.abs(out[inner] - truth[inner])
    assert refined[inner].all()
    # rounding leaves 0.29 px RMS; the plane through 25 codes (and the odd exact one) a quarter of it
    assert np.sqrt(np.mean(err ** 2)) < 0.25 / np.sqrt(12), np.sqrt(np.mean(err ** 2))
    # the predicted sigma is the error's scale or above it, never far below (measured: the error is 0.48
    # of it, the windows' scatter, rounding and curvature, counted as noise; under 1.5 the prediction
    # holds, above 0.3 it still means something)
    ratio = np.sqrt(np.mean(err ** 2) / np.mean(s[inner] ** 2))
    assert 0.3 < ratio < 1.5, ratio
    # across the step the u codes are kept as they were (v runs on smoothly there and is refined)
    edge = (np.abs(x - 49.5) < 2) & (pixel // W >= 2) & (pixel // W < H - 2) & ~sub
    assert not refined[edge, 0].any() and np.array_equal(out[edge, 0], codes[edge, 0])
    assert refined[edge, 1].all()


def test_window_sums_at_a_few_pixels_equal_the_image_filters():
    """refine_integer_codes sums the windows of a few integer codes among sub-pixel ones at their own
    pixels (kernels.stereo_support.window_sums, reading each window's samples through the pixels' sample
    index): the same sums as the image-wide separable filters, borders (outside = no sample) included,
    to float64 rounding (the sums reach ~1e7; 1e-6 of slack is ~1e-13 relative)."""
    import warp as wp

    from ringscan.kernels import init_warp
    from ringscan.kernels.stereo_support import window_sums

    init_warp()
    rng = np.random.default_rng(3)
    H, W, r = 23, 31, 2
    w = np.where(rng.random((H, W)) < 0.8, rng.uniform(1, 100, (H, W)), 0.0)
    p = rng.uniform(0, 800, (H, W)) * (w > 0)
    at = np.r_[0, W - 1, W * H - 1, W * (H - 1), rng.choice(W * H, 40, replace=False)]
    pixel = np.flatnonzero(w.ravel() > 0)
    sample_of = np.full(H * W, -1, np.int32)
    sample_of[pixel] = np.arange(pixel.size)
    got = window_sums(wp.array(at.astype(np.int32), dtype=wp.int32, device="cpu"),
                      wp.array(sample_of, dtype=wp.int32, device="cpu"),
                      wp.array(p.ravel()[pixel], dtype=wp.float64, device="cpu"),
                      wp.array(w.ravel()[pixel], dtype=wp.float64, device="cpu"), width=W, height=H, radius=r).numpy()
    off = np.arange(-r, r + 1, dtype=np.float64)
    one = np.ones_like(off)

    def filt(a, kx, ky):
        return cv2.sepFilter2D(a, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT).ravel()[at]

    want = (filt(w, one, one), filt(w, off, one), filt(w, one, off), filt(w, off * off, one), filt(w, off, off),
            filt(w, one, off * off), filt(w * p, one, one), filt(w * p, off, one), filt(w * p, one, off),
            filt(w * p * p, one, one), filt((w > 0).astype(np.float64), one, one))
    for g, x in zip(got, want):
        np.testing.assert_allclose(g, x, rtol=1e-12, atol=1e-6)
