"""``ringscan fuse`` and ``ringscan mesh`` on a synthetic reconstruction folder."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from ringscan.tools.cli import main
from tests.support.fusion_synth import point_to_mesh, synthetic_scan, write_recon


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    """Four views (every 90 degrees) of the synthetic scan as a reconstruction folder."""
    obj, rig, angles, views = synthetic_scan()
    folder = tmp_path_factory.mktemp("recon")
    write_recon(folder, views[::2], rig)
    return folder, obj


def test_fuse_command_writes_reruns_and_keeps_a_truth_file(recon, tmp_path, capsys):
    """One output folder, three runs: everything asked for; a rerun asking for less removes (and
    names) what it does not rewrite; a truth file lying where a stale mesh would is kept."""
    folder, obj = recon
    out = tmp_path / "out"
    rc = main(["fuse", str(folder), "--out", str(out), "--formats", "ply,obj,stl", "--voxel", "0.5",
               "--poisson-depth", "6", "--no-progress"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "view_006" in text and "poisson mesh" in text
    for name in ("fused.ply", "mesh.ply", "mesh.obj", "mesh.stl", "preview.png", "fuse_report.json"):
        assert (out / name).is_file(), name
    rep = json.loads((out / "fuse_report.json").read_text())
    assert len(rep["fusion"]["views"]) == 4 and rep["settings"]["fuse"]["voxel_mm"] == 0.5
    assert rep["settings"]["mesh"]["poisson_depth"] == 6
    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.stl"))
    o3d.utility.random.seed(0)
    d = point_to_mesh(np.asarray(mesh.sample_points_uniformly(10000).points), obj)
    assert d.mean() < 0.05  # mm; depth-6 Poisson of 0.03 mm noise lies ~0.01 mm from the truth
    head = (out / "mesh.obj").read_text().splitlines()[:4]
    assert "# object name: mesh" in [ln.rstrip() for ln in head]  # not the temporary file's name
    assert not any(".tmp" in ln for ln in head)

    # the reruns are about the outputs: the turntable axis trusted (--no-refine; the first run refined the views)
    args = ["fuse", str(folder), "--out", str(out), "--voxel", "1", "--poisson-depth", "5", "--no-progress",
            "--no-preview", "--no-refine"]
    assert main([*args, "--formats", "ply"]) == 0
    text = capsys.readouterr().out
    assert "removed mesh.obj, mesh.stl, preview.png: left in" in text
    assert sorted(p.name for p in out.iterdir() if p.is_file()) == ["fuse_report.json", "fused.ply", "mesh.ply"]
    rep = json.loads((out / "fuse_report.json").read_text())
    assert rep["outputs"]["removed"] == ["mesh.obj", "mesh.stl", "preview.png"]

    truth = out / "mesh.stl"  # the truth given lies where an earlier run's mesh would
    o3d.io.write_triangle_mesh(str(truth), obj)
    assert main([*args, "--truth", str(truth)]) == 0
    assert truth.is_file() and len(o3d.io.read_triangle_mesh(str(truth)).triangles) == len(obj.triangles)
    rep = json.loads((out / "fuse_report.json").read_text())
    assert not rep["outputs"].get("removed")  # nothing stale this time, and never the truth
    assert rep["truth"]["mesh_to_truth_mean"] < 0.1  # mm; depth-5 Poisson cells are ~1.7 mm


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
