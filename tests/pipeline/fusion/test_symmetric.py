"""Refinement cannot spin a symmetric object: the turntable angle is a prior that the
refinement corrects only as far as the views' overlap fixes it (pipeline/fusion/turntable.py,
docs/fusion.md "Symmetric objects").

Pure geometry: a sphere, a cylinder and an asymmetric blob ray-cast by a small camera
(tests/support/fusion_synth.py) with 0.03 mm of noise along the rays, at their true
turntable angles but one view (view_002) reported 2 degrees off."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.fusion.turntable import (
    WEAK_MOTION_RATIO,
    FuseSettings,
    fuse_views,
    overlap_information,
    weak_motions,
)
from tests.support.fusion_synth import lumpy_object, point_to_mesh, scan_views, small_rig

ANGLES = tuple(k * 60.0 for k in range(6))
OFF_DEG = 2.0
"""view_002's reported turntable angle is this far from the one it was scanned at."""
SETTINGS = FuseSettings(voxel_mm=0.5)
Z = np.array([0.0, 0.0, 1.0])  # the default rig's turntable axis: world z through the origin


def _scan(mesh):
    """(views with view_002's angle off by OFF_DEG, rig): 6 views of ``mesh`` by a 240 x 192 camera."""
    rig = small_rig(240, 192, 480.0)
    views = scan_views(mesh, rig, ANGLES, noise_mm=0.03)
    views[2] = dataclasses.replace(views[2], turntable_deg=views[2].turntable_deg + OFF_DEG)
    return views, rig


def _spin_deg(P: np.ndarray) -> float:
    """The turn of a correction about the turntable axis (degrees, signed)."""
    R = P[:3, :3]
    angle = math.acos(min(1.0, max(-1.0, (np.trace(R) - 1.0) / 2.0)))
    if angle < 1e-12:
        return 0.0
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2.0 * math.sin(angle))
    return math.degrees(angle) * float(axis @ Z)


def _sphere():
    m = o3d.geometry.TriangleMesh.create_sphere(25.0, resolution=80)
    return m.translate((0.0, 0.0, 25.0))


def _cylinder():
    m = o3d.geometry.TriangleMesh.create_cylinder(20.0, 40.0, resolution=120, split=20)
    return m.translate((0.0, 0.0, 20.0))


def _held_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and "does not fix the turntable angle" in r.getMessage()]


def test_sphere_keeps_every_turntable_pose(caplog):
    mesh = _sphere()
    views, rig = _scan(mesh)
    with caplog.at_level(logging.WARNING, logger="ringscan.pipeline.fusion.turntable"):
        res = fuse_views(views, rig, settings=SETTINGS)
    for r, P in zip(res.residuals, res.corrections):
        # Without the check ICP turned these views by 45-180 degrees and moved them 5-25 mm (the
        # caps of a sphere overlap best when they coincide). With it the views keep the turntable
        # pose to the noise: 0.006 mm and 0.022 degrees measured (0.03 mm noise a point).
        assert r.correction_mm < 0.05 and r.correction_deg < 0.1, r
        assert abs(_spin_deg(P)) < 0.01
        assert r.angle_held is True and r.motions_held == 3  # the sphere's three rotations
    # view_002's 2 degrees cannot be seen on a sphere, and do no harm: it lies on the truth.
    assert point_to_mesh(np.asarray(res.views[2].points), mesh).mean() < 0.03  # 0.018 mm measured
    warned = _held_warnings(caplog)
    assert len(warned) == 1 and "6 of 6 views" in warned[0] and "view_005" in warned[0]
    assert res.report()["angle_held"] == [f"view_{i:03d}" for i in range(6)]


def test_cylinder_keeps_its_spin_and_refines_the_rest(caplog):
    mesh = _cylinder()
    views, rig = _scan(mesh)
    with caplog.at_level(logging.WARNING, logger="ringscan.pipeline.fusion.turntable"):
        res = fuse_views(views, rig, settings=SETTINGS)
    for r, P in zip(res.residuals, res.corrections):
        # The spin about the cylinder's (the turntable's) axis stays where the turntable put it:
        # <= 0.01 degrees measured (without the check: 45-180 degrees). The other motions are
        # refined and move by the noise: tilts of up to 0.12 degrees, 0.18 mm measured, as on
        # the asymmetric blob below (0.29 degrees).
        assert abs(_spin_deg(P)) < 0.02
        assert r.correction_mm < 0.3 and r.correction_deg < 0.3, r
        assert r.angle_held is True and r.motions_held == 1  # the spin alone: the top fixes the rest
    assert point_to_mesh(np.asarray(res.views[2].points), mesh).mean() < 0.08  # 0.053 mm measured
    assert len(_held_warnings(caplog)) == 1


