"""Synthetic turntable views for the fusion, meshing and view tests.

A closed, lumpy, asymmetric test object (a sphere with smooth radial bumps) stands
in the object frame; for every turntable angle theta it is turned by theta about
the turntable axis (docs/design.md §11) and ray-cast from the rig's camera through a pixel
grid, as a scanner would see it. Points get Gaussian noise along the camera ray.
Fusing the views with the right axis must give the object back.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import open3d as o3d

from ringscan.pipeline.formats.rig import Camera, Rig, Turntable, default_rig, turntable_transform
from ringscan.pipeline.fusion.turntable import FusionView


def lumpy_object(radius: float = 22.0, center=(3.0, -2.0, 30.0), resolution: int = 60) -> o3d.geometry.TriangleMesh:
    """A closed asymmetric blob in the object frame (mm)."""
    m = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=resolution)
    v = np.asarray(m.vertices)
    th = np.arccos(np.clip(v[:, 2], -1, 1))
    ph = np.arctan2(v[:, 1], v[:, 0])
    r = radius * (1.0 + 0.12 * np.sin(3 * ph) * np.sin(th) ** 2 + 0.08 * np.cos(2 * th) + 0.05 * np.cos(ph - 0.7))
    m.vertices = o3d.utility.Vector3dVector(v * r[:, None] * np.array([1.0, 0.85, 1.1]) + np.asarray(center))
    m.compute_vertex_normals()
    m.compute_triangle_normals()
    return m


def small_rig(width: int = 640, height: int = 512, focal: float = 1300.0) -> Rig:
    """The default virtual rig with a smaller camera (same pose)."""
    r = default_rig()
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
    cam = dataclasses.replace(r.camera, width=width, height=height, K=K, dist=np.zeros(5))
    return dataclasses.replace(r, camera=cam)


def camera_rays(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Unit world-frame ray directions (H*W, 3) of an undistorted camera, and its centre."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    x = (u.ravel() - cam.K[0, 2]) / cam.K[0, 0]
    y = (v.ravel() - cam.K[1, 2]) / cam.K[1, 1]
    d = np.stack([x, y, np.ones_like(x)], axis=1) @ cam.R  # R^T applied to camera-frame rays
    return d / np.linalg.norm(d, axis=1, keepdims=True), cam.center


def scan_views(mesh: o3d.geometry.TriangleMesh, rig: Rig, angles_deg, *, noise_mm: float = 0.03,
               seed: int = 0, turntable: Turntable | None = None) -> list[FusionView]:
    """Ray-cast ``mesh`` (object frame) turned by each angle about the turntable axis.

    ``turntable`` is the true axis (default: the rig's).
    """
    rng = np.random.default_rng(seed)
    tt = turntable or rig.turntable
    dirs, c = camera_rays(rig.camera)
    views = []
    for i, th in enumerate(angles_deg):
        m = o3d.geometry.TriangleMesh(mesh).transform(turntable_transform(tt, th))
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
        rays = np.concatenate([np.broadcast_to(c, dirs.shape), dirs], axis=1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy().astype(np.float64)
        ok = np.isfinite(t)
        t = t[ok] + rng.normal(0.0, noise_mm, ok.sum())
        pts = c + dirs[ok] * t[:, None]
        views.append(FusionView(name=f"view_{i:03d}", points=pts, turntable_deg=float(th), camera_center=c.copy(),
                               confidence=np.ones(len(pts))))
    return views


def point_to_mesh(points: np.ndarray, mesh: o3d.geometry.TriangleMesh) -> np.ndarray:
    """Unsigned distance of each point to the mesh surface (mm)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()


def visible_truth(mesh: o3d.geometry.TriangleMesh, rig: Rig, angles_deg, n: int = 20000, seed: int = 1) -> np.ndarray:
    """Points sampled on the truth surface that at least one view sees (object frame)."""
    pts = np.asarray(mesh.sample_points_uniformly(n, use_triangle_normal=True).points)
    seen = np.zeros(len(pts), bool)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    for th in angles_deg:
        cam = turntable_transform(rig.turntable, -th)
        c = cam[:3, :3] @ rig.camera.center + cam[:3, 3]
        d = pts - c
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(c, d.shape), d / dist[:, None]], axis=1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        seen |= np.abs(t - dist) < 0.05
    return pts[seen]


ANGLES = tuple(float(a) for a in np.arange(8) * 45.0)


@functools.lru_cache(maxsize=2)
def synthetic_scan(noise_mm: float = 0.03):
    """(object mesh, rig, angles, views): 8 turntable views of the lumpy object with
    a 400 x 320 camera (cached; treat as read-only)."""
    rig = small_rig(400, 320, 800.0)
    obj = lumpy_object()
    return obj, rig, ANGLES, tuple(scan_views(obj, rig, ANGLES, noise_mm=noise_mm))


def wrong_axis(rig: Rig, tilt_deg: float = 0.5, offset_mm: float = 1.0) -> Rig:
    """The rig with its turntable axis tilted by ``tilt_deg`` and moved by ``offset_mm``."""
    a = np.radians(tilt_deg)
    tt = Turntable(axis_point=rig.turntable.axis_point + np.array([offset_mm, 0.0, 0.0]),
                   axis_dir=np.array([np.sin(a), 0.0, np.cos(a)]))
    return dataclasses.replace(rig, turntable=tt)


def write_recon(folder, views, rig: Rig, *, with_normals: bool = False) -> None:
    """Write views as a reconstruction folder (report.json + one PLY per view)."""
    from ringscan.pipeline.formats.atomic import atomic_write_json
    from ringscan.pipeline.formats.ply import write_ply
    from ringscan.pipeline.formats.rig import rig_to_dict

    entries = []
    for i, v in enumerate(views):
        f = {"x": v.points[:, 0].astype(np.float32), "y": v.points[:, 1].astype(np.float32),
             "z": v.points[:, 2].astype(np.float32)}
        if with_normals and v.normals is not None:
            f.update(nx=v.normals[:, 0], ny=v.normals[:, 1], nz=v.normals[:, 2])
        n = len(v.points)
        f.update(ring=np.arange(n, dtype=np.int32) % 50, view=np.full(n, i, np.int32),
                 confidence=np.ones(n, np.float32))
        write_ply(folder / f"{v.name}.ply", f)
        entries.append({"name": v.name, "turntable_deg": v.turntable_deg, "ply": f"{v.name}.ply",
                        "camera_center": v.camera_center.tolist(), "points": n})
    atomic_write_json(folder / "report.json", {"scan": str(folder), "views": entries, "rig": rig_to_dict(rig)})
