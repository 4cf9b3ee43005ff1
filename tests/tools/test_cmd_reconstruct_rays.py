"""``ringscan reconstruct --rays`` on a two-camera scan: the rays chosen, the
calibration check printed per view and written to report.json, the per-point
residual in the PLY; two-camera rays on a one-camera scan: one line, exit 1."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ringscan.pipeline.formats.ply import read_ply
from ringscan.tools.cli import main
from tests.support.tiny_scan import simulate_tiny_scan
from tests.support.two_camera_scan import simulate_two_camera_scan


@pytest.fixture(scope="module")
def stereo_folder(tmp_path_factory):
    return simulate_two_camera_scan(tmp_path_factory.mktemp("stereo") / "scan").folder


def test_rays_camera_camera_prints_the_epipolar_check(stereo_folder, tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["reconstruct", str(stereo_folder), "--out", str(out), "--rays", "camera-camera", "--device", "cpu",
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "view_000: camera-camera: epipolar distance of the camera matches: median" in text
    assert "does not fit" not in text
    rep = json.loads((out / "report.json").read_text())
    v = rep["views"][0]
    assert v["rays"] == "camera-camera" and v["calibration_check"]["kind"] == "epipolar"
    assert v["calibration_check"]["median_px"] < 0.3 and v["calibration_check"]["fits"]
    assert rep["settings"]["stereo"]["rays"] == "camera-camera"
    ply = read_ply(out / "view_000.ply")
    assert np.all(ply["residual"] >= 0) and np.median(ply["residual"]) < 0.5
    # the residual map of that view, with its check
    assert main(["view", "--residuals", str(out / "view_000.ply"), "--out", str(tmp_path / "res.png")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    summ = json.loads(lines[0])
    assert summ["points"] == ply["residual"].size and summ["calibration_check"]["kind"] == "epipolar"
    assert abs(summ["median"] - np.median(ply["residual"])) < 1e-6
    assert (tmp_path / "res.png").stat().st_size > 1000


def test_rays_all_prints_the_projector_against_the_cameras(stereo_folder, tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["reconstruct", str(stereo_folder), "--out", str(out), "--rays", "all", "--device", "cpu",
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    chk = json.loads((out / "report.json").read_text())["views"][0]["stereo"]["projector_check"]
    line = [t for t in text.splitlines() if "projector against the cameras' points" in t]
    assert len(line) == 1 and line[0].startswith("view_000: all: ") and f"({chk['samples']} samples)" in line[0]
    assert not chk["floor_applied"] and "discounted" not in line[0]  # the virtual rig's projector is right


def test_two_camera_rays_on_a_one_camera_scan_is_one_line(tmp_path, capsys):
    scan = simulate_tiny_scan(tmp_path / "tiny")
    assert main(["reconstruct", str(scan.folder), "--out", str(tmp_path / "rec"), "--rays", "all", "--device", "cpu",
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "needs a two-camera view" in err and "Traceback" not in err, err
    assert not (tmp_path / "rec").exists()  # checked before anything is written


def test_projector_rays_with_an_uncalibrated_projector_is_one_line(stereo_folder, tmp_path, capsys):
    import dataclasses
    import shutil

    from ringscan.pipeline.formats.rig import UncalibratedLight
    from ringscan.pipeline.formats.scan import load_scan, save_scan

    folder = tmp_path / "scan"
    shutil.copytree(stereo_folder, folder)
    scan = load_scan(folder)
    li = scan.rig.light
    save_scan(dataclasses.replace(scan, rig_ref=None, rig=dataclasses.replace(
        scan.rig, light=UncalibratedLight(width=li.width, height=li.height, gamma=li.gamma))))
    for rays in ("all", "camera-projector"):
        assert main(["reconstruct", str(folder), "--out", str(tmp_path / rays), "--rays", rays, "--device", "cpu",
                     "--no-progress"]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "not calibrated" in err and "Traceback" not in err, err
        assert not (tmp_path / rays).exists()


def test_rays_is_a_choice(capsys):
    with pytest.raises(SystemExit) as e:
        main(["reconstruct", "x", "--out", "y", "--rays", "both"])
    assert e.value.code == 2


@pytest.fixture(scope="module")
def no_angle_folder(tmp_path_factory):
    from tests.support.two_camera_scan import ANGLE_PATTERNS
    return simulate_two_camera_scan(tmp_path_factory.mktemp("noangle") / "scan",
                                    patterns={**ANGLE_PATTERNS, "bits": 3, "angle_steps": 0}).folder


def test_two_camera_rays_need_a_codec_with_the_full_projector_coordinate(no_angle_folder, tmp_path, capsys):
    # gray-rings without the angle code: its samples carry the ring radius only, so the
    # cameras cannot be matched; refused before anything is written (settings.json included)
    for rays in ("camera-camera", "all"):
        out = tmp_path / rays
        assert main(["reconstruct", str(no_angle_folder), "--out", str(out), "--rays", rays, "--device", "cpu",
                     "--no-progress"]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err, err
        assert "scan.json" in err and "ring radius only" in err and "--angle-steps" in err, err
        assert not out.exists()
    # auto on a calibrated projector: camera 1 and the projector
    out = tmp_path / "auto"
    assert main(["reconstruct", str(no_angle_folder), "--out", str(out), "--device", "cpu", "--no-progress"]) == 0
    v = json.loads((out / "report.json").read_text())["views"][0]
    assert v["rays"] == "camera-projector" and v["points"] > 0


def test_auto_on_an_uncalibrated_projector_without_the_angle_is_one_line(no_angle_folder, tmp_path, capsys):
    import dataclasses
    import shutil

    from ringscan.pipeline.formats.rig import UncalibratedLight
    from ringscan.pipeline.formats.scan import load_scan, save_scan

    folder = tmp_path / "scan"
    shutil.copytree(no_angle_folder, folder)
    scan = load_scan(folder)
    li = scan.rig.light
    save_scan(dataclasses.replace(scan, rig_ref=None, rig=dataclasses.replace(
        scan.rig, light=UncalibratedLight(width=li.width, height=li.height, gamma=li.gamma))))
    assert main(["reconstruct", str(folder), "--out", str(tmp_path / "rec"), "--device", "cpu",
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "ring radius only" in err and "calibrated projector" in err, err
    assert not (tmp_path / "rec").exists()
