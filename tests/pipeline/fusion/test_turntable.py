"""Fusion of turntable views (pipeline/fusion/turntable.py) against a known object."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.fusion.recon import fuse_recon, load_recon, recon_folder
from ringscan.pipeline.fusion.turntable import FuseSettings, FusionView, fuse_views, plane_residuals
from tests.support.fusion_synth import point_to_mesh, synthetic_scan, visible_truth, write_recon, wrong_axis

FAST = FuseSettings(voxel_mm=0.5)


@pytest.fixture(scope="module")
def scan():
    return synthetic_scan()


@pytest.fixture(scope="module")
def fused_right(scan):
    obj, rig, angles, views = scan
    return fuse_views(list(views), rig, settings=FAST)


def _cloud_to_truth(res, obj) -> np.ndarray:
    return point_to_mesh(np.asarray(res.cloud.points), obj)


def test_fused_cloud_matches_the_object(scan, fused_right):
    obj, rig, angles, views = scan
    d = _cloud_to_truth(fused_right, obj)
    # 0.03 mm noise per point, averaged by the voxel grid: the fused cloud lies on the truth.
    assert d.mean() < 0.03
    assert np.quantile(d, 0.99) < 0.1
    # Completeness: the part of the object the views saw is covered.
    vis = visible_truth(obj, rig, angles, n=5000)
    tree = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.asarray(fused_right.cloud.points)))
    tree.knn_index()
    _, d2 = tree.knn_search(o3d.core.Tensor(vis), 1)
    assert np.mean(np.sqrt(d2.numpy()[:, 0]) < 1.0) > 0.9
    assert len(fused_right.residuals) == 8 and fused_right.pose_graph is not None


def test_views_turned_back_by_minus_theta(scan):
    """Without refinement, the right axis alone must put every view on the object."""
    obj, rig, angles, views = scan
    res = fuse_views(list(views), rig, settings=dataclasses.replace(FAST, refine=False))
    for pcd in res.views:
        assert point_to_mesh(np.asarray(pcd.points), obj).mean() < 0.05
    np.testing.assert_allclose(res.corrections, np.broadcast_to(np.eye(4), (8, 4, 4)))
    # The camera centre turns with the view: at 180 degrees it is mirrored through the axis.
    c0, c4 = res.camera_centers[0], res.camera_centers[4]
    np.testing.assert_allclose(c4[:2], -c0[:2], atol=1e-9)
    assert c4[2] == pytest.approx(c0[2])


def test_refinement_recovers_a_wrong_axis(scan, fused_right):
    obj, rig, angles, views = scan
    bad = wrong_axis(rig, 0.5, 1.0)
    right = _cloud_to_truth(fused_right, obj).mean()
    unrefined = _cloud_to_truth(fuse_views(list(views), bad, settings=dataclasses.replace(FAST, refine=False)),
                                obj).mean()
    res = fuse_views(list(views), bad, settings=FAST)
    refined = _cloud_to_truth(res, obj).mean()
    assert unrefined > 10 * right  # the wrong axis matters ...
    assert refined <= 1.5 * right  # ... and the refinement undoes it
    r = {v.name: v for v in res.residuals}
    assert r["view_000"].correction_mm == pytest.approx(0.0, abs=1e-9)  # angle 0 is held fixed
    # The view at 180 degrees was moved most: ~2 mm for a 1 mm axis offset.
    assert 1.5 < r["view_004"].correction_mm < 3.5
    assert r["view_004"].rmse_before_mm > 5 * r["view_004"].rmse_mm
    assert all(v.fitness > 0.95 for v in res.residuals)


def test_normals_point_out_of_the_object(scan, fused_right):
    obj, rig, angles, views = scan
    pts = np.asarray(fused_right.cloud.points)
    nrm = np.asarray(fused_right.cloud.normals)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj))
    # A step along the normal must leave the object (signed distance grows).
    out = scene.compute_signed_distance(o3d.core.Tensor((pts + 0.5 * nrm).astype(np.float32))).numpy()
    assert np.mean(out > 0.2) > 0.98


def test_outliers_and_ground_plane_removed(scan):
    obj, rig, angles, views = scan
    rng = np.random.default_rng(3)
    v0 = views[0]
    lo, hi = v0.points.min(axis=0), v0.points.max(axis=0)
    stray = rng.uniform(lo - 5, hi + 5, (60, 3))
    stray = stray[point_to_mesh(stray, obj) > 2.0]
    xy = rng.uniform(-15, 15, (3000, 2))
    plane = np.column_stack([xy, rng.normal(0, 0.03, len(xy))])
    pts = np.concatenate([v0.points, stray, plane])
    noisy = dataclasses.replace(v0, points=pts, confidence=np.ones(len(pts)))
    res = fuse_views([noisy], rig, settings=FAST)
    d = _cloud_to_truth(res, obj)
    assert d.max() < 0.3  # stray points and the plane are gone
    assert res.residuals[0].points_kept < len(v0.points) + 1
    keep_plane = fuse_views([noisy], rig, settings=dataclasses.replace(FAST, ground_clip_mm=None))
    assert np.sum(np.abs(np.asarray(keep_plane.cloud.points)[:, 2]) < 0.2) > 1000


def test_min_confidence_drops_points(scan):
    obj, rig, angles, views = scan
    v0 = views[0]
    conf = np.where(np.arange(len(v0.points)) % 2 == 0, 0.9, 0.1)
    res = fuse_views([dataclasses.replace(v0, confidence=conf)], rig,
                     settings=dataclasses.replace(FAST, min_confidence=0.5, statistical_neighbors=0, radius_mm=0))
    assert res.residuals[0].points_kept == int(np.sum(conf >= 0.5))


def test_mappings_and_an_empty_view_are_accepted(scan):
    obj, rig, angles, views = scan
    vs = [dict(points=v.points, turntable_deg=v.turntable_deg, camera_center=v.camera_center) for v in views[:3]]
    vs.append(dict(name="empty", points=np.zeros((0, 3)), turntable_deg=270.0, camera_center=views[0].camera_center))
    res = fuse_views(vs, rig, settings=FAST)
    assert res.names[-1] == "empty" and res.residuals[-1].points_kept == 0
    assert len(res.views[-1].points) == 0
    assert _cloud_to_truth(res, obj).mean() < 0.03


def test_a_view_of_two_points_fuses_with_the_others(scan):
    """A view that keeps only two points after cleaning has no normals: it is fused, and the other views'
    residuals are measured against the views that have them (it raised IndexError: the normals of the
    reference views no longer lined up with their points)."""
    obj, rig, angles, views = scan
    few = FusionView(name="few", points=views[1].points[:2].copy(), turntable_deg=views[1].turntable_deg,
                     camera_center=views[1].camera_center, confidence=np.ones(2))
    res = fuse_views([views[0], few, views[2]], rig,
                     settings=FuseSettings(voxel_mm=0.5, radius_mm=0, statistical_neighbors=0))
    assert res.names == [views[0].name, "few", views[2].name] and len(res.views[1].points) == 2
    assert res.residuals[0].points_kept > 0 and _cloud_to_truth(res, obj).mean() < 0.03


def test_bad_input(scan):
    obj, rig, angles, views = scan
    with pytest.raises(ValueError, match="non-empty"):
        fuse_views([], rig)
    with pytest.raises(ValueError, match=r"views\[0\].*shape \(N, 3\)"):
        fuse_views([dict(points=np.zeros((5, 2)), turntable_deg=0.0, camera_center=[0, 0, 1])], rig)
    with pytest.raises(ValueError, match="normals"):
        fuse_views([dict(points=np.zeros((5, 3)), normals=np.zeros((4, 3)), turntable_deg=0.0,
                         camera_center=[0, 0, 1])], rig)
    with pytest.raises(ValueError, match="no turntable"):
        fuse_views(list(views[:2]), dataclasses.replace(rig, turntable=None))
    with pytest.raises(ValueError, match="no points left"):
        fuse_views([dataclasses.replace(views[0], points=views[0].points - [0, 0, 500.0])], rig)
    with pytest.raises(ValueError, match="voxel_mm"):
        fuse_views(list(views[:1]), rig, settings=FuseSettings(voxel_mm=-1))
    with pytest.raises(ValueError, match="unknown keys"):
        fuse_views([dict(points=np.zeros((5, 3)), turntable_deg=0.0, camera_center=[0, 0, 1], colour=1)], rig)


def test_recon_folder_roundtrip(scan, tmp_path, fused_right):
    obj, rig, angles, views = scan
    write_recon(tmp_path, views, rig)
    vs, rig2, rep = load_recon(tmp_path)
    assert [v.name for v in vs] == [v.name for v in views]
    np.testing.assert_allclose(vs[3].points, views[3].points, atol=1e-4)
    assert rig2.turntable is not None and rep["views"][2]["ply"] == "view_002.ply"
    res = fuse_recon(tmp_path, settings=FAST)
    assert _cloud_to_truth(res, obj).mean() < 0.03
    assert json.dumps(res.report())  # JSON-ready


def test_recon_folder_errors(scan, tmp_path):
    obj, rig, angles, views = scan
    write_recon(tmp_path, views[:2], rig)
    (tmp_path / "view_001.ply").unlink()
    with pytest.raises(FormatError, match="view_001.ply: file not found"):
        load_recon(tmp_path)
    rep = json.loads((tmp_path / "report.json").read_text())
    rep["views"][0]["turntable_deg"] = "ten"
    (tmp_path / "report.json").write_text(json.dumps(rep))
    with pytest.raises(FormatError, match=r"views\[0\]\.turntable_deg"):
        load_recon(tmp_path)
    with pytest.raises(FormatError, match="not found"):
        recon_folder(tmp_path / "nothing")
    (tmp_path / "plain").mkdir()
    with pytest.raises(FormatError, match="neither"):
        recon_folder(tmp_path / "plain")
    (tmp_path / "scan").mkdir()
    (tmp_path / "scan" / "scan.json").write_text("{}")
    with pytest.raises(ValueError, match="scan folder"):
        fuse_recon(tmp_path / "scan")


def test_view_cloud_dataclass_is_frozen(scan):
    v = scan[3][0]
    assert isinstance(v, FusionView)
    with pytest.raises(dataclasses.FrozenInstanceError):
        v.name = "x"


def test_plane_residuals_of_points_off_a_plane():
    # A grid on z = 0 (normals +z) and points 0.2 mm above half of it, 5 mm above the rest:
    # the near half pairs within 1 mm, at a point-to-plane distance of exactly 0.2 mm.
    g = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), axis=-1).reshape(-1, 2)
    q = np.column_stack([g, np.zeros(len(g))])
    normals = np.tile([0.0, 0.0, 1.0], (len(q), 1))
    p = q[::2] + [0.3, 0.0, 0.2]
    p[len(p) // 2:, 2] = 5.0
    frac, rms = plane_residuals(o3d, p, q, normals, 1.0)
    assert frac == pytest.approx(0.5)
    assert rms == pytest.approx(0.2, abs=1e-12)
    assert plane_residuals(o3d, p + [0.0, 0.0, 10.0], q, normals, 1.0) is None
    assert plane_residuals(o3d, p[:0], q, normals, 1.0) is None

