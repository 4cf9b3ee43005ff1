"""pipeline.calibrate.importer: OpenCV calibration files with the rational and thin-prism lens
models (8, 12 and zero-tilt 14 coefficients) are read as given; a tilted sensor and other counts
are refused naming the file and the key; the decoded maps' encoding is its plain statement's."""

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.importer import encode_decoded, stereo_rig
from ringscan.pipeline.calibrate.opencv_files import read_opencv_calibration, read_stereo_calibration
from ringscan.pipeline.calibrate.procam import procam_rig
from ringscan.pipeline.formats.rig import parse_rig, rig_to_dict
from ringscan.pipeline.geometry import camera_pixels

RATIONAL = np.array([1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15])
PRISM = np.r_[RATIONAL, 0.002, -0.0005, -0.001, 0.0003]
CAM_K = np.array([[900.0, 0, 319.5], [0, 900.0, 255.5], [0, 0, 1]])
PROJ_K = np.array([[1500.0, 0, 511.5], [0, 1500.0, 383.5], [0, 0, 1]])
R = cv2.Rodrigues(np.array([0.0, 0.2, 0.0]))[0]
T = np.array([-120.0, 0.0, 10.0])


def _procam_xml(path, cam_dist, proj_dist):
    """A camera-projector calibration as OpenCV's FileStorage writes it (XML)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("cam_int", CAM_K)
    fs.write("cam_dist", np.asarray(cam_dist, np.float64).reshape(1, -1))
    fs.write("proj_int", PROJ_K)
    fs.write("proj_dist", np.asarray(proj_dist, np.float64).reshape(1, -1))
    fs.write("rotation", R)
    fs.write("translation", T.reshape(3, 1))
    fs.release()


def test_a_rational_procam_calibration_is_read_as_given(tmp_path):
    """8 coefficients for the camera, 12 for the projector: read as OpenCV wrote them, kept by the rig
    (and its file), and the rig's camera projects as cv2.projectPoints with the file's 8 does."""
    p = tmp_path / "calibration_result.xml"
    _procam_xml(p, RATIONAL, PRISM)
    d = read_opencv_calibration(p)
    np.testing.assert_array_equal(d["cam_dist"], RATIONAL)
    np.testing.assert_array_equal(d["proj_dist"], PRISM)
    rig = procam_rig(cam_K=d["cam_K"], cam_dist=d["cam_dist"], cam_size=(640, 512), proj_K=d["proj_K"],
                     proj_dist=d["proj_dist"], proj_size=(1024, 768), R=d["R"], T=d["T"], z_range=(300.0, 600.0))
    np.testing.assert_array_equal(rig.camera.dist, RATIONAL)
    np.testing.assert_array_equal(rig.light.dist, PRISM)
    back = parse_rig(rig_to_dict(rig))
    np.testing.assert_array_equal(back.camera.dist, RATIONAL)
    X = np.random.default_rng(0).uniform([-60, -60, 0], [60, 60, 200], (100, 3))
    Xc = X @ rig.camera.R.T + rig.camera.t
    ref = cv2.projectPoints(Xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), CAM_K, RATIONAL)[0].reshape(-1, 2)
    five = cv2.projectPoints(Xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), CAM_K, RATIONAL[:5])[0].reshape(-1, 2)
    assert np.abs(camera_pixels(back, X) - ref).max() < 1e-9
    assert np.abs(five - ref).max() > 1.0  # dropping k4..k6 would be far off


def test_a_stereo_calibration_with_14_coefficients_and_no_tilt_reads_as_12(tmp_path):
    p = tmp_path / "calibrationParameters.yml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("cam1_intrinsics", CAM_K)
    fs.write("cam1_distorsion", RATIONAL.reshape(1, 8))
    fs.write("cam2_intrinsics", CAM_K)
    fs.write("cam2_distorsion", np.r_[PRISM, 0.0, 0.0].reshape(1, 14))
    fs.write("R", R)
    fs.write("T", T.reshape(3, 1))
    fs.release()
    cal = read_stereo_calibration(p)
    np.testing.assert_array_equal(cal["cam1_dist"], RATIONAL)
    np.testing.assert_array_equal(cal["cam2_dist"], PRISM)
    cal["cam1_size"] = cal["cam2_size"] = (640, 512)
    rig = stereo_rig(cal, projector=(1024, 768), z_range=(300.0, 600.0))
    np.testing.assert_array_equal(rig.camera.dist, RATIONAL)
    np.testing.assert_array_equal(rig.camera2.dist, PRISM)


@pytest.mark.parametrize("cam_dist,match", [
    (np.r_[PRISM, 0.001, 0.0], r"cam_dist: tilted-sensor model \(taux, tauy\) not supported"),
    (np.r_[RATIONAL[:5], 0.1], r"cam_dist: expected 4, 5, 8 or 12 finite distortion coefficients"),
    (np.r_[RATIONAL[:7], np.nan], r"cam_dist: expected 4, 5, 8 or 12 finite distortion coefficients"),
])
def test_other_lens_models_are_refused_naming_the_file_and_key(tmp_path, cam_dist, match):
    p = tmp_path / "calibration_result.xml"
    _procam_xml(p, cam_dist, RATIONAL)
    with pytest.raises(CalibrationError, match=match) as e:
        read_opencv_calibration(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("width,scale", [(1920, 32), (2560, 16), (3840, 16)])
def test_the_decoded_maps_take_a_scale_that_holds_the_projectors_width(width, scale):
    """The imported scan's maps (16-bit fixed point) at 32 steps a px held coordinates up to 2046 px: a 2560 or
    3840 px projector's farther columns were dropped as they were written. The spec now carries the scale
    that holds the projector (16 for these), and scan.json keeps it."""
    import dataclasses

    from ringscan.pipeline.calibrate.importer import ImportSettings, _decoded_spec
    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.formats.rig import default_rig

    rig = default_rig(light_model="perspective")
    K = rig.light.K.copy()
    K[0, 2], K[1, 2] = (width - 1) / 2, 539.5
    rig = dataclasses.replace(rig, light=dataclasses.replace(rig.light, width=width, height=1080, K=K))
    spec = _decoded_spec(rig, ImportSettings())
    assert spec.scale == scale and spec.to_dict()["scale"] == scale
    assert parse_patterns(spec.to_dict(), source="test").scale == scale  # read back from scan.json
    assert (width - 0.5 + 1) * spec.scale <= 65535  # the last column's centre fits


def _plain_encode(u, v, contrast, scale):
    """encode_decoded's statement, one plain expression a step (the import's maps before its in-place form)."""
    def enc(a):
        ok = np.isfinite(a) & (a > -1 + 1.0 / scale) & (a < 65535.0 / scale - 1)
        x = (np.where(ok, a, 0) + 1.0) * scale
        q = np.round(x)
        whole = (q % scale == 0) & (a != np.round(a)) & (scale > 1)
        q = np.where(whole, q + np.where(x >= q, 1.0, -1.0), q)
        return np.where(ok, q, 0).astype(np.uint16)

    fu, fv = enc(u), enc(v)
    bad = (fu == 0) | (fv == 0)
    fu[bad] = 0
    fv[bad] = 0
    return fu, fv, np.clip(np.asarray(contrast, np.float64) * 257.0, 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("scale", [32, 16, 3, 1, 32.0, 2.5])
def test_encode_decoded_writes_what_its_plain_statement_writes(scale):
    """The maps' in-place encoding gives the plain expressions' values to the bit: sub-pixel, whole-pixel and
    near-grid coordinates (written one step aside), NaN, +-inf, out of the 16-bit range, both map orders, a
    scale that is not a power of two; contrast clipped to 16 bits."""
    rng = np.random.default_rng(int(scale * 10))
    h, w = 61, 47
    top = 65535.0 / scale
    u, v = rng.uniform(-2, top + 1, (h, w)), rng.uniform(-0.99, 700, (h, w))
    u[rng.random((h, w)) < 0.1] = np.nan
    v[rng.random((h, w)) < 0.1] = np.nan
    some = rng.random((h, w)) < 0.2
    u[some] = np.round(u[some])
    near = rng.random((h, w)) < 0.2
    v[near] = np.round(v[near] * scale) / scale + rng.choice([-1e-4, 1e-4, 0.0], int(near.sum()))
    u[0, :4] = [np.inf, -np.inf, top - 1, -1 + 1.0 / scale]
    c = rng.uniform(-5, 300, (h, w)).astype(np.float32)
    for a, b, cc in ((u, v, c), (np.asfortranarray(u), np.asfortranarray(v), np.asfortranarray(c))):
        got, want = encode_decoded(a, b, cc, scale), _plain_encode(a, b, cc, scale)
        for g, x in zip(got, want):
            assert g.dtype == np.uint16 and np.array_equal(g, x)
    assert (got[0] > 0).sum() > 0.5 * h * w and (got[1] % max(scale, 2) == 0).any()
