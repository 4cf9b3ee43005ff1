"""Calibration from matches against a known rig: extrinsics refined (pipeline/calibrate/rig_refine.py), a projector
fitted (projector_fit.py), the rig written as OpenCV files (opencv_files.py)."""

from __future__ import annotations

import math
import types
from dataclasses import replace

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.importer import procam_pose
from ringscan.pipeline.calibrate.opencv_files import read_opencv_calibration
from ringscan.pipeline.calibrate.opencv_files import write_opencv_procam, write_opencv_stereo
from ringscan.pipeline.calibrate.projector_fit import ProjectorSettings, fit_projector, procam_rig_from_fit
from ringscan.pipeline.calibrate.rig_refine import (
    MAX_SCALE_STD,
    refine_extrinsics,
    refine_procam_rig,
    refine_stereo_rig,
    relative_pose,
    rotation_angle_deg,
    triangulate_pair,
)
from ringscan.pipeline.formats.rig import Rig, Volume
from tests.support.stereo_truth import oblique_devices, observe, project


def rotated(dev, deg: float, axis=(0.3, -0.8, 0.5)):
    """The device turned by ``deg`` about its own centre."""
    rv = np.asarray(axis, float)
    rv *= math.radians(deg) / np.linalg.norm(rv)
    Rd, _ = cv2.Rodrigues(rv)
    return replace(dev, R=Rd @ dev.R, t=Rd @ dev.t)


@pytest.fixture(scope="module")
def seen():
    return observe(20000, noise_px=0.1, seed=3)


@pytest.fixture(scope="module")
def seen_6k():
    """6000 matches of the same devices and noise: the three-device bundle's time grows faster than the
    matches (18 s for 20000 on two cores, 3.4 s for these); its bounds hold with a margin of 2x or more
    (measured: rotation 0.00085 deg, baseline 0.053 mm, projector epipolar median 0.10 px)."""
    return observe(6000, noise_px=0.1, seed=3)


def test_refine_from_a_rotated_rig_returns_the_true_pose(seen):
    _, u1, u2, _ = seen
    cam1, cam2, _ = oblique_devices()
    ref = refine_extrinsics(cam1, rotated(cam2, 2.0), u1, u2)
    Rt, tt = relative_pose(cam1, cam2)
    assert rotation_angle_deg(ref.R @ Rt.T) < 0.01
    assert np.linalg.norm(ref.t - tt) < 0.2  # mm, over a 1.7 m baseline
    assert ref.baseline_mm == pytest.approx(np.linalg.norm(tt), rel=1e-9)
    assert ref.rotation_change_deg == pytest.approx(2.0, abs=0.02)
    # 0.1 px noise per coordinate: the matches fit the true geometry to ~0.1 px, the rotated one by tens of px
    assert ref.epipolar_before.median_px > 20
    assert ref.epipolar_after.median_px < 0.12
    assert ref.reprojection_after.rms_px < 0.1
    assert ref.problems == []


def test_refine_from_a_far_start_uses_the_essential_matrix(seen):
    _, u1, u2, _ = seen
    cam1, cam2, _ = oblique_devices()
    ref = refine_extrinsics(cam1, rotated(cam2, 120.0, axis=(1, 0.2, 0)), u1, u2)
    Rt, tt = relative_pose(cam1, cam2)
    assert ref.start == "essential"
    assert rotation_angle_deg(ref.R @ Rt.T) < 0.01
    assert np.linalg.norm(ref.t - tt) < 0.2


def test_refine_scales_to_a_given_baseline(seen):
    _, u1, u2, _ = seen
    cam1, cam2, _ = oblique_devices()
    ref = refine_extrinsics(cam1, rotated(cam2, 2.0), u1, u2, baseline_mm=1000.0)
    _, tt = relative_pose(cam1, cam2)
    assert np.linalg.norm(ref.t) == pytest.approx(1000.0)
    assert np.degrees(np.arccos(np.dot(ref.t, tt) / (1000.0 * np.linalg.norm(tt)))) < 0.01


def test_refine_procam_moves_the_camera_and_keeps_the_projector(seen):
    _, u1, _, up = seen
    cam1, _, proj = oblique_devices()
    rig = Rig(camera=rotated(cam1, 2.0), light=proj, volume=Volume(0.0, 2000.0, 3000.0))
    out, ref = refine_procam_rig(rig, u1, up)
    assert out.light is proj and out.volume == rig.volume
    assert rotation_angle_deg(out.camera.R @ cam1.R.T) < 0.01
    assert np.linalg.norm(out.camera.center - cam1.center) < 0.3  # mm, 0.9 m from the projector
    assert ref.epipolar_before.median_px > 20 and ref.epipolar_after.median_px < 0.12


