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

import logging
import time
from dataclasses import dataclass

import numpy as np

from ringscan.pipeline.formats.meshes import open3d_lib
from ringscan.pipeline.formats.settings import check_finite_settings
from ringscan.pipeline.fusion.threads import check_threads, open3d_threads, poisson_threads

log = logging.getLogger(__name__)

__all__ = ["MAX_COORDINATE_MM", "MIN_MESH_POINTS", "drop_unusable_points", "MeshSettings", "MeshResult",
           "check_mesh_settings", "finish_mesh", "drop_small_components", "mesh_info", "clean_mesh", "poisson_mesh", "watertight_poisson", "make_watertight", "orient_normals", "compare_to_truth"]


MAX_COORDINATE_MM = 1e6
"""Points with a coordinate beyond +-this (1 km) are dropped before meshing: no
turntable scan is that large, such values come from a broken file or
triangulation, and they wreck the meshing's octree and Qhull's arithmetic."""

MIN_MESH_POINTS = 10
"""Fewest points a cloud needs to be meshed."""


def drop_unusable_points(cloud, *, max_coordinate_mm: float = MAX_COORDINATE_MM):
    """Drop points that meshing cannot use: a NaN or infinite coordinate or normal,
    or a coordinate beyond +-``max_coordinate_mm``.

    Returns:
        (the cloud without them (the same object when none was dropped),
        {"non_finite": n, "out_of_range": m}).
    """
    pts = np.asarray(cloud.points)
    bad_nf = ~np.all(np.isfinite(pts), axis=1)
    if cloud.has_normals():
        bad_nf |= ~np.all(np.isfinite(np.asarray(cloud.normals)), axis=1)
    with np.errstate(invalid="ignore"):
        bad_range = ~bad_nf & np.any(np.abs(pts) > max_coordinate_mm, axis=1)
    counts = {"non_finite": int(bad_nf.sum()), "out_of_range": int(bad_range.sum())}
    bad = bad_nf | bad_range
    if bad.any():
        cloud = cloud.select_by_index(np.nonzero(~bad)[0].tolist())
        log.info("dropped %d points with a NaN or infinite coordinate and %d beyond +-%g mm", counts["non_finite"],
                    counts["out_of_range"], max_coordinate_mm)
    return cloud, counts


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
    threads: int = 1
    """CPU threads of Poisson and the rest of Open3D while meshing: 1 gives the same
    bytes from run to run; 0 (every core) is faster, and then Poisson's vertex order
    and last bits vary (a triangle more or less after trimming;
    :mod:`ringscan.pipeline.fusion.threads`)."""


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


def check_mesh_settings(s: MeshSettings) -> None:
    if not isinstance(s, MeshSettings):
        raise ValueError(f"settings must be a MeshSettings, got {type(s).__name__}")
    check_finite_settings(s)
    check_threads("MeshSettings", s.threads)
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
    o3d = open3d_lib()
    if not isinstance(cloud, o3d.geometry.PointCloud):
        raise ValueError(f"cloud must be an open3d.geometry.PointCloud, got {type(cloud).__name__}")
    if len(cloud.points) < 10:
        raise ValueError(f"cloud has {len(cloud.points)} points: too few to mesh (need at least 10)")
    if normals and not cloud.has_normals():
        raise ValueError("cloud has no normals: Poisson needs oriented normals (fuse_views gives them)")


def finish_mesh(mesh, s: MeshSettings):
    mesh.remove_unreferenced_vertices()
    if s.smooth_iterations > 0 and len(mesh.triangles):
        mesh = mesh.filter_smooth_taubin(number_of_iterations=s.smooth_iterations)
    mesh.compute_vertex_normals()
    mesh.compute_triangle_normals()
    return mesh


def drop_small_components(mesh, min_triangles: int, keep_largest_only: bool = False) -> int:
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


def mesh_info(mesh, t0: float, **extra) -> dict:
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
    o3d = open3d_lib()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=s.poisson_depth, scale=s.poisson_scale if scale is None else scale,
            linear_fit=s.poisson_linear_fit, n_threads=poisson_threads(s.threads))
    if not cloud.has_colors():
        # Open3D gives the mesh black vertex colours when the cloud has none.
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.zeros((0, 3)))
    return mesh, np.asarray(dens)


