"""Scenes for the virtual rig: procedural objects (plane, sphere, cube, chessboard,
terrain, corner: a block with a 90-degree V-groove, for inter-reflection), loaded mesh files, and resting poses for "flip and rescan".

Every scene is a triangle mesh in millimetres in the world frame (docs/design.md §2,
§16): it stands on the reference plane z = 0 and is centred on the light axis;
``size_mm`` is the longest side of its axis-aligned bounding box (before the cube's
turn about z). The scenes (among them ``plate:H``, a flat plate at height H for
``ringscan calibrate light``), the mesh loading (``up`` axis, scaling) and the named
poses are described in docs/virtual_rig.md ("Scenes") and docs/fusion.md (``--pose``).
:func:`place_scene` moves a scene's bounding-box centre to a world point and
:func:`add_wall` adds a wall z = Z to it (a rig looking at a bust in front of a wall,
docs/virtual_rig.md, "The oblique rig").
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.errors import FormatError

log = logging.getLogger(__name__)

SCENES = ("plane", "sphere", "cube", "terrain", "chessboard", "corner")
TETRA_DEG = math.degrees(math.acos(-1.0 / 3.0))   # 109.47: the angle between tetrahedron directions
POSES = {"upright": (), "upside-down": (("x", 180.0),), "side-x": (("x", 90.0),), "side-y": (("y", 90.0),),
         "tetra-1": (("x", TETRA_DEG),), "tetra-2": (("z", 120.0), ("x", TETRA_DEG)),
         "tetra-3": (("z", 240.0), ("x", TETRA_DEG))}
CUBE_TURN_DEG = 30.0
SPHERE_SUBDIVISIONS = 6
TERRAIN_CELLS = 240
TERRAIN_HEIGHT_RATIO = 25.0 / 80.0
CREASE_DEG = 40.0
CHESSBOARD_CORNERS = (9, 6)
"""Inner corners (columns, rows) of the ``chessboard`` scene's board."""
CHESSBOARD_THICKNESS_MM = 2.0
CHESSBOARD_DARK = 0.04
"""Albedo of the black squares (printer ink)."""
CHESSBOARD_LIGHT = 0.8
"""Albedo of the white squares and the margin (paper)."""
CORNER_BASE_RATIO = 1.0 / 8.0
"""The ``corner`` block's base under its groove, as a share of ``size_mm``."""
WALL_HALF_SIZE_MM = 10000.0
"""Half the side of :func:`add_wall`'s square: wider than any view of a rig within 100 m."""
WALL_ALBEDO = 0.8
"""Albedo of the wall's faces when the scene carries per-face albedo (else the render's one albedo)."""
DATA_DIR = Path(__file__).resolve().parent / "data"
"""The meshes the package ships (package data), each beside its licence."""
SHIPPED_MESHES = {"spot": ("spot.obj", "spot_LICENSE.md")}
"""Shipped mesh name -> (mesh file, licence file) in :data:`DATA_DIR`: Keenan Crane's Spot
(public domain; 11533 vertices, 23062 triangles, 0.7 MB), the default object of ``ringscan demo``.
A name here is also a scene name of :func:`make_scene`."""

__all__ = [
    "SCENES",
    "POSES",
    "SceneMesh",
    "pose_rotation",
    "pose_scene",
    "place_scene",
    "add_wall",
    "parse_point",
    "make_scene",
    "make_chessboard",
    "load_mesh_file",
    "SHIPPED_MESHES",
    "shipped_mesh",
    "icosphere",
    "corner_normals",
]


@dataclass(frozen=True)
class SceneMesh:
    """A scene's object as a triangle mesh in the world frame (mm), standing on z = 0."""

    vertices: np.ndarray
    """(N, 3) float64 vertex positions (mm)."""
    faces: np.ndarray
    """(M, 3) int32 vertex indices, counter-clockwise seen from outside."""
    name: str
    """Scene name (``plane``, ``sphere``, ...) or the mesh file's stem."""
    face_albedo: np.ndarray | None = None
    """(M,) float64 albedo of each face in [0, 1] (a printed texture), or None: the
    render settings' one albedo everywhere. The reference plane always has that one."""

    @property
    def is_empty(self) -> bool:
        """True for the ``plane`` scene (no object)."""
        return self.faces.shape[0] == 0


