"""Several poses of one object (flip and rescan): pose_scene, fuse_poses, the CLI."""

from __future__ import annotations

import functools
import json
import math

import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.fusion.poses import AlignmentError, PoseSettings, fuse_poses
from ringscan.pipeline.simulate.scenes import SceneMesh, make_scene, pose_rotation, pose_scene
from tests.support.fusion_synth import lumpy_object, scan_views, small_rig, write_recon

FAST = PoseSettings(ransac_trials=2, ransac_iterations=50_000, voxel_mm=0.5)


def _rot_err_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(R) - 1.0) / 2.0))))


@functools.lru_cache(maxsize=1)
def _object_in_two_poses():
    """(upright mesh, flipped mesh, T flipped-frame -> upright-frame)."""
    m = lumpy_object()
    # A few Gaussian knobs make it distinctive enough for FPFH features.
    v = np.asarray(m.vertices)
    c = v.mean(axis=0)
    u = (v - c) / np.linalg.norm(v - c, axis=1, keepdims=True)
    rng = np.random.default_rng(7)
    dirs = rng.normal(size=(9, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    bump = sum(4.0 * np.exp(-(1.0 - u @ d) / 0.02) for d in dirs)
    m.vertices = o3d.utility.Vector3dVector(v + u * bump[:, None])
    scene = SceneMesh(vertices=np.asarray(m.vertices), faces=np.asarray(m.triangles, np.int32), name="lumpy")
    up, T_up = pose_scene(scene, None)
    down, T_down = pose_scene(scene, "x:110,z:40")

    def mesh(s):
        out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(s.vertices), o3d.utility.Vector3iVector(s.faces))
        out.compute_triangle_normals()
        return out

    return mesh(up), mesh(down), T_up @ np.linalg.inv(T_down)


def _partial_cloud(mesh, *, min_nz: float, n: int = 40_000, noise: float = 0.02, seed: int = 0):
    """Points of the surface facing up (normal z > min_nz), as a lit-from-above scan sees it."""
    o3d.utility.random.seed(seed)
    pcd = mesh.sample_points_uniformly(n, use_triangle_normal=True)
    nrm = np.asarray(pcd.normals)
    keep = nrm[:, 2] > min_nz
    rng = np.random.default_rng(seed)
    out = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        np.asarray(pcd.points)[keep] + rng.normal(0.0, noise, (int(keep.sum()), 3))))
    out.normals = o3d.utility.Vector3dVector(nrm[keep])
    return out


def test_pose_scene_turns_and_sets_down():
    s = make_scene("cube", size_mm=40.0)
    same, T = pose_scene(s, "upright")
    assert same is s and np.array_equal(T, np.eye(4))
    for pose in ("upside-down", "side-x", "side-y", "x:135,z:20"):
        p, T = pose_scene(s, pose)
        assert np.allclose(s.vertices @ T[:3, :3].T + T[:3, 3], p.vertices)
        assert abs(p.vertices[:, 2].min()) < 1e-9
        lo, hi = p.vertices.min(0), p.vertices.max(0)
        assert np.allclose(0.5 * (lo + hi)[:2], 0.0, atol=1e-9)
    assert np.allclose(pose_rotation("upside-down"), np.diag([1.0, -1.0, -1.0]))
    assert np.allclose(pose_rotation("side-x") @ [0, 1, 0], [0, 0, 1])       # +y side up
    assert np.allclose(pose_rotation("side-y") @ [-1, 0, 0], [0, 0, 1])      # -x side up
    d = np.stack([pose_rotation(p).T @ [0.0, 0.0, 1.0] for p in ("upright", "tetra-1", "tetra-2", "tetra-3")])
    G = d @ d.T
    assert np.allclose(G[~np.eye(4, dtype=bool)], -1.0 / 3.0)           # a regular tetrahedron of up directions
    for bad in ("sideways", "w:3", "x:abc", "x90"):
        with pytest.raises(ValueError, match="pose"):
            pose_rotation(bad)


