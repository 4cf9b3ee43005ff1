"""``ringscan import`` of captures as cameras and people name them: frames named by the camera (in
natural name order, the order printed), a plain-text image list; every one decodes to the same
projector coordinates as the same frames named graycode_NN."""

from __future__ import annotations

import logging
import shutil

import cv2
import numpy as np
import pytest

from ringscan.pipeline.formats.images import read_image
from ringscan.tools.cli import main
from tests.support.printed import printed_figure
from tests.support.synthetic_captures import write_capture

PROJ = (128, 96)


def _procam_xml(path):
    """A camera-projector calibration as OpenCV's FileStorage writes it (no units in it)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("cam_int", np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]]))
    fs.write("cam_dist", np.zeros((1, 5)))
    fs.write("proj_int", np.array([[250.0, 0, 63.5], [0, 250.0, 47.5], [0, 0, 1]]))
    fs.write("proj_dist", np.zeros((1, 5)))
    fs.write("rotation", cv2.Rodrigues(np.array([0.0, 0.2, 0.0]))[0])
    fs.write("translation", np.array([[-120.0], [0.0], [10.0]]))
    fs.release()


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A one-camera capture (graycode_NN), the same frames named DSC8.JPG .. DSC37.JPG, and a calibration."""
    work = tmp_path_factory.mktemp("import_names")
    write_capture(work / "graycode", projector=PROJ)
    frames = sorted((work / "graycode").glob("graycode_*.png"))
    (work / "cap_target").mkdir()
    for k, p in enumerate(frames):
        # PNG bytes under a camera's name (the reader goes by content; .JPG as the camera names them)
        shutil.copy(p, work / "cap_target" / f"DSC{k + 8}.JPG")
    _procam_xml(work / "calib.yml")
    return work, frames


def _run(capsys, *args):
    rc = main([str(a) for a in args])
    out = capsys.readouterr()
    return rc, out.out, out.err


def _decoded(scan, view):
    return [read_image(scan / view / f"{k}.png") for k in ("proj_u", "proj_v")]


def test_frames_named_by_the_camera_import_in_name_order(capture, tmp_path, capsys):
    work, _ = capture
    common = ["--rig", work / "calib.yml", "--projector", f"{PROJ[0]}x{PROJ[1]}", "--depth", "300", "600"]
    rc, out, err = _run(capsys, "import", work / "graycode", *common, "--out", tmp_path / "a")
    assert rc == 0, err
    rc, out, err = _run(capsys, "import", work / "cap_target", *common, "--out", tmp_path / "b")
    assert rc == 0, err
    # the order is printed: DSC8 first (not DSC10, as a plain sort would have it), DSC37 last
    assert "cap_target: frames taken in name order, DSC8.JPG (first) .. DSC37.JPG (last)" in out, out
    for a, b in zip(_decoded(tmp_path / "a", "graycode"), _decoded(tmp_path / "b", "cap_target")):
        assert np.array_equal(a, b)


def test_a_plain_text_list_imports_as_its_frames(capture, tmp_path, capsys):
    work, frames = capture
    lst = tmp_path / "target.txt"
    lst.write_text("# the target, in capture order\n\n" + "\n".join(str(p) for p in frames) + "\n")
    common = ["--rig", work / "calib.yml", "--projector", f"{PROJ[0]}x{PROJ[1]}", "--depth", "300", "600"]
    rc, out, err = _run(capsys, "import", lst, *common, "--out", tmp_path / "scan")
    assert rc == 0, err
    assert "target: " in out and "pixels decoded" in out
    rc, _, err = _run(capsys, "import", work / "graycode", *common, "--out", tmp_path / "ref")
    assert rc == 0, err
    for a, b in zip(_decoded(tmp_path / "scan", "target"), _decoded(tmp_path / "ref", "graycode")):
        assert np.array_equal(a, b)


def test_a_count_that_does_not_fit_is_refused_before_anything_is_written(capture, tmp_path, capsys):
    work, _ = capture
    cap = tmp_path / "short"
    shutil.copytree(work / "cap_target", cap)
    (cap / "DSC37.JPG").unlink()
    rc, out, err = _run(capsys, "import", cap, "--rig", work / "calib.yml", "--projector", "128x96", "--out",
                        tmp_path / "scan")
    assert rc != 0 and not (tmp_path / "scan").exists()
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert (f"{cap}: no frames named graycode_NN.<ext> (from 00) or pattern_camN_imK.<ext> (OpenCV's sample, "
            "from 1); found 29 image(s) of other names (DSC8.JPG .. DSC36.JPG), but a 128x96 projector in layout "
            "opencv-graycode has 30") in err, err


# ---------------------------------------------------------------------- units

def _baseline(scan):
    from ringscan.pipeline.formats.scan import load_scan

    rig = load_scan(scan).rig
    return float(np.linalg.norm(rig.light.center - rig.camera.center)), rig.volume