def test_asymmetric_object_still_gets_its_angle_corrected(caplog):
    mesh = lumpy_object()
    views, rig = _scan(mesh)
    with caplog.at_level(logging.WARNING, logger="ringscan.pipeline.fusion.turntable"):
        res = fuse_views(views, rig, settings=SETTINGS)
    spins = [_spin_deg(P) for P in res.corrections]
    # view_002 is turned back by the 2 degrees its angle was off (2.04 measured); the others
    # keep theirs to the noise (<= 0.04 degrees of spin measured).
    assert spins[2] == pytest.approx(OFF_DEG, abs=0.1)
    assert max(abs(s) for k, s in enumerate(spins) if k != 2) < 0.1
    assert all(r.angle_held is False and r.motions_held == 0 for r in res.residuals)
    assert point_to_mesh(np.asarray(res.views[2].points), mesh).mean() < 0.03  # 0.019 mm measured
    assert _held_warnings(caplog) == [] and res.report()["angle_held"] == []


def test_no_refinement_checks_nothing():
    views, rig = _scan(_sphere())
    res = fuse_views(views[:2], rig, settings=dataclasses.replace(SETTINGS, refine=False))
    assert all(r.angle_held is None and r.motions_held is None for r in res.residuals)


# ----------------------------------------------------------------------------- the check itself


def _patch(kind: str, n: int = 4000, seed: int = 0):
    """(points, unit normals) of a patch of a surface, exactly on it."""
    rng = np.random.default_rng(seed)
    if kind == "sphere":  # a 60-degree cap of a sphere of radius 25 about (0, 0, 25)
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v = v[v[:, 2] > 0.5]
        return v * 25.0 + [0.0, 0.0, 25.0], v
    if kind == "cylinder":  # a 90-degree strip of the side of a cylinder of radius 20 about z
        a = rng.uniform(0.0, math.pi / 2, n)
        z = rng.uniform(5.0, 35.0, n)
        nrm = np.stack([np.cos(a), np.sin(a), np.zeros(n)], axis=1)
        return nrm * 20.0 + np.stack([np.zeros(n), np.zeros(n), z], axis=1), nrm
    if kind == "plane":
        p = np.concatenate([rng.uniform(-20, 20, (n, 2)), np.full((n, 1), 10.0)], axis=1)
        return p, np.tile(Z, (n, 1))
    if kind == "box":  # three faces of a box meeting at a corner
        k = rng.integers(0, 3, n)
        p = rng.uniform(0.0, 20.0, (n, 3))
        p[np.arange(n), k] = 20.0
        return p, np.eye(3)[k]
    raise ValueError(kind)


@pytest.mark.parametrize("kind, free, turn_free", [
    ("sphere", 3, True),      # every rotation about the centre slides the cap along itself
    ("cylinder", 2, True),    # the spin about its axis and the slide along it
    ("plane", 3, True),       # two slides in the plane, the turn about its normal (the axis here)
    ("box", 0, False),        # three faces fix everything
])
def test_weak_motions_of_pure_shapes(kind, free, turn_free):
    p, n = _patch(kind)
    H, matched = overlap_information(p, p, n, max_distance_mm=1.0)
    assert len(matched) == len(p)  # a patch against itself: every point matched
    assert weak_motions(H, matched, axis=(np.zeros(3), Z)) == (free, turn_free)


def test_weak_motions_of_a_view_of_the_blob():
    """The asymmetric blob's overlap fixes every motion, with a margin of more than 2x over
    the ratio (1.4e-2 and above measured on 8-view scans, docs/fusion.md)."""
    rig = small_rig(240, 192, 480.0)
    (view,) = scan_views(lumpy_object(), rig, (0.0,), noise_mm=0.0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(view.points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5, max_nn=40))
    H, matched = overlap_information(view.points, view.points, np.asarray(pcd.normals), max_distance_mm=1.0)
    assert weak_motions(H, matched) == (0, None)
    assert weak_motions(H, matched, ratio=WEAK_MOTION_RATIO * 2) == (0, None)


