"""``ringscan import`` of OpenCV's structured-light sample layout (two cameras, pattern_camN_imK frames, an
image list, a camera-camera calibration file) against the virtual two-camera rig's truth, and its bad input."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.opencv_files import read_opencv_calibration, read_stereo_calibration
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import DECODED_SCALE
from ringscan.pipeline.formats.rig import has_calibrated_light
from ringscan.pipeline.formats.scan import as_camera2, load_scan, read_view_frames
from ringscan.pipeline.simulate.opencv_graycode import read_graycode_truth, render_graycode_captures
from ringscan.tools.cli import main
from tests.support.opencv_graycode_rig import PH, PW, small_stereo_rig

PROJ = f"{PW}x{PH}"


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """The virtual two-camera rig's Gray code as OpenCV's sample stores it (320x256 cameras, 128x96 projector)."""
    out = tmp_path_factory.mktemp("stereo") / "r"
    rig = small_stereo_rig()
    render_graycode_captures(out, rig=rig, scene="sphere", size_mm=50.0, progress=False, device="cpu")
    return out, rig


def _err(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def _decoded(scan, view, *, camera=1):
    s = as_camera2(scan) if camera == 2 else scan
    v = view.camera2 if camera == 2 else view
    fr = read_view_frames(s, v, ["proj_u", "proj_v"]).astype(np.float64)
    ok = (fr[0] > 0) & (fr[1] > 0)
    return np.where(ok, fr[0] / DECODED_SCALE - 1, np.nan), np.where(ok, fr[1] / DECODED_SCALE - 1, np.nan)


def test_two_camera_import_from_folder_and_list(rendered, tmp_path, capsys):
    """The capture folder and its image list give the same two-camera scan: camera 1's decoded frames as the
    view's, camera 2's under view.camera2, each within 0.1 px (median) of its camera's truth projector
    coordinates; the rig in camera 1's frame with an uncalibrated projector, the truth depths inside its volume."""
    out, rig = rendered
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["import", str(out / "capture_0"), "--rig", str(out / "calibrationParameters.yml"),
                 "--projector", PROJ, "--out", str(a)]) == 0
    text = capsys.readouterr().out
    assert "camera 2:" in text and "uncalibrated" in text and "--rays camera-camera" in text
    assert main(["import", str(out / "capture_0.yml"), "--rig", str(out / "calibrationParameters.yml"),
                 "--projector", PROJ, "--out", str(b)]) == 0
    capsys.readouterr()
    sa, sb = load_scan(a), load_scan(b)
    assert [v.name for v in sa.views] == [v.name for v in sb.views] == ["capture_0"]
    va, vb = sa.views[0], sb.views[0]
    assert va.camera2 is not None and va.camera2.frames["proj_u"] == "capture_0/cam2/proj_u.png"
    for k in ("proj_u", "proj_v", "contrast"):
        assert np.array_equal(read_image(a / va.frames[k]), read_image(b / vb.frames[k]))
        assert np.array_equal(read_image(a / va.camera2.frames[k]), read_image(b / vb.camera2.frames[k]))
    r = sa.rig
    assert r.light.model == "uncalibrated" and not has_calibrated_light(r)
    assert (r.light.width, r.light.height) == (PW, PH)
    assert np.allclose(r.camera.R, np.eye(3)) and np.allclose(r.camera.t, 0)
    R = rig.camera2.R @ rig.camera.R.T
    assert np.allclose(r.camera2.R, R) and np.allclose(r.camera2.t, rig.camera2.t - R @ rig.camera.t)
    for cam in (1, 2):
        truth = read_graycode_truth(out, camera=cam)
        u, v = _decoded(sa, va, camera=cam)
        inner = cv2.erode((truth["lit"] & np.isfinite(truth["depth"])).astype(np.uint8), np.ones((5, 5), np.uint8))
        sel = inner.astype(bool) & np.isfinite(u)
        assert sel.sum() > 10000 and sel.sum() > 0.98 * inner.sum(), cam
        e = np.hypot(u[sel] - truth["proj"][..., 0][sel], v[sel] - truth["proj"][..., 1][sel])
        assert np.median(e) < 0.1 and np.percentile(e, 95) < 0.3, (cam, np.median(e), np.percentile(e, 95))
    z1 = read_graycode_truth(out, camera=1)["depth"]
    z1 = z1[np.isfinite(z1)]
    assert r.volume.z_min < z1.min() and z1.max() < r.volume.z_max     # from the decoded matches, with margins
    assert r.volume.z_max < 2 * z1.max()