def test_an_opencv_calibration_says_its_units_are_assumed_or_given(capture, tmp_path, capsys):
    work, _ = capture
    common = ["--rig", work / "calib.yml", "--projector", "128x96", "--depth", "300", "600"]
    rc, out, err = _run(capsys, "import", work / "graycode", *common, "--out", tmp_path / "mm")
    assert rc == 0, err
    assert "units: calib.yml states none: assuming millimetres (give --units" in out, out
    rc, out, err = _run(capsys, "import", work / "graycode", *common, "--units", "cm", "--out", tmp_path / "cm")
    assert rc == 0, err
    assert "units: cm (10 mm, --units): calib.yml converted to mm" in out, out
    (b_mm, v_mm), (b_cm, v_cm) = _baseline(tmp_path / "mm"), _baseline(tmp_path / "cm")
    # the translation and --depth are in the file's units: 10 times longer in mm (float64 arithmetic)
    assert b_cm == pytest.approx(10 * b_mm, rel=1e-9) and b_mm == pytest.approx(np.hypot(120.0, 10.0), rel=1e-9)
    assert v_cm.z_max - v_cm.z_min == pytest.approx(10 * (v_mm.z_max - v_mm.z_min), rel=1e-9)
    import json

    units = [json.loads((tmp_path / s / "scan.json").read_text())["imported"]["units"] for s in ("mm", "cm")]
    assert units == [{"mm_per_unit": 1.0, "source": "assumed"}, {"mm_per_unit": 10.0, "source": "given"}]
    # a number: the millimetres of one unit (a board square counted as 1)
    rc, out, err = _run(capsys, "import", work / "graycode", *common, "--units", "25", "--out", tmp_path / "sq")
    assert rc == 0, err
    assert _baseline(tmp_path / "sq")[0] == pytest.approx(25 * b_mm, rel=1e-9)


def test_a_calibration_in_metres_is_doubted_aloud(capture, tmp_path, capsys, caplog):
    work, _ = capture
    fs = cv2.FileStorage(str(work / "calib.yml"), cv2.FILE_STORAGE_READ)
    cal = {k: fs.getNode(k).mat() for k in ("cam_int", "cam_dist", "proj_int", "proj_dist", "rotation",
                                           "translation")}
    fs.release()
    fs = cv2.FileStorage(str(tmp_path / "metres.yml"), cv2.FILE_STORAGE_WRITE)
    for k, v in cal.items():
        fs.write(k, v / 1000.0 if k == "translation" else v)
    fs.release()
    common = ["--rig", tmp_path / "metres.yml", "--projector", "128x96", "--depth", "0.3", "0.6"]
    with caplog.at_level(logging.WARNING):
        rc, out, err = _run(capsys, "import", work / "graycode", *common, "--out", tmp_path / "a")
    assert rc == 0, err
    # the printed baseline read back as a number: the file's translation over 1000, to the printed 6 digits
    # (a printed figure's last digit may differ on another machine; the value may not)
    said = printed_figure(caplog.text, "the calibration's baseline is {} units: metres? give --units")
    assert said == pytest.approx(float(np.linalg.norm(cal["translation"])) / 1000.0, rel=1e-5), caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        rc, out, err = _run(capsys, "import", work / "graycode", *common, "--units", "m", "--out", tmp_path / "b")
    assert rc == 0 and "baseline" not in caplog.text, caplog.text
    assert _baseline(tmp_path / "b")[0] == pytest.approx(np.hypot(120.0, 10.0), rel=1e-6)


def test_units_that_do_not_apply_or_do_not_read_are_refused(capture, tmp_path, capsys):
    work, _ = capture
    from ringscan.pipeline.calibrate.opencv_files import read_opencv_calibration
    from ringscan.pipeline.calibrate.procam import procam_rig
    from ringscan.pipeline.formats.rig import save_rig

    c = read_opencv_calibration(work / "calib.yml")
    save_rig(tmp_path / "rig.json", procam_rig(cam_K=c["cam_K"], cam_dist=c["cam_dist"], cam_size=(160, 120),
                                               proj_K=c["proj_K"], proj_dist=c["proj_dist"], proj_size=PROJ,
                                               R=c["R"], T=c["T"], z_range=(300.0, 600.0)))
    for rig, units, want in ((tmp_path / "rig.json", "cm", "rig.json is a ringscan rig, which states its units "
                                                           "(mm); --units is for an OpenCV calibration file"),
                             (work / "calib.yml", "furlong", "--units: expected mm, cm, m, in or the millimetres "
                                                             "of one unit"),
                             (work / "calib.yml", "-3", "got '-3'")):
        rc, out, err = _run(capsys, "import", work / "graycode", "--rig", rig, "--projector", "128x96", "--units",
                            units, "--out", tmp_path / "scan")
        assert rc != 0 and want in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "scan").exists()
    rc, out, err = _run(capsys, "import", work / "graycode", "--rig", tmp_path / "rig.json", "--projector", "128x96",
                        "--out", tmp_path / "scan")
    assert rc == 0 and "units: mm (rig.json states them)" in out, err