# ----------------------------------------------------------------------------- geometry helpers


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere: (vertices (N, 3) float64, faces (M, 3) int32), outward CCW.

    Each subdivision splits every triangle into four and pushes the new vertices
    onto the sphere; ``subdivisions`` = 6 gives 81920 faces.
    """
    p = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array([[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0],
                  [0, -1, p], [0, 1, p], [0, -1, -p], [0, 1, -p],
                  [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]], np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
                  [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
                  [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                  [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        e.sort(axis=1)
        uniq, inv = np.unique(e, axis=0, return_inverse=True)
        inv = inv.ravel()
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + v.shape[0]  # m01, m12, m20 per face
        v = np.concatenate([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, m01, m20], 1), np.stack([b, m12, m01], 1),
                            np.stack([c, m20, m12], 1), np.stack([m01, m12, m20], 1)])
    return v, f.astype(np.int32)


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals (M, 3) and face areas (M,)."""
    p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
    n = np.cross(p1 - p0, p2 - p0)
    a = np.linalg.norm(n, axis=1)
    return n / np.maximum(a, 1e-300)[:, None], 0.5 * a


def corner_normals(vertices: np.ndarray, faces: np.ndarray, *, crease_deg: float = CREASE_DEG) -> np.ndarray:
    """Shading normals per face corner, (M, 3, 3) float64.

    The normal at corner k of face f is the area-weighted mean of the normals of the
    faces around that vertex that turn less than ``crease_deg`` from face f: smooth
    surfaces shade smoothly, and edges sharper than the crease angle (a cube's) stay
    sharp. Faces of zero area get their neighbours' normal (or zero when alone).
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    m = faces.shape[0]
    if m == 0:
        return np.zeros((0, 3, 3))
    fn, area = _face_normals(vertices, faces)
    corner_vert = faces.ravel()                    # corner c = 3 f + k
    order = np.argsort(corner_vert, kind="stable")
    sorted_vert = corner_vert[order]
    deg = np.bincount(corner_vert, minlength=vertices.shape[0])
    start = np.concatenate([[0], np.cumsum(deg)[:-1]])
    reps = deg[sorted_vert]                         # partners of each sorted corner
    i_idx = np.repeat(np.arange(order.size), reps)
    offs = np.arange(i_idx.size) - np.repeat(np.cumsum(reps) - reps, reps)
    j_idx = start[sorted_vert[i_idx]] + offs
    ci, cj = order[i_idx], order[j_idx]             # corner ids sharing a vertex
    fi, fj = ci // 3, cj // 3
    keep = np.einsum("ij,ij->i", fn[fi], fn[fj]) >= math.cos(math.radians(crease_deg))
    w = area[fj[keep]][:, None] * fn[fj[keep]]
    acc = np.stack([np.bincount(ci[keep], weights=w[:, k], minlength=3 * m) for k in range(3)], 1)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(norm > 1e-300, acc / np.maximum(norm, 1e-300), np.repeat(fn, 3, axis=0))
    return out.reshape(m, 3, 3)


def _place(vertices: np.ndarray, size_mm: float) -> np.ndarray:
    """Scale to ``size_mm`` on the longest bounding-box side, stand on z = 0, centre on the axis."""
    lo, hi = vertices.min(0), vertices.max(0)
    ext = float((hi - lo).max())
    if not ext > 0:
        raise ValueError("mesh has zero extent")
    v = (vertices - 0.5 * (lo + hi)) * (size_mm / ext)
    v[:, 2] -= v[:, 2].min()
    return v


def _rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- procedural scenes


def _sphere(size_mm: float) -> SceneMesh:
    v, f = icosphere(SPHERE_SUBDIVISIONS)
    r = 0.5 * size_mm
    return SceneMesh(vertices=v * r + np.array([0.0, 0.0, r]), faces=f, name="sphere")


def _cube(size_mm: float) -> SceneMesh:
    c = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], np.float64)
    f = np.array([[0, 2, 1], [1, 2, 3],   # bottom (z = 0), normal -z
                  [4, 5, 6], [5, 7, 6],   # top, +z
                  [0, 1, 4], [1, 5, 4],   # y = 0, -y
                  [2, 6, 3], [3, 6, 7],   # y = 1, +y
                  [0, 4, 2], [2, 4, 6],   # x = 0, -x
                  [1, 3, 5], [3, 7, 5]],  # x = 1, +x
                 np.int32)
    v = (c - [0.5, 0.5, 0.0]) * size_mm
    return SceneMesh(vertices=v @ _rot_z(CUBE_TURN_DEG).T, faces=f, name="cube")


def _terrain_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth heightfield over the unit square [-0.5, 0.5]^2, max 1, 0 on the border."""
    hills = [  # (x0, y0, sigma, height)
        (-0.18, -0.12, 0.13, 1.00),
        (0.20, 0.15, 0.10, 0.75),
        (0.15, -0.22, 0.08, 0.55),
        (-0.20, 0.22, 0.11, 0.60),
        (0.02, 0.02, 0.06, 0.35),
    ]
    h = np.zeros_like(x)
    for x0, y0, s, a in hills:
        h += a * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * s * s))
    h += 0.08 * (1.0 + np.sin(2 * np.pi * 3.0 * x) * np.cos(2 * np.pi * 2.0 * y))

    def window(t):  # 1 inside, smooth fall to 0 over the outer 15 % of each side
        d = np.clip((0.5 - np.abs(t)) / 0.15, 0.0, 1.0)
        return d * d * (3.0 - 2.0 * d)

    return h * window(x) * window(y)