def poisson_mesh(cloud, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Screened Poisson surface of an oriented cloud (see :func:`_poisson_mesh`), with
    Open3D on ``settings.threads`` threads."""
    with open3d_threads(getattr(settings, "threads", 1)):
        return _poisson_mesh(cloud, settings=settings)


def _poisson_mesh(cloud, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Screened Poisson surface of an oriented cloud, trimmed (or watertight).

    Args:
        cloud: ``o3d.geometry.PointCloud`` with oriented normals.
        settings: ``poisson_*``, ``density_quantile``, ``trim_distance_mm``,
            ``watertight`` and cleanup fields are used.
    """
    check_mesh_settings(settings)
    _check_cloud(cloud, normals=True)
    s = settings
    t0 = time.perf_counter()
    if s.watertight:
        return watertight_poisson(cloud, s, "poisson", t0)
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
    small = drop_small_components(mesh, s.min_component_triangles) if s.min_component_triangles else 0
    mesh = finish_mesh(mesh, s)
    info = mesh_info(mesh, t0, trimmed_density=n_density, trimmed_total=int(drop.sum()),
                      small_piece_triangles_removed=small)
    log.info("Poisson mesh: %d vertices, %d triangles (%d vertices trimmed)", info["vertices"], info["triangles"],
             info["trimmed_total"])
    return MeshResult(mesh=mesh, method="poisson", watertight=None, info=info)


def _distance_to_points(q: np.ndarray, pts: np.ndarray) -> np.ndarray:
    o3d = open3d_lib()
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(pts, np.float64)))
    nns.knn_index()
    _, d2 = nns.knn_search(o3d.core.Tensor(np.ascontiguousarray(q, np.float64)), 1)
    return np.sqrt(d2.numpy()[:, 0])


def watertight_poisson(cloud, s: MeshSettings, method: str, t0: float) -> MeshResult:
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
    info = mesh_info(mesh, t0, watertight=wt, poisson_scale=scale)
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
    drop_small_components(mesh, 0, keep_largest_only=True)
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    mesh.compute_triangle_normals()
    return mesh


# ----------------------------------------------------------------------------- TSDF


# ----------------------------------------------------------------------------- front doors


def orient_normals(cloud, *, k: int = 20):
    """Estimate normals of a bare cloud and orient them outward, in place.

    Normals come from PCA over the ``k`` nearest neighbours, are made consistent
    over the cloud (Open3D's tangent-plane propagation) and flipped as a whole when
    most point toward the centroid (right for a single closed object). Clouds from
    :func:`~ringscan.pipeline.fusion.turntable.fuse_views` need none of this: their normals are
    oriented toward each view's camera.
    """
    o3d = open3d_lib()
    if len(cloud.points) < 3:
        raise ValueError(f"cloud has {len(cloud.points)} points: too few to estimate normals")
    pts = np.asarray(cloud.points)
    if not np.all(np.isfinite(pts)):
        raise ValueError("cloud has NaN or infinite coordinates (drop them first: drop_unusable_points)")
    c = pts - pts.mean(axis=0)
    lam, vec = np.linalg.eigh(c.T @ c / len(c))
    spread = np.sqrt(np.maximum(lam, 0.0))
    if spread[2] == 0.0:
        raise ValueError(f"all {len(pts)} points of the cloud lie at one place: no surface to mesh")
    if spread[1] < 1e-6 * spread[2]:
        raise ValueError(f"the {len(pts)} points of the cloud lie on a line: no surface to mesh")
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=k))
    if spread[0] < 1e-4 * spread[2]:
        # Flat (Qhull, behind the tangent-plane propagation, fails on coplanar
        # points): every normal along the plane's normal, toward +z when it can.
        n = vec[:, 0] if vec[2, 0] >= 0 else -vec[:, 0]
        cloud.orient_normals_to_align_with_direction(n)
        return cloud
    try:
        cloud.orient_normals_consistent_tangent_plane(k)
    except RuntimeError as e:
        raise ValueError(f"cannot orient the cloud's normals ({str(e).splitlines()[0][:200]})") from None
    nrm = np.asarray(cloud.normals)
    if np.mean(np.einsum("ij,ij->i", nrm, pts - pts.mean(axis=0)) < 0) > 0.5:
        cloud.normals = o3d.utility.Vector3dVector(-nrm)
    return cloud


# ----------------------------------------------------------------------------- files


# ----------------------------------------------------------------------------- measurement


def compare_to_truth(mesh, truth, *, samples: int = 200_000, within_mm: float = 0.5, seed: int = 0) -> dict:
    """Distances between a mesh and the truth mesh, both ways, from surface samples.

    Returns ``mesh_to_truth_mean``, ``truth_to_mesh_mean``, ``chamfer`` (their
    mean), the 95th percentiles, and ``truth_within`` (fraction of the truth
    surface within ``within_mm`` of the mesh). Distances are point-to-surface (mm).
    """
    o3d = open3d_lib()
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


