"""``ringscan calibrate refine`` and ``projector-from-scan`` on scans of a known rig.

The camera-projector scans are imported-style (``decoded`` codec) scans rendered
exactly here: every camera pixel's ray meets a wavy surface and the projector
pixel there is written in the codec's 1/32 px fixed point. Two-camera matching
(``match_view``) is stood in for by exact matches of the same rig (monkeypatched),
so these tests check the commands, not the matcher.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.importer import procam_pose

from ringscan.pipeline.calibrate.opencv_files import read_opencv_calibration
from ringscan.pipeline.calibrate.rig_refine import relative_pose, rotation_angle_deg
from ringscan.pipeline.formats.patterns import DECODED_SCALE
from ringscan.pipeline.formats.rig import Rig, UncalibratedLight, load_rig, save_rig
from ringscan.tools import cmd_calibrate_scan
from ringscan.tools.cli import main
from tests.support.decoded_scan import VOLUME, write_decoded_scan
from tests.support.stereo_truth import oblique_devices, observe


def turned(dev, deg: float):
    rv = np.array([0.3, -0.8, 0.5])
    rv *= math.radians(deg) / np.linalg.norm(rv)
    Rd, _ = cv2.Rodrigues(rv)
    return replace(dev, R=Rd @ dev.R, t=Rd @ dev.t)


def surface_z(x, y):
    return 300 + 150 * np.sin(x / 300.0) * np.cos(y / 250.0)


def decoded_frames(cam, proj, step: int = 1):
    """proj_u, proj_v, contrast frames of the camera seeing the wavy surface under the projector."""
    ys, xs = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    pix = np.stack([xs.ravel(), ys.ravel()], 1)
    n = cv2.undistortPoints(pix.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)
    d = np.concatenate([n, np.ones((n.shape[0], 1))], 1) @ cam.R  # world directions
    C = cam.center
    s = (300.0 - C[2]) / d[:, 2]
    for _ in range(30):  # fixed point on the surface (slopes are small)
        X = C + s[:, None] * d
        s = (surface_z(X[:, 0], X[:, 1]) - C[2]) / d[:, 2]
    X = C + s[:, None] * d
    up, _ = cv2.projectPoints((X @ proj.R.T + proj.t).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), proj.K, proj.dist)
    up = up.reshape(-1, 2)
    ok = (up[:, 0] >= 0) & (up[:, 0] <= proj.width - 1) & (up[:, 1] >= 0) & (up[:, 1] <= proj.height - 1)
    fu = np.where(ok, np.round((up[:, 0] + 1) * DECODED_SCALE), 0).astype(np.uint16).reshape(cam.height, cam.width)
    fv = np.where(ok, np.round((up[:, 1] + 1) * DECODED_SCALE), 0).astype(np.uint16).reshape(cam.height, cam.width)
    return {"proj_u": fu, "proj_v": fv, "contrast": np.where(ok, 200 * 257, 0).astype(np.uint16).reshape(fu.shape)}


def half_camera(cam):
    """``cam`` at half its resolution, the same field of view (a quarter of the pixels to render and refine)."""
    K = cam.K.copy()
    K[:2, :2] /= 2.0
    K[:2, 2] = (K[:2, 2] + 0.5) / 2.0 - 0.5
    return replace(cam, width=cam.width // 2, height=cam.height // 2, K=K)


@pytest.fixture(scope="module")
def procam_scan(tmp_path_factory):
    """A camera-projector scan of the wavy surface, camera 1 at half resolution (960x640)."""
    folder = tmp_path_factory.mktemp("procam")
    cam1, _, proj = oblique_devices()
    cam1 = half_camera(cam1)
    rig = Rig(camera=cam1, light=proj, volume=VOLUME)
    write_decoded_scan(folder, rig, decoded_frames(cam1, proj))
    return folder


@pytest.fixture(scope="module")
def stereo_scan(tmp_path_factory):
    folder = tmp_path_factory.mktemp("stereo")
    cam1, cam2, _ = oblique_devices()
    write_decoded_scan(folder, Rig(camera=cam1, camera2=cam2, light=UncalibratedLight(width=1280, height=800),
                           volume=VOLUME))
    return folder


@pytest.fixture
def matched(monkeypatch):
    """match_view stood in for by exact (0.1 px noise) matches of the true rig."""
    X, u1, u2, up = observe(20000, noise_px=0.1, seed=5)
    monkeypatch.setattr(cmd_calibrate_scan, "view_matches",
                        lambda scan, view, *, device, ring_curvature: (u1, u2, up, None))


def test_refine_a_procam_scan_brings_the_camera_back(procam_scan, tmp_path, capsys):
    cam1, _, proj = oblique_devices()
    cam1 = half_camera(cam1)  # the scan's
    bad = tmp_path / "bad.json"
    save_rig(bad, Rig(camera=turned(cam1, 2.0), light=proj, volume=VOLUME))
    out = tmp_path / "fixed.json"
    # 20000 of the scan's decoded pixels (960x640; the default takes 200000): measured 1e-4 deg, 0.006 mm and
    # 0.007 px after, the bounds below 50x that; the subsample's own path (a seeded random subset) runs too
    assert main(["calibrate", "refine", str(procam_scan), "--rig", str(bad), "--out", str(out),
                 "--report", str(tmp_path / "rep.json"), "--max-matches", "20000", "-q"]) == 0
    text = capsys.readouterr().out
    assert "camera against the projector: 20000 matches used" in text and "epipolar distance  before" in text
    rig = load_rig(out)
    assert rotation_angle_deg(rig.camera.R @ cam1.R.T) < 0.01
    assert np.linalg.norm(rig.camera.center - cam1.center) < 0.5
    rep = json.loads((tmp_path / "rep.json").read_text())
    assert rep["epipolar_px"]["before"]["median_px"] > 20 and rep["epipolar_px"]["after"]["median_px"] < 0.05
    R, T = procam_pose(rig)
    d = read_opencv_calibration(tmp_path / "fixed.yml")
    assert np.allclose(d["R"], R) and np.allclose(d["T"], T)


def test_refine_a_stereo_scan_brings_camera_2_back(stereo_scan, tmp_path, matched, capsys):
    cam1, cam2, _ = oblique_devices()
    bad = tmp_path / "bad.json"
    save_rig(bad, Rig(camera=cam1, camera2=turned(cam2, 2.0), light=UncalibratedLight(1280, 800), volume=VOLUME))
    out = tmp_path / "fixed.json"
    assert main(["calibrate", "refine", str(stereo_scan), "--rig", str(bad), "--out", str(out),
                 "--opencv", str(tmp_path / "cv.yaml"), "-q"]) == 0
    assert "camera 2 against camera 1" in capsys.readouterr().out
    rig = load_rig(out)
    assert rotation_angle_deg(rig.camera2.R @ cam2.R.T) < 0.01
    assert rig.camera.R.tolist() == cam1.R.tolist()
    fs = cv2.FileStorage(str(tmp_path / "cv.yaml"), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode("R").mat(), relative_pose(rig.camera, rig.camera2)[0])
    fs.release()
    assert not (tmp_path / "fixed.yml").exists()


def test_projector_from_scan_writes_a_procam_rig(stereo_scan, tmp_path, matched, capsys):
    out = tmp_path / "procam.json"
    assert main(["calibrate", "projector-from-scan", str(stereo_scan), "--out", str(out), "--stereo-out",
                 str(tmp_path / "three.json"), "-q"]) == 0
    printed = capsys.readouterr().out
    assert "projector: RMS reprojection error" in printed
    # the lens has k1, k2 and no tangential terms: auto says what it chose and why, and the points' depth
    assert "distortion p1, p2: held at 0 (auto" in printed and "distortion k1: fitted" in printed
    assert "depth along the projector's axis" in printed
    cam1, _, proj = oblique_devices()
    rig = load_rig(out)
    R, T = procam_pose(rig)
    Rt, Tt = relative_pose(cam1, proj)
    assert rotation_angle_deg(R @ Rt.T) < 0.1 and np.linalg.norm(T - Tt) < 1.0
    assert abs(rig.light.K[0, 0] / proj.K[0, 0] - 1) < 0.005
    assert np.allclose(read_opencv_calibration(tmp_path / "procam.yml")["R"], R)
    three = load_rig(tmp_path / "three.json")
    assert three.camera2 is not None and np.linalg.norm(three.light.center - proj.center) < 1.0


@pytest.mark.parametrize("flag, expect", [((), True), (("--ring-curvature", "off"), False)])
def test_the_calibrate_commands_match_with_the_ring_curvature_correction(stereo_scan, tmp_path, monkeypatch, flag,
                                                                        expect):
    # a fit of intrinsics takes the blurred ring edge's 1/rho shift for focal length and distance: on by default
    import ringscan.pipeline.reconstruct.stereo as stereo

    seen = []

    def stop(scan, view, *, device, settings):
        seen.append(settings.sample.ring_curvature)
        raise RuntimeError("matched")

    monkeypatch.setattr(stereo, "match_view", stop)
    for cmd in ("refine", "projector-from-scan"):
        with pytest.raises(RuntimeError, match="matched"):
            main(["calibrate", cmd, str(stereo_scan), "--out", str(tmp_path / f"{cmd}.json"), "-q", *flag])
    assert seen == [expect, expect]


def test_two_view_leaves_the_projector_out_of_the_cli_refine(stereo_scan, tmp_path, matched, capsys):
    """refine --pair cameras on a rig with a calibrated projector: by default the projector joins (three-device),
    --two-view leaves it out (the epipolar adjustment alone); both bring camera 2 back."""
    cam1, cam2, proj = oblique_devices()
    bad = tmp_path / "bad.json"
    save_rig(bad, Rig(camera=cam1, camera2=turned(cam2, 2.0), light=proj, volume=VOLUME))
    got = {}
    for extra in ([], ["--two-view"]):
        name = "two" if extra else "three"
        out = tmp_path / f"{name}.json"
        assert main(["calibrate", "refine", str(stereo_scan), "--rig", str(bad), "--out", str(out),
                     "--report", str(tmp_path / f"{name}_rep.json"), "--max-matches", "4000", "-q", *extra]) == 0
        got[name] = (capsys.readouterr().out, json.loads((tmp_path / f"{name}_rep.json").read_text()), load_rig(out))
    for name, (text, rep, rig) in got.items():
        assert rotation_angle_deg(rig.camera2.R @ cam2.R.T) < 0.01, name
        assert rig.light.R.tolist() == proj.R.tolist()  # the projector is held
    text, rep, _ = got["three"]
    assert rep["method"] == "three-device" and rep["third_device"] == "projector" and rep["bundle_matches_used"] > 0
    assert "projector against camera 1 (held)" in text and "bundle adjustment over camera 1, camera 2" in text
    text, rep, _ = got["two"]
    assert rep["method"] == "two-view" and rep["third_device"] is None and rep["light_epipolar_px"] is None
    assert rep["bundle_matches_used"] == 0 and "bundle adjustment" not in text and "(held)" not in text


def test_refine_the_projector_of_a_two_camera_rig_with_camera_2_held(stereo_scan, tmp_path, matched, capsys):
    """refine --pair projector on a two-camera rig: camera 2 (pose held) joins the adjustment as the third device
    and the projector comes back; where camera 2's own pose does not fit, it is left out with a note, and
    --two-view leaves it out."""
    cam1, cam2, proj = oblique_devices()

    def run(name, rig, *extra):
        src, out = tmp_path / f"{name}_in.json", tmp_path / f"{name}.json"
        save_rig(src, rig)
        assert main(["calibrate", "refine", str(stereo_scan), "--rig", str(src), "--pair", "projector",
                     "--out", str(out), "--report", str(tmp_path / f"{name}_rep.json"), "--max-matches", "4000", "-q",
                     *extra]) == 0
        return capsys.readouterr().out, json.loads((tmp_path / f"{name}_rep.json").read_text()), load_rig(out)

    text, rep, rig = run("three", Rig(camera=cam1, camera2=cam2, light=turned(proj, 2.0), volume=VOLUME))
    assert "projector against camera 1" in text and "camera 2 against camera 1 (held)" in text
    assert rep["method"] == "three-device" and rep["third_device"] == "camera 2" and rep["pair"] == "projector"
    assert rep["epipolar_px"]["before"]["median_px"] > 20 and rep["epipolar_px"]["after"]["median_px"] < 0.15
    assert rotation_angle_deg(rig.light.R @ proj.R.T) < 0.01 and np.linalg.norm(rig.light.center - proj.center) < 1
    assert rig.camera.R.tolist() == cam1.R.tolist() and rig.camera2.R.tolist() == cam2.R.tolist()
    R, T = procam_pose(rig)
    assert np.allclose(read_opencv_calibration(tmp_path / "three.yml")["R"], R)
    # camera 2's own pose off: it cannot serve as the held third device
    text, rep, rig = run("off", Rig(camera=cam1, camera2=turned(cam2, 2.0), light=turned(proj, 2.0), volume=VOLUME))
    assert rep["method"] == "two-view" and rep["light_epipolar_px"]["median_px"] > 1.0
    assert "note: camera 2 was left out of the adjustment" in text and "--pair cameras" in text
    assert rotation_angle_deg(rig.light.R @ proj.R.T) < 0.01
    _, rep, _ = run("two", Rig(camera=cam1, camera2=cam2, light=turned(proj, 2.0), volume=VOLUME), "--two-view")
    assert rep["method"] == "two-view" and rep["third_device"] is None

def _one_line_error(capsys, *words):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    return err


def test_bad_input_one_line_nothing_written(procam_scan, stereo_scan, tmp_path, capsys):
    out = tmp_path / "o.json"
    cam1, cam2, proj = oblique_devices()
    stereo_rig = tmp_path / "stereo.json"  # its camera 1 the size of procam_scan's: refused for being two cameras
    save_rig(stereo_rig, Rig(camera=half_camera(cam1), camera2=cam2, light=UncalibratedLight(1280, 800),
                             volume=VOLUME))
    scan_json = procam_scan / "scan.json"
    cases = [
        # a procam rig where a two-camera one is needed
        (["calibrate", "projector-from-scan", str(procam_scan), "--out", str(out)], 1, ["one camera", "two-camera"]),
        # a two-camera rig for a one-camera scan
        (["calibrate", "refine", str(procam_scan), "--rig", str(stereo_rig), "--out", str(out)], 1,
         ["two cameras", "the scan"]),
        (["calibrate", "refine", str(stereo_scan), "--pair", "projector", "--out", str(out)], 1,
         ["not calibrated", "projector-from-scan"]),
        (["calibrate", "refine", str(procam_scan), "--pair", "cameras", "--out", str(out)], 1, ["one camera"]),
        (["calibrate", "refine", str(tmp_path / "nothing"), "--out", str(out)], 1, ["nothing"]),
        (["calibrate", "refine", str(procam_scan), "--rig", str(tmp_path / "x.yml"), "--out", str(out)], 1,
         ["OpenCV", "JSON"]),
        (["calibrate", "refine", str(procam_scan), "--out", str(out), "--opencv", str(tmp_path / "x.txt")], 1,
         [".txt"]),
        (["calibrate", "refine", str(procam_scan), "--out", str(tmp_path / "x.yml")], 1, [".json"]),
        (["calibrate", "refine", str(procam_scan), "--out", str(scan_json)], 1, ["overwrite"]),
        (["calibrate", "refine", str(procam_scan), "--out", str(out), "--view", "nope"], 1, ["nope", "v1"]),
        (["calibrate", "refine", str(procam_scan), "--out", str(out), "--max-matches", "5"], 2, ["--max-matches"]),
        (["calibrate", "refine", str(procam_scan), "--out", str(out), "--baseline", "-3"], 2, ["--baseline"]),
        (["calibrate", "projector-from-scan", str(stereo_scan), "--out", str(out), "--projector", "12"], 2,
         ["--projector"]),
        (["calibrate", "projector-from-scan", str(stereo_scan), "--out", str(out), "--tangential", "maybe"], 2,
         ["--tangential"]),
    ]
    (tmp_path / "x.yml").write_text("%YAML:1.0\n")
    before = scan_json.read_bytes()
    for argv, rc, words in cases:
        assert main(argv) == rc, argv
        _one_line_error(capsys, *words)
        assert not out.exists() and not out.with_suffix(".yml").exists()
    assert scan_json.read_bytes() == before


def test_a_flat_scene_is_refused_unless_forced(stereo_scan, tmp_path, monkeypatch, capsys):
    cam1, cam2, proj = oblique_devices()
    rng = np.random.default_rng(2)
    X = np.stack([rng.uniform(-800, 800, 8000), rng.uniform(0, 1200, 8000), np.full(8000, 250.0)], 1)
    from tests.support.stereo_truth import project

    (u1, o1), (u2, o2), (up, op) = project(cam1, X), project(cam2, X), project(proj, X)
    ok = o1 & o2 & op
    monkeypatch.setattr(cmd_calibrate_scan, "view_matches", lambda scan, view, **kw: (u1[ok], u2[ok], up[ok], None))
    out = tmp_path / "p.json"
    assert main(["calibrate", "projector-from-scan", str(stereo_scan), "--out", str(out)]) == 1
    _one_line_error(capsys, "nearly on one plane", "principal point")
    assert not out.exists()


# ----------------------------------------------------------------------------- through match_view


@pytest.fixture(scope="module")
def virtual_two_camera(tmp_path_factory):
    """A two-camera scan of the virtual rig (a sphere on the plane) with a perspective projector."""
    from ringscan.pipeline.formats.rig import default_rig
    from tests.support.two_camera_scan import simulate_two_camera_scan, two_camera_rig

    rig = replace(two_camera_rig(), light=default_rig(light_model="perspective").light)
    folder = tmp_path_factory.mktemp("virtual2") / "scan"
    simulate_two_camera_scan(folder, rig=rig)
    return folder, rig


def sphere_errors(folder, rig) -> float:
    """Median distance (mm) of the scan's camera-camera points under ``rig`` from the 80 mm sphere
    or the plane (whichever is nearer)."""
    from ringscan.pipeline.calibrate.rig_refine import triangulate_pair
    from ringscan.pipeline.formats.scan import load_scan
    from ringscan.pipeline.reconstruct.stereo import match_view

    scan = load_scan(folder)
    m = match_view(scan, scan.views[0], device="cpu")
    c1, c2 = rig.camera, rig.camera2
    n1 = cv2.undistortPoints(m.uv1.reshape(-1, 1, 2), c1.K, c1.dist).reshape(-1, 2)
    n2 = cv2.undistortPoints(m.uv2.reshape(-1, 1, 2), c2.K, c2.dist).reshape(-1, 2)
    R, t = relative_pose(c1, c2)
    X = (triangulate_pair(R, t, n1, n2) - c1.t) @ c1.R
    d = np.minimum(np.abs(np.linalg.norm(X - np.array([0.0, 0.0, 40.0]), axis=1) - 40.0), np.abs(X[:, 2]))
    return float(np.median(d))


def test_refine_and_projector_from_a_matched_scan(virtual_two_camera, tmp_path, capsys):
    folder, rig = virtual_two_camera
    bad = tmp_path / "bad.json"
    save_rig(bad, replace(rig, camera2=turned(rig.camera2, 2.0)))
    out = tmp_path / "fixed.json"
    assert main(["calibrate", "refine", str(folder), "--rig", str(bad), "--out", str(out), "--device", "cpu",
                 "--report", str(tmp_path / "rep.json"), "-q"]) == 0
    rep = json.loads((tmp_path / "rep.json").read_text())
    fixed = load_rig(out)
    # the true rig's own residual over the same matches
    assert main(["calibrate", "refine", str(folder), "--out", str(tmp_path / "true.json"), "--device", "cpu",
                 "--report", str(tmp_path / "true_rep.json"), "-q"]) == 0
    true_med = json.loads((tmp_path / "true_rep.json").read_text())["epipolar_px"]["before"]["median_px"]
    assert rep["epipolar_px"]["before"]["median_px"] > 1.0  # the turned rig does not fit
    assert abs(rep["epipolar_px"]["after"]["median_px"] - true_med) < 0.1
    assert rotation_angle_deg(fixed.camera2.R @ rig.camera2.R.T) < 0.1
    # issue 21's target: the refined rig's camera-camera points within 10 % of the true rig's error
    # (the calibrated projector joins the adjustment; two views alone leave them ~2x the true rig's)
    assert rep["method"] == "three-device"
    err_fixed, err_true = sphere_errors(folder, fixed), sphere_errors(folder, rig)
    assert err_fixed <= 1.1 * err_true, (err_fixed, err_true)
    capsys.readouterr()
    procam = tmp_path / "procam.json"
    assert main(["calibrate", "projector-from-scan", str(folder), "--rig", str(out), "--out", str(procam),
                 "--device", "cpu", "-q"]) == 0
    got = load_rig(procam)
    R, T = procam_pose(got)
    Rt, Tt = relative_pose(rig.camera, rig.light)
    assert abs(got.light.K[0, 0] / rig.light.K[0, 0] - 1) < 0.01
    assert rotation_angle_deg(R @ Rt.T) < 0.2 and np.linalg.norm(T - Tt) < 3.0
