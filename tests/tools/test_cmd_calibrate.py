"""``ringscan calibrate`` and ``ringscan import`` end to end (real captures where present)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import default_rig, load_rig, save_rig
from ringscan.tools.cli import main
from tests.support.printed import assert_figures_as_quoted, printed_figure
from tests.support.procam_crop import crop_decoded_scan
from tests.support.shared_data import need_shared
from tests.support.synthetic_captures import write_capture

ROOT = Path(__file__).resolve().parents[2]
OPENCV_RTOL = 1e-3
"""How far OpenCV's fits of the same corners may move a figure from machine to machine (its threads and
the BLAS): ~1e-4 of a value seen (the projector's fy 1876.6 on one machine, 1876.7 on another; cx 457.4
and 457.5), with room to spare, and still well under the fits' own uncertainty (a principal point from
three board poses is known to a few px, not tenths)."""


@pytest.fixture(scope="module")
def boards_found_once():
    """While this module's tests run, ``calibrate camera`` and ``calibrate pose`` look for the board in each image
    once (their detect_board remembered by the image's pixels, the board, the name and the settings): the tests
    give the same few images many times over (capture_1..3's white frames; the twelve wide-lens images, to two
    lens models), and what the commands do with the corners (their checks, fits and messages) still runs every
    time. Each call gets its own copy of the view. tests/pipeline/calibrate/test_board.py covers the detection."""
    import hashlib

    from ringscan.pipeline.calibrate import board
    from ringscan.tools import cmd_calibrate_light

    found = {}
    detect = board.detect_board

    def detect_once(image, **kw):
        img = np.ascontiguousarray(image)
        key = (hashlib.sha1(img.tobytes()).hexdigest(), img.shape, str(img.dtype), repr(sorted(kw.items())))
        if key not in found:
            found[key] = detect(image, **kw)
        v = found[key]
        return dataclasses.replace(v, corners=None if v.corners is None else v.corners.copy(),
                                   ids=None if v.ids is None else v.ids.copy())

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(board, "detect_board", detect_once)  # calibrate camera's (board.detect_board_images)
        mp.setattr(cmd_calibrate_light, "detect_board", detect_once)  # calibrate pose's
        yield


@pytest.fixture(scope="module")
def procam(shared_data, boards_found_once):
    """The captures; while this module's tests run, ``calibrate procam`` decodes each capture folder once (its
    read_capture and capture_corners remembered by their inputs): the tests give capture_1..3 ten times over,
    and what the command does with the corners (its checks, fits and messages) still runs every time.
    tests/pipeline/calibrate/test_procam_real.py covers the decoding itself. The board is looked for once in
    each image too (:func:`boards_found_once`)."""
    import os

    from ringscan.pipeline.calibrate import procam

    need_shared(shared_data / "procam" / "capture_1", "procam captures")
    caps, corners = {}, {}
    read, find = procam.read_capture, procam.capture_corners

    def read_once(folder, **kw):
        key = (os.path.realpath(folder), repr(sorted(kw.items())))
        if key not in caps:
            caps[key] = read(folder, **kw)
        return caps[key]

    def corners_once(cap, **kw):
        key = (id(cap), repr(sorted(kw.items())))
        if key not in corners:
            corners[key] = (cap, find(cap, **kw))  # cap kept: its id is not reused
        return dataclasses.replace(corners[key][1])  # its own object, as a fresh decode gives

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(procam, "read_capture", read_once)  # calibrate procam's (procam.capture_corners_of_folders)
        mp.setattr(procam, "capture_corners", corners_once)
        yield shared_data / "procam"


def test_camera_without_a_board_exits_1_and_writes_nothing(tmp_path, procam, capsys):
    out = tmp_path / "cam.json"
    rc = main(["calibrate", "camera", str(procam / "capture_1" / "graycode_41.png"),
               str(procam / "capture_2" / "graycode_41.png"), "--square", "75", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1 and "no image shows the 9x7 board" in err and "Traceback" not in err
    assert not out.exists()


def test_procam_wrong_layout_exits_1(tmp_path, capsys):
    write_capture(tmp_path / "c1", projector=(128, 96))
    rig = tmp_path / "rig.json"
    rc = main(["calibrate", "procam", str(tmp_path / "c1"), "--square", "75", "--projector", "128x96",
               "--layout", "opencv-graycode-wb-first", "--out", str(rig)])
    assert rc == 1 and "not layout 'opencv-graycode-wb-first'" in capsys.readouterr().err
    assert not rig.exists()


@pytest.fixture(scope="module")
def procam_123(procam, tmp_path_factory):
    """``calibrate procam`` of capture_1..3 (docs/calibration.md), run once for the tests that use its rig:
    (the rig file, what the command printed)."""
    import contextlib
    import io

    rig = tmp_path_factory.mktemp("procam") / "rig.json"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(["calibrate", "procam", *[str(procam / f"capture_{i}") for i in (1, 2, 3)], "--square", "75",
                   "--projector", "1024x768", "--out", str(rig)])
    assert rc == 0
    return rig, out.getvalue()


@pytest.mark.slow
def test_procam_then_import_then_reconstruct(tmp_path, procam, procam_123):
    rig, text = procam_123
    caps = [str(procam / f"capture_{i}") for i in (1, 2, 3)]
    # the figures docs/calibration.md quotes for this command
    assert_figures_as_quoted(text, (ROOT / "docs" / "calibration.md").read_text(),
                             "stereo: RMS reprojection error {} px; baseline {};", rtol=OPENCV_RTOL,
                             why="OpenCV's fits move in their last digits from machine to machine")
    r = load_rig(rig)
    assert r.light.model == "perspective" and r.light.K[1, 2] > 768
    scan = tmp_path / "scan"
    assert main(["import", caps[2], "--rig", str(rig), "--projector", "1024x768", "--out", str(scan)]) == 0
    # Reconstructed here: the imported scan cut to a window of the camera image around the board (the decoded
    # frames are per camera pixel: the window is the scan a camera of its size, principal point moved by its
    # corner, would have taken; tests/support/procam_crop.py). The whole image gave 530k points of 1.31M pixels.
    x0, y0, w, h = 480, 310, 460, 330
    crop_decoded_scan(scan, x0, y0, w, h)
    out = tmp_path / "out"
    assert main(["reconstruct", str(scan), "--out", str(out), "--device", "cpu"]) == 0
    ply = read_ply(out / "capture_3.ply")
    # the whole image's bound (500k of 1.31M pixels, 38 %) scaled to the window's pixels; the window is
    # mostly board, lit and decoded, so it holds more than that share
    assert len(ply["x"]) > 0.38 * w * h
    # the board is flat: points in the middle of the board (camera pixels inside its corners) fit a plane
    u, v = ply["u"] + x0, ply["v"] + y0  # the full image's pixels
    assert u.min() >= x0 and u.max() < x0 + w and v.min() >= y0 and v.max() < y0 + h
    on = (u > 520) & (u < 900) & (v > 350) & (v < 600)
    P = np.stack([ply["x"][on], ply["y"][on], ply["z"][on]], 1).astype(np.float64)
    c = P.mean(0)
    n = np.linalg.svd(P - c, full_matrices=False)[2][2]
    res = (P - c) @ n
    assert len(P) > 20_000 and np.sqrt(np.mean(res ** 2)) < 1.5


def test_import_opencv_file(tmp_path, procam, capsys, caplog, monkeypatch):
    from ringscan.pipeline.calibrate import importer

    scan = tmp_path / "scan"
    # the share of weak pixels that warns, lowered below capture_1's (~21 %: its dim table and walls)
    monkeypatch.setattr(importer, "LOW_MODULATION_WARN_SHARE", 0.1)
    argv = ["import", str(procam / "capture_1"), "--rig", str(procam / "calibration_result.xml"),
            "--projector", "1024x768"]
    with caplog.at_level("WARNING"):
        assert main([*argv, "--out", str(scan)]) == 0
    assert (scan / "scan.json").is_file() and (scan / "capture_1" / "proj_u.png").is_file()
    st = json.loads((scan / "scan.json").read_text())["imported"]["stats"]["capture_1"]
    # the dim table and walls: their finest bits do not stand clear of the noise (benchmarks/graycode_clearance.py)
    assert st["low_modulation"] > 10_000 and 0.02 < st["coarse_share"] < 0.5 and 1.0 < st["noise"] < 3.0
    out = capsys.readouterr().out
    assert printed_figure(out, "{} left out: low_modulation") == st["low_modulation"]
    assert "capture_1: the finest projector bits barely modulate at" in caplog.text
    # --integer leaves out the pixels whose finest bits are guesses too
    assert main([*argv, "--integer", "--out", str(tmp_path / "int")]) == 0
    sti = json.loads((tmp_path / "int" / "scan.json").read_text())["imported"]["stats"]["capture_1"]
    assert sti["coarse_share"] == 0 and sti["decoded"] < st["decoded"]
    assert sti["low_modulation"] > st["low_modulation"]


# ----------------------------------------------------------------------------- calibrations that know they are wrong


def _procam(procam, tmp_path, *idx, extra=()):
    rig = tmp_path / "rig.json"
    rc = main(["calibrate", "procam", *[str(procam / f"capture_{i}") for i in idx], "--square", "75",
               "--projector", "1024x768", "--out", str(rig), *extra])
    return rc, rig


def test_procam_one_capture_three_times_is_refused(tmp_path, procam, capsys):
    # Today's OpenCV fit of this: RMS 0.35 px, camera fx 3871 (true 3452), baseline 1431 (true 674).
    rc, rig = _procam(procam, tmp_path, 1, 1, 1)
    err = capsys.readouterr().err
    assert rc == 1 and "only 1 distinct board pose" in err and "capture_1 = capture_1 (0.00 px)" in err
    assert len(err.strip().splitlines()) == 1 and not rig.exists()
    rc, rig = _procam(procam, tmp_path, 1, 1, 1, extra=["--force"])  # nothing to stand behind: not even forced
    assert rc == 1 and not rig.exists()
    rc, rig = _procam(procam, tmp_path, 1, 2, 2)
    assert rc == 1 and "only 2 distinct board pose" in capsys.readouterr().err and not rig.exists()


def test_procam_min_views_below_three_is_refused(tmp_path, procam, capsys):
    for n in ("-1", "0", "2"):
        rc, rig = _procam(procam, tmp_path, 1, 2, extra=["--min-views", n])
        assert rc == 2 and "--min-views: expected an integer >= 3" in capsys.readouterr().err and not rig.exists()


def test_procam_a_repeated_capture_is_left_out(tmp_path, procam, procam_123, capsys):
    rc, rig = _procam(procam, tmp_path, 1, 2, 3, 3)
    out = capsys.readouterr().out
    assert rc == 0 and "capture_3 = capture_3 (0.00 px): the same board pose as the earlier view, left out" in out
    # the numbers of capture_1..3 as docs/calibration.md quotes them
    doc = (ROOT / "docs" / "calibration.md").read_text()
    for template in ("camera: RMS reprojection error {} px over 3 views; fx {} fy {} cx {} cy {};",
                     "projector: RMS reprojection error {} px over 3 views; fx {} fy {} cx {} cy {};",
                     "stereo: RMS reprojection error {} px; baseline {}; T {}, {}, {}"):
        assert_figures_as_quoted(out, doc, template, rtol=OPENCV_RTOL,
                                 why="OpenCV's fits move in their last digits from machine to machine")
    r = load_rig(rig)
    assert abs(r.camera.K[0, 0] - 3451.7) < 0.1
    # the rig of capture_1..3 given once: the same fit (OpenCV's fits of the same corners differ from run to run,
    # by up to 2e-6 of a value, in the camera's k2; the repeat left in moves the camera's R and t by 1e-3 to 2e-2)
    once = load_rig(procam_123[0])
    for a, b in ((r.camera, once.camera), (r.light, once.light)):
        for key in ("K", "dist", "R", "t"):
            np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=1e-4, atol=1e-7, err_msg=key)


def test_camera_one_image_three_times_is_refused(tmp_path, procam, capsys):
    w = str(procam / "capture_1" / "graycode_40.png")
    out = tmp_path / "cam.json"
    assert main(["calibrate", "camera", w, w, w, "--square", "75", "--out", str(out)]) == 1
    assert "only 1 distinct board pose" in capsys.readouterr().err and not out.exists()


def test_camera_images_of_another_size_than_the_rig_are_refused_unless_forced(tmp_path, procam, capsys):
    r = default_rig()  # a 1280x1024 camera; made 640x512 here
    save_rig(tmp_path / "rig.json", dataclasses.replace(r, camera=dataclasses.replace(r.camera, width=640, height=512)))
    before = (tmp_path / "rig.json").read_bytes()
    whites = [str(procam / f"capture_{i}" / "graycode_40.png") for i in (1, 2, 3)]
    argv = ["calibrate", "camera", *whites, "--square", "75", "--rig", str(tmp_path / "rig.json")]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "the images are 1280x1024, the camera of" in err and "--force" in err
    assert (tmp_path / "rig.json").read_bytes() == before
    assert main(argv + ["--force"]) == 0
    assert load_rig(tmp_path / "rig.json").camera.width == 1280


def test_pose_on_a_procam_rig_moves_the_projector_with_the_camera(tmp_path, procam, procam_123, capsys):
    import shutil

    rig = shutil.copy(procam_123[0], tmp_path / "rig.json")  # pose rewrites it

    def baseline(r):
        return float(np.linalg.norm(-r.light.R.T @ r.light.t + r.camera.R.T @ r.camera.t))

    b0 = baseline(load_rig(rig))
    assert main(["calibrate", "pose", str(procam / "capture_1" / "graycode_40.png"), "--square", "75",
                 "--rig", str(rig)]) == 0
    r = load_rig(rig)
    assert abs(baseline(r) - b0) < 1e-6 and abs(b0 - 673.7) < 0.1  # before: 3578
    assert abs(printed_figure(capsys.readouterr().out, "baseline {} kept") - b0) < 0.05  # printed to 0.1
    # the camera really moved into the board's frame: it now looks down at the plane z = 0 from above
    assert (-r.camera.R.T @ r.camera.t)[2] > 1000


def _grey(tmp_path, name, value):
    rng = np.random.default_rng(int(value))
    albedo = rng.uniform(0.5, 0.9, (64, 80))
    irr = (5 + 200 * albedo * (value / 255) ** 2.2) / 255  # a light of gamma 2.2
    img = np.clip(np.round(255 * irr ** (1 / 2.2)), 0, 255).astype(np.uint8)  # a camera of gamma 2.2 (the rig's)
    cv2.imwrite(str(tmp_path / name), img)
    return str(tmp_path / name)


def test_response_refuses_repeated_frames_and_bad_levels(tmp_path, capsys):
    save_rig(tmp_path / "rig.json", default_rig())
    before = (tmp_path / "rig.json").read_bytes()
    g = {v: _grey(tmp_path, f"g{v}.png", v) for v in (0, 64, 128, 192, 255)}
    rig = ["--rig", str(tmp_path / "rig.json")]
    # the middle frame given for three levels: today a flat curve and gamma 0.9 written
    rc = main(["calibrate", "response", g[0], g[128], g[128], g[128], g[255], "--levels", "0", "64", "128", "192",
               "255", *rig])
    err = capsys.readouterr().err
    assert rc == 1 and "is the same image as" in err and "does not rise" in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "rig.json").read_bytes() == before
    for bad in ("nan", "inf", "-1", "300"):
        rc = main(["calibrate", "response", *g.values(), "--levels", "0", bad, "128", "192", "255", *rig])
        assert rc == 2 and "--levels: values must be finite and in 0..255" in capsys.readouterr().err
    assert (tmp_path / "rig.json").read_bytes() == before
    assert main(["calibrate", "response", *g.values(), "--levels", "0", "64", "128", "192", "255", *rig]) == 0
    # the frames' light has gamma 2.2; 0.05 is the fit's spread over the albedo noise and 8-bit rounding
    assert abs(printed_figure(capsys.readouterr().out, "light gamma {}") - 2.2) < 0.05


def test_calibration_md_gives_the_exit_status_a_refused_calibration_has(tmp_path, capsys):
    """docs/calibration.md said a refused calibration exits 2; the code (and docs/cli.md, bad_input.md) say 1."""
    import re
    from pathlib import Path

    save_rig(tmp_path / "rig.json", default_rig())
    g = {v: _grey(tmp_path, f"g{v}.png", v) for v in (0, 128, 255)}
    rc = main(["calibrate", "response", g[0], g[128], g[128], g[255], "--levels", "0", "64", "128", "255", "--rig",
               str(tmp_path / "rig.json")])
    assert "not writing" in capsys.readouterr().err
    text = (Path(__file__).resolve().parents[2] / "docs" / "calibration.md").read_text()
    section = text[text.index("## What a calibration cannot stand behind"):]
    said = re.search(r"refuses to write a result it cannot stand behind: one line naming every reason, exit\s+"
                     r"status (\d)", section)
    assert said and int(said[1]) == rc == 1, (said and said[0], rc)


def _grey12(tmp_path, name, value):
    """The ramp frame of :func:`_grey` as a 12-bit camera gives it (values 0..4095 in a 16-bit PNG), its
    brightest pixels saturated."""
    rng = np.random.default_rng(int(value))
    albedo = rng.uniform(0.5, 0.9, (64, 80))
    albedo[:8] = 2.0  # a shiny strip: clipped at 4095 in the white frame
    irr = (5 + 200 * albedo * (value / 255) ** 2.2) / 255
    img = np.clip(np.round(4095 * irr ** (1 / 2.2)), 0, 4095).astype(np.uint16)
    cv2.imwrite(str(tmp_path / name), img)
    return str(tmp_path / name)


def test_response_of_a_12_bit_camera_with_frame_bits(tmp_path, capsys):
    save_rig(tmp_path / "rig.json", default_rig())
    g = [_grey12(tmp_path, f"g{v}.png", v) for v in (0, 64, 128, 192, 255)]
    argv = ["calibrate", "response", *g, "--levels", "0", "64", "128", "192", "255", "--rig", str(tmp_path / "rig.json")]
    # without it the frames are read as 16-bit ones, dark: refused, and the message says what to give
    assert main(argv + ["--force"]) == 1
    assert "a 10- or 12-bit camera's frames? give their bits (--frame-bits)" in capsys.readouterr().err
    assert main(argv + ["--frame-bits", "12"]) == 0
    assert abs(printed_figure(capsys.readouterr().out, "light gamma {}") - 2.2) < 0.05  # as above
    assert abs(json.loads((tmp_path / "rig.json").read_text())["light"]["response"]["gamma"] - 2.2) < 0.05
    img = cv2.imread(g[4], cv2.IMREAD_UNCHANGED)
    img[0, 0] = 5000  # above the 12-bit range
    cv2.imwrite(g[4], img)
    assert main(argv + ["--frame-bits", "12"]) == 1
    err = capsys.readouterr().err
    assert "g255.png: frame holds 5000, above the 12-bit range --frame-bits says (4095)" in err
    assert main(argv + ["--frame-bits", "7"]) == 2 and "--frame-bits" in capsys.readouterr().err


# ----------------------------------------------------------------------------- bad input (docs/bad_input.md)


def _err(capsys):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.fixture
def capture_and_rig(tmp_path):
    """A synthetic capture ``caps/c1`` (160x120 camera, 128x96 projector) and a perspective rig for it."""
    from ringscan.pipeline.calibrate.procam import procam_rig
    from ringscan.pipeline.formats.rig import save_rig

    write_capture(tmp_path / "caps" / "c1")
    K = np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]])
    PK = np.array([[160.0, 0, 63.5], [0, 160.0, 47.5], [0, 0, 1]])
    rig = procam_rig(cam_K=K, cam_dist=np.zeros(5), cam_size=(160, 120), proj_K=PK, proj_dist=np.zeros(5),
                     proj_size=(128, 96), R=np.eye(3), T=np.array([-100.0, 0, 0]), z_range=(300.0, 700.0))
    save_rig(tmp_path / "rig.json", rig)
    return tmp_path / "caps" / "c1", tmp_path / "rig.json"


@pytest.mark.parametrize("extra,message,code", [
    (["--square", "1e308"], "--board/--square/--marker: board: square size must be a number of mm from 0.01 to 10000, "
                            "got 1e+308", 2),
    (["--square", "nan"], "square size must be a number of mm from 0.01 to 10000, got nan", 2),
    (["--square", "5", "--board=--"], "--board: expected WxH (e.g. 9x7), got '--'", 2),
    (["--square", "5", "--projector=--"], "--projector: expected WxH (e.g. 9x7), got '--'", 2),
    (["--square", "5", "--projector", "5x" + "9" * 5000], "--projector: expected WxH (e.g. 9x7), got '5x999999999", 2),
    (["--square", "5", "--window", "100000"], "--window: expected camera px from 1 to 200, got 100000", 2),
    (["--square", "5", "--max-tilt", "nan"], "--max-tilt: expected degrees from 0 to 90, got nan", 2),
    # output files that cannot be written: the run's input, not its options (exit 1, docs/cli.md)
    (["--square", "5", "--report", "{out}"], "{out}: given to both --out and --report: one would overwrite the other",
     1),
    (["--square", "5", "--out", "{frame}"], "{frame}: writing it would overwrite the input {frame}; choose another "
                                            "output", 1),
])
def test_procam_bad_options_refused_before_anything(tmp_path, capsys, extra, message, code):
    frame = tmp_path / "c1" / "graycode_28.png"
    write_capture(tmp_path / "c1")
    before = frame.read_bytes()
    out = tmp_path / "rig.json"
    extra = [a.format(out=out, frame=frame) for a in extra]
    rc = main(["calibrate", "procam", str(tmp_path / "c1"), "--projector", "128x96", "--out", str(out), *extra])
    err = _err(capsys)
    assert rc == code and err.startswith("ringscan calibrate procam: error: "), err
    assert message.format(out=out, frame=frame) in err, err
    assert not out.exists() and frame.read_bytes() == before


def test_camera_out_must_not_overwrite_an_image_or_its_rig(tmp_path, capsys, capture_and_rig):
    cap, rig = capture_and_rig
    img = cap / "graycode_28.png"
    before = img.read_bytes()
    assert main(["calibrate", "camera", str(img), "--square", "5", "--out", str(img)]) == 1
    assert _err(capsys) == (f"ringscan calibrate camera: error: {img}: writing it would overwrite the input {img}; "
                            "choose another output")
    assert main(["calibrate", "camera", str(img), "--square", "5", "--out", str(rig), "--rig", str(rig)]) == 1
    assert _err(capsys).endswith(f"{rig}: given to both --out and --rig: one would overwrite the other")
    assert img.read_bytes() == before


def test_import_view_names_checked_before_anything_is_written(tmp_path, capsys, capture_and_rig):
    """`import .` names the view by the folder's real name (before: '' wrote proj_u.png into /); a name that is not
    folder-safe, or two captures of one name, are refused before anything is written."""
    import os
    import shutil

    cap, rig = capture_and_rig
    out = tmp_path / "scan"
    cwd = os.getcwd()
    try:
        os.chdir(cap)
        assert main(["import", ".", "--rig", str(rig), "--projector", "128x96", "--out", str(out)]) == 0
    finally:
        os.chdir(cwd)
    capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == ["c1", "scan.json"]
    (cap / "sub").mkdir()
    out2 = tmp_path / "o" / "scan2"
    assert main(["import", f"{cap}/sub/..", "--rig", str(rig), "--projector", "128x96", "--out", str(out2)]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["scan2"]  # nothing beside --out
    assert (out2 / "c1" / "proj_u.png").is_file()
    for bad, why in (("bad:name", "contains ':'"), ("new\nline", "contains '\\n'"), (".hidden", "starts with a dot")):
        folder = tmp_path / "caps" / bad
        shutil.copytree(cap, folder)
        out = tmp_path / f"out_{len(why)}"
        rc = main(["import", str(folder), "--rig", str(rig), "--projector", "128x96", "--out", str(out)])
        err = _err(capsys)
        assert rc == 1 and f"is not a folder-safe name ({why})" in err, err
        assert not out.exists()
    other = tmp_path / "x" / "c1"
    shutil.copytree(cap, other)
    out = tmp_path / "two"
    rc = main(["import", str(cap), str(other), "--rig", str(rig), "--projector", "128x96", "--out", str(out)])
    assert rc == 1 and _err(capsys) == (f"ringscan import: error: {other}: has the name 'c1' of the capture {cap}: two "
                                        "views of one name (give capture folders of different names)")
    assert not out.exists()


def test_import_into_an_existing_scan_is_refused(tmp_path, capsys, capture_and_rig):
    cap, rig = capture_and_rig
    out = tmp_path / "scan"
    assert main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(out)]) == 0
    capsys.readouterr()
    before = (out / "scan.json").read_bytes()
    rc = main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(out)])
    assert rc == 1 and _err(capsys) == (f"ringscan import: error: {out}: already holds a scan (scan.json); choose "
                                        "another folder (import writes a new scan)")
    assert (out / "scan.json").read_bytes() == before


def test_import_rig_that_is_a_fifo_or_a_device(tmp_path, capsys, capture_and_rig):
    import os

    cap, _ = capture_and_rig
    fifo = tmp_path / "rig.json.fifo"
    os.mkfifo(fifo)
    for rig in (fifo, "/dev/zero", tmp_path / "calib.xml"):
        if str(rig).endswith(".xml"):
            os.mkfifo(rig)
        rc = main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(tmp_path / "s")])
        err = _err(capsys)
        assert rc == 1 and err.startswith(f"ringscan import: error: {rig}: is a ") and "not a regular file" in err, err
    assert not (tmp_path / "s").exists()


def test_import_into_a_folder_another_run_holds_is_refused(tmp_path, capsys, capture_and_rig):
    import os

    from ringscan.pipeline.formats.atomic import LOCK_NAME, lock_folder

    cap, rig = capture_and_rig
    out = tmp_path / "scan"
    out.mkdir()
    with lock_folder(out, what="reconstruct"):  # flock: a second open of the file conflicts, even in one process
        rc = main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(out)])
        assert rc == 1 and _err(capsys) == (f"ringscan import: error: {out}: in use by another ringscan run "
                                            f"(reconstruct, process {os.getpid()}); wait for it to end or choose "
                                            f"another output folder (lock file {LOCK_NAME})")
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    assert main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["c1", "scan.json"]
def test_response_with_a_pattern_that_matched_nothing_says_so(tmp_path, capsys):
    from ringscan.pipeline.formats.rig import default_rig, save_rig

    rig = tmp_path / "rig.json"
    save_rig(rig, default_rig())
    before = rig.read_bytes()
    pattern = str(tmp_path / "ramp" / "*.png")  # what the shell passes on when the glob matches nothing
    rc = main(["calibrate", "response", pattern, "--levels", "0", "128", "255", "--rig", str(rig)])
    assert rc == 1
    assert capsys.readouterr().err.strip() == (f"ringscan calibrate response: error: {pattern}: no file matches this "
                                               "pattern (the shell passed it on as it was)")
    assert rig.read_bytes() == before


def test_camera_plot_draws_the_residuals_of_the_fit(tmp_path, procam, capsys):
    import cv2

    from ringscan.pipeline.calibrate.board import Board, detect_board
    from ringscan.pipeline.calibrate.camera import calibrate_camera, reprojection_residuals
    from ringscan.pipeline.formats.images import read_image

    images = [procam / f"capture_{i}" / "graycode_40.png" for i in (1, 2, 3)]  # the white frames
    plot = tmp_path / "res.png"
    assert main(["calibrate", "camera", *map(str, images), "--square", "75", "--out", str(tmp_path / "c.json"),
                 "--plot", str(plot), "--no-progress"]) == 0
    assert f"wrote {plot}" in capsys.readouterr().out
    assert cv2.imread(str(plot)).shape == (560, 1200, 3)
    # The residuals drawn are the fit's: their RMS per view is OpenCV's per-view error.
    board = Board(9, 7, 75.0)
    views = [detect_board(read_image(p), board=board, name=f"v{i}") for i, p in enumerate(images)]
    cal = calibrate_camera(views, board=board, size=(1280, 1024))
    res = reprojection_residuals(views, board, cal)
    assert list(res) == cal.names
    for name, e in zip(cal.names, cal.per_view):
        corners, r = res[name]
        assert len(corners) == 63 and np.sqrt(np.mean(np.sum(r ** 2, axis=1))) == pytest.approx(e, rel=1e-6)


def test_import_min_contrast(tmp_path, capsys, capture_and_rig):
    """--min-contrast sets the decode's threshold; out of range it is a usage error (exit 2)
    and nothing is written."""
    cap, rig = capture_and_rig
    out = tmp_path / "s"
    assert main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--min-contrast", "5",
                 "--out", str(out)]) == 0
    assert "pixels decoded" in capsys.readouterr().out
    for bad in ("-1", "255", "nan"):
        out = tmp_path / f"bad_{bad}"
        rc = main(["import", str(cap), "--rig", str(rig), "--projector", "128x96", "--min-contrast", bad,
                   "--out", str(out)])
        assert rc == 2 and "--min-contrast" in _err(capsys)
        assert not out.exists()


def test_import_frame_bits(tmp_path, capsys, capture_and_rig):
    """--frame-bits reads a 12-bit camera's 16-bit captures as their 8-bit original decodes;
    without it the capture has no contrast and the message says to give it; out of range it
    is a usage error (exit 2) and nothing is written."""
    import json

    cap, rig = capture_and_rig
    c12 = tmp_path / "caps" / "c12"
    c12.mkdir()
    for p in sorted(cap.glob("graycode_*.png")):
        v = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.uint16)
        cv2.imwrite(str(c12 / p.name), (v << 4) | (v >> 4))  # 0..4095
    base = ["import", "--rig", str(rig), "--projector", "128x96"]
    assert main([*base, str(cap), "--out", str(tmp_path / "s8")]) == 0
    out8 = capsys.readouterr().out
    assert main([*base, str(c12), "--frame-bits", "12", "--out", str(tmp_path / "s12")]) == 0
    out12 = capsys.readouterr().out
    decoded = [line.split(":")[1] for line in (out8, out12) for line in line.splitlines() if "pixels decoded" in line]
    assert len(decoded) == 2 and decoded[0] == decoded[1]  # the same count of pixels decoded
    d = json.loads((tmp_path / "s12" / "scan.json").read_text())
    assert d["imported"]["frame_bits"] == 12 and "frame_bits" not in d  # the decoded frames are coordinates
    assert main([*base, str(c12), "--out", str(tmp_path / "s")]) == 1
    err = _err(capsys)
    assert "no projector light" in err and "a 10- or 12-bit camera's frames? give their bits" in err
    for bad in ("7", "17"):
        assert main([*base, str(c12), "--frame-bits", bad, "--out", str(tmp_path / f"bad{bad}")]) == 2
        assert "--frame-bits: expected a whole number" in _err(capsys)
        assert not (tmp_path / f"bad{bad}").exists()


# ----------------------------------------------------------------------------- --lens-model (a wide-angle lens)

WIDE_SIZE = (800, 640)
WIDE_K = np.array([[437.5, 0, 399.5], [0, 437.5, 319.5], [0, 0, 1]])
WIDE_DIST = np.array([1.0, 0.3, 0, 0, 0.01, 1.4, 0.6, 0.05])
"""A strong rational lens (k1, k2, p1, p2, k3, k4, k5, k6; radial only, so that it can be rendered): the image's
corners 55 degrees off axis (tests/pipeline/calibrate/test_camera.py's lens at 800x640)."""


@pytest.fixture(scope="module")
def wide_images(tmp_path_factory):
    """Twelve ChArUco images rendered through the wide lens: four boards reaching into the image's corners (partly
    outside it), eight around the middle."""
    from ringscan.pipeline.calibrate.board import Board, board_points
    from tests.support.synthetic_captures import point_toward, render_charuco

    board = Board(9, 7, 30.0, charuco="DICT_5X5_100")
    poses = [(-25 * np.sign(v - 320), 25 * np.sign(u - 400), (u, v), 300)
             for u, v in [(70, 60), (730, 60), (70, 580), (730, 580)]]
    poses += [(ax, ay, px, 350) for ax, ay, px in [
        (25, 0, (400, 320)), (0, 25, (400, 320)), (-20, -20, (400, 320)), (15, -15, (190, 320)),
        (-15, 15, (610, 320)), (10, 10, (400, 155)), (-10, 10, (400, 485)), (20, 20, (400, 320))]]
    centre = board_points(board).astype(np.float64).mean(0)
    folder = tmp_path_factory.mktemp("wide")
    out = []
    for i, (ax, ay, px, z) in enumerate(poses):
        R = cv2.Rodrigues(np.array([np.radians(ax), np.radians(ay), 0.0]))[0]
        t = point_toward(px, z, WIDE_K, WIDE_DIST) - R @ centre
        img = render_charuco(board, K=WIDE_K, dist=WIDE_DIST, size=WIDE_SIZE, rvec=cv2.Rodrigues(R)[0], tvec=t,
                             seed=i)
        cv2.imwrite(str(folder / f"v{i:02d}.png"), img)
        out.append(str(folder / f"v{i:02d}.png"))
    return out


def test_camera_rational_lens_model_recovers_a_wide_lens(tmp_path, wide_images, boards_found_once, capsys):
    base = ["calibrate", "camera", *wide_images, "--square", "30", "--charuco", "DICT_5X5_100", "--no-progress"]
    assert main([*base, "--out", str(tmp_path / "standard.json")]) == 0
    r = default_rig()
    save_rig(tmp_path / "rig.json", dataclasses.replace(r, camera=dataclasses.replace(r.camera, width=800, height=640)))
    assert main([*base, "--lens-model", "rational", "--out", str(tmp_path / "rational.json"),
                 "--rig", str(tmp_path / "rig.json")]) == 0
    assert "lens model: rational (8 coefficients)" in capsys.readouterr().out
    std = json.loads((tmp_path / "standard.json").read_text())
    rat = json.loads((tmp_path / "rational.json").read_text())
    # the default's outputs are as they were: 5 coefficients, no lens_model key
    assert len(std["camera"]["dist"]) == 5 and list(std["report"]["std"])[-1] == "k3"
    assert "lens_model" not in std["report"]
    assert len(rat["camera"]["dist"]) == 8 and rat["report"]["lens_model"] == "rational"
    assert rat["report"]["problems"] == [] and list(rat["report"]["std"])[-1] == "k6"
    # The rendered corners are found to ~0.1 px (ChArUco's sub-pixel corners against the true
    # projection): the rational fit is at that floor, the standard one 5x above it.
    assert rat["report"]["rms_px"] < 0.12 and std["report"]["rms_px"] > 4 * rat["report"]["rms_px"]
    # the rig file holds the 8 coefficients, as fitted
    cam = load_rig(tmp_path / "rig.json").camera
    np.testing.assert_allclose(cam.dist, rat["camera"]["dist"], rtol=0, atol=0)
    # Rays all across the image land where the true lens puts them, to within three of the fit's
    # own standard deviations of the principal point and (times the ray's normalised radius, up to
    # 2.9 here) the focal length: 0.8 px at the centre, 2.9 px at the image's corners, where this
    # fit is 2.3 px off (its corner views hold 26-35 corners each, found to ~0.1 px).
    g = np.stack(np.meshgrid(np.linspace(-3, 3, 121), np.linspace(-3, 3, 121)), -1).reshape(-1, 2)
    rays = np.c_[g, np.ones(len(g))]
    true = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), WIDE_K, WIDE_DIST)[0].reshape(-1, 2)
    inside = np.all((true >= 0) & (true <= np.array(WIDE_SIZE) - 1), 1)
    s = rat["report"]["std"]
    for block, limit in ((rat["camera"], 3 * (np.hypot(s["cx"], s["cy"]) + s["fx"] * np.hypot(*g[inside].T))),
                         (std["camera"], None)):
        fit = cv2.projectPoints(rays[inside], np.zeros(3), np.zeros(3), np.array(block["K"]),
                                np.array(block["dist"]))[0].reshape(-1, 2)
        err = np.linalg.norm(fit - true[inside], axis=1)
        if limit is not None:
            assert np.all(err <= limit) and err.max() < 3.0, (err.max(), limit.min())
        else:
            assert err.max() > 20  # the standard model cannot follow the lens into the corners