def test_stereo_with_projector_rig_and_one_camera(rendered, tmp_path, capsys):
    """--projector-rig adds the projector (camera 1 - projector file) in camera 1's frame; --camera 1 with the
    procam file alone gives the one-camera scan of camera 1's frames (as before for graycode_NN folders)."""
    out, rig = rendered
    s3 = tmp_path / "s3"
    assert main(["import", str(out / "capture_0"), "--rig", str(out / "calibrationParameters.yml"),
                 "--projector-rig", str(out / "procam.yml"), "--projector", PROJ, "--out", str(s3)]) == 0
    r = load_scan(s3).rig
    Rp = rig.light.R @ rig.camera.R.T
    assert r.light.model == "perspective" and np.allclose(r.light.R, Rp)
    assert np.allclose(r.light.t, rig.light.t - Rp @ rig.camera.t) and r.camera2 is not None
    one = tmp_path / "one"
    assert main(["import", str(out / "capture_0"), "--rig", str(out / "procam.yml"), "--camera", "1",
                 "--projector", PROJ, "--out", str(one)]) == 0
    capsys.readouterr()
    s1 = load_scan(one)
    assert s1.rig.camera2 is None and s1.views[0].camera2 is None
    assert np.array_equal(read_image(one / "capture_0" / "proj_u.png"), read_image(s3 / "capture_0" / "proj_u.png"))


def test_stereo_file_read_and_named_for_what_it_is(rendered, tmp_path):
    out, _ = rendered
    with pytest.raises(CalibrationError, match=r"camera-camera \(stereo\) calibration .*projector-from-scan"):
        read_opencv_calibration(out / "calibrationParameters.yml")
    with pytest.raises(CalibrationError, match="a camera-projector calibration"):
        read_stereo_calibration(out / "procam.yml")
    # 'cam1_distortion' spelled right, and R, T given only as RT_cam1_2_cam2
    text = (out / "calibrationParameters.yml").read_text().replace("_distorsion", "_distortion")
    text = text.replace("\nR:", "\nR_unused:").replace("\nT:", "\nT_unused:")
    (tmp_path / "c.yml").write_text(text)
    a, b = read_stereo_calibration(out / "calibrationParameters.yml"), read_stereo_calibration(tmp_path / "c.yml")
    for k in ("cam1_dist", "cam2_dist", "R", "T"):
        assert np.allclose(a[k], b[k]), k


def _copy(out, tmp_path, name="cap"):
    dst = tmp_path / name
    shutil.copytree(out / "capture_0", dst)
    return dst


