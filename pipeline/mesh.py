"""Meshing of fused clouds (Open3D): Poisson or TSDF, watertight option, export.

- **Poisson** (default): screened Poisson reconstruction of the oriented fused
  cloud; then trimming of the surface that Poisson invents where no view looked:
  vertices whose Poisson density is below a quantile, and vertices farther than a
  distance from every input point.
- **TSDF**: each view's points are drawn into a depth map of that view's camera
  (moved into the object frame with the view's pose) and integrated into Open3D's
  sparse voxel-block TSDF (``VoxelBlockGrid``, the successor of
  ``ScalableTSDFVolume``, whose Open3D 0.20 build cannot take millimetre depth
  maps). The depth maps have a pixel of a quarter voxel (not the camera's own
  resolution) and every point paints a small disk of its tangent plane into them,
  so that sparse ring samples make a dense depth map without the error of
  nearest-pixel depth on slopes; small holes are closed by a neighbour-median
  fill. A bare point cloud (no views) is integrated the same way from virtual
  cameras around it, each drawing only the points that face it.
- **Watertight**: Poisson without any trimming, then cleanup (near-duplicate
  vertices merged, degenerate triangles and non-manifold edges removed, only the
  largest connected piece kept); the result is checked with Open3D's
  ``is_watertight()``. With TSDF, the TSDF surface's vertices and normals go
  through the same watertight Poisson.

Meshes are written as PLY, OBJ or STL (from the extension), atomically.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import FormatError
from .io import atomic_path, atomic_write_json, write_ply

log = logging.getLogger(__name__)

__all__ = [
    "MeshSettings",
    "MeshResult",
    "poisson_mesh",
    "tsdf_mesh",
    "mesh_cloud",
    "mesh_fused",
    "make_watertight",
    "orient_normals",
    "clean_mesh",
    "write_mesh",
    "read_mesh",
    "read_cloud",
    "write_cloud",
    "compare_to_truth",
    "fuse_and_mesh",
    "MESH_FORMATS",
]

MESH_FORMATS = (".ply", ".obj", ".stl")
"""Mesh file formats written and read (chosen by extension)."""
FUSE_REPORT_FORMAT = "ringscan.fuse/1"
_MAX_SPLAT_PX = 24


# ----------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class MeshSettings:
    """How a fused cloud becomes a mesh (lengths in mm)."""

    method: str = "poisson"
    """"poisson" (screened Poisson) or "tsdf" (truncated signed distance fusion)."""
    watertight: bool = False
    """Make a closed, manifold mesh (untrimmed Poisson + cleanup), checked with is_watertight()."""
    poisson_depth: int = 9
    """Octree depth: the grid has 2^depth cells across the cloud's bounding cube
    (9 gives ~0.2 mm cells on a 100 mm object)."""
    poisson_scale: float = 1.1
    """Poisson's bounding cube is this much larger than the cloud's."""
    watertight_scale: float = 2.0
    """Watertight mode: Poisson's bounding cube is at least this much larger than the
    cloud, so the surface closes inside it where no view looked (the base)."""
    poisson_linear_fit: bool = True
    """Place iso-surface vertices by linear interpolation (more accurate on fine grids)."""
    density_quantile: float = 0.02
    """Trim vertices whose Poisson density is below this quantile (0 keeps all)."""
    trim_distance_mm: float | None = 1.5
    """Trim vertices farther than this from every input point (None keeps all);
    this removes the lid Poisson puts where no view looked (the object's base)."""
    tsdf_voxel_mm: float = 0.4
    """TSDF voxel size; also the pixel size of the depth maps at the object."""
    tsdf_trunc_voxels: float = 4.0
    """TSDF truncation distance in voxels."""
    tsdf_supersample: int = 4
    """Depth-map pixels per TSDF voxel (across): the TSDF reads the depth of the
    nearest pixel, so a pixel as large as a voxel costs ~voxel/2 x slope of error."""
    tsdf_splat_mm: float | None = None
    """Radius of the tangent-plane disk each point paints into a depth map (None:
    1.5 x the median distance to the 4th-nearest neighbour in the view)."""
    tsdf_fill_px: int = 2
    """Depth-map hole filling: passes of neighbour-median fill for empty pixels
    surrounded by at least 5 of 8 filled neighbours."""
    tsdf_virtual_views: int = 14
    """Virtual cameras around a bare cloud (TSDF without views)."""
    min_component_triangles: int = 100
    """Connected pieces with fewer triangles than this are removed (0 keeps all)."""
    smooth_iterations: int = 0
    """Taubin smoothing passes after meshing (0: none)."""


@dataclass
class MeshResult:
    """A mesh and what was done to make it."""

    mesh: "o3d.geometry.TriangleMesh"  # noqa: F821
    """The mesh, with vertex and triangle normals."""
    method: str
    watertight: bool | None
    """Open3D's is_watertight() when a watertight mesh was asked for; else None."""
    info: dict
    """Counts and checks: vertices, triangles, trimmed vertices, edge_manifold, closed, seconds."""


# ----------------------------------------------------------------------------- helpers


def _o3d():
    import open3d as o3d

    return o3d


def _check_settings(s: MeshSettings) -> None:
    if not isinstance(s, MeshSettings):
        raise ValueError(f"settings must be a MeshSettings, got {type(s).__name__}")
    if s.method not in ("poisson", "tsdf"):
        raise ValueError(f"MeshSettings.method must be 'poisson' or 'tsdf', got {s.method!r}")
    if not 1 <= s.poisson_depth <= 12:
        raise ValueError(f"MeshSettings.poisson_depth must be in 1..12, got {s.poisson_depth}")
    if not 0 <= s.density_quantile < 1:
        raise ValueError(f"MeshSettings.density_quantile must be in [0, 1), got {s.density_quantile}")
    if s.trim_distance_mm is not None and s.trim_distance_mm <= 0:
        raise ValueError(f"MeshSettings.trim_distance_mm must be > 0 or None, got {s.trim_distance_mm}")
    if s.tsdf_voxel_mm <= 0 or s.tsdf_trunc_voxels <= 0:
        raise ValueError("MeshSettings.tsdf_voxel_mm and tsdf_trunc_voxels must be > 0")
    if s.tsdf_supersample < 1:
        raise ValueError(f"MeshSettings.tsdf_supersample must be >= 1, got {s.tsdf_supersample}")
    if s.tsdf_splat_mm is not None and s.tsdf_splat_mm <= 0:
        raise ValueError(f"MeshSettings.tsdf_splat_mm must be > 0 or None, got {s.tsdf_splat_mm}")
    if s.tsdf_virtual_views < 1:
        raise ValueError(f"MeshSettings.tsdf_virtual_views must be >= 1, got {s.tsdf_virtual_views}")


def _check_cloud(cloud, *, normals: bool) -> None:
    o3d = _o3d()
    if not isinstance(cloud, o3d.geometry.PointCloud):
        raise ValueError(f"cloud must be an open3d.geometry.PointCloud, got {type(cloud).__name__}")
    if len(cloud.points) < 10:
        raise ValueError(f"cloud has {len(cloud.points)} points: too few to mesh (need at least 10)")
    if normals and not cloud.has_normals():
        raise ValueError("cloud has no normals: Poisson needs oriented normals (fuse_views gives them)")


def _finish(mesh, s: MeshSettings):
    mesh.remove_unreferenced_vertices()
    if s.smooth_iterations > 0 and len(mesh.triangles):
        mesh = mesh.filter_smooth_taubin(number_of_iterations=s.smooth_iterations)
    mesh.compute_vertex_normals()
    mesh.compute_triangle_normals()
    return mesh


def _drop_small_components(mesh, min_triangles: int, keep_largest_only: bool = False) -> int:
    if len(mesh.triangles) == 0:
        return 0
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels = np.asarray(labels)
    counts = np.asarray(counts)
    if keep_largest_only:
        drop = labels != int(np.argmax(counts))
    else:
        drop = counts[labels] < min_triangles
    if drop.any():
        mesh.remove_triangles_by_mask(drop)
        mesh.remove_unreferenced_vertices()
    return int(drop.sum())


def _mesh_info(mesh, t0: float, **extra) -> dict:
    info = {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
            "edge_manifold": bool(mesh.is_edge_manifold(allow_boundary_edges=True)),
            "closed": bool(mesh.is_edge_manifold(allow_boundary_edges=False)) if len(mesh.triangles) else False,
            "vertex_manifold": bool(mesh.is_vertex_manifold())}
    info.update(extra)
    info["seconds"] = round(time.perf_counter() - t0, 3)
    return info


def clean_mesh(mesh, *, merge_mm: float | None = None):
    """Tidy a mesh: merge near-duplicate vertices (within ``merge_mm``; default
    1e-4 of the mesh's extent), drop degenerate and duplicate triangles,
    non-manifold edges and unused vertices. Returns the tidied mesh (use it).

    Poisson's marching cubes leaves vertices a hair apart that make Open3D's
    self-intersection test fire; merging them fixes that.
    """
    if len(mesh.vertices):
        if merge_mm is None:
            ext = np.asarray(mesh.get_max_bound()) - np.asarray(mesh.get_min_bound())
            merge_mm = 1e-4 * max(float(np.max(ext)), 1e-9)
        mesh = mesh.merge_close_vertices(merge_mm)
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_duplicated_vertices()
    mesh.remove_non_manifold_edges()
    mesh.remove_unreferenced_vertices()
    return mesh


# ----------------------------------------------------------------------------- Poisson


def _poisson(cloud, s: MeshSettings, scale: float | None = None):
    o3d = _o3d()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=s.poisson_depth, scale=s.poisson_scale if scale is None else scale,
            linear_fit=s.poisson_linear_fit)
    if not cloud.has_colors():
        # Open3D gives the mesh black vertex colours when the cloud has none.
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.zeros((0, 3)))
    return mesh, np.asarray(dens)