def test_refine_refuses_too_few_matches(seen):
    _, u1, u2, _ = seen
    cam1, cam2, _ = oblique_devices()
    with pytest.raises(CalibrationError, match="only 20 matches"):
        refine_extrinsics(cam1, cam2, u1[:20], u2[:20])


def test_refine_of_unrelated_matches_says_it_determines_nothing(seen):
    _, u1, u2, _ = seen
    cam1, cam2, _ = oblique_devices()
    rng = np.random.default_rng(0)
    ref = refine_extrinsics(cam1, cam2, u1[:3000], u2[rng.permutation(3000)])
    assert ref.problems and any("fit the refined pose" in p or "in front" in p for p in ref.problems)


def triangulated(seen):
    """Points triangulated by the two (true) cameras from their noisy pixels, in the world frame."""
    X, u1, u2, up = seen
    cam1, cam2, _ = oblique_devices()
    R, t = relative_pose(cam1, cam2)
    n1 = cv2.undistortPoints(u1.reshape(-1, 1, 2), cam1.K, cam1.dist).reshape(-1, 2)
    n2 = cv2.undistortPoints(u2.reshape(-1, 1, 2), cam2.K, cam2.dist).reshape(-1, 2)
    Xc = triangulate_pair(R, t, n1, n2)
    return (Xc - cam1.t) @ cam1.R, up


def test_fit_projector_recovers_the_projector(seen):
    Xw, up = triangulated(seen)
    assert np.median(np.linalg.norm(Xw - seen[0], axis=1)) < 0.5  # the cameras' own error (mm)
    _, _, proj = oblique_devices()
    fit = fit_projector(Xw, up, size=(1280, 800))
    K = fit.light.K
    assert abs(K[0, 0] / proj.K[0, 0] - 1) < 0.005 and abs(K[1, 1] / proj.K[1, 1] - 1) < 0.005
    assert abs(K[0, 2] - proj.K[0, 2]) < 0.005 * 1280 and abs(K[1, 2] - proj.K[1, 2]) < 0.005 * 800
    assert rotation_angle_deg(fit.light.R @ proj.R.T) < 0.1
    assert np.linalg.norm(fit.light.center - proj.center) < 1.0
    assert fit.light.dist[0] == pytest.approx(proj.dist[0], abs=0.01)
    assert fit.rms_px < 0.3 and fit.problems == []
    assert np.isfinite(fit.condition) and fit.std["fx"] < 0.005 * K[0, 0]


def test_fit_projector_leaves_out_wrong_pairs(seen):
    Xw, up = triangulated(seen)
    up = up.copy()
    up[::20] += 40.0  # 5 % wrong codes
    fit = fit_projector(Xw, up, size=(1280, 800))
    _, _, proj = oblique_devices()
    assert fit.outliers >= len(up) // 20
    assert abs(fit.light.K[0, 0] / proj.K[0, 0] - 1) < 0.005
    assert np.linalg.norm(fit.light.center - proj.center) < 1.0


def plane_pairs(tilt_deg: float):
    """Projector pixels (0.1 px noise) of points on a plane through (0, 600, 200) tilted about world x."""
    _, _, proj = oblique_devices()
    K = proj.K.copy()
    K[1, 1] = K[0, 0]  # square pixels, no distortion: what the planar fit assumes
    proj = replace(proj, K=K, dist=np.zeros(5))
    rng = np.random.default_rng(1)
    a, b = rng.uniform(-900, 900, 5000), rng.uniform(-700, 700, 5000)
    c, s = math.cos(math.radians(tilt_deg)), math.sin(math.radians(tilt_deg))
    X = np.stack([a, 600 + c * b, 200 + s * b], 1)
    up, ok = project(proj, X)
    return proj, X[ok], up[ok] + rng.normal(0, 0.1, (int(ok.sum()), 2))


def test_fit_projector_refuses_a_plane_and_fits_a_tilted_one_with_a_known_principal_point():
    proj, X, up = plane_pairs(30.0)
    with pytest.raises(CalibrationError, match="nearly on one plane"):
        fit_projector(X, up, size=(1280, 800))
    fit = fit_projector(X, up, size=(1280, 800),
                        settings=ProjectorSettings(principal_point=(proj.K[0, 2], proj.K[1, 2])))
    assert "cx" in fit.fixed and any("one plane" in p for p in fit.problems)
    assert abs(fit.light.K[0, 0] / proj.K[0, 0] - 1) < 0.005, fit.std