def test_bad_input_one_line_each_nothing_written(rendered, tmp_path, capsys):
    out, _ = rendered
    stereo, procam = str(out / "calibrationParameters.yml"), str(out / "procam.yml")
    scan = tmp_path / "scan"

    def run(capture, rig=stereo, *extra):
        rc = main(["import", str(capture), "--rig", rig, "--projector", PROJ, "--out", str(scan), *extra])
        assert rc == 1 and not scan.exists()
        return _err(capsys)

    # one camera's frames missing
    c = _copy(out, tmp_path, "no_cam2")
    for p in c.glob("pattern_cam2_*"):
        p.unlink()
    err = run(c)
    assert f"{c}: camera 2's frames are missing" in err, err
    c = _copy(out, tmp_path, "no_cam1")
    for p in c.glob("pattern_cam1_*"):
        p.unlink()
    assert f"{c}: camera 1's frames are missing" in run(c)
    c = _copy(out, tmp_path, "gap")
    (c / "pattern_cam2_im7.png").unlink()
    err = run(c)
    assert "29 pattern_cam2_imK frames, but a 128x96 projector in layout opencv-graycode has 30" in err, err
    # frames of different sizes
    c = _copy(out, tmp_path, "sizes")
    img = read_image(c / "pattern_cam1_im5.png")
    cv2.imwrite(str(c / "pattern_cam1_im5.png"), img[:, :300])
    err = run(c)
    assert f"{c / 'pattern_cam1_im5.png'}: frame is 300x256, pattern_cam1_im1.png is 320x256" in err, err
    # a frame count that does not fit the projector
    err = main(["import", str(out / "capture_0"), "--rig", stereo, "--projector", "256x96", "--out", str(scan)])
    err = _err(capsys)
    assert "30 pattern_cam1_imK frames, but a 256x96 projector in layout opencv-graycode has 32" in err, err
    assert not scan.exists()
    # names that do not match, as many as one camera's frames: taken in name order as one camera's, which
    # the stereo file does not fit; one fewer: refused, naming what the layout has
    c = tmp_path / "renamed"
    c.mkdir()
    for p in (out / "capture_0").glob("pattern_cam1_*"):
        shutil.copy(p, c / p.name.replace("pattern_cam1_im", "img_"))
    err = run(c)
    assert f"{stereo}: a camera-camera (stereo) calibration" in err, err
    (c / "img_30.png").unlink()
    err = run(c)
    assert "no frames named graycode_NN.<ext> (from 00) or pattern_camN_imK.<ext>" in err, err
    assert "found 29 image(s) of other names (img_1.png .. img_29.png), but a 128x96 projector" in err, err
    # a YAML listing files that do not exist
    lst = tmp_path / "list.yml"
    lst.write_text((out / "capture_0.yml").read_text())  # paths relative to the list's folder: not here
    err = run(lst)
    assert f"{lst}: cam1[0]: capture_0/pattern_cam1_im1.png not found" in err, err
    # a YAML that is not FileStorage
    bad = tmp_path / "bad.yml"
    bad.write_text("- just\n- a list\n: of : nothing\n")
    err = run(bad)
    assert f"{bad}: not an OpenCV FileStorage file" in err, err
    err = run(out / "capture_0", str(bad))
    assert f"{bad}: not an OpenCV FileStorage file" in err, err
    # a stereo file given where a procam file is needed: a one-camera capture, or --camera alone
    gc = tmp_path / "gc"
    gc.mkdir()
    for k in range(1, 31):
        shutil.copy(out / "capture_0" / f"pattern_cam1_im{k}.png", gc / f"graycode_{k - 1:02d}.png")
    for args in ((gc,), (out / "capture_0", stereo, "--camera", "1")):
        err = run(*args)
        assert f"{stereo}: a camera-camera (stereo) calibration" in err and "projector-from-scan" in err, err
    # two cameras' frames with a one-camera rig
    err = run(out / "capture_0", procam)
    assert "holds two cameras' frames, but the rig" in err and "--camera 1" in err, err
    # the calibration's image size against the frames
    text = (out / "calibrationParameters.yml").read_text().replace("cam2_size: [ 320, 256 ]", "cam2_size: [ 640, 512 ]")
    (tmp_path / "big.yml").write_text(text)
    err = run(out / "capture_0", str(tmp_path / "big.yml"))
    assert "camera 2's frames are 320x256, the rig's camera 2 is 640x512" in err, err
    # --projector-rig without a stereo --rig: a usage error
    assert main(["import", str(gc), "--rig", procam, "--projector-rig", procam, "--projector", PROJ,
                 "--out", str(scan)]) == 2
    assert "--projector-rig goes with a camera-camera" in capsys.readouterr().err and not scan.exists()