def poisson_mesh(cloud, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Screened Poisson surface of an oriented cloud, trimmed (or watertight).

    Args:
        cloud: ``o3d.geometry.PointCloud`` with oriented normals.
        settings: ``poisson_*``, ``density_quantile``, ``trim_distance_mm``,
            ``watertight`` and cleanup fields are used.
    """
    _check_settings(settings)
    _check_cloud(cloud, normals=True)
    s = settings
    t0 = time.perf_counter()
    if s.watertight:
        return _watertight_poisson(cloud, s, "poisson", t0)
    mesh, dens = _poisson(cloud, s)
    drop = np.zeros(len(mesh.vertices), bool)
    if s.density_quantile > 0 and len(dens):
        drop |= dens < np.quantile(dens, s.density_quantile)
    n_density = int(drop.sum())
    if s.trim_distance_mm is not None and len(mesh.vertices):
        d = _distance_to_points(np.asarray(mesh.vertices), np.asarray(cloud.points))
        drop |= d > s.trim_distance_mm
    mesh.remove_vertices_by_mask(drop)
    mesh = clean_mesh(mesh)
    small = _drop_small_components(mesh, s.min_component_triangles) if s.min_component_triangles else 0
    mesh = _finish(mesh, s)
    info = _mesh_info(mesh, t0, trimmed_density=n_density, trimmed_total=int(drop.sum()),
                      small_piece_triangles_removed=small)
    log.info("Poisson mesh: %d vertices, %d triangles (%d vertices trimmed)", info["vertices"], info["triangles"],
             info["trimmed_total"])
    return MeshResult(mesh=mesh, method="poisson", watertight=None, info=info)


def _distance_to_points(q: np.ndarray, pts: np.ndarray) -> np.ndarray:
    o3d = _o3d()
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(pts, np.float64)))
    nns.knn_index()
    _, d2 = nns.knn_search(o3d.core.Tensor(np.ascontiguousarray(q, np.float64)), 1)
    return np.sqrt(d2.numpy()[:, 0])


def _watertight_poisson(cloud, s: MeshSettings, method: str, t0: float) -> MeshResult:
    """Untrimmed Poisson in a roomy bounding cube (so that the surface closes inside
    it even where no view looked), cleaned; retried once in a larger cube."""
    scale = max(s.poisson_scale, s.watertight_scale)
    for attempt in range(2):
        mesh, _ = _poisson(cloud, s, scale)
        mesh = make_watertight(mesh)
        if mesh.is_edge_manifold(allow_boundary_edges=False) and len(mesh.triangles):
            break
        log.info("Poisson surface not closed in a cube %.1fx the cloud: retrying larger", scale)
        scale *= 1.5
    wt = bool(mesh.is_watertight())
    info = _mesh_info(mesh, t0, watertight=wt, poisson_scale=scale)
    if not wt:
        log.warning("the mesh is not watertight after cleanup (closed %s, vertex manifold %s)",
                    info["closed"], info["vertex_manifold"])
    return MeshResult(mesh=mesh, method=method, watertight=wt, info=info)


def make_watertight(mesh):
    """Clean an untrimmed Poisson mesh into one closed manifold piece.

    Merges near-duplicate vertices, removes degenerate/duplicate triangles and
    non-manifold edges, keeps the largest connected piece, and recomputes normals.
    Check the result with ``mesh.is_watertight()``.
    """
    mesh = clean_mesh(mesh)
    _drop_small_components(mesh, 0, keep_largest_only=True)
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    mesh.compute_triangle_normals()
    return mesh


# ----------------------------------------------------------------------------- TSDF


def _splat_radius_mm(pts: np.ndarray) -> float:
    """A splat radius that closes the gaps between neighbouring samples: 1.5 x the
    median distance to the 4th-nearest neighbour."""
    o3d = _o3d()
    sub = pts if len(pts) <= 20000 else pts[np.linspace(0, len(pts) - 1, 20000).astype(np.int64)]
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(pts, np.float64)))
    nns.knn_index()
    k = min(5, len(pts))
    _, d2 = nns.knn_search(o3d.core.Tensor(np.ascontiguousarray(sub, np.float64)), k)
    return 1.5 * float(np.median(np.sqrt(d2.numpy()[:, k - 1])))


def _depth_map(pts: np.ndarray, nrm: np.ndarray | None, K: np.ndarray, E: np.ndarray, w: int, h: int,
               splat_px: int, fill: int) -> np.ndarray:
    """Depth per pixel (float32, 0 = empty) of points seen by camera (K, E).

    Every point is splatted as a disk of ``splat_px`` pixels radius of its tangent
    plane (with normals; else at its own depth): each pixel of the disk gets the
    depth where the pixel's own ray meets that plane. Per pixel, the front surface
    wins (splats within ``2 x splat`` of the nearest depth), and among those the
    point whose projection is nearest to the pixel centre.
    """
    pc = pts @ E[:3, :3].T + E[:3, 3]
    ok = pc[:, 2] > 1e-6
    pc = pc[ok]
    n = None if nrm is None else nrm[ok] @ E[:3, :3].T
    z = pc[:, 2]
    uf = K[0, 0] * pc[:, 0] / z + K[0, 2]
    vf = K[1, 1] * pc[:, 1] / z + K[1, 2]
    u0 = np.rint(uf).astype(np.int64)
    v0 = np.rint(vf).astype(np.int64)
    depth = np.zeros((h, w), np.float32)
    if len(z) == 0:
        return depth
    r = max(int(splat_px), 0)
    offs = [(dx, dy) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dx * dx + dy * dy <= r * r + r]
    pix_all, dep_all, d2_all = [], [], []
    px_mm = z / K[0, 0]  # one pixel at each point's depth
    for dx, dy in offs:
        u = u0 + dx
        v = v0 + dy
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        if n is not None:
            ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(u))], axis=1)
            nr = np.einsum("ij,ij->i", n, ray)
            good = np.abs(nr) > 0.2
            t = np.einsum("ij,ij->i", n, pc) / np.where(good, nr, 1.0)
            # Grazing planes would throw depths far off: keep only moderate slopes.
            inside &= good & (np.abs(t - z) <= 3.0 * (r + 1) * px_mm)
        else:
            t = z
        pix_all.append((v * w + u)[inside])
        dep_all.append(t[inside])
        d2_all.append(((u - uf) ** 2 + (v - vf) ** 2)[inside])
    pix = np.concatenate(pix_all)
    dep = np.concatenate(dep_all)
    d2 = np.concatenate(d2_all)
    if len(pix) == 0:
        return depth
    front = np.full(h * w, np.inf)
    np.minimum.at(front, pix, dep)
    tol = 2.0 * (r + 1) * float(np.median(px_mm))
    keep = dep <= front[pix] + tol
    pix, dep, d2 = pix[keep], dep[keep], d2[keep]
    order = np.lexsort((d2, pix))
    first = np.unique(pix[order], return_index=True)[1]
    sel = order[first]
    depth.ravel()[pix[sel]] = dep[sel]
    return _fill_holes(depth, fill)


def _fill_holes(depth: np.ndarray, passes: int) -> np.ndarray:
    """Fill empty pixels that have >= 5 filled 8-neighbours with their median depth."""
    for _ in range(passes):
        pad = np.pad(depth, 1)
        h, w = depth.shape
        nb = np.stack([pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                       for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
        filled = nb > 0
        cnt = filled.sum(axis=0)
        target = (depth == 0) & (cnt >= 5)
        if not target.any():
            break
        vals = np.where(filled, nb, np.nan)[:, target]
        depth = depth.copy()
        depth[target] = np.nanmedian(vals, axis=0)
    return depth


def _integrate(jobs, voxel: float, trunc_voxels: float):
    """TSDF-integrate jobs (points (N, 3), normals (N, 3) or None, K, E (4x4
    object -> camera), w, h, splat_px, fill).

    Returns (legacy mesh, number of depth maps integrated).

    Uses Open3D's sparse voxel-block TSDF (``o3d.t.geometry.VoxelBlockGrid``, the
    tensor-API successor of ``ScalableTSDFVolume``): the legacy ScalableTSDFVolume
    of Open3D 0.20 divides float depth maps by 1000 when it allocates its volume
    units, so it finds no surface in millimetre depth maps.
    """
    o3d = _o3d()
    dev = o3d.core.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3d.core.float32, o3d.core.float32),
                                        attr_channels=((1), (1)), voxel_size=voxel, block_resolution=8,
                                        block_count=50_000, device=dev)
    used = 0
    for pts, nrm, K, E, w, h, splat, fill in jobs:
        depth = _depth_map(pts, nrm, K, E, w, h, splat, fill)
        if not (depth > 0).any():
            continue
        zmax = float(depth.max()) + 2 * trunc_voxels * voxel
        dimg = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth)))
        Kt = o3d.core.Tensor(np.asarray(K, np.float64))
        Et = o3d.core.Tensor(np.asarray(E, np.float64))
        blocks = vbg.compute_unique_block_coordinates(dimg, Kt, Et, depth_scale=1.0, depth_max=zmax,
                                                      trunc_voxel_multiplier=float(trunc_voxels))
        vbg.integrate(blocks, dimg, Kt, Et, depth_scale=1.0, depth_max=zmax, trunc_voxel_multiplier=float(trunc_voxels))
        used += 1
    if used == 0:
        return o3d.geometry.TriangleMesh(), 0
    return vbg.extract_triangle_mesh(weight_threshold=0.5).to_legacy(), used


def _depth_camera(pts: np.ndarray, E: np.ndarray, pixel_mm: float, margin: int = 4):
    """Intrinsics and image size of a virtual pinhole camera with extrinsics E whose
    pixel is ``pixel_mm`` wide at the median depth of ``pts`` and that frames them."""
    pc = pts @ E[:3, :3].T + E[:3, 3]
    pc = pc[pc[:, 2] > 1e-6]
    if len(pc) == 0:
        return None
    f = float(np.median(pc[:, 2])) / pixel_mm
    x = pc[:, 0] / pc[:, 2] * f
    y = pc[:, 1] / pc[:, 2] * f
    x0, x1, y0, y1 = x.min(), x.max(), y.min(), y.max()
    w = int(math.ceil(x1 - x0)) + 2 * margin + 1
    h = int(math.ceil(y1 - y0)) + 2 * margin + 1
    if w * h > 16_000_000:
        raise ValueError(f"TSDF depth map would be {w}x{h} pixels: increase MeshSettings.tsdf_voxel_mm "
                         "or lower tsdf_supersample")
    K = np.array([[f, 0, margin - x0], [0, f, margin - y0], [0, 0, 1.0]])
    return K, w, h


def _look_at_E(eye, target, up_hint) -> np.ndarray:
    from .rig import look_at

    R, t = look_at(eye, target, up_hint)
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = R, t
    return E


def tsdf_mesh(source, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """TSDF fusion of per-view depth maps (Open3D's sparse voxel-block TSDF).

    Args:
        source: a :class:`~ringscan.pipeline.fuse.FuseResult` (each view's cloud is
            projected into its own camera: the rig's camera moved into the object
            frame with the view's pose), or an oriented ``o3d.geometry.PointCloud``
            (integrated from ``tsdf_virtual_views`` virtual cameras around it, each
            seeing only the points whose normals face it).
        settings: ``tsdf_*``, ``watertight`` and cleanup fields are used.
    """
    from .fuse import FuseResult

    _check_settings(settings)
    s = settings
    o3d = _o3d()
    t0 = time.perf_counter()
    jobs = []
    px_mm = s.tsdf_voxel_mm / s.tsdf_supersample
    if isinstance(source, FuseResult):
        if source.rig is None:
            raise ValueError("TSDF from views needs the rig's camera: the FuseResult has no rig")
        cam = source.rig.camera
        Ew = np.eye(4)
        Ew[:3, :3], Ew[:3, 3] = cam.R, cam.t
        for pcd, T in zip(source.views, source.transforms):
            pts = np.asarray(pcd.points)
            if len(pts) == 0:
                continue
            E = Ew @ np.linalg.inv(T)  # object -> world (at the view's angle) -> camera
            splat = min(math.ceil((s.tsdf_splat_mm or _splat_radius_mm(pts)) / px_mm), _MAX_SPLAT_PX)
            kc = _depth_camera(pts, E, px_mm, margin=splat + 2)
            if kc is not None:
                nrm = np.asarray(pcd.normals) if pcd.has_normals() else None
                jobs.append((pts, nrm, kc[0], E, kc[1], kc[2], splat, s.tsdf_fill_px))
    else:
        _check_cloud(source, normals=True)
        pts = np.asarray(source.points)
        nrm = np.asarray(source.normals)
        splat = min(math.ceil((s.tsdf_splat_mm or _splat_radius_mm(pts)) / px_mm), _MAX_SPLAT_PX)
        ctr = 0.5 * (np.asarray(source.get_min_bound()) + np.asarray(source.get_max_bound()))
        radius = float(np.linalg.norm(pts - ctr, axis=1).max())
        # Fibonacci sphere of view directions.
        n = s.tsdf_virtual_views
        k = np.arange(n) + 0.5
        zc = 1 - 2 * k / n
        ph = math.pi * (1 + 5 ** 0.5) * k
        dirs = np.stack([np.sqrt(1 - zc ** 2) * np.cos(ph), np.sqrt(1 - zc ** 2) * np.sin(ph), zc], axis=1)
        for d in dirs:
            eye = ctr + d * 4.0 * max(radius, 1e-3)
            up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            E = _look_at_E(eye, ctr, up)
            facing = np.einsum("ij,ij->i", nrm, eye - pts) > 0.2 * np.linalg.norm(eye - pts, axis=1)
            if facing.sum() < 10:
                continue
            kc = _depth_camera(pts[facing], E, px_mm, margin=splat + 2)
            jobs.append((pts[facing], nrm[facing], kc[0], E, kc[1], kc[2], splat, s.tsdf_fill_px))
    if not jobs:
        raise ValueError("no view has points to integrate")
    mesh, used = _integrate(jobs, s.tsdf_voxel_mm, s.tsdf_trunc_voxels)
    if len(mesh.triangles) == 0:
        raise ValueError("TSDF integration gave an empty surface (is tsdf_voxel_mm far too large?)")
    if s.watertight:
        mesh.compute_vertex_normals()
        dense = o3d.geometry.PointCloud(mesh.vertices)
        dense.normals = mesh.vertex_normals
        return _watertight_poisson(dense, s, "tsdf", t0)
    mesh = clean_mesh(mesh)
    small = _drop_small_components(mesh, s.min_component_triangles) if s.min_component_triangles else 0
    mesh = _finish(mesh, s)
    info = _mesh_info(mesh, t0, depth_maps=used, small_piece_triangles_removed=small)
    log.info("TSDF mesh: %d vertices, %d triangles from %d depth maps", info["vertices"], info["triangles"], len(jobs))
    return MeshResult(mesh=mesh, method="tsdf", watertight=None, info=info)


# ----------------------------------------------------------------------------- front doors


def mesh_cloud(cloud, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Mesh a bare oriented cloud with ``settings.method``."""
    _check_settings(settings)
    if settings.method == "tsdf":
        return tsdf_mesh(cloud, settings=settings)
    return poisson_mesh(cloud, settings=settings)


def mesh_fused(result, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Mesh a :class:`~ringscan.pipeline.fuse.FuseResult`: Poisson on its fused
    cloud, or TSDF from its views' depth maps."""
    _check_settings(settings)
    if settings.method == "tsdf":
        return tsdf_mesh(result, settings=settings)
    return poisson_mesh(result.cloud, settings=settings)


def orient_normals(cloud, *, k: int = 20):
    """Estimate normals of a bare cloud and orient them outward, in place.

    Normals come from PCA over the ``k`` nearest neighbours, are made consistent
    over the cloud (Open3D's tangent-plane propagation) and flipped as a whole when
    most point toward the centroid (right for a single closed object). Clouds from
    :func:`~ringscan.pipeline.fuse.fuse_views` need none of this: their normals are
    oriented toward each view's camera.
    """
    o3d = _o3d()
    if len(cloud.points) < 3:
        raise ValueError(f"cloud has {len(cloud.points)} points: too few to estimate normals")
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=k))
    cloud.orient_normals_consistent_tangent_plane(k)
    pts = np.asarray(cloud.points)
    nrm = np.asarray(cloud.normals)
    if np.mean(np.einsum("ij,ij->i", nrm, pts - pts.mean(axis=0)) < 0) > 0.5:
        cloud.normals = o3d.utility.Vector3dVector(-nrm)
    return cloud


# ----------------------------------------------------------------------------- files


def _ext(path: Path, allowed) -> str:
    ext = path.suffix.lower()
    if ext not in allowed:
        raise ValueError(f"{path}: unsupported extension {ext or '(none)'!r}; use one of {', '.join(allowed)}")
    return ext


def write_mesh(path: str | os.PathLike, mesh) -> None:
    """Write a mesh as PLY (binary), OBJ or STL, chosen by extension; atomically.

    Normals are computed when missing (STL needs triangle normals).
    """
    o3d = _o3d()
    path = Path(path)
    ext = _ext(path, MESH_FORMATS)
    if len(mesh.triangles) == 0:
        raise ValueError(f"{path}: the mesh has no triangles")
    if not mesh.has_triangle_normals():
        mesh.compute_triangle_normals()
    if not mesh.has_vertex_normals():
        mesh.compute_vertex_normals()
    with atomic_path(path) as tmp:
        kw = {"write_ascii": False} if ext != ".obj" else {}
        # (OBJ keeps vertex normals only: Open3D's warning about triangle normals is noise.)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            ok = o3d.io.write_triangle_mesh(str(tmp), mesh, write_vertex_colors=mesh.has_vertex_colors(), **kw)
        if not ok:
            raise FormatError(path, "Open3D could not write the mesh")


def read_mesh(path: str | os.PathLike):
    """Read a PLY/OBJ/STL mesh with Open3D; FormatError when missing or without triangles."""
    o3d = _o3d()
    path = Path(path)
    _ext(path, MESH_FORMATS)
    if not path.is_file():
        raise FormatError(path, "file not found")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise FormatError(path, "no triangles in the file (not a mesh, or unreadable)")
    return mesh


def read_cloud(path: str | os.PathLike):
    """Read a point cloud (PLY/PCD/XYZ...) with Open3D; FormatError when missing or empty."""
    o3d = _o3d()
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "file not found")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pcd = o3d.io.read_point_cloud(str(path))
    if len(pcd.points) == 0:
        raise FormatError(path, "no points in the file (not a point cloud, or unreadable)")
    return pcd