def test_fit_projector_says_a_facing_plane_does_not_fix_the_focal_length():
    # a plane parallel to the projector's image: focal length and distance trade exactly, the RMS stays small
    proj, X, up = plane_pairs(0.0)
    fit = fit_projector(X, up, size=(1280, 800),
                        settings=ProjectorSettings(principal_point=(proj.K[0, 2], proj.K[1, 2])))
    assert fit.rms_px < 0.3
    assert any("do not determine the focal length" in p for p in fit.problems)


def test_fit_projector_refuses_too_few_points_and_a_wrong_size(seen):
    Xw, up = triangulated(seen)
    with pytest.raises(CalibrationError, match="only 50 points"):
        fit_projector(Xw[:50], up[:50], size=(1280, 800))
    with pytest.raises(CalibrationError, match="outside a 640x400 projector"):
        fit_projector(Xw, up, size=(640, 400))


def test_procam_rig_from_fit_reprojects_like_the_truth(seen):
    Xw, up = triangulated(seen)
    cam1, _, proj = oblique_devices()
    fit = fit_projector(Xw, up, size=(1280, 800))
    rig = procam_rig_from_fit(cam1, fit.light, Xw)
    R, T = procam_pose(rig)
    Rt, Tt = relative_pose(cam1, proj)
    assert rotation_angle_deg(R @ Rt.T) < 0.1 and np.linalg.norm(T - Tt) < 1.0
    assert rig.volume.z_max > 0


def test_opencv_procam_file_reads_back(tmp_path):
    cam1, _, proj = oblique_devices()
    rig = Rig(camera=cam1, light=proj, volume=Volume(0.0, 2000.0, 3000.0))
    p = tmp_path / "procam.yml"
    write_opencv_procam(p, rig)
    d = read_opencv_calibration(p)
    R, T = relative_pose(cam1, proj)
    assert np.allclose(d["cam_K"], cam1.K) and np.allclose(d["proj_K"], proj.K)
    assert np.allclose(d["cam_dist"], cam1.dist) and np.allclose(d["proj_dist"], proj.dist)
    assert np.allclose(d["R"], R) and np.allclose(d["T"], T)
    assert d["cam_size"] == (1920, 1280)
    assert [p.name for p in tmp_path.iterdir()] == ["procam.yml"]  # no temporary left


def test_opencv_stereo_file_has_the_sample_layout(tmp_path):
    cam1, cam2, _ = oblique_devices()
    p = tmp_path / "stereo.yml"
    write_opencv_stereo(p, types.SimpleNamespace(camera=cam1, camera2=cam2))
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    R, T = relative_pose(cam1, cam2)
    assert np.allclose(fs.getNode("cam1_intrinsics").mat(), cam1.K)
    assert np.allclose(fs.getNode("cam2_distorsion").mat().ravel(), cam2.dist)
    assert [int(fs.getNode("cam2_size").at(i).real()) for i in range(2)] == [1920, 1280]
    assert np.allclose(fs.getNode("R").mat(), R) and np.allclose(fs.getNode("T").mat().ravel(), T)
    # as in OpenCV's structured-light test data: the 4x4 [R | T; 0 0 0 1], written before R and T
    assert np.allclose(fs.getNode("RT_cam1_2_cam2").mat(), np.vstack([np.hstack([R, T[:, None]]), [[0, 0, 0, 1]]]))
    keys = list(fs.root().keys())
    fs.release()
    assert keys == ["cam1_intrinsics", "cam1_distorsion", "cam1_size", "cam2_intrinsics", "cam2_distorsion",
                    "cam2_size", "RT_cam1_2_cam2", "R", "T"]


def test_opencv_writers_refuse_the_wrong_rig(tmp_path):
    cam1, _, proj = oblique_devices()
    rig = Rig(camera=cam1, light=proj, volume=Volume(0.0, 2000.0, 3000.0))
    with pytest.raises(CalibrationError, match="one camera"):
        write_opencv_stereo(tmp_path / "s.yml", rig)
    assert not (tmp_path / "s.yml").exists()


