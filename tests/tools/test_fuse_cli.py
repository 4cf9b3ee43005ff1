"""``ringscan fuse`` and ``ringscan mesh`` on a synthetic reconstruction folder."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from ringscan.tools.cli import main
from tests.pipeline.fusion.fusion_synth import point_to_mesh, synthetic_scan, write_recon


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    obj, rig, angles, views = synthetic_scan()
    folder = tmp_path_factory.mktemp("recon")
    write_recon(folder, views, rig)
    return folder, obj


def test_fuse_command_writes_cloud_mesh_preview_report(recon, tmp_path, capsys):
    folder, obj = recon
    out = tmp_path / "out"
    rc = main(["fuse", str(folder), "--out", str(out), "--formats", "ply,stl", "--voxel", "0.5",
               "--poisson-depth", "7", "--no-progress"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "view_007" in text and "poisson mesh" in text
    for name in ("fused.ply", "mesh.ply", "mesh.stl", "preview.png", "fuse_report.json"):
        assert (out / name).is_file(), name
    rep = json.loads((out / "fuse_report.json").read_text())
    assert len(rep["fusion"]["views"]) == 8 and rep["settings"]["fuse"]["voxel_mm"] == 0.5
    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.stl"))
    o3d.utility.random.seed(0)
    d = point_to_mesh(np.asarray(mesh.sample_points_uniformly(10000).points), obj)
    assert d.mean() < 0.05


def test_mesh_command_watertight_from_a_bare_cloud(recon, tmp_path, capsys):
    folder, obj = recon
    pc = obj.sample_points_uniformly(8000)  # no normals: the command estimates and orients them
    cloud = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(str(cloud), pc)
    out = tmp_path / "m.obj"
    rc = main(["mesh", str(cloud), "--out", str(out), "--watertight", "--poisson-depth", "6"])
    assert rc == 0
    assert "watertight True" in capsys.readouterr().out
    mesh = o3d.io.read_triangle_mesh(str(out))
    mesh.merge_close_vertices(1e-9)
    assert mesh.is_watertight()
    signed = o3d.t.geometry.RaycastingScene()
    signed.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    # The object's centre is inside the mesh: it is closed around the right side.
    c = np.asarray(obj.vertices).mean(axis=0, keepdims=True).astype(np.float32)
    assert signed.compute_signed_distance(o3d.core.Tensor(c)).numpy()[0] < -10


def test_fuse_and_mesh_errors(tmp_path, capsys):
    assert main(["fuse", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 1
    assert "not found" in capsys.readouterr().err
    assert main(["fuse", str(tmp_path), "--out", str(tmp_path / "o")]) == 1
    assert "neither a reconstruction folder" in capsys.readouterr().err
    assert main(["fuse", str(tmp_path), "--out", str(tmp_path / "o"), "--formats", "gltf"]) == 2
    assert "--formats" in capsys.readouterr().err
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).normal(size=(50, 3))))
    o3d.io.write_point_cloud(str(tmp_path / "c.ply"), pc)
    assert main(["mesh", str(tmp_path / "c.ply"), "--out", str(tmp_path / "m.gltf")]) == 1
    assert "extension" in capsys.readouterr().err


def test_two_fuse_runs_of_two_poses_give_the_same_bytes(tmp_path):
    # docs/fusion.md "Reproducibility": RANSAC (seeded), ICP and Poisson on one thread;
    # three runs of this used to give three different fused.ply / mesh.ply.
    from tests.pipeline.fusion.fusion_synth import scan_views, small_rig
    from tests.pipeline.fusion.test_poses import _object_in_two_poses

    up, down, _ = _object_in_two_poses()
    rig = small_rig(320, 256, 640.0)
    for name, mesh in (("a", up), ("b", down)):
        (tmp_path / name).mkdir()
        write_recon(tmp_path / name, scan_views(mesh, rig, (0.0, 90.0, 180.0, 270.0), noise_mm=0.02), rig)
    outs = []
    for k in range(2):
        out = tmp_path / f"out{k}"
        assert main(["fuse", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out), "--no-preview",
                     "--no-progress", "--device", "cpu", "--voxel", "0.5", "--poisson-depth", "7"]) == 0
        outs.append(out)
    for name in ("fused.ply", "mesh.ply"):
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name

    def without_times(d):
        if isinstance(d, dict):
            return {k: without_times(v) for k, v in d.items() if k != "seconds"}
        if isinstance(d, list):
            return [without_times(v) for v in d]
        return d

    reps = [without_times(json.loads((o / "fuse_report.json").read_text())) for o in outs]
    assert reps[0]["fusion"] == reps[1]["fusion"] and reps[0]["mesh"] == reps[1]["mesh"]
def test_fuse_rerun_removes_and_names_the_meshes_it_does_not_rewrite(recon, tmp_path, capsys):
    folder, _ = recon
    out = tmp_path / "out"
    args = ["fuse", str(folder), "--out", str(out), "--voxel", "1", "--poisson-depth", "6", "--no-progress"]
    assert main([*args, "--formats", "ply,obj,stl"]) == 0
    head = (out / "mesh.obj").read_text().splitlines()[:4]
    assert "# object name: mesh" in [ln.rstrip() for ln in head]  # not the temporary file's name
    assert not any(".tmp" in ln for ln in head)
    capsys.readouterr()
    assert main([*args, "--formats", "ply", "--no-preview"]) == 0
    text = capsys.readouterr().out
    assert "removed mesh.obj, mesh.stl, preview.png: left in" in text
    assert sorted(p.name for p in out.iterdir() if p.is_file()) == ["fuse_report.json", "fused.ply", "mesh.ply"]
    rep = json.loads((out / "fuse_report.json").read_text())
    assert rep["outputs"]["removed"] == ["mesh.obj", "mesh.stl", "preview.png"]


def test_fuse_rerun_keeps_a_truth_file_in_its_folder(recon, tmp_path, capsys):
    folder, obj = recon
    out = tmp_path / "out"
    out.mkdir()
    truth = out / "mesh.stl"  # the truth given lies where an earlier run's mesh would
    o3d.io.write_triangle_mesh(str(truth), obj)
    assert main(["fuse", str(folder), "--out", str(out), "--voxel", "1", "--poisson-depth", "6", "--no-progress",
                 "--no-preview", "--truth", str(truth)]) == 0
    assert truth.is_file()