def test_no_overlap_leaves_everything_free():
    H, matched = overlap_information(np.zeros((0, 3)), np.ones((5, 3)), np.tile(Z, (5, 1)), max_distance_mm=1.0)
    assert len(matched) == 0 and weak_motions(H, matched, axis=(np.zeros(3), Z)) == (6, True)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match=r"target_normals must have shape \(5, 3\), got \(4, 3\)"):
        overlap_information(np.zeros((3, 3)), np.ones((5, 3)), np.ones((4, 3)), max_distance_mm=1.0)
    with pytest.raises(ValueError, match="max_distance_mm must be > 0"):
        overlap_information(np.zeros((3, 3)), np.ones((5, 3)), np.ones((5, 3)), max_distance_mm=0.0)
    with pytest.raises(ValueError, match=r"H must be a finite \(6, 6\) matrix"):
        weak_motions(np.eye(5), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"ratio must lie in \(0, 1\)"):
        weak_motions(np.eye(6), np.zeros((3, 3)), ratio=2.0)


# ----------------------------------------------------------------------------- sparse ring curves


def _ring_curves_on_sphere(radius=20.0, spacing_mm=3.2, step_mm=1.3, noise_mm=0.02, seed=0):
    """(points, radial unit normals) of latitude circles on a sphere about the origin, spacing_mm
    apart in height and sampled every step_mm along each (the paper's sparse rings, one point a
    camera pixel), the upper cap only (what a camera above sees)."""
    rng = np.random.default_rng(seed)
    pts = []
    for z in np.arange(2.0, radius - 1.0, spacing_mm):
        r = math.sqrt(radius * radius - z * z)
        t = np.arange(0.0, 2 * math.pi * r, step_mm) / r
        pts.append(np.stack([r * np.cos(t), r * np.sin(t), np.full(t.size, z)], 1))
    P = np.concatenate(pts)
    n = P / np.linalg.norm(P, axis=1, keepdims=True)
    return P + noise_mm * rng.standard_normal(P.shape), n


def test_normals_of_sparse_ring_curves_lie_across_the_surface():
    """Rings 3.2 mm apart: a 2.5 mm normal neighbourhood holds one ring, a line, whose PCA
    normal is any direction across it. Such points take their normal from the nearest
    points instead, which reach the neighbouring rings."""
    from ringscan.pipeline.fusion.turntable import _estimate_surface_normals

    P, n = _ring_curves_on_sphere()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    s = FuseSettings()
    plain = o3d.geometry.PointCloud(pcd)
    plain.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=s.normal_radius_mm, max_nn=s.normal_max_nn))
    _estimate_surface_normals(o3d, pcd, s)

    def error_deg(c):
        return np.degrees(np.arccos(np.clip(np.abs(np.sum(np.asarray(c.normals) * n, axis=1)), 0, 1)))

    # measured: 0.24 / 0.80 degrees (median / p90) against 58 / 84 within the radius alone
    assert np.median(error_deg(plain)) > 20
    assert np.median(error_deg(pcd)) < 2 and np.percentile(error_deg(pcd), 90) < 5


def test_sparse_ring_views_of_a_sphere_keep_their_turntable_poses(tmp_path, caplog):
    """Six views of the tiny scan's sphere (7 ring curves a view, ~240 points): point-to-plane
    ICP between views snaps one view's curves onto its neighbour's wherever they run, and the
    pose graph turned views by 50-69 degrees. A pair ICP carries further than its own matching
    window has slid, not corrected: it keeps the turntable's relative pose, and one line says so."""
    from ringscan.pipeline.fusion.recon import fuse_recon
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan
    from tests.support.tiny_scan import simulate_tiny_scan

    scan = simulate_tiny_scan(tmp_path / "scan", turntable_deg=tuple(k * 60.0 for k in range(6)))
    reconstruct_scan(scan, tmp_path / "rec", progress=False)
    with caplog.at_level(logging.WARNING, logger="ringscan.pipeline.fusion.turntable"):
        res = fuse_recon(tmp_path / "rec", settings=FuseSettings(radius_mm=0.0, statistical_neighbors=0))
    # measured: up to 6.4 degrees and 1.8 mm (the rest of what the sparse curves let ICP slide)
    assert max(r.correction_deg for r in res.residuals) < 10
    slid = [r.getMessage() for r in caplog.records if "further than its" in r.getMessage()]
    assert len(slid) == 1 and "kept at the turntable's relative pose" in slid[0]