def test_jpeg_frames_and_a_list_with_absolute_paths(rendered, tmp_path, capsys):
    """OpenCV's sample stores JPEGs: the same capture as .jpg (quality 95) imports with both cameras, and an
    image list of absolute paths elsewhere finds them."""
    out, _ = rendered
    jpg = tmp_path / "jpg"
    jpg.mkdir()
    for p in (out / "capture_0").glob("*.png"):
        cv2.imwrite(str(jpg / (p.stem + ".jpg")), read_image(p), [cv2.IMWRITE_JPEG_QUALITY, 95])
    lst = tmp_path / "lists" / "statue.yml"
    lst.parent.mkdir()
    fs = cv2.FileStorage(str(lst), cv2.FILE_STORAGE_WRITE)
    for c in (1, 2):
        fs.startWriteStruct(f"cam{c}", cv2.FileNode_SEQ)
        for k in range(1, 31):
            fs.write("", str(jpg / f"pattern_cam{c}_im{k}.jpg"))
        fs.endWriteStruct()
    fs.release()
    for cap, name in ((jpg, "jpg"), (lst, "statue")):
        scan = tmp_path / f"s_{name}"
        assert main(["import", str(cap), "--rig", str(out / "calibrationParameters.yml"), "--projector", PROJ,
                     "--out", str(scan)]) == 0
        capsys.readouterr()
        s = load_scan(scan)
        assert [v.name for v in s.views] == [name] and s.views[0].camera2 is not None
        truth = read_graycode_truth(out, camera=2)
        u, v = _decoded(s, s.views[0], camera=2)
        inner = cv2.erode((truth["lit"] & np.isfinite(truth["depth"])).astype(np.uint8),
                          np.ones((5, 5), np.uint8)).astype(bool)
        sel = inner & np.isfinite(u)
        assert sel.sum() > 0.98 * inner.sum()
        e = np.hypot(u[sel] - truth["proj"][..., 0][sel], v[sel] - truth["proj"][..., 1][sel])
        assert np.median(e) < 0.1, np.median(e)


def test_stereo_file_as_filestorage_json(rendered, tmp_path, capsys):
    """cv::FileStorage writes JSON too: --rig stereo.json (no ringscan 'format') is read as the OpenCV file."""
    out, _ = rendered
    src = cv2.FileStorage(str(out / "calibrationParameters.yml"), cv2.FILE_STORAGE_READ)
    js = cv2.FileStorage(str(tmp_path / "stereo.json"), cv2.FILE_STORAGE_WRITE)
    for k in ("cam1_intrinsics", "cam1_distorsion", "cam2_intrinsics", "cam2_distorsion", "R", "T"):
        js.write(k, src.getNode(k).mat())
    js.release()
    src.release()
    a, b = read_stereo_calibration(out / "calibrationParameters.yml"), read_stereo_calibration(tmp_path / "stereo.json")
    assert b["cam1_size"] is None and all(np.allclose(a[k], b[k]) for k in ("cam1_K", "cam2_dist", "R", "T"))
    scan = tmp_path / "s"
    assert main(["import", str(out / "capture_0"), "--rig", str(tmp_path / "stereo.json"), "--projector", PROJ,
                 "--out", str(scan)]) == 0
    capsys.readouterr()
    r = load_scan(scan).rig
    assert (r.camera2.width, r.camera2.height) == (320, 256)     # the sizes from the frames when the file has none


# ----------------------------------------------------------------------------- OpenCV's own files, as it writes them
# Facts checked against OpenCV's sources (docs/calibration.md, "I have OpenCV's sample captures"):
# opencv_contrib modules/structured_light/samples/cap_pattern.cpp (frame names), samples/pointcloud.cpp
# (image list: the first top-level node is camera 1's list, then cam2; relative paths as imread takes them),
# and the sample's calibration file in the structured-light test data (key order, cam sizes as [w, h],
# RT_cam1_2_cam2 as the 4x4 [R | T; 0 0 0 1], R and T as cv::stereoRectify takes them, extra keys).


