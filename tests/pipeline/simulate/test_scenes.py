"""Scenes: placement on the plane, sizes, closed outward meshes, loaded models, bad input."""

import math

import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.simulate.scan import prepare_scene
from ringscan.pipeline.simulate.scenes import (
    SCENES,
    add_wall,
    corner_normals,
    icosphere,
    load_mesh_file,
    make_chessboard,
    make_scene,
    parse_point,
    place_scene,
    pose_scene,
)


def _closed_outward(s):
    """(closed and consistently oriented, signed volume): every directed edge once, its reverse once."""
    f = s.faces.astype(np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = s.vertices.shape[0]
    fwd = np.sort(e[:, 0] * n + e[:, 1])
    rev = np.sort(e[:, 1] * n + e[:, 0])
    closed = bool(np.all(np.diff(fwd) > 0) and np.array_equal(fwd, rev))
    v = s.vertices
    vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6
    return closed, vol


@pytest.mark.parametrize("name", ["sphere", "cube", "terrain", "chessboard", "corner"])
def test_procedural_scenes_stand_on_the_plane(name):
    s = make_scene(name, size_mm=60.0)
    lo, hi = s.vertices.min(0), s.vertices.max(0)
    assert lo[2] == 0.0
    assert np.allclose(0.5 * (lo[:2] + hi[:2]), 0.0, atol=1e-9)         # centred on the light axis
    assert s.faces.dtype == np.int32 and s.vertices.dtype == np.float64
    watertight, vol = _closed_outward(s)
    assert watertight and vol > 0                                      # closed, normals outward


def test_sphere_is_a_sphere_resting_on_the_origin():
    s = make_scene("sphere")                                           # default 80 mm: radius 40
    r = np.linalg.norm(s.vertices - [0, 0, 40.0], axis=1)
    assert np.allclose(r, 40.0, atol=1e-9)
    assert s.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    _, vol = _closed_outward(s)
    assert vol == pytest.approx(4 / 3 * math.pi * 40.0 ** 3, rel=1e-3)


def test_cube_is_turned_and_sized():
    s = make_scene("cube", size_mm=50.0)
    _, vol = _closed_outward(s)
    assert vol == pytest.approx(50.0 ** 3)
    assert s.vertices[:, 2].max() == pytest.approx(50.0)
    v = s.vertices
    n = np.cross(v[s.faces[:, 1]] - v[s.faces[:, 0]], v[s.faces[:, 2]] - v[s.faces[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    side = np.abs(n[:, 2]) < 1e-9
    assert side.sum() == 8
    ang = np.degrees(np.arctan2(n[side, 1], n[side, 0])) % 90.0
    assert np.allclose(ang, 30.0)                                      # no side face axis-aligned


def test_terrain_heights_and_border():
    s = make_scene("terrain")
    v = s.vertices
    assert v[:, 2].max() == pytest.approx(25.0)
    assert np.ptp(v[:, 0]) == pytest.approx(80.0) and np.ptp(v[:, 1]) == pytest.approx(80.0)
    border = (np.abs(np.abs(v[:, 0]) - 40.0) < 1e-9) | (np.abs(np.abs(v[:, 1]) - 40.0) < 1e-9)
    assert border.sum() > 100 and np.all(v[border, 2] == 0.0)         # meets the plane all round
    assert (v[:, 2] > 5.0).mean() > 0.2                                # and is not flat


def test_plane_scene_is_empty():
    s = make_scene("plane")
    assert s.is_empty and s.vertices.shape == (0, 3) and s.faces.shape == (0, 3)
    assert corner_normals(s.vertices, s.faces).shape == (0, 3, 3)


def test_corner_normals_sharp_and_smooth():
    c = make_scene("cube")
    cn = corner_normals(c.vertices, c.faces)
    v = c.vertices
    fn = np.cross(v[c.faces[:, 1]] - v[c.faces[:, 0]], v[c.faces[:, 2]] - v[c.faces[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    assert np.allclose(cn, fn[:, None, :], atol=1e-12)                # 90 deg edges stay sharp
    vv, ff = icosphere(4)
    cs = corner_normals(vv, ff)
    assert np.abs(cs - vv[ff]).max() < 6e-3                           # smooth: close to radial


def test_loaded_model_merges_seams_and_stands_up(model_path):
    p = model_path("odedstein_spot.obj")
    s = make_scene(p, size_mm=70.0)
    raw = o3d.io.read_triangle_mesh(str(p))                            # split at texture seams
    assert s.vertices.shape[0] < 0.2 * len(raw.vertices)              # duplicates merged
    watertight, vol = _closed_outward(s)
    assert watertight and vol > 0
    ext = np.ptp(s.vertices, axis=0)
    assert ext.max() == pytest.approx(70.0)
    assert s.vertices[:, 2].min() == 0.0
    # Y-up model turned to Z-up: the model's y extent is now the height.
    rv = np.asarray(raw.vertices)
    k = 70.0 / np.ptp(rv, axis=0).max()
    assert ext[2] == pytest.approx(np.ptp(rv[:, 1]) * k)
    assert ext[1] == pytest.approx(np.ptp(rv[:, 2]) * k)
    z_up = load_mesh_file(p, size_mm=70.0, up="z")
    assert np.ptp(z_up.vertices[:, 2]) == pytest.approx(np.ptp(rv[:, 2]) * k)


def test_bad_scenes(tmp_path):
    with pytest.raises(ValueError, match="'spere'.*unknown.*sphere"):
        make_scene("spere")
    with pytest.raises(FormatError, match="not found"):
        make_scene(tmp_path / "missing.obj")
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not a mesh\n")
    with pytest.raises(FormatError, match="bad.obj.*no triangles"):
        make_scene(bad)
    with pytest.raises(ValueError, match="size_mm"):
        make_scene("sphere", size_mm=0)
    with pytest.raises(ValueError, match="up"):
        load_mesh_file(bad, up="x")
    assert set(SCENES) == {"plane", "sphere", "cube", "terrain", "chessboard", "corner"}


def test_corner_is_a_right_angled_groove_facing_up():
    """The ``corner`` block: 60 mm square, base 60 / 8 = 7.5 mm under a 90-degree V-groove along y whose
    crease runs at x = 0, z = 7.5 and whose faces rise to z = 37.5 at x = +-30 (known by construction)."""
    s = make_scene("corner", size_mm=60.0)
    watertight, vol = _closed_outward(s)
    assert watertight
    # the pentagon's area (60 x 37.5 less the groove's triangle, 60 x 30 / 2) times the 60 mm length
    assert vol == pytest.approx((60.0 * 37.5 - 0.5 * 60.0 * 30.0) * 60.0, rel=1e-12)
    assert np.allclose(s.vertices.min(0), [-30.0, -30.0, 0.0]) and np.allclose(s.vertices.max(0), [30.0, 30.0, 37.5])
    v = s.vertices
    p0, p1, p2 = (v[s.faces[:, k]] for k in range(3))
    n = np.cross(p1 - p0, p2 - p0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    r = 1.0 / math.sqrt(2.0)
    groove = [np.isclose(n, [r, 0, r], atol=1e-12).all(1), np.isclose(n, [-r, 0, r], atol=1e-12).all(1)]
    for g, sign in zip(groove, (1.0, -1.0)):
        assert g.sum() == 2                                     # each face: two triangles, outward up the groove
        pts = np.concatenate([p0[g], p1[g], p2[g]])
        # every vertex on its plane z = 7.5 - sign * x (through the crease, 45 degrees)
        assert np.allclose(pts[:, 2], 7.5 - sign * pts[:, 0], atol=1e-12)
        assert np.ptp(pts[:, 1]) == pytest.approx(60.0)         # the whole length of the block
    # the faces meet at 90 degrees: their normals are orthogonal
    assert float(np.dot(n[groove[0]][0], n[groove[1]][0])) == pytest.approx(0.0, abs=1e-12)


def test_chessboard_squares_and_corners():
    s = make_scene("chessboard", size_mm=96.0)            # 9 x 6 inner corners, squares 96 / 12 = 8 mm
    lo, hi = s.vertices.min(0), s.vertices.max(0)
    assert np.allclose(hi - lo, [96.0, 72.0, 2.0])
    assert s.face_albedo.shape == (s.faces.shape[0],)
    top = np.flatnonzero(np.all(s.vertices[s.faces][:, :, 2] == 2.0, axis=1))
    c = s.vertices[s.faces[top]].mean(1)
    i, j = np.floor(c[:, 0] / 8.0 + 5.0), np.floor(c[:, 1] / 8.0 + 3.5)   # square indices, 10 x 7 squares
    board = (i >= 0) & (i <= 9) & (j >= 0) & (j <= 6)
    dark = s.face_albedo[top] < 0.5
    assert np.array_equal(dark, board & ((i + j) % 2 == 0))
    assert np.unique(i[board] * 7 + j[board]).size == 70 and dark.sum() == 2 * 35
    assert np.all(s.face_albedo[~np.isin(np.arange(len(s.faces)), top)] == 0.8)
    # Inner corner (i, j) where four squares meet, at ((i + 1 - 5) 8, (j + 1 - 3.5) 8, 2).
    assert np.any(np.all(np.isclose(s.vertices, [(0 + 1 - 5) * 8.0, (0 + 1 - 3.5) * 8.0, 2.0]), axis=1))
    posed, _ = pose_scene(s, "x:10")
    assert posed.face_albedo is s.face_albedo
    with pytest.raises(ValueError, match="cols"):
        make_chessboard(1, 6, 5.0)
    with pytest.raises(ValueError, match="dark"):
        make_chessboard(9, 6, 5.0, dark=2.0)


def test_place_and_wall():
    """A bust in front of a wall: the bounding-box centre moved to the point, the wall
    two triangles of the plane z = Z behind it, both recorded as truth."""
    s = make_scene("cube", size_mm=50.0)
    placed, T = place_scene(s, (100.0, -20.0, 300.0))
    lo, hi = placed.vertices.min(0), placed.vertices.max(0)
    assert np.allclose(0.5 * (lo + hi), [100.0, -20.0, 300.0])
    assert np.allclose(placed.vertices, s.vertices + T[:3, 3]) and np.allclose(T[:3, :3], np.eye(3))
    walled = add_wall(placed, 200.0)
    assert walled.faces.shape[0] == s.faces.shape[0] + 2
    w = walled.vertices[walled.faces[-2:]].reshape(-1, 3)
    assert np.all(w[:, 2] == 200.0) and np.ptp(w[:, 0]) >= 10000 and np.ptp(w[:, 1]) >= 10000
    n = np.cross(w[1] - w[0], w[2] - w[0])
    assert n[2] > 0                                         # counter-clockwise seen from +z
    assert np.array_equal(walled.vertices[: s.vertices.shape[0]], placed.vertices)
    with pytest.raises(ValueError, match="behind the wall"):
        add_wall(placed, 280.0)
    for bad in (float("nan"), -1e300, True):
        with pytest.raises(ValueError, match="wall: expected"):
            add_wall(placed, bad)
    board = add_wall(place_scene(make_scene("chessboard", size_mm=60.0), (0, 0, 50))[0], 10.0)
    assert board.face_albedo.shape == (board.faces.shape[0],) and np.all(board.face_albedo[-2:] == 0.8)
    # prepare_scene: pose, then place, then wall; the transform maps the upright scene to the placed one
    sc, info = prepare_scene("cube", size_mm=50.0, pose="x:90", place=(0.0, 0.0, 500.0), wall_z=100.0)
    T = np.array(info["pose"]["transform"])
    up = make_scene("cube", size_mm=50.0)
    assert np.allclose(up.vertices @ T[:3, :3].T + T[:3, 3], sc.vertices[:-4])
    assert info["wall_z"] == 100.0 and info["pose"]["place"] == [0.0, 0.0, 500.0]
    assert prepare_scene("cube", size_mm=50.0)[1] == {}


@pytest.mark.parametrize("text", ["1,2", "1,2,x", "1,2,nan", "1,2,3,4", "", "1e9,0,0"])
def test_parse_point_rejects(text):
    with pytest.raises(ValueError, match="--place"):
        parse_point(text, what="--place")
    assert parse_point("-50,436,1000", what="--place") == (-50.0, 436.0, 1000.0)
def test_plate_scene_is_a_plane_at_a_height():
    s = make_scene("plate:40")
    assert s.name == "plate_40mm" and np.all(s.vertices[:, 2] == 40.0)
    a, b, c = s.vertices[s.faces[0]]
    n = np.cross(b - a, c - a)
    assert n[2] > 0 and np.ptp(s.vertices[:, 0]) >= 2000.0  # faces up; wider than any camera's view
    for bad in ("plate:0", "plate:-5", "plate:x", "plate:nan"):
        with pytest.raises(ValueError, match="plate:H"):
            make_scene(bad)
