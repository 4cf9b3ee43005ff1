"""The fused cloud keeps each point's standard deviation (fused.ply ``sigma``): the
points of one view in a voxel share one error, the views' errors are independent
(pipeline/fusion/turntable.py ``merge_clouds``)."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.formats.meshes import write_cloud
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.fusion.turntable import merge_clouds


def _cloud(points):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))


def test_sigma_of_a_voxels_mean():
    # voxel 1 (about the origin): two points of view A, one of view B; voxel 2 (10 mm off): view C's
    a = _cloud([[0.01, 0.0, 0.0], [0.02, 0.01, 0.0]])
    b = _cloud([[0.0, 0.02, 0.01]])
    c = _cloud([[10.0, 0.0, 0.0]])
    out, source, conf, sigma = merge_clouds([a, b, c], [np.array([0.5, 1.0]), np.array([0.3]), np.array([1.0])],
                                            voxel_mm=1.0, sigmas=[np.array([0.03, 0.04]), np.array([0.05]),
                                                                  np.array([np.nan])])
    pts = np.asarray(out.points)
    v1, v2 = int(np.argmin(pts[:, 0])), int(np.argmax(pts[:, 0]))
    assert len(pts) == 2 and source[v1] == 0 and source[v2] == 2
    assert conf[v1] == pytest.approx(0.6)  # the mean of 0.5, 1.0, 0.3
    # the voxel's point is the mean of 3 points: 2/3 of view A's (RMS sigma sqrt((0.03^2 + 0.04^2) / 2),
    # one error for both) and 1/3 of view B's 0.05: sqrt((2 * 0.0354 / 3)^2 + (0.05 / 3)^2)
    want = math.sqrt((2 / 3 * math.sqrt((0.03 ** 2 + 0.04 ** 2) / 2)) ** 2 + (0.05 / 3) ** 2)
    assert sigma.dtype == np.float32 and sigma[v1] == pytest.approx(want, rel=1e-6)  # float32: 7 digits
    assert math.isnan(sigma[v2])  # view C's point had none


def test_one_view_keeps_its_sigma_two_views_average_theirs():
    pts = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]
    (_, _, _, one) = merge_clouds([_cloud(pts)], [np.ones(3)], voxel_mm=1.0, sigmas=[np.full(3, 0.02)])
    assert one == pytest.approx([0.02], rel=1e-6)  # three points of one view: not 0.02 / sqrt(3)
    (_, _, _, two) = merge_clouds([_cloud(pts[:1]), _cloud(pts[1:2])], [np.ones(1), np.ones(1)], voxel_mm=1.0,
                                  sigmas=[np.array([0.02]), np.array([0.02])])
    assert two == pytest.approx([0.02 / math.sqrt(2)], rel=1e-6)
    (_, _, _, kept) = merge_clouds([_cloud(pts)], [np.ones(3)], voxel_mm=0.0, sigmas=[np.array([0.1, 0.2, 0.3])])
    assert kept == pytest.approx([0.1, 0.2, 0.3], rel=1e-6)  # no voxel grid: every point as it was
    (_, _, _, none) = merge_clouds([_cloud(pts)], [np.ones(3)], voxel_mm=1.0)
    assert np.all(np.isnan(none))
    with pytest.raises(ValueError, match="2 sigmas for 3 points"):
        merge_clouds([_cloud(pts)], [np.ones(3)], voxel_mm=1.0, sigmas=[np.ones(2)])


def test_fused_ply_holds_sigma_and_confidence(tmp_path):
    cloud = _cloud([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    write_cloud(tmp_path / "fused.ply", cloud, view=np.array([0, 1]), confidence=np.array([0.5, 0.75]),
                sigma=np.array([0.02, np.nan]))
    ply = read_ply(tmp_path / "fused.ply")
    assert ply["confidence"].tolist() == [0.5, 0.75] and ply["view"].tolist() == [0, 1]
    assert ply["sigma"][0] == pytest.approx(0.02) and math.isnan(ply["sigma"][1])
