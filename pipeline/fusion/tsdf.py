"""TSDF meshing: each view's points are splatted into a depth map seen from its own
camera, the depth maps are integrated into a TSDF volume (Open3D) and the surface
extracted by marching cubes.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from ringscan.pipeline.formats.meshes import open3d_lib
from ringscan.pipeline.formats.rig import look_at
from ringscan.pipeline.fusion.mesh import (
    MeshResult,
    MeshSettings,
    _check_cloud,
    check_mesh_settings,
    clean_mesh,
    drop_small_components,
    finish_mesh,
    mesh_info,
    watertight_poisson,
)
from ringscan.pipeline.fusion.threads import open3d_threads
from ringscan.pipeline.fusion.turntable import FuseResult

log = logging.getLogger(__name__)

__all__ = ["tsdf_mesh"]


_MAX_SPLAT_PX = 24


def _splat_radius_mm(pts: np.ndarray) -> float:
    """A splat radius that closes the gaps between neighbouring samples: 1.5 x the
    median distance to the 4th-nearest neighbour."""
    o3d = open3d_lib()
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
    o3d = open3d_lib()
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

    R, t = look_at(eye, target, up_hint)
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = R, t
    return E


def tsdf_mesh(source, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """TSDF fusion (see :func:`_tsdf_mesh`), with Open3D on ``settings.threads`` threads."""
    with open3d_threads(getattr(settings, "threads", 1)):
        return _tsdf_mesh(source, settings=settings)


def _tsdf_mesh(source, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """TSDF fusion of per-view depth maps (Open3D's sparse voxel-block TSDF).

    Args:
        source: a :class:`~ringscan.pipeline.fusion.turntable.FuseResult` (each view's cloud is
            projected into its own camera: the rig's camera moved into the object
            frame with the view's pose), or an oriented ``o3d.geometry.PointCloud``
            (integrated from ``tsdf_virtual_views`` virtual cameras around it, each
            seeing only the points whose normals face it).
        settings: ``tsdf_*``, ``watertight`` and cleanup fields are used.
    """

    check_mesh_settings(settings)
    s = settings
    o3d = open3d_lib()
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
        return watertight_poisson(dense, s, "tsdf", t0)
    mesh = clean_mesh(mesh)
    small = drop_small_components(mesh, s.min_component_triangles) if s.min_component_triangles else 0
    mesh = finish_mesh(mesh, s)
    info = mesh_info(mesh, t0, depth_maps=used, small_piece_triangles_removed=small)
    log.info("TSDF mesh: %d vertices, %d triangles from %d depth maps", info["vertices"], info["triangles"], len(jobs))
    return MeshResult(mesh=mesh, method="tsdf", watertight=None, info=info)