def _write_sample_calibration(path, rig, *, with_rt=True, with_r_t=True):
    """The two cameras as OpenCV's structured-light sample's calibrationParameters.yml has them, written by
    cv2.FileStorage: X_cam2 = R X_cam1 + T (stereoCalibrate's R, T), and stereoRectify's outputs of them."""
    c1, c2 = rig.camera, rig.camera2
    R = c2.R @ c1.R.T
    T = (c2.t - R @ c1.t).reshape(3, 1)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(c1.K, c1.dist, c2.K, c2.dist, (c1.width, c1.height), R, T,
                                                flags=0, alpha=-1)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, c in (("cam1", c1), ("cam2", c2)):
        fs.write(f"{k}_intrinsics", np.asarray(c.K, np.float64))
        fs.write(f"{k}_distorsion", np.asarray(c.dist, np.float64).reshape(1, 5))
        fs.startWriteStruct(f"{k}_size", cv2.FileNode_SEQ | cv2.FileNode_FLOW)  # cv::Size
        fs.write("", int(c.width))
        fs.write("", int(c.height))
        fs.endWriteStruct()
    if with_rt:
        fs.write("RT_cam1_2_cam2", np.vstack([np.hstack([R, T]), [[0.0, 0.0, 0.0, 1.0]]]))
    if with_r_t:
        fs.write("R", R)
        fs.write("T", T)
    fs.write("stereo_error", 0.4)
    for k, m in (("Q", Q), ("R1", R1), ("R2", R2), ("P1", P1), ("P2", P2)):
        fs.write(k, m)
    fs.release()
    return R, T.ravel(), R1, R2


def test_the_samples_calibration_file_maps_camera_1_to_camera_2(rendered, tmp_path):
    """A calibrationParameters.yml as OpenCV writes it (extra keys, 4x4 RT, R and T that stereoRectify takes):
    the imported rig puts a truth point where both true cameras see it, and R, T given only as the 4x4
    RT_cam1_2_cam2 read the same."""
    from ringscan.pipeline.calibrate.importer import stereo_rig
    from ringscan.pipeline.geometry import project_points

    _, rig = rendered
    full, only_rt, bad = tmp_path / "cal.yml", tmp_path / "rt.yml", tmp_path / "bad.yml"
    R, T, R1, R2 = _write_sample_calibration(full, rig)
    _write_sample_calibration(only_rt, rig, with_r_t=False)
    a, b = read_stereo_calibration(full), read_stereo_calibration(only_rt)
    assert a["cam1_size"] == a["cam2_size"] == (320, 256)
    for k in ("cam1_K", "cam1_dist", "cam2_K", "cam2_dist", "R", "T"):
        assert np.allclose(a[k], b[k]), k
    # ground truth: world points seen by the true cameras; the imported rig (camera 1's frame) triangulates
    # their pixels back to the points in camera 1's frame
    r = stereo_rig(a, projector=(PW, PH), z_range=(100.0, 2000.0))
    X = np.random.default_rng(1).uniform([-30, -30, 0], [30, 30, 60], (50, 3))
    c1, c2 = rig.camera, rig.camera2
    u1 = project_points(X, c1.R, c1.t, c1.K, c1.dist)
    u2 = project_points(X, c2.R, c2.t, c2.K, c2.dist)
    n1 = cv2.undistortPoints(u1.reshape(-1, 1, 2), r.camera.K, r.camera.dist).reshape(-1, 2)
    n2 = cv2.undistortPoints(u2.reshape(-1, 1, 2), r.camera2.K, r.camera2.dist).reshape(-1, 2)
    P2 = np.hstack([r.camera2.R, r.camera2.t.reshape(3, 1)])
    H = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]), P2, n1.T, n2.T)
    got = (H[:3] / H[3]).T
    assert np.abs(got - (X @ c1.R.T + c1.t)).max() < 1e-6
    # the file's R1, R2 are stereoRectify's of the rig's pose in that sense (the inverse pose swaps them)
    R1b, R2b, *_ = cv2.stereoRectify(r.camera.K, r.camera.dist, r.camera2.K, r.camera2.dist, (320, 256),
                                     r.camera2.R, r.camera2.t.reshape(3, 1), flags=0, alpha=-1)
    assert np.allclose(R1b, R1) and np.allclose(R2b, R2) and not np.allclose(R1b, R2)
    # a 4x4 RT that is not [R | T; 0 0 0 1]
    text = only_rt.read_text()
    fs = cv2.FileStorage(str(only_rt), cv2.FILE_STORAGE_READ)
    rt = fs.getNode("RT_cam1_2_cam2").mat()
    fs.release()
    rt[3, 3] = 2.0
    fs = cv2.FileStorage(str(bad), cv2.FILE_STORAGE_WRITE)
    fs.write("cam1_intrinsics", c1.K)
    fs.write("cam1_distorsion", c1.dist.reshape(1, 5))
    fs.write("cam2_intrinsics", c2.K)
    fs.write("cam2_distorsion", c2.dist.reshape(1, 5))
    fs.write("RT_cam1_2_cam2", rt)
    fs.release()
    assert "RT_cam1_2_cam2" in text
    with pytest.raises(CalibrationError, match=r"RT_cam1_2_cam2: a 4x4 \[R \| T\] ends in the row 0 0 0 1"):
        read_stereo_calibration(bad)