def _terrain(size_mm: float) -> SceneMesh:
    n = TERRAIN_CELLS
    g = np.linspace(-0.5, 0.5, n + 1)
    X, Y = np.meshgrid(g, g, indexing="xy")
    H = _terrain_height(X, Y)
    H /= H.max()
    H[0, :] = H[-1, :] = H[:, 0] = H[:, -1] = 0.0
    top = np.stack([X.ravel() * size_mm, Y.ravel() * size_mm, H.ravel() * TERRAIN_HEIGHT_RATIO * size_mm], 1)
    idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = [np.stack([a, b, d], 1), np.stack([a, d, c], 1)]   # CCW seen from +z
    # Bottom: a fan from the centre of the base to every border edge (normal -z).
    border = np.concatenate([idx[0, :-1], idx[:-1, -1], idx[-1, :0:-1], idx[:0:-1, 0]])  # CCW from +z
    centre = top.shape[0]
    nxt = np.roll(border, -1)
    faces.append(np.stack([np.full_like(border, centre), nxt, border], 1))
    v = np.concatenate([top, [[0.0, 0.0, 0.0]]])
    return SceneMesh(vertices=v, faces=np.concatenate(faces).astype(np.int32), name="terrain")


def make_chessboard(
    cols: int = CHESSBOARD_CORNERS[0],
    rows: int = CHESSBOARD_CORNERS[1],
    square_mm: float = 80.0 / 12.0,
    *,
    margin_mm: float | None = None,
    thickness_mm: float = CHESSBOARD_THICKNESS_MM,
    dark: float = CHESSBOARD_DARK,
    light: float = CHESSBOARD_LIGHT,
) -> SceneMesh:
    """A chessboard printed on a flat plate lying on z = 0, centred on the axis.

    The board has (cols + 1) x (rows + 1) squares of ``square_mm`` (so ``cols`` x
    ``rows`` inner corners, OpenCV's pattern size), square (i, j) black where i + j
    is even (i along x, j along y), inside a white margin of ``margin_mm`` (default
    one square). The plate is a closed box ``thickness_mm`` thick; its top is a grid
    whose cells are the squares, so each face carries one albedo. Inner corner
    (i, j) lies at x = (i + 1 - (cols + 1) / 2) * square_mm, y = (j + 1 - (rows + 1) / 2)
    * square_mm, z = thickness_mm.
    """
    for name, v in (("cols", cols), ("rows", rows)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
            raise ValueError(f"make_chessboard: {name} must be an integer >= 2, got {v!r}")
    margin_mm = square_mm if margin_mm is None else margin_mm
    for name, v in (("square_mm", square_mm), ("thickness_mm", thickness_mm)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"make_chessboard: {name} must be > 0, got {v!r}")
    if not (isinstance(margin_mm, (int, float)) and math.isfinite(margin_mm) and margin_mm > 0):
        raise ValueError(f"make_chessboard: margin_mm must be > 0, got {margin_mm!r}")
    for name, v in (("dark", dark), ("light", light)):
        if not (isinstance(v, (int, float)) and 0 <= v <= 1):
            raise ValueError(f"make_chessboard: {name} albedo must be in [0, 1], got {v!r}")
    xs = np.concatenate([[-margin_mm], np.arange(cols + 2) * square_mm, [(cols + 1) * square_mm + margin_mm]])
    ys = np.concatenate([[-margin_mm], np.arange(rows + 2) * square_mm, [(rows + 1) * square_mm + margin_mm]])
    xs -= 0.5 * (cols + 1) * square_mm
    ys -= 0.5 * (rows + 1) * square_mm
    nx, ny = xs.size, ys.size
    X, Y = np.meshgrid(xs, ys, indexing="xy")
    top = np.stack([X.ravel(), Y.ravel(), np.full(X.size, float(thickness_mm))], 1)
    bot = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    cj, ci = np.divmod(np.arange(a.size), nx - 1)
    i, j = ci - 1, cj - 1
    square = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
    cell_albedo = np.where(square & ((i + j) % 2 == 0), float(dark), float(light))
    nb = top.shape[0]
    faces = [np.stack([a, b, d], 1), np.stack([a, d, c], 1),                # top, CCW from +z
             np.stack([a, d, b], 1) + nb, np.stack([a, c, d], 1) + nb]      # bottom, facing -z
    albedo = [cell_albedo, cell_albedo, np.full(a.size, float(light)), np.full(a.size, float(light))]
    loop = np.concatenate([idx[0, :-1], idx[:-1, -1], idx[-1, :0:-1], idx[:0:-1, 0]])  # CCW from +z
    nxt = np.roll(loop, -1)
    faces += [np.stack([loop, loop + nb, nxt + nb], 1), np.stack([loop, nxt + nb, nxt], 1)]  # walls, outward
    albedo += [np.full(loop.size, float(light))] * 2
    return SceneMesh(vertices=np.concatenate([top, bot]), faces=np.concatenate(faces).astype(np.int32),
                     name="chessboard", face_albedo=np.concatenate(albedo))


def _corner(size_mm: float) -> SceneMesh:
    """A block with a concave 90-degree corner: a right-angled V-groove along y cut into its top.

    The block is ``size_mm`` square in x and y; its cross-section (in x, z) is the pentagon
    (-S/2, 0), (S/2, 0), (S/2, b + S/2), (0, b), (-S/2, b + S/2) with S = ``size_mm`` and a base
    b = :data:`CORNER_BASE_RATIO` S: the groove's two faces, normals (-1, 0, 1) / sqrt 2 and
    (1, 0, 1) / sqrt 2, meet at 90 degrees along the crease x = 0, z = b. Seen from above (the
    light) and from the camera's side (-y), both faces are lit and visible, and each lights the
    other: light bounced once between them (inter-reflection) is what the scene is for.
    """
    S = size_mm
    b = CORNER_BASE_RATIO * S
    sec = np.array([[-S / 2, 0.0], [S / 2, 0.0], [S / 2, b + S / 2], [0.0, b], [-S / 2, b + S / 2]])
    n = len(sec)
    front = np.stack([sec[:, 0], np.full(n, -S / 2), sec[:, 1]], 1)   # y = -S/2: vertices 0..4
    back = front + [0.0, S, 0.0]                                        # y = +S/2: vertices 5..9
    faces = [[0, 1, 2], [0, 2, 3], [0, 3, 4]]                           # the front pentagon, normal -y
    faces += [[5, 8, 7], [5, 9, 8], [5, 7, 6]]                          # the back pentagon, normal +y
    for i in range(n):                                                  # the sides around the section
        j = (i + 1) % n
        faces += [[i, i + n, j + n], [i, j + n, j]]
    return SceneMesh(vertices=np.concatenate([front, back]), faces=np.array(faces, np.int32), name="corner")


# ----------------------------------------------------------------------------- public


def load_mesh_file(path: str | os.PathLike, *, size_mm: float = 80.0, up: str = "auto") -> SceneMesh:
    """Load a mesh file with Open3D and place it as a scene (see the module docstring).

    Raises:
        FormatError: the file is missing, unreadable or holds no triangles.
        ValueError: bad ``size_mm`` or ``up``.
    """
    import open3d as o3d

    path = Path(path)
    if up not in ("auto", "y", "z"):
        raise ValueError(f"up: expected 'auto', 'y' or 'z', got {up!r}")
    if not path.is_file():
        raise FormatError(path, "mesh file not found")
    try:
        mesh = o3d.io.read_triangle_mesh(str(path))
    except Exception as e:  # Open3D raises RuntimeError for some unreadable formats
        raise FormatError(path, f"Open3D cannot read this mesh ({e})") from None
    if len(mesh.triangles) == 0:
        raise FormatError(path, "no triangles read (not a mesh file Open3D can read, or a point cloud)")
    n_in = len(mesh.vertices)
    mesh.remove_duplicated_vertices()
    mesh.remove_duplicated_triangles()
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    v = np.asarray(mesh.vertices, np.float64).copy()
    f = np.asarray(mesh.triangles, np.int64).astype(np.int32)
    if f.shape[0] == 0 or not np.all(np.isfinite(v)):
        raise FormatError(path, "mesh has no valid triangles (all degenerate) or non-finite vertices")
    log.info("%s: %d vertices (%d before merging duplicates), %d triangles", path.name, v.shape[0], n_in, f.shape[0])
    if up == "auto":
        up = "z" if path.suffix.lower() == ".stl" else "y"
    if up == "y":
        v = v @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]).T
    try:
        v = _place(v, size_mm)
    except ValueError:
        raise FormatError(path, "mesh has zero extent") from None
    return SceneMesh(vertices=v, faces=f, name=path.stem)


