"""``ringscan evaluate`` on two-camera scans against the virtual rig's truth (camera
1's): a scan simulated with ``--camera2`` whose projector is then made
``uncalibrated`` (coverage from the light the simulator recorded, ``truth.light``),
and the ``decoded`` codec (no rings: coverage over camera 1's lit pixels)."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.rig import UncalibratedLight, rig_to_dict, save_rig
from ringscan.pipeline.formats.scan import load_scan, save_scan
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.tools.cli import main
from tests.support.two_camera_scan import two_camera_rig


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """``ringscan simulate --camera2`` of a small rig (320x256 cameras, gray-rings with the angle code)."""
    root = tmp_path_factory.mktemp("eval2")
    rig = dataclasses.replace(two_camera_rig(), camera2=None)
    save_rig(root / "rig.json", rig)
    assert main(["simulate", "--rig", str(root / "rig.json"), "--camera2", "--scene", "sphere", "--codec",
                 "gray-rings", "--bits", "5", "--pitch", "16", "--sector-bits", "6", "--angle-steps", "4",
                 "--out", str(root / "scan"), "--device", "cpu", "--no-progress"]) == 0
    return root


def _uncalibrated_copy(src, dst, *, keep_truth_light=True):
    shutil.copytree(src, dst)
    scan = load_scan(dst)
    li = scan.rig.light
    extra = scan.extra
    if not keep_truth_light:
        extra = {**extra, "truth": {k: v for k, v in extra["truth"].items() if k != "light"}}
    save_scan(dataclasses.replace(scan, rig_ref=None, extra=extra, rig=dataclasses.replace(
        scan.rig, light=UncalibratedLight(width=li.width, height=li.height, gamma=li.gamma))))
    return load_scan(dst)


def test_evaluate_a_two_camera_scan_with_an_uncalibrated_projector(simulated, tmp_path, capsys):
    scan = _uncalibrated_copy(simulated / "scan", tmp_path / "scan")
    # the light the simulator rendered with
    assert scan.extra["truth"]["light"] == rig_to_dict(load_scan(simulated / "scan").rig)["light"]
    rep = reconstruct_scan(scan, tmp_path / "rec", progress=False)
    assert rep["views"][0]["rays"] == "camera-camera"
    assert main(["evaluate", str(tmp_path / "rec"), "--truth", str(scan.folder), "--report",
                 str(tmp_path / "ev.json"), "--no-progress"]) == 0
    ev = json.loads((tmp_path / "ev.json").read_text())
    v = ev["views"]["view_000"]
    assert v["points"] == rep["views"][0]["points"] and v["median_mm"] < 0.05, v
    # the same figures as against the calibrated original (the recorded light is the real one)
    twin = evaluate_recon(tmp_path / "rec", simulated / "scan")["views"]["view_000"]
    assert v["coverage"] == pytest.approx(twin["coverage"]) and v["truth_pixels"] == twin["truth_pixels"]
    assert v["coverage_radius_mm"] == pytest.approx(twin["coverage_radius_mm"])
    # camera-camera: what both cameras see (the opposite camera sees about half of camera 1's sphere)
    assert 0.3 < v["coverage"] < 0.95, v["coverage"]
    # no recorded light (a scan simulated before ringscan recorded it): camera 1's lit pixels,
    # two camera pixels, no slope allowance; still the same distances
    bare = _uncalibrated_copy(simulated / "scan", tmp_path / "bare", keep_truth_light=False)
    b = evaluate_recon(tmp_path / "rec", bare)["views"]["view_000"]
    assert b["median_mm"] == pytest.approx(v["median_mm"]) and b["truth_pixels"] >= v["truth_pixels"]
    assert b["coverage"] is not None and 0.0 < b["coverage"] <= 1.0


def test_evaluate_the_decoded_codec(tmp_path):
    from tests.support.two_camera_scan import simulate_decoded_two_camera_scan

    scan = simulate_decoded_two_camera_scan(tmp_path / "scan", integer=True)
    rep = reconstruct_scan(scan, tmp_path / "rec", progress=False)  # auto: all three rays
    ev = evaluate_recon(tmp_path / "rec", scan)["views"]["view_000"]
    assert ev["points"] == rep["views"][0]["points"] and ev["median_mm"] < 0.05, ev
    # the decoded pixels are camera 1's lit ones; auto fills those camera 2 does not see
    assert ev["coverage"] > 0.95, ev["coverage"]