def test_fuse_poses_recovers_the_known_transform():
    up, down, T_true = _object_in_two_poses()
    a = _partial_cloud(up, min_nz=-0.3, seed=1)
    b = _partial_cloud(down, min_nz=-0.3, seed=2)
    res = fuse_poses([a, b], names=["upright", "flipped"], settings=FAST)
    r = res.registrations[1]
    dT = np.linalg.inv(T_true) @ r.transform
    c = np.asarray(b.points).mean(axis=0)
    t_err = np.linalg.norm((r.transform[:3, :3] - T_true[:3, :3]) @ c + r.transform[:3, 3] - T_true[:3, 3])
    assert _rot_err_deg(dT[:3, :3]) < 0.5
    assert t_err < 0.5
    assert r.fitness >= FAST.min_fitness and r.plane_rmse_mm <= FAST.max_rmse_mm and r.aligned_with == "upright"
    assert np.array_equal(res.transforms[0], np.eye(4)) and res.registrations[0].fitness == 1.0
    # The merged cloud covers the whole object, normals still outward.
    d = o3d.t.geometry.RaycastingScene()
    d.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(up))
    pts = np.asarray(res.cloud.points, np.float32)
    assert np.quantile(d.compute_distance(o3d.core.Tensor(pts)).numpy(), 0.95) < 0.3
    ctr = np.asarray(up.vertices).mean(axis=0)
    outward = np.einsum("ij,ij->i", np.asarray(res.cloud.normals), pts - ctr) > 0
    assert outward.mean() > 0.97
    assert set(np.unique(res.point_view)) == {0, 1}
    rep = res.report()
    assert rep["poses"][1]["name"] == "flipped" and len(rep["poses"][1]["transform"]) == 4
    json.dumps(rep)


def test_three_poses_go_through_the_pose_graph():
    """With three poses every pair is registered and the pose graph refines them all."""
    up, down, T_down = _object_in_two_poses()
    scene = SceneMesh(vertices=np.asarray(up.vertices), faces=np.asarray(up.triangles, np.int32), name="lumpy")
    third, T3 = pose_scene(scene, "y:-100,z:70")
    side = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(third.vertices),
                                     o3d.utility.Vector3iVector(third.faces))
    side.compute_triangle_normals()
    T_side = np.linalg.inv(T3)                       # up is already upright: side frame -> up frame
    clouds = [_partial_cloud(mesh, min_nz=-0.3, seed=k) for k, mesh in enumerate((up, down, side))]
    res = fuse_poses(clouds, names=["up", "down", "side"], settings=FAST)
    assert res.pose_graph is not None and len(res.pose_graph.edges) == 3
    for i, T_true in ((1, T_down), (2, T_side)):
        T = res.transforms[i]
        c = np.asarray(clouds[i].points).mean(axis=0)
        assert _rot_err_deg((np.linalg.inv(T_true) @ T)[:3, :3]) < 0.5, i
        assert np.linalg.norm((T[:3, :3] - T_true[:3, :3]) @ c + T[:3, 3] - T_true[:3, 3]) < 0.5, i
    assert res.report()["poses"][2]["fitness"] >= FAST.min_fitness
    assert set(np.unique(res.point_view)) == {0, 1, 2}


def test_failed_alignment_names_the_pose():
    up, _, _ = _object_in_two_poses()
    a = _partial_cloud(up, min_nz=-0.3, seed=1)
    rng = np.random.default_rng(3)
    # A dense 12 mm cube of random points: enough points to register (min_points), nothing that
    # matches the object. (Sparse junk spread over the object's size made RANSAC run all its
    # iterations, seconds per trial, for the same failure.)
    junk = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.uniform(-6, 6, (3000, 3))))
    junk.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (3000, 1)))
    with pytest.raises(AlignmentError, match="'junk_scan'.*fail"):
        fuse_poses([a, junk], names=["ref", "junk_scan"], settings=FAST)
    with pytest.raises(AlignmentError, match="'tiny'.*too few points"):
        fuse_poses([a, o3d.geometry.PointCloud(a).random_down_sample(0.01)], names=["ref", "tiny"], settings=FAST)
    with pytest.raises(ValueError, match="no normals"):
        fuse_poses([a, o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.uniform(0, 1, (50, 3))))])
    with pytest.raises(ValueError, match="non-empty"):
        fuse_poses([])
    with pytest.raises(ValueError, match="names"):
        fuse_poses([a, a], names=["one"])
    with pytest.raises(ValueError, match="min_fitness"):
        fuse_poses([a], settings=PoseSettings(min_fitness=2.0))


def _without_times(d):
    if isinstance(d, dict):
        return {k: _without_times(v) for k, v in d.items() if k != "seconds"}
    if isinstance(d, list):
        return [_without_times(v) for v in d]
    return d