PLATE_HALF_MM = 1000.0
"""Half the side of the ``plate:H`` scene: wider than any camera's view of it."""


def _plate(key: str) -> SceneMesh:
    """``plate:H``: a flat plate, top at z = H mm."""
    try:
        h = float(key.split(":", 1)[1])
    except ValueError:
        h = float("nan")
    if not (math.isfinite(h) and h > 0):
        raise ValueError(f"scene {key!r}: expected plate:H with a height H > 0 in mm (plane is the height 0)")
    r = PLATE_HALF_MM
    v = np.array([[-r, -r, h], [r, -r, h], [r, r, h], [-r, r, h]], float)
    return SceneMesh(vertices=v, faces=np.array([[0, 1, 2], [0, 2, 3]], np.int32), name=f"plate_{h:g}mm")


def shipped_mesh(name: str = "spot") -> tuple[Path, Path]:
    """The (mesh file, licence file) paths of a mesh the package ships (:data:`SHIPPED_MESHES`).

    Raises:
        ValueError: an unknown name.
        FileNotFoundError: the package was installed without its data files.
    """
    if name not in SHIPPED_MESHES:
        raise ValueError(f"shipped mesh {name!r}: unknown (known: {', '.join(SHIPPED_MESHES)})")
    mesh, licence = (DATA_DIR / f for f in SHIPPED_MESHES[name])
    for f in (mesh, licence):
        if not f.is_file():
            raise FileNotFoundError(f"{f}: missing; the ringscan package was installed without its data files")
    return mesh, licence


