"""The image-space neighbour filter drops isolated points and keeps surfaces."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.point_filter import NeighbourFilterSettings, mark_isolated_points
from tests.support.plane_points import plane_points


def test_keeps_a_surface_and_drops_outliers(device):
    cam, X, pix = plane_points()
    X = X.copy()
    X[100] += [0, 0, 20.0]  # a mixed pixel 20 mm (25 footprints) off the plane
    X[500] += [0, 0, -15.0]
    status = np.zeros(len(X), np.int32)
    status[7] = 3  # not a point: neither filtered nor a neighbour
    out = mark_isolated_points(wp.array(X, dtype=wp.vec3, device=device), wp.array(pix, device=device),
                               wp.array(status, device=device), camera=cam, width=40, height=30,
                               isolated_status=6).numpy()
    assert out[100] == 6 and out[500] == 6 and out[7] == 3
    assert np.sum(out == 6) == 2


def test_disabled_and_empty(device):
    cam, X, pix = plane_points()
    X[3] += [0, 0, 50.0]
    st = wp.zeros(len(X), dtype=wp.int32, device=device)
    out = mark_isolated_points(wp.array(X, dtype=wp.vec3, device=device), wp.array(pix, device=device), st,
                               camera=cam, width=40, height=30, isolated_status=6,
                               settings=NeighbourFilterSettings(radius=0)).numpy()
    assert np.all(out == 0)
    e = mark_isolated_points(wp.empty(0, dtype=wp.vec3, device=device), wp.empty(0, dtype=wp.int32, device=device),
                             wp.empty(0, dtype=wp.int32, device=device), camera=cam, width=40, height=30,
                             isolated_status=6)
    assert e.shape == (0,)


def test_bad_input(device):
    cam, X, pix = plane_points()
    with pytest.raises(ValueError, match="pixel must be"):
        mark_isolated_points(wp.array(X, dtype=wp.vec3, device=device), wp.array(pix[:3], device=device),
                             wp.zeros(len(X), dtype=wp.int32, device=device), camera=cam, width=40, height=30,
                             isolated_status=6)


def test_points_in_pixel_order_or_not_give_the_same_marks(device):
    """Points sorted by pixel take the slot-free path (window rows as runs of the
    arrays); shuffled ones the slot map: the marks are the same, point for point."""
    rng = np.random.default_rng(5)
    cam, X, pix = plane_points()
    X = np.concatenate([X, X + rng.normal(0, 0.05, X.shape).astype(np.float32)])  # two points a pixel
    pix = np.concatenate([pix, pix])
    X[rng.choice(len(X), 60, replace=False)] += rng.normal(0, 4.0, (60, 3)).astype(np.float32)
    status = np.where(rng.random(len(X)) < 0.1, 2, 0).astype(np.int32)
    order = np.argsort(pix, kind="stable")
    X, pix, status = X[order], pix[order], status[order]
    shuffle = rng.permutation(len(X))

    def marks(idx):
        return mark_isolated_points(wp.array(X[idx], dtype=wp.vec3, device=device), wp.array(pix[idx], device=device),
                                    wp.array(status[idx], device=device), camera=cam, width=40, height=30,
                                    isolated_status=6,
                                    settings=NeighbourFilterSettings(min_neighbours=4, tolerance=1.0)).numpy()

    a = marks(np.arange(len(X)))
    b = np.empty_like(a)
    b[shuffle] = marks(shuffle)
    assert np.array_equal(a, b)
    assert 20 < np.sum(a == 6) < 200 and np.all(a[status == 2] == 2)


def test_the_noise_floor_scales_with_a_scene_in_other_units(device):
    """The same scene in metres (a calibration in metres read as mm): the outliers 25 footprints off the plane
    are 0.02 units away, under the 0.05 floor in 'mm'; the floor is held to half a footprint, so they are
    dropped as in mm (before: kept, every neighbour agreed). In mm the floor stays 0.05 mm (the marks of the
    first test)."""
    cam, X, pix = plane_points(z=0.4)  # 0.4 units away, footprint 0.0008 units
    X = X.copy()
    X[100] += [0, 0, 0.02]
    X[500] += [0, 0, -0.015]
    X[300] += [0, 0, 0.0002]  # a quarter of a footprint: noise, kept
    out = mark_isolated_points(wp.array(X, dtype=wp.vec3, device=device), wp.array(pix, device=device),
                               wp.zeros(len(X), dtype=wp.int32, device=device), camera=cam, width=40, height=30,
                               isolated_status=6).numpy()
    assert out[100] == 6 and out[500] == 6 and np.sum(out == 6) == 2
