"""``ringscan batch`` prints each scan's calibration check (its worst view: epipolar
distance of a two-camera scan, the warning of a rig that does not fit) and writes it
into batch_report.json."""

from __future__ import annotations

import dataclasses
import json
import shutil

import cv2
import numpy as np

from ringscan.pipeline.formats.scan import load_scan, save_scan
from ringscan.tools.cli import main
from tests.support.two_camera_scan import simulate_two_camera_scan


def _rotate_camera2(folder, deg):
    """Camera 2's rotation relative to camera 1 off by ``deg`` (its translation kept)."""
    scan = load_scan(folder)
    rig = scan.rig
    c1, c2 = rig.camera, rig.camera2
    R_rel = c2.R @ c1.R.T
    T_rel = c2.t - R_rel @ c1.t
    R_bad = cv2.Rodrigues(np.array([0.0, np.radians(deg), 0.0]))[0] @ R_rel
    bad = dataclasses.replace(c2, R=R_bad @ c1.R, t=R_bad @ c1.t + T_rel)
    save_scan(dataclasses.replace(scan, rig_ref=None, rig=dataclasses.replace(rig, camera2=bad)))


def test_batch_prints_and_reports_each_scans_calibration_check(tmp_path, capsys):
    root = tmp_path / "scans"
    simulate_two_camera_scan(root / "good")
    shutil.copytree(root / "good", root / "off")
    _rotate_camera2(root / "off", 2.0)
    out = tmp_path / "out"
    assert main(["batch", str(root), "--out", str(out), "--workers", "0", "--rays", "camera-camera",
                 "--device", "cpu", "--no-progress"]) == 0
    lines = capsys.readouterr().out.splitlines()
    checks = {ln.split(":")[0]: ln for ln in lines if "calibration check" in ln}
    assert set(checks) == {"good", "off"}, lines
    assert "worst view view_000 (camera-camera): epipolar distance" in checks["good"]
    assert "warning" not in checks["good"]
    assert "warning: the rig file does not fit the images in 1 view(s)" in checks["off"]
    rep = {e["scan"]: e for e in json.loads((out / "batch_report.json").read_text())["scans"]}
    good, off = rep["good"]["calibration_check"], rep["off"]["calibration_check"]
    assert good["kind"] == off["kind"] == "epipolar" and good["view"] == "view_000"
    assert good["fits"] and good["median_px"] < 0.3 and good["views_not_fitting"] == 0
    assert not off["fits"] and off["median_px"] > 3.0 and off["views_not_fitting"] == 1
    # the same check as the scan's own report.json
    own = json.loads((out / "off" / "report.json").read_text())["views"][0]["calibration_check"]
    assert off["median_px"] == own["median_px"] and off["p95_px"] == own["p95_px"]
    # a rerun skips the scans (done) and still prints their checks
    assert main(["batch", str(root), "--out", str(out), "--workers", "0", "--rays", "camera-camera",
                 "--device", "cpu", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "skipped" in text and text.count("calibration check, worst view") == 2, text


def test_batch_reports_a_projector_that_misses_the_cameras(tmp_path, capsys):
    """Three rays: each scan's line says how far the projector misses the two cameras' points, and warns
    where its calibration is off by pixels (the light moved 2 projector px, which camera-projector checks
    cannot see along camera 1's rays); batch_report.json carries it."""
    root = tmp_path / "scans"
    simulate_two_camera_scan(root / "good")
    shutil.copytree(root / "good", root / "off")
    scan = load_scan(root / "off")
    li = scan.rig.light
    moved = dataclasses.replace(li, t=li.t + li.pixel_pitch_mm * np.array([1.6, 1.2, 0.0]))
    save_scan(dataclasses.replace(scan, rig_ref=None, rig=dataclasses.replace(scan.rig, light=moved)))
    out = tmp_path / "out"
    assert main(["batch", str(root), "--out", str(out), "--workers", "0", "--rays", "all", "--device", "cpu",
                 "--no-progress"]) == 0
    lines = {ln.split(":")[0]: ln for ln in capsys.readouterr().out.splitlines() if "calibration check" in ln}
    assert "projector against the cameras' points, worst view view_000" in lines["good"]
    assert "discounted" not in lines["good"] and "warning" not in lines["good"], lines["good"]
    assert "its ray discounted in 1 view(s)" in lines["off"]
    assert "warning: the projector's calibration does not fit the cameras' in 1 view(s)" in lines["off"]
    rep = {e["scan"]: e for e in json.loads((out / "batch_report.json").read_text())["scans"]}
    p_good = rep["good"]["calibration_check"]["projector_check"]
    p_off = rep["off"]["calibration_check"]["projector_check"]
    assert p_good["residual_px_median"] < 0.5 < 1.0 < p_off["residual_px_median"]
    assert p_off["views_discounted"] == p_off["views_not_fitting"] == 1