def make_scene(name_or_path: str | os.PathLike, *, size_mm: float = 80.0, up: str = "auto") -> SceneMesh:
    """Build a scene by name (``plane``, ``sphere``, ``cube``, ``terrain``, ``chessboard``, ``corner``, or a
    shipped mesh: ``spot``) or load a mesh file.

    Args:
        name_or_path: a procedural scene name or the path of a mesh file.
        size_mm: the longest side of the object's bounding box (mm).
        up: the up axis of a mesh file (``auto``, ``y`` or ``z``; see the module docstring).

    Raises:
        ValueError: an unknown scene name (that is not a file either) or a bad size.
        FormatError: an unreadable mesh file.
    """
    if isinstance(size_mm, bool) or not isinstance(size_mm, (int, float)) or not math.isfinite(size_mm) or size_mm <= 0:
        raise ValueError(f"size_mm: expected a positive number of millimetres, got {size_mm!r}")
    size_mm = float(size_mm)
    key = os.fspath(name_or_path)
    if key == "plane":
        return SceneMesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int32), name="plane")
    if key.startswith("plate:"):
        return _plate(key)
    if key == "sphere":
        return _sphere(size_mm)
    if key == "cube":
        return _cube(size_mm)
    if key == "terrain":
        return _terrain(size_mm)
    if key == "corner":
        return _corner(size_mm)
    if key == "chessboard":
        cols, rows = CHESSBOARD_CORNERS
        return make_chessboard(cols, rows, size_mm / (max(cols, rows) + 3))
    if key in SHIPPED_MESHES:
        return load_mesh_file(shipped_mesh(key)[0], size_mm=size_mm, up=up)
    p = Path(key)
    if p.suffix or p.exists() or os.sep in key or "/" in key:
        return load_mesh_file(p, size_mm=size_mm, up=up)
    raise ValueError(f"scene {key!r}: unknown (known: {', '.join((*SCENES, *SHIPPED_MESHES))}, or the path of an OBJ/PLY/STL file)")


