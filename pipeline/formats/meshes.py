"""Meshes and point clouds through Open3D: PLY, OBJ and STL by extension."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.ply import check_ply, write_ply

log = logging.getLogger(__name__)

__all__ = ["MESH_FORMATS", "write_mesh", "read_mesh", "read_cloud", "write_cloud", "drop_non_finite", "open3d_lib"]


MESH_FORMATS = (".ply", ".obj", ".stl")
"""Mesh file formats written and read (chosen by extension)."""


def _ext(path: Path, allowed) -> str:
    ext = path.suffix.lower()
    if ext not in allowed:
        raise ValueError(f"{path}: unsupported extension {ext or '(none)'!r}; use one of {', '.join(allowed)}")
    return ext


def write_mesh(path: str | os.PathLike, mesh) -> None:
    """Write a mesh as PLY (binary), OBJ or STL, chosen by extension; atomically.

    Normals are computed when missing (STL needs triangle normals).
    """
    o3d = open3d_lib()
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
        if ext == ".obj":
            _name_obj_object(tmp, path.stem)


def _name_obj_object(obj: Path, name: str) -> None:
    """Open3D names the OBJ's object after the file it writes, here the temporary
    one: put the real name in that comment line, in place (padded to the same length)."""
    with open(obj, "r+b") as fh:
        head = fh.read(512)
        key = b"# object name: "
        i = head.find(key)
        if i < 0:
            return
        j = head.find(b"\n", i)
        if j < 0:
            return
        old = head[i + len(key):j]
        new = name.encode("utf-8", "replace")[:len(old)]
        fh.seek(i + len(key))
        fh.write(new.ljust(len(old)))


def _check_input(path: Path) -> None:
    """FormatError for a missing file or a truncated PLY (Open3D reads a truncated PLY
    up to where it ends, without a word)."""
    if not path.is_file():
        raise FormatError(path, "file not found")
    if path.suffix.lower() == ".ply":
        check_ply(path)


def read_mesh(path: str | os.PathLike):
    """Read a PLY/OBJ/STL mesh with Open3D; FormatError when missing or without triangles."""
    o3d = open3d_lib()
    path = Path(path)
    _ext(path, MESH_FORMATS)
    _check_input(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise FormatError(path, "no triangles in the file (not a mesh, or unreadable)")
    return mesh


def read_cloud(path: str | os.PathLike):
    """Read a point cloud (PLY/PCD/XYZ...) with Open3D; FormatError when missing,
    empty, or (PLY) truncated. Non-finite points are kept (see :func:`drop_non_finite`)."""
    o3d = open3d_lib()
    path = Path(path)
    _check_input(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pcd = o3d.io.read_point_cloud(str(path))
    if len(pcd.points) == 0:
        raise FormatError(path, "no points in the file (not a point cloud, or unreadable)")
    return pcd


def write_cloud(path: str | os.PathLike, cloud, *, view: np.ndarray | None = None,
                confidence: np.ndarray | None = None, sigma: np.ndarray | None = None) -> None:
    """Write a cloud as binary PLY: x, y, z, nx, ny, nz (when present), view, confidence,
    sigma (each per-point array when given, one per point)."""
    pts = np.asarray(cloud.points)
    f = {"x": pts[:, 0].astype(np.float32), "y": pts[:, 1].astype(np.float32), "z": pts[:, 2].astype(np.float32)}
    if cloud.has_normals():
        n = np.asarray(cloud.normals)
        f.update(nx=n[:, 0].astype(np.float32), ny=n[:, 1].astype(np.float32), nz=n[:, 2].astype(np.float32))
    if view is not None and len(view) == len(pts):
        f["view"] = np.asarray(view, np.int32)
    if confidence is not None and len(confidence) == len(pts):
        f["confidence"] = np.asarray(confidence, np.float32)
    if sigma is not None and len(sigma) == len(pts):
        f["sigma"] = np.asarray(sigma, np.float32)
    write_ply(path, f, comments=["ringscan fused cloud, object frame, mm"])


def drop_non_finite(geom) -> tuple[object, int]:
    """Remove the points (or mesh vertices, with their triangles) that have a NaN or
    infinite coordinate or normal.

    Returns:
        (the geometry, how many points or vertices were removed). A point cloud is
        returned as a new cloud; a mesh is changed in place.
    """
    if hasattr(geom, "triangles"):
        v = np.asarray(geom.vertices)
        bad = ~np.all(np.isfinite(v), axis=1)
        if geom.has_vertex_normals():
            bad |= ~np.all(np.isfinite(np.asarray(geom.vertex_normals)), axis=1)
        if bad.any():
            geom.remove_vertices_by_mask(bad)
        return geom, int(bad.sum())
    pts = np.asarray(geom.points)
    bad = ~np.all(np.isfinite(pts), axis=1)
    if geom.has_normals():
        bad |= ~np.all(np.isfinite(np.asarray(geom.normals)), axis=1)
    if not bad.any():
        return geom, 0
    return geom.select_by_index(np.nonzero(~bad)[0].tolist()), int(bad.sum())


def open3d_lib():
    """Open3D, imported on first use (a heavy optional import: ``import ringscan``
    stays fast and headless tools never load it)."""
    import open3d as o3d

    return o3d