def write_cloud(path: str | os.PathLike, cloud, *, view: np.ndarray | None = None,
                confidence: np.ndarray | None = None) -> None:
    """Write a cloud as binary PLY: x, y, z, nx, ny, nz (when present), view, confidence."""
    pts = np.asarray(cloud.points)
    f = {"x": pts[:, 0].astype(np.float32), "y": pts[:, 1].astype(np.float32), "z": pts[:, 2].astype(np.float32)}
    if cloud.has_normals():
        n = np.asarray(cloud.normals)
        f.update(nx=n[:, 0].astype(np.float32), ny=n[:, 1].astype(np.float32), nz=n[:, 2].astype(np.float32))
    if view is not None and len(view) == len(pts):
        f["view"] = np.asarray(view, np.int32)
    if confidence is not None and len(confidence) == len(pts):
        f["confidence"] = np.asarray(confidence, np.float32)
    write_ply(path, f, comments=["ringscan fused cloud, object frame, mm"])


# ----------------------------------------------------------------------------- measurement


def compare_to_truth(mesh, truth, *, samples: int = 200_000, within_mm: float = 0.5, seed: int = 0) -> dict:
    """Distances between a mesh and the truth mesh, both ways, from surface samples.

    Returns ``mesh_to_truth_mean``, ``truth_to_mesh_mean``, ``chamfer`` (their
    mean), the 95th percentiles, and ``truth_within`` (fraction of the truth
    surface within ``within_mm`` of the mesh). Distances are point-to-surface (mm).
    """
    o3d = _o3d()
    if len(mesh.triangles) == 0 or len(truth.triangles) == 0:
        raise ValueError("both meshes need triangles")
    o3d.utility.random.seed(seed)
    a = np.asarray(mesh.sample_points_uniformly(samples).points)
    b = np.asarray(truth.sample_points_uniformly(samples).points)

    def dist(pts, m):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
        return scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy().astype(np.float64)

    d_mt = dist(a, truth)
    d_tm = dist(b, mesh)
    return {"mesh_to_truth_mean": float(d_mt.mean()), "truth_to_mesh_mean": float(d_tm.mean()),
            "chamfer": float(0.5 * (d_mt.mean() + d_tm.mean())),
            "mesh_to_truth_p95": float(np.quantile(d_mt, 0.95)), "truth_to_mesh_p95": float(np.quantile(d_tm, 0.95)),
            "truth_within": float(np.mean(d_tm <= within_mm)), "within_mm": within_mm}