def test_the_samples_names_list_and_paths_as_opencv_reads_them(rendered, tmp_path, monkeypatch, capsys):
    """cap_pattern's frames with its output path glued on (no separator), an image list whose first list is not
    named cam1 and whose relative paths are the current folder's (as pointcloud.cpp reads it), and the sample's
    calibration file: each imports to the frames of the capture as it is."""
    out, rig = rendered
    cal = tmp_path / "calibrationParameters.yml"
    _write_sample_calibration(cal, rig)
    ref = tmp_path / "ref"
    assert main(["import", str(out / "capture_0"), "--rig", str(cal), "--projector", PROJ, "--out", str(ref)]) == 0
    glued = tmp_path / "glued"
    glued.mkdir()
    for p in (out / "capture_0").glob("pattern_cam*"):
        shutil.copy(p, glued / ("scan01" + p.name))
    monkeypatch.chdir(out)  # the list's paths are relative to the current folder, not the list's
    lst = tmp_path / "lists" / "images_list.yml"
    lst.parent.mkdir()
    fs = cv2.FileStorage(str(lst), cv2.FILE_STORAGE_WRITE)
    for name, c in (("images", 1), ("cam2", 2)):
        fs.startWriteStruct(name, cv2.FileNode_SEQ)
        for k in range(1, 31):
            fs.write("", f"capture_0/pattern_cam{c}_im{k}.png")
        fs.endWriteStruct()
    fs.release()
    for cap, name in ((glued, "glued"), (lst, "images_list")):
        scan = tmp_path / f"s_{name}"
        assert main(["import", str(cap), "--rig", str(cal), "--projector", PROJ, "--out", str(scan)]) == 0
        s = load_scan(scan)
        assert s.views[0].name == name and s.views[0].camera2 is not None
        for key in ("proj_u", "proj_v"):
            assert np.array_equal(read_image(scan / s.views[0].frames[key]), read_image(ref / "capture_0" / f"{key}.png"))
            assert np.array_equal(read_image(scan / s.views[0].camera2.frames[key]),
                                  read_image(ref / "capture_0" / "cam2" / f"{key}.png"))
    capsys.readouterr()
    # two prefixes in one folder: one line naming them, nothing written
    shutil.copy(out / "capture_0" / "pattern_cam1_im1.png", glued / "pattern_cam1_im1.png")
    scan = tmp_path / "s_two"
    assert main(["import", str(glued), "--rig", str(cal), "--projector", PROJ, "--out", str(scan)]) == 1
    err = _err(capsys)
    assert f"{glued}: pattern_camN_imK frames with 2 different prefixes" in err and not scan.exists(), err
