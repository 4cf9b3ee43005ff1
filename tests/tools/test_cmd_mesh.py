"""``ringscan mesh`` on clouds meshing cannot use as they are: non-finite or huge
coordinates are dropped and counted, too few points and truncated files are errors
naming the file."""

from __future__ import annotations

import re

import numpy as np
import open3d as o3d
import pytest

from ringscan.tools.cli import main

R = 20.0


def _sphere(n=3000, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return R * v / np.linalg.norm(v, axis=1, keepdims=True)


def _write(path, pts):
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    return path


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e30])
def test_unusable_points_are_dropped_and_counted(tmp_path, capsys, bad):
    pts = _sphere()
    pts[::10, 1] = bad
    cloud = _write(tmp_path / "c.ply", pts)
    out = tmp_path / "m.ply"
    assert main(["mesh", str(cloud), "--out", str(out), "--poisson-depth", "6"]) == 0
    text = capsys.readouterr().out
    if np.isfinite(bad):
        assert "dropped 0 of 3000 points with a NaN or infinite coordinate or normal, and 300 beyond +-1e+06 mm" in text
    else:
        assert "dropped 300 of 3000 points with a NaN or infinite coordinate or normal, and 0 beyond" in text
    v = np.asarray(o3d.io.read_triangle_mesh(str(out)).vertices)
    assert len(v) > 500 and np.all(np.isfinite(v))
    assert np.abs(np.linalg.norm(v, axis=1) - R).max() < 1.0  # the sphere, not the outliers


@pytest.mark.parametrize("pts,match", [
    (_sphere(5), "5 usable points \\(of 5\\): too few to mesh \\(need at least 10\\)"),
    (np.full((100, 3), np.nan), "0 usable points \\(of 100\\): too few to mesh"),
    (_sphere(12), "meshing its 12 points gave no surface"),
    (np.zeros((50, 3)), "all 50 points of the cloud lie at one place"),
    (np.outer(np.arange(50.0), [1.0, 2.0, 3.0]), "the 50 points of the cloud lie on a line"),
])
def test_clouds_that_cannot_be_meshed(tmp_path, capsys, pts, match):
    cloud = _write(tmp_path / "c.ply", pts)
    assert main(["mesh", str(cloud), "--out", str(tmp_path / "m.ply"), "--poisson-depth", "6"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ringscan mesh: error: {cloud}: ") and len(err.splitlines()) == 1, err
    assert re.search(match, err), err
    assert not (tmp_path / "m.ply").exists()


def test_a_flat_cloud_is_meshed(tmp_path):
    g = np.random.default_rng(1).uniform(-10, 10, size=(2000, 2))
    cloud = _write(tmp_path / "flat.ply", np.c_[g, np.full(len(g), 5.0)])
    assert main(["mesh", str(cloud), "--out", str(tmp_path / "m.ply"), "--poisson-depth", "6"]) == 0
    v = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "m.ply")).vertices)
    assert len(v) > 100 and np.abs(v[:, 2] - 5.0).max() < 0.5


def test_a_truncated_ply_is_an_error(tmp_path, capsys):
    cloud = _write(tmp_path / "c.ply", _sphere())
    raw = cloud.read_bytes()
    cloud.write_bytes(raw[: len(raw) // 2])
    assert main(["mesh", str(cloud), "--out", str(tmp_path / "m.ply")]) == 1
    err = capsys.readouterr().err
    assert f"{cloud}: truncated or corrupt PLY" in err
    assert not (tmp_path / "m.ply").exists()


def test_mesh_does_not_overwrite_its_cloud(tmp_path, capsys):
    cloud = _write(tmp_path / "c.ply", _sphere())
    before = cloud.read_bytes()
    assert main(["mesh", str(cloud), "--out", str(cloud)]) == 1
    assert "would overwrite the input" in capsys.readouterr().err and cloud.read_bytes() == before