# ----------------------------------------------------------------------------- one call for the demo


def fuse_and_mesh(recon_dir, out_dir: str | os.PathLike, *, fuse_settings=None,
                  mesh_settings: MeshSettings = MeshSettings(), formats=(".ply",), preview: bool = True,
                  rig=None, truth=None, device: str | None = None, progress: bool = False,
                  pose_settings=None) -> dict:
    """Fuse a reconstruction folder (or a scan folder), mesh it, write everything.

    Writes into ``out_dir``: ``fused.ply`` (the fused cloud), ``mesh.<ext>`` for each
    of ``formats`` (ply, obj, stl), ``preview.png`` (when ``preview``; see
    :mod:`ringscan.pipeline.visualize`) and ``fuse_report.json`` (per-view residuals,
    mesh checks, resolved settings, and the figures against ``truth`` when given).
    A scan folder is reconstructed first into ``out_dir/recon``.

    ``recon_dir`` may also be a list of folders: scans of the same object in several
    poses (flip and rescan). The first is the reference pose; each is fused on its
    own, the others are aligned to it (:func:`ringscan.pipeline.fuse.fuse_poses`,
    with ``pose_settings``) and everything is merged in its object frame. Scan
    folders are then reconstructed into ``out_dir/recon/pose_<i>``; the report's
    ``fusion.poses`` holds each pose's transform, fitness and inlier RMSE, and
    ``fused.ply``'s ``view`` property is the pose index.

    Args:
        truth: a truth mesh (``o3d.geometry.TriangleMesh``, a mesh file, or a
            simulated scan folder whose ``truth/object.ply`` is used) to measure the
            mesh against with :func:`compare_to_truth`.

    Returns:
        The report dictionary (also written to ``fuse_report.json``).
    """
    from .fuse import FuseSettings, PoseSettings, fuse_recon, fuse_recons

    fuse_settings = FuseSettings() if fuse_settings is None else fuse_settings
    pose_settings = PoseSettings() if pose_settings is None else pose_settings
    sources = [recon_dir] if isinstance(recon_dir, (str, bytes, os.PathLike)) else list(recon_dir)
    if not sources:
        raise ValueError("no source folder given")
    multi = len(sources) > 1
    if multi and rig is not None:
        raise ValueError("rig: a replacement rig applies to a single source only")
    _check_settings(mesh_settings)
    out_dir = Path(out_dir)
    fmts = []
    for f in formats:
        f = str(f).lower()
        f = f if f.startswith(".") else f".{f}"
        _ext(Path("mesh" + f), MESH_FORMATS)
        fmts.append(f)
    truth_mesh = _load_truth(truth) if truth is not None else None
    t0 = time.perf_counter()
    if multi:
        fused = fuse_recons(sources, settings=fuse_settings, pose_settings=pose_settings, work_dir=out_dir / "recon",
                            device=device, progress=progress)
    else:
        fused = fuse_recon(sources[0], settings=fuse_settings, rig=rig, work_dir=out_dir / "recon", device=device,
                           progress=progress)
    t_fuse = time.perf_counter() - t0
    # TSDF from several poses integrates the merged cloud (virtual views), not the per-view depth maps.
    mres = mesh_cloud(fused.cloud, settings=mesh_settings) if multi else mesh_fused(fused, settings=mesh_settings)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_cloud(out_dir / "fused.ply", fused.cloud, view=fused.point_view, confidence=fused.point_confidence)
    outputs = {"cloud": "fused.ply", "meshes": []}
    for f in fmts:
        write_mesh(out_dir / f"mesh{f}", mres.mesh)
        outputs["meshes"].append(f"mesh{f}")
    if preview:
        from .visualize import render_to_png

        res = render_to_png([mres.mesh], out_dir / "preview.png")
        outputs["preview"] = "preview.png"
        outputs["preview_renderer"] = res.renderer
    rep = {"format": FUSE_REPORT_FORMAT, "source": str(Path(sources[0]).resolve()),
           "fusion": fused.report(), "mesh": {"method": mres.method, "watertight": mres.watertight, **mres.info},
           "settings": {"fuse": dataclasses.asdict(fuse_settings), "mesh": dataclasses.asdict(mesh_settings)},
           "outputs": outputs}
    if multi:
        rep["sources"] = [str(Path(p).resolve()) for p in sources]
        rep["settings"]["poses"] = dataclasses.asdict(pose_settings)
    if truth_mesh is not None:
        rep["truth"] = compare_to_truth(mres.mesh, truth_mesh)
    rep["seconds"] = {"fuse": round(t_fuse, 3), "total": round(time.perf_counter() - t0, 3)}
    atomic_write_json(out_dir / "fuse_report.json", rep)
    return rep


def _load_truth(truth):
    o3d = _o3d()
    if isinstance(truth, o3d.geometry.TriangleMesh):
        return truth
    p = Path(truth)
    if p.is_dir():
        from .io import read_json

        t = read_json(p / "scan.json").get("truth")
        if not isinstance(t, dict) or not isinstance(t.get("mesh"), str):
            raise FormatError(p / "scan.json", "truth.mesh: this scan has no ground truth mesh")
        p = p / t["mesh"]
    return read_mesh(p)
