"""Pictures (pipeline/preview/): renders checked pixel by pixel against the camera."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.preview.colour import colorize, depth_heatmap, error_heatmap, heatmap, ring_overlay
from ringscan.pipeline.preview.render import (
    ViewSettings,
    offscreen_available,
    render_geometries,
    render_to_png,
    view_camera,
)

CENTER = np.array([5.0, -3.0, 20.0])
RADIUS = 10.0
SMALL = ViewSettings(width=240, height=180)


def _renderers():
    return ["software", "open3d"]


@pytest.fixture(params=_renderers())
def renderer(request):
    if request.param == "open3d" and not offscreen_available():
        pytest.skip("Open3D's offscreen renderer cannot start here (needs libvulkan1 + mesa-vulkan-drivers)")
    return request.param


def _sphere():
    """A convex ellipsoid (its silhouette is the hull of its projected vertices)."""
    m = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=60)
    m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) * [RADIUS, 0.8 * RADIUS, 1.1 * RADIUS] + CENTER)
    m.compute_vertex_normals()
    return m


def _expected_mask(points: np.ndarray, K, E, shape) -> np.ndarray:
    pc = points @ E[:3, :3].T + E[:3, 3]
    uv = (pc[:, :2] / pc[:, 2:3]) * [K[0, 0], K[1, 1]] + K[:2, 2]
    hull = cv2.convexHull(np.rint(uv).astype(np.int32))
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def _iou(a, b) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def _object_mask(img: np.ndarray) -> np.ndarray:
    return np.any(img != 255, axis=2)  # white background, drawn exactly


def test_mesh_render_shows_the_object_where_the_camera_puts_it(renderer):
    sphere = _sphere()
    res = render_geometries(sphere, settings=ViewSettings(width=240, height=180, renderer=renderer))
    assert res.renderer == renderer and res.image.shape == (180, 240, 3) and res.image.dtype == np.uint8
    got = _object_mask(res.image)
    want = _expected_mask(np.asarray(sphere.vertices), res.K, res.E, got.shape)
    assert want.sum() > 1000  # the object fills a good part of the frame
    assert _iou(got, want) > 0.9
    # Shaded, neither black nor washed out, and lit unevenly (it is a sphere).
    vals = res.image[got].mean(axis=1)
    assert 40 < vals.mean() < 240 and vals.std() > 5


def test_cloud_render_and_framing(renderer):
    pc = _sphere().sample_points_uniformly(20000, use_triangle_normal=True)
    s = ViewSettings(width=200, height=200, azimuth_deg=30.0, elevation_deg=60.0, renderer=renderer)
    res = render_geometries([pc], settings=s)
    got = _object_mask(res.image)
    want = _expected_mask(np.asarray(pc.points), res.K, res.E, got.shape)
    assert _iou(got, want) > 0.85
    # The view direction is the one asked for: the camera sits at azimuth 30, elevation 60.
    R, t = res.E[:3, :3], res.E[:3, 3]
    eye = -R.T @ t
    d = (eye - CENTER) / np.linalg.norm(eye - CENTER)
    assert np.degrees(np.arcsin(d[2])) == pytest.approx(60.0, abs=1.0)
    assert np.degrees(np.arctan2(d[1], d[0])) == pytest.approx(30.0, abs=1.0)


def test_render_to_png_with_colour_bar(tmp_path):
    sphere = _sphere()
    values = np.asarray(sphere.vertices)[:, 2]
    painted = colorize(sphere, values, vmin=values.min(), vmax=values.max())
    out = tmp_path / "p.png"
    render_to_png(painted, out, settings=ViewSettings(width=160, height=120, renderer="software"),
                  colorbar_spec={"vmin": 10.0, "vmax": 30.0, "cmap": "turbo", "label": "z (mm)"})
    img = cv2.imread(str(out))
    assert img.shape == (120, 160 + 110, 3)
    bar = img[:, 160:]
    assert (np.abs(bar.astype(int) - 255).sum(axis=2) > 30).sum() > 500  # the bar and its labels
    # Top of the object is red-ish (high z, turbo), bottom blue-ish.
    obj = np.argwhere(np.any(img[:, :160] != 255, axis=2))
    top = img[obj[:, 0].min() + 3, int(np.median(obj[:, 1]))].astype(int)
    bottom = img[obj[:, 0].max() - 3, int(np.median(obj[:, 1]))].astype(int)
    assert top[2] > top[0] and bottom[0] > bottom[2]


def test_colorize_marks_missing_values_grey():
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.zeros((3, 3))))
    out = colorize(pc, np.array([0.0, np.nan, 1.0]), vmin=0.0, vmax=1.0)
    c = np.asarray(out.colors)
    np.testing.assert_allclose(c[1], [0.5, 0.5, 0.5])
    assert not np.allclose(c[0], c[2]) and not pc.has_colors()  # input untouched
    with pytest.raises(ValueError, match="shape"):
        colorize(pc, np.zeros(4))


def test_view_camera_frames_the_bounds():
    lo, hi = np.array([-10.0, -20.0, 0.0]), np.array([30.0, 5.0, 40.0])
    K, E = view_camera((lo, hi), settings=SMALL)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pc = corners @ E[:3, :3].T + E[:3, 3]
    uv = pc[:, :2] / pc[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
    assert np.all(pc[:, 2] > 0)
    assert np.all((uv >= 0) & (uv <= [SMALL.width - 1, SMALL.height - 1]))


def test_render_bad_input():
    with pytest.raises(ValueError, match="no geometries"):
        render_geometries([])
    with pytest.raises(ValueError, match="PointCloud or TriangleMesh"):
        render_geometries([np.zeros((3, 3))])
    with pytest.raises(ValueError, match="empty"):
        render_geometries([o3d.geometry.PointCloud()], settings=ViewSettings(renderer="software"))
    with pytest.raises(ValueError, match="renderer"):
        render_geometries([_sphere()], settings=ViewSettings(renderer="opengl"))


def test_ring_overlay_colours_each_ring(tmp_path):
    img = np.full((48, 64), 200, np.uint8)
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    u = np.concatenate([32 + r * np.cos(t) for r in (6, 12, 18)])
    v = np.concatenate([24 + r * np.sin(t) for r in (6, 12, 18)])
    ring = np.repeat(np.arange(3), len(t))
    out = ring_overlay(img, u, v, ring, radius=0, out=tmp_path / "o.png")
    assert out.shape == (48, 64, 3) and (tmp_path / "o.png").is_file()
    cols = [tuple(out[int(round(24 + r * np.sin(0.3))), int(round(32 + r * np.cos(0.3)))]) for r in (6, 12, 18)]
    assert len(set(cols)) == 3  # neighbouring rings differ
    assert all(max(c) > 200 for c in cols)  # saturated colours over the dimmed image
    assert tuple(out[2, 2]) == (120, 120, 120)  # 200 dimmed to 0.6
    dense = ring_overlay(img.astype(np.uint16) * 257, u, v, 6.0 + ring * 6.0)  # float rho: colour bar added
    assert dense.shape == (48, 64 + 110, 3)
    with pytest.raises(ValueError, match="one length"):
        ring_overlay(img, u, v[:-1], ring)
    with pytest.raises(ValueError, match="image"):
        ring_overlay(np.zeros((2, 2, 2, 2)), u, v, ring)


def test_heatmaps_map_values_to_colours(tmp_path):
    a = np.tile(np.linspace(0.0, 10.0, 50), (40, 1))
    a[5, 5] = np.nan
    out = heatmap(a, vmin=0.0, vmax=10.0, out=tmp_path / "h.png")
    assert out.shape == (40, 50 + 110, 3) and (tmp_path / "h.png").is_file()
    assert tuple(out[5, 5]) == (40, 40, 40)
    turbo = cv2.applyColorMap(np.array([[0, 255]], np.uint8), cv2.COLORMAP_TURBO)[0]
    np.testing.assert_array_equal(out[0, 0], turbo[0])
    np.testing.assert_array_equal(out[0, 49], turbo[1])
    err = np.linspace(-1.0, 1.0, 41)[None, :].repeat(10, axis=0)
    e = error_heatmap(err, limit=1.0)
    assert np.all(e[0, 20] > 230)  # zero error is white
    assert e[0, 0][0] > e[0, 0][2] and e[0, 40][2] > e[0, 40][0]  # blue below, red above
    d = depth_heatmap(np.where(a > 5, a, 0.0))
    assert tuple(d[0, 0]) == (40, 40, 40)  # depth 0 = no data
    with pytest.raises(ValueError, match="2D"):
        heatmap(np.zeros(5))
    with pytest.raises(ValueError, match="colour map"):
        heatmap(a, cmap="rainbowish")


def test_auto_falls_back_to_software_when_open3d_fails(monkeypatch, caplog):
    from ringscan.pipeline.preview import render as visualize

    def broken(*a, **k):
        raise RuntimeError("the Open3D renderer could not start or failed (exit code -6): no Vulkan")

    monkeypatch.setattr(visualize, "_render_open3d", broken)
    monkeypatch.delenv(visualize.RENDERER_ENV, raising=False)
    res = render_geometries(_sphere(), settings=SMALL)
    assert res.renderer == "software" and _object_mask(res.image).sum() > 1000
    assert "falling back to the software renderer" in caplog.text
    with pytest.raises(RuntimeError, match="mesa-vulkan-drivers"):
        render_geometries(_sphere(), settings=ViewSettings(width=64, height=48, renderer="open3d"))
    monkeypatch.setenv(visualize.RENDERER_ENV, "software")
    assert render_geometries(_sphere(), settings=ViewSettings(width=64, height=48)).renderer == "software"