def test_camera_lens_model_bad_combinations_are_refused(tmp_path, wide_images, capsys):
    out = tmp_path / "cam.json"
    base = ["calibrate", "camera", *wide_images[:3], "--square", "30", "--charuco", "DICT_5X5_100", "--out", str(out)]
    for model in ("rational", "thin-prism"):
        for fix in ("yes", "no"):
            assert main([*base, "--lens-model", model, "--fix-k3", fix]) == 2
            assert _err(capsys) == (f"ringscan calibrate camera: error: --fix-k3 applies to --lens-model standard "
                                    f"only (the {model} model always fits k3) (see `ringscan calibrate camera "
                                    f"--help`)")
    with pytest.raises(SystemExit) as e:  # argparse's own refusal of a choice
        main([*base, "--lens-model", "fisheye"])
    assert e.value.code == 2
    assert "argument --lens-model: invalid choice: 'fisheye'" in capsys.readouterr().err.strip().splitlines()[-1]
    # three views and the board nowhere near the image's corners: refused, one line, nothing written
    assert main([*base, "--lens-model", "rational"]) == 1
    err = _err(capsys)
    assert "3 distinct views < 8: too few to determine its 8 distortion coefficients" in err
    assert "--force writes it anyway" in err
    assert not out.exists()


def test_charuco_takes_every_predefined_dictionary_in_any_case(tmp_path, capsys):
    from ringscan.tools.cli import build_parser

    args = build_parser("calibrate").parse_args(["calibrate", "camera", "a.png", "--square", "30", "--charuco",
                                                 "dict_5x5_1000"])
    assert args.charuco == "DICT_5X5_1000"  # (before: refused, not among ten dictionaries)
    with pytest.raises(SystemExit) as e:  # argparse's usage error, before anything is read
        main(["calibrate", "camera", str(tmp_path / "a.png"), "--square", "30", "--charuco", "DICT_9X9_50",
              "--out", str(tmp_path / "cam.json")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err, err
    assert "unknown ArUco dictionary 'DICT_9X9_50'" in err and "DICT_APRILTAG_36h11" in err, err
    assert not (tmp_path / "cam.json").exists()