# ----------------------------------------------------------------------------- poses


def _axis_rotation(axis: str, deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == "y":
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return _rot_z(deg)


def pose_rotation(pose: str | None) -> np.ndarray:
    """The 3x3 rotation of a pose: a name of :data:`POSES` or ``AXIS:DEG[,AXIS:DEG...]``.

    None and ``upright`` give the identity.

    Raises:
        ValueError: an unknown name or a malformed spec (naming the bad part).
    """
    if pose is None:
        return np.eye(3)
    if not isinstance(pose, str):
        raise ValueError(f"pose: expected a name ({', '.join(POSES)}) or 'AXIS:DEG,...', got {pose!r}")
    key = pose.strip().lower()
    if key in POSES:
        turns = POSES[key]
    else:
        turns = []
        for part in key.split(","):
            axis, sep, deg = part.strip().partition(":")
            try:
                val = float(deg)
            except ValueError:
                val = float("nan")
            if not sep or axis.strip() not in ("x", "y", "z") or not math.isfinite(val):
                raise ValueError(f"pose {pose!r}: expected one of {', '.join(POSES)} or 'AXIS:DEG[,AXIS:DEG...]' "
                                 f"with AXIS x, y or z (bad part {part.strip()!r})")
            turns.append((axis.strip(), val))
    R = np.eye(3)
    for axis, deg in turns:
        R = _axis_rotation(axis, deg) @ R
    return R


def pose_scene(scene: SceneMesh, pose: str | None) -> tuple[SceneMesh, np.ndarray]:
    """The scene turned into ``pose`` and set down again on z = 0, centred on the axis.

    Returns:
        (posed scene, T): T is the 4x4 rigid transform from the scene's frame to the
        posed scene's frame (``posed.vertices = scene.vertices @ T[:3, :3].T + T[:3, 3]``).
        The ``upright`` pose (and None) returns the scene unchanged and the identity.
    """
    R = pose_rotation(pose)
    T = np.eye(4)
    if scene.is_empty or np.allclose(R, np.eye(3), atol=0.0, rtol=0.0):
        return scene, T
    v = scene.vertices
    c = 0.5 * (v.min(0) + v.max(0))
    w = (v - c) @ R.T
    lo, hi = w.min(0), w.max(0)
    shift = -np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    T[:3, :3] = R
    T[:3, 3] = shift - R @ c
    return SceneMesh(vertices=w + shift, faces=scene.faces, name=scene.name, face_albedo=scene.face_albedo), T


# ----------------------------------------------------------------------------- placement and wall


def parse_point(text: str, *, what: str = "point") -> tuple[float, float, float]:
    """``"X,Y,Z"`` (mm) -> a finite 3-tuple.

    Raises:
        ValueError: naming ``what`` and the bad text.
    """
    parts = str(text).split(",")
    try:
        xyz = tuple(float(p) for p in parts)
    except ValueError:
        xyz = ()
    if len(xyz) != 3 or not all(math.isfinite(c) for c in xyz):
        raise ValueError(f"{what}: expected X,Y,Z in mm (three finite numbers), got {text!r}")
    if max(abs(c) for c in xyz) > 100000.0:
        raise ValueError(f"{what}: {text!r} lies more than 100 m from the origin")
    return xyz


def place_scene(scene: SceneMesh, at) -> tuple[SceneMesh, np.ndarray]:
    """Move the scene so that the centre of its bounding box lies at ``at`` (world mm).

    Returns:
        (moved scene, T): T the 4x4 translation from the scene's frame to the moved one.
    """
    at = np.asarray(at, np.float64)
    if at.shape != (3,) or not np.all(np.isfinite(at)):
        raise ValueError(f"place_scene: expected a finite (x, y, z) point, got {at!r}")
    T = np.eye(4)
    if scene.is_empty:
        raise ValueError("place_scene: the plane scene has no object to place")
    v = scene.vertices
    T[:3, 3] = at - 0.5 * (v.min(0) + v.max(0))
    return SceneMesh(vertices=v + T[:3, 3], faces=scene.faces, name=scene.name, face_albedo=scene.face_albedo), T


def add_wall(scene: SceneMesh, z_mm: float, *, half_size_mm: float = WALL_HALF_SIZE_MM) -> SceneMesh:
    """The scene plus a wall: the square |x|, |y| <= ``half_size_mm`` of the plane z = ``z_mm``.

    Two triangles, counter-clockwise seen from +z (the renderer turns normals to the
    camera either way). The object must lie wholly on the +z side of the wall.

    Raises:
        ValueError: a bad ``z_mm``, or an object reaching through the wall.
    """
    if isinstance(z_mm, bool) or not isinstance(z_mm, (int, float)) or not math.isfinite(z_mm) \
            or abs(z_mm) > 100000.0:
        raise ValueError(f"wall: expected a z in mm within 100 m of the reference plane, got {z_mm!r}")
    if not scene.is_empty and float(scene.vertices[:, 2].min()) < z_mm:
        raise ValueError(f"wall: the object reaches down to z = {scene.vertices[:, 2].min():.1f} mm, behind the "
                         f"wall at z = {z_mm:g} mm (place it in front: --place)")
    h = float(half_size_mm)
    wv = np.array([[-h, -h, z_mm], [h, -h, z_mm], [h, h, z_mm], [-h, h, z_mm]], np.float64)
    n = scene.vertices.shape[0]
    wf = np.array([[0, 1, 2], [0, 2, 3]], np.int32) + n
    albedo = None
    if scene.face_albedo is not None:
        albedo = np.concatenate([scene.face_albedo, np.full(2, WALL_ALBEDO)])
    return SceneMesh(vertices=np.concatenate([scene.vertices.reshape(-1, 3), wv]),
                     faces=np.concatenate([scene.faces.reshape(-1, 3), wf]).astype(np.int32),
                     name=scene.name, face_albedo=albedo)