def test_cli_fuses_several_sources_to_the_same_bytes_every_run(tmp_path, capsys):
    """``ringscan fuse A B``: B aligned to A by the known transform, a per-pose report; run twice, the
    same bytes (docs/fusion.md "Reproducibility": RANSAC seeded, ICP and Poisson on one thread;
    three runs of this used to give three different fused.ply / mesh.ply); a pose that does not
    align is an error naming it, and nothing is written."""
    from ringscan.tools.cli import main

    up, down, T_true = _object_in_two_poses()
    rig = small_rig(320, 256, 640.0)
    angles = (0.0, 120.0, 240.0)
    for name, mesh in (("a", up), ("b", down)):
        (tmp_path / name).mkdir()
        write_recon(tmp_path / name, scan_views(mesh, rig, angles, noise_mm=0.02), rig)
    outs = [tmp_path / "out", tmp_path / "again"]
    for out in outs:
        rc = main(["fuse", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out), "--no-preview",
                   "--no-progress", "--device", "cpu", "--voxel", "0.5", "--poisson-depth", "6"])
        assert rc == 0
        assert "fitness" in capsys.readouterr().out
    out = outs[0]
    rep = json.loads((out / "fuse_report.json").read_text())
    poses = rep["fusion"]["poses"]
    assert [p["name"] for p in poses] == [str(tmp_path / "a"), str(tmp_path / "b")]
    T = np.asarray(poses[1]["transform"])
    assert _rot_err_deg((np.linalg.inv(T_true) @ T)[:3, :3]) < 0.5
    assert (out / "fused.ply").is_file() and (out / "mesh.ply").is_file()
    assert rep["settings"]["poses"]["voxel_mm"] == 0.5 and len(rep["sources"]) == 2
    # The second run: the same files, the same report but for the timings.
    for name in ("fused.ply", "mesh.ply"):
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name
    again = _without_times(json.loads((outs[1] / "fuse_report.json").read_text()))
    rep = _without_times(rep)
    assert rep["fusion"] == again["fusion"] and rep["mesh"] == again["mesh"]
    # A source that does not align is an error naming it, and nothing is written: a dense
    # 12 mm cube of random points (enough to register, matching nothing; see
    # test_failed_alignment_names_the_pose).
    rng = np.random.default_rng(0)
    (tmp_path / "bad").mkdir()
    views = scan_views(up, rig, angles[:1])
    junk = [type(views[0])(name="view_000", points=rng.uniform(-6, 6, (3000, 3)) + [0, 0, 40],
                          turntable_deg=0.0, camera_center=views[0].camera_center)]
    write_recon(tmp_path / "bad", junk, rig)
    out2 = tmp_path / "out2"
    rc = main(["fuse", str(tmp_path / "a"), str(tmp_path / "bad"), "--out", str(out2), "--no-preview",
               "--no-progress", "--device", "cpu", "--poisson-depth", "6"])
    err = capsys.readouterr().err
    assert rc == 1 and f"pose '{tmp_path / 'bad'}'" in err and "failed to align" in err
    assert not (out2 / "fused.ply").exists()


def test_simulate_with_a_pose_writes_the_posed_truth(tmp_path, capsys):
    from ringscan.pipeline.formats.atomic import read_json
    from ringscan.pipeline.formats.meshes import read_mesh
    from ringscan.pipeline.simulate.scan import simulate_scan
    from ringscan.pipeline.simulate.virtual_rig import RenderSettings
    from tests.support.simulate_rig import small_rig as sim_rig
    from tests.support.simulate_rig import small_spec

    kw = dict(scene="cube", rig=sim_rig(), patterns=small_spec(), views=1, settings=RenderSettings(supersample=1),
              device="cpu", progress=False, size_mm=40.0)
    simulate_scan(tmp_path / "up", **kw)
    simulate_scan(tmp_path / "side", pose="side-x", **kw)
    t_up, t_side = read_json(tmp_path / "up" / "scan.json")["truth"], read_json(tmp_path / "side" / "scan.json")["truth"]
    assert "pose" not in t_up                                            # default: unchanged scan.json
    assert t_side["pose"]["name"] == "side-x"
    T = np.asarray(t_side["pose"]["transform"])
    up = np.asarray(read_mesh(tmp_path / "up" / t_up["mesh"]).vertices)
    side = np.asarray(read_mesh(tmp_path / "side" / t_side["mesh"]).vertices)
    assert np.allclose(up @ T[:3, :3].T + T[:3, 3], side, atol=1e-4)
    assert abs(side[:, 2].min()) < 1e-6
    with pytest.raises(ValueError, match="pose 'sideways'"):
        simulate_scan(tmp_path / "bad", pose="sideways", **kw)