def test_stereo_rig_refine_keeps_camera_1_and_a_two_camera_rig_moves_its_projector(seen):
    _, u1, u2, up = seen
    cam1, cam2, proj = oblique_devices()
    rig = Rig(camera=cam1, camera2=rotated(cam2, 2.0), light=rotated(proj, 1.0), volume=Volume(0.0, 2000.0, 3000.0))
    out, _ = refine_stereo_rig(rig, u1, u2)
    assert out.camera is cam1 and out.light is rig.light
    assert rotation_angle_deg(out.camera2.R @ cam2.R.T) < 0.01 and np.linalg.norm(out.camera2.center - cam2.center) < 0.3
    out, _ = refine_procam_rig(out, u1, up)  # two cameras: the projector moves, the cameras stay
    assert out.camera is cam1
    assert rotation_angle_deg(out.light.R @ proj.R.T) < 0.01 and np.linalg.norm(out.light.center - proj.center) < 0.3
    with pytest.raises(CalibrationError, match="one camera"):
        refine_stereo_rig(Rig(camera=cam1, light=proj, volume=rig.volume), u1, u2)


def test_refine_with_the_calibrated_projector_adjusts_all_three_and_leaves_out_one_that_does_not_fit(seen_6k):
    _, u1, u2, up = seen_6k
    cam1, cam2, proj = oblique_devices()
    Rt, tt = relative_pose(cam1, cam2)
    s = np.full(len(u1), 0.1)
    ref = refine_extrinsics(cam1, rotated(cam2, 2.0), u1, u2, light=proj, uv_light=up, sigma1=s, sigma2=s,
                            sigma_light=s)
    assert ref.method == "three-device" and ref.bundle_used == len(u1)
    assert ref.light_epipolar.median_px < 0.2
    assert rotation_angle_deg(ref.R @ Rt.T) < 0.005
    assert np.linalg.norm(ref.t - tt) < 0.1
    assert ref.epipolar_after.median_px < 0.12 and ref.problems == []
    # a projector whose pose does not fit camera 1's matches is not held against camera 2
    off = refine_extrinsics(cam1, rotated(cam2, 2.0), u1, u2, light=rotated(proj, 1.0), uv_light=up)
    assert off.method == "two-view" and off.light_epipolar.median_px > 1.0
    assert "left out" in off.notes[0]
    assert rotation_angle_deg(off.R @ Rt.T) < 0.01


def _depths(cam1, cam2, R, t, ua, ub):
    n1 = cv2.undistortPoints(ua.reshape(-1, 1, 2).astype(np.float64), cam1.K, cam1.dist).reshape(-1, 2)
    n2 = cv2.undistortPoints(ub.reshape(-1, 1, 2).astype(np.float64), cam2.K, cam2.dist).reshape(-1, 2)
    X = cv2.triangulatePoints(np.eye(3, 4), np.c_[R, t], n1.T, n2.T)
    return X[2] / X[3]


def test_refine_says_how_far_the_matches_fix_the_scale(seen):
    _, u1, u2, _ = seen
    cam1, cam2, _ = oblique_devices()
    clean = refine_extrinsics(cam1, rotated(cam2, 2.0), u1, u2)
    # 0.1 px noise over 20k matches and a 1.7 m baseline: the vergence, and so the scale, is well fixed
    assert clean.scale_std < 5e-4 and not any("scale" in n for n in clean.notes)
    # camera 2's lens bends its pixels radially in a way the rig does not know (k1 = 0.02 more): the
    # epipolar fit still looks good, but the pose fitted to each quarter of the image turns about the
    # vergence axis, and the scale of the depths is fixed only to ~0.5 %, which it says
    c = cam2.K[:2, 2]
    f = cam2.K[0, 0]
    x = (u2 - c) / f
    bent = c + f * x * (1 + 0.02 * (x ** 2).sum(1, keepdims=True))
    ref = refine_extrinsics(cam1, rotated(cam2, 2.0), u1, bent)
    assert ref.epipolar_after.median_px < 0.2
    assert ref.scale_std > 10 * clean.scale_std and ref.vergence_std_deg > 10 * clean.vergence_std_deg
    Rt, tt = relative_pose(cam1, cam2)
    scale_error = abs(np.median(_depths(cam1, cam2, ref.R, ref.t, u1, bent) / _depths(cam1, cam2, Rt, tt, u1, bent))
                      - 1)
    assert scale_error < 3 * ref.scale_std  # the stated uncertainty covers the scale the pose actually gives
    assert ref.report()["scale_std"] == ref.scale_std
    assert ref.scale_std > MAX_SCALE_STD and any("known distance" in n for n in ref.notes)
