"""ringscan's Python API: plain functions from a scan to per-view clouds, one fused
object, a mesh and the figures against the truth, in memory (docs/api.md).

    import ringscan

    scan = ringscan.load_scan("out/demo/scan")          # or ringscan.simulate(folder, ...)
    views = ringscan.reconstruct(scan)                  # one ReconstructedView a view
    fused = ringscan.fuse(views)                        # o3d.t.geometry.PointCloud, object frame
    mesh = ringscan.mesh(fused)                         # o3d.t.geometry.TriangleMesh
    figures = ringscan.evaluate(views, scan)            # a simulated scan's truth

Each function checks its input first and raises one ``ValueError`` (a
:class:`~ringscan.pipeline.formats.errors.FormatError` for a file) naming what is wrong;
options are keyword-only. ``import ringscan`` loads none of this: the package's
``__getattr__`` imports this module (and Warp, Open3D) on the first use of a name.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ringscan.pipeline.codecs import DEFAULT_CODEC
from ringscan.pipeline.evaluate.metrics import distance_stats, evaluate_points, point_distances
from ringscan.pipeline.formats.meshes import open3d_lib
from ringscan.pipeline.formats.patterns import PatternSpec, default_patterns, parse_patterns
from ringscan.pipeline.formats.rig import Rig, rig_to_dict, turntable_transform
from ringscan.pipeline.formats.scan import Scan, check_view_frames
from ringscan.pipeline.formats.scan import load_scan as _load_scan
from ringscan.pipeline.formats.settings import (
    check_finite_settings,
    check_settings_types,
    settings_from_dict,
    settings_to_dict,
)
from ringscan.pipeline.fusion.mesh import MeshSettings, compare_to_truth, drop_unusable_points, orient_normals
from ringscan.pipeline.fusion.meshing import mesh_cloud
from ringscan.pipeline.fusion.turntable import FuseSettings, FusionView, fuse_views
from ringscan.pipeline.fusion.workflow import load_truth_mesh
from ringscan.pipeline.reconstruct.settings import ReconstructSettings, check_setting_ranges
from ringscan.pipeline.reconstruct.view import check_rays, reconstruct_view
from ringscan.pipeline.simulate.scan import simulate_scan

log = logging.getLogger(__name__)

__all__ = ["ReconstructedView", "load_scan", "simulate", "reconstruct", "fuse", "mesh", "evaluate", "POINT_ATTRIBUTES"]

POINT_ATTRIBUTES = ("positions", "normals", "ring", "rho", "view", "confidence", "u", "v", "sigma", "residual",
                    "sector_residual")
"""The per-point attributes of a :func:`reconstruct` cloud: those of the view's PLY
(docs/formats.md, "Outputs"; x, y, z are ``positions``) and the estimated ``normals``."""

NORMAL_RADIUS_MM = FuseSettings().normal_radius_mm
"""Normals of a reconstructed view: PCA over this radius (at most ``NORMAL_MAX_NN``
points), as fusion estimates them: it must span several rings."""
NORMAL_MAX_NN = FuseSettings().normal_max_nn


@dataclass(frozen=True)
class ReconstructedView:
    """One reconstructed view: its cloud and where it was taken from."""

    name: str
    """The view's name in the scan (e.g. ``view_000``)."""
    index: int
    """Its index in the scan's views (the cloud's ``view`` attribute)."""
    cloud: "o3d.t.geometry.PointCloud"  # noqa: F821
    """The points in the world frame (mm), with every attribute of :data:`POINT_ATTRIBUTES`:
    ``positions``, ``normals`` (float32 (N, 3)), ``ring``, ``view`` (int32 (N, 1)), ``rho``,
    ``confidence``, ``u``, ``v``, ``sigma``, ``residual``, ``sector_residual`` (float32 (N, 1))."""
    turntable_deg: float
    """The turntable angle of the view (degrees)."""
    camera_center: np.ndarray
    """(3,) camera 1's centre in the world frame (mm): every normal points to its side."""
    pose: np.ndarray
    """(4, 4) world -> object frame as the turntable puts it (turned back by ``turntable_deg``
    about the rig's axis, before any refinement)."""
    rig: Rig
    """The scan's rig."""
    stats: dict
    """The view's counts and times (report.json's view entry: samples, points, dropped...)."""


# ----------------------------------------------------------------------------- checks


def _as_scan(scan, what: str) -> Scan:
    if isinstance(scan, Scan):
        return scan
    if isinstance(scan, (str, os.PathLike)):
        return _load_scan(scan)
    raise ValueError(f"{what}: expected a scan (ringscan.load_scan) or a scan folder, got {type(scan).__name__}")


def _settings(cls, settings, overrides: dict, what: str):
    """``settings`` (an instance of ``cls`` or None) with ``overrides`` (field -> value; a nested
    block as a dict of its fields or an instance), every value checked (a named ValueError)."""
    if settings is None:
        settings = cls()
    if not isinstance(settings, cls):
        raise ValueError(f"{what}: settings must be a {cls.__name__}, got {type(settings).__name__}")
    d = settings_to_dict(settings)
    for k, v in overrides.items():
        if k not in d:
            raise ValueError(f"{what}: unknown setting {k!r} (settings of {cls.__name__}: {', '.join(d)})")
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            v = settings_to_dict(v)
        d[k] = {**d[k], **v} if isinstance(d[k], dict) and isinstance(v, Mapping) else v
    try:
        s = settings_from_dict(cls, d)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what}: {e}") from None
    check_finite_settings(s, where=what)
    return s


# ----------------------------------------------------------------------------- functions


def load_scan(path: str | os.PathLike) -> Scan:
    """Read a scan folder (scan.json, its rig and frames: docs/formats.md).

    Raises:
        FormatError: naming the file and field that is missing or wrong.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"load_scan: expected a scan folder's path, got {type(path).__name__}")
    return _load_scan(path)


def simulate(folder: str | os.PathLike, *, scene: str | os.PathLike = "sphere", views: int = 8,
             size_mm: float = 80.0, patterns: PatternSpec | Mapping | None = None, rig: Rig | None = None,
             device: str | None = None) -> Scan:
    """Render a turntable scan with the virtual rig (docs/virtual_rig.md) into ``folder``
    (its frames and ground truth are files: the renderer writes them as it goes).

    Args:
        scene: a procedural scene (``sphere``, ``cube``, ``terrain``, ``plane``...) or a mesh file.
        views: turntable views at k * 360 / views degrees.
        size_mm: the object's longest side.
        patterns: the pattern set (a PatternSpec or a scan.json ``patterns`` block); default
            gray-rings with its defaults for the rig's projector (``ringscan demo``'s).
        rig: the rig (default: the built-in virtual rig).
        device: Warp device (None: CUDA when present, else the CPU).

    Returns:
        The scan, loaded.
    """
    from ringscan.pipeline.formats.rig import default_rig

    if not isinstance(folder, (str, os.PathLike)):
        raise ValueError(f"simulate: folder must be a path, got {type(folder).__name__}")
    if isinstance(views, bool) or not isinstance(views, int) or views < 1:
        raise ValueError(f"simulate: views must be a whole number >= 1, got {views!r}")
    if isinstance(size_mm, bool) or not isinstance(size_mm, (int, float)) or not np.isfinite(size_mm) \
            or size_mm <= 0:
        raise ValueError(f"simulate: size_mm must be a finite number > 0, got {size_mm!r}")
    if rig is not None and not isinstance(rig, Rig):
        raise ValueError(f"simulate: rig must be a Rig (ringscan.pipeline.load_rig), got {type(rig).__name__}")
    rig = default_rig() if rig is None else rig
    if patterns is None:
        patterns = default_patterns(DEFAULT_CODEC, width=rig.light.width, height=rig.light.height)
    elif isinstance(patterns, Mapping):
        patterns = parse_patterns(dict(patterns), source="simulate: patterns")
    elif not isinstance(patterns, PatternSpec):
        raise ValueError(f"simulate: patterns must be a PatternSpec or a mapping, got {type(patterns).__name__}")
    return simulate_scan(folder, scene=scene, rig=rig, patterns=patterns, views=views, size_mm=float(size_mm),
                         device=device, progress=False)


def reconstruct(scan: Scan | str | os.PathLike, *, settings: ReconstructSettings | None = None,
                views: Sequence[str] | None = None, device: str | None = None,
                **overrides) -> list[ReconstructedView]:
    """Reconstruct a scan's views in memory (no folder written): one cloud a view, with
    every per-point attribute its PLY would hold, normals estimated and turned toward
    the camera, and the view's name and pose (:class:`ReconstructedView`).

    Args:
        scan: a scan (:func:`load_scan`, :func:`simulate`) or its folder.
        settings: reconstruction settings (``ReconstructSettings``; default its defaults).
        views: the names of the views to reconstruct (default: all, in the scan's order).
        device: Warp device (None: CUDA when present, else the CPU).
        **overrides: settings by field, over ``settings``: ``min_confidence=0.5``,
            ``triangulate={"constraint": "rings"}`` (a nested block as a dict of its fields).

    Raises:
        ValueError: an unknown setting or a value of the wrong type or range (naming it), an
            unknown view name; FormatError: a frame file that is missing or wrong (before any view
            is reconstructed).
    """
    scan = _as_scan(scan, "reconstruct")
    s = _settings(ReconstructSettings, settings, overrides, "reconstruct")
    check_settings_types(s)
    check_setting_ranges(s)
    if views is None:
        chosen = list(scan.views)
    else:
        if isinstance(views, (str, bytes)) or not isinstance(views, Sequence):
            raise ValueError(f"reconstruct: views must be a list of view names, got {views!r}")
        names = {v.name for v in scan.views}
        unknown = [v for v in views if v not in names]
        if unknown:
            raise ValueError(f"reconstruct: unknown view(s) {', '.join(map(repr, unknown))} in {scan.path} "
                             f"(its views: {', '.join(sorted(names))})")
        chosen = [v for v in scan.views if v.name in set(views)]
    for v in chosen:
        check_view_frames(scan, v)
    check_rays(scan, chosen, s)
    out = []
    for view in chosen:
        cloud = reconstruct_view(scan, view, settings=s, device=device)
        index = scan.views.index(view)
        center = scan.rig.camera.center
        out.append(ReconstructedView(
            name=view.name, index=index, cloud=_tensor_cloud(cloud, index, center), turntable_deg=view.turntable_deg,
            camera_center=np.array(center, np.float64),
            pose=turntable_transform(scan.rig.turntable, -view.turntable_deg), rig=scan.rig, stats=cloud.stats))
        log.info("%s: %d points", view.name, cloud.points.shape[0])
    return out


def _tensor_cloud(cloud, index: int, center: np.ndarray):
    """A view's NumPy cloud (:class:`~ringscan.pipeline.reconstruct.view.ViewCloud`) as an Open3D
    tensor cloud: the PLY's properties as (N, 1) attributes, normals toward ``center``."""
    o3d = open3d_lib()
    n = cloud.points.shape[0]
    t = o3d.core.Tensor

    def column(a, dtype):
        return t(np.ascontiguousarray(np.asarray(a, dtype).reshape(n, 1)))

    nan = np.full(n, np.nan, np.float32)
    pcd = o3d.t.geometry.PointCloud(t(np.ascontiguousarray(cloud.points, np.float32)))
    pcd.point["ring"] = column(cloud.ring, np.int32)
    pcd.point["rho"] = column(cloud.rho, np.float32)
    pcd.point["view"] = column(np.full(n, index), np.int32)
    pcd.point["confidence"] = column(cloud.confidence, np.float32)
    pcd.point["u"] = column(cloud.uv[:, 0], np.float32)
    pcd.point["v"] = column(cloud.uv[:, 1], np.float32)
    pcd.point["sigma"] = column(cloud.sigma, np.float32)
    pcd.point["residual"] = column(nan if cloud.residual is None else cloud.residual, np.float32)
    pcd.point["sector_residual"] = column(nan if cloud.sector_residual is None else cloud.sector_residual, np.float32)
    if n >= 3:  # the legacy cloud's estimate: the same normals as the tensor cloud's, in half the time
        legacy = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points.astype(np.float64)))
        legacy.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_MM, max_nn=NORMAL_MAX_NN))
        legacy.orient_normals_towards_camera_location(np.asarray(center, np.float64))
        pcd.point["normals"] = t(np.asarray(legacy.normals, np.float32))
    else:  # too few points for a plane: the direction to the camera
        d = np.asarray(center, np.float64) - cloud.points.astype(np.float64)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        pcd.point["normals"] = t(np.ascontiguousarray(d, np.float32).reshape(n, 3))
    return pcd


def _check_views(views, what: str) -> list[ReconstructedView]:
    if isinstance(views, ReconstructedView):
        views = [views]
    if isinstance(views, (str, bytes, os.PathLike)) or not isinstance(views, Sequence) or not views:
        raise ValueError(f"{what}: expected the views ringscan.reconstruct returned, or a scan")
    bad = [i for i, v in enumerate(views) if not isinstance(v, ReconstructedView)]
    if bad:
        raise ValueError(f"{what}: views[{bad[0]}] is a {type(views[bad[0]]).__name__}, not a ReconstructedView "
                         "(ringscan.reconstruct returns them; a bare cloud has no turntable angle to fuse by)")
    return list(views)


def fuse(views_or_scan, *, settings: FuseSettings | None = None, device: str | None = None,
         return_report: bool = False, **overrides):
    """Fuse a scan's views into one cloud in the object frame (docs/fusion.md): each view
    turned back by its turntable angle, cleaned, refined (where the views' overlap fixes the
    motion: a symmetric object keeps its turntable angles, with a warning), merged on a voxel grid.

    Args:
        views_or_scan: the views :func:`reconstruct` returned, or a scan (reconstructed first,
            in memory, with the default settings).
        settings: fusion settings (``FuseSettings``); ``**overrides`` by field over them
            (``voxel_mm=0.5``, ``refine=False``).
        device: Warp device for the reconstruction of a scan.
        return_report: also return the fusion report (per view: points kept, residuals before
            and after refinement, the correction, ``angle_held``; fuse_report.json's ``fusion``).

    Returns:
        An ``o3d.t.geometry.PointCloud`` (mm, object frame) with ``positions``, ``normals``
        (outward), ``view`` (int32 (N, 1): a view that saw the point), ``confidence`` (the mean
        over the merged points) and ``sigma`` (the fused point's standard deviation, mm: the
        views' errors independent, :func:`~ringscan.pipeline.fusion.turntable.merge_clouds`),
        as fused.ply holds them; with ``return_report``, (cloud, report).
    """
    s = _settings(FuseSettings, settings, overrides, "fuse")
    if isinstance(views_or_scan, (Scan, str, os.PathLike)):
        views = reconstruct(views_or_scan, device=device)
    else:
        views = _check_views(views_or_scan, "fuse")
    rig = views[0].rig
    if any(v.rig is not rig and rig_to_dict(v.rig) != rig_to_dict(rig) for v in views):
        raise ValueError("fuse: the views are of scans with different rigs (one scan's views fuse; several "
                         "poses of an object: ringscan.pipeline.fuse_poses)")
    # the view's own normals are left out: fusion estimates them on the cleaned cloud, as
    # `ringscan fuse` does from the PLYs (the same fused cloud)
    fv = [FusionView(name=v.name, points=v.cloud.point.positions.numpy().astype(np.float64),
                     turntable_deg=v.turntable_deg, camera_center=v.camera_center,
                     confidence=_column(v.cloud, "confidence"), sigma=_column(v.cloud, "sigma")) for v in views]
    res = fuse_views(fv, rig, settings=s)
    o3d = open3d_lib()
    out = o3d.t.geometry.PointCloud.from_legacy(res.cloud, o3d.core.float32)
    n = len(res.cloud.points)
    out.point["view"] = o3d.core.Tensor(np.asarray([v.index for v in views], np.int32)[res.point_view].reshape(n, 1))
    out.point["confidence"] = o3d.core.Tensor(np.asarray(res.point_confidence, np.float32).reshape(n, 1))
    out.point["sigma"] = o3d.core.Tensor(np.asarray(res.point_sigma, np.float32).reshape(n, 1))
    return (out, res.report()) if return_report else out


def _column(cloud, name: str) -> np.ndarray | None:
    return cloud.point[name].numpy().reshape(-1).astype(np.float64) if name in cloud.point else None


def mesh(cloud, *, settings: MeshSettings | None = None, **overrides):
    """Mesh a cloud with oriented normals (:func:`fuse`'s, or any Open3D cloud: clouds
    without normals get them estimated and turned outward) by screened Poisson or TSDF
    (docs/fusion.md, "Meshing").

    Args:
        cloud: an ``o3d.t.geometry.PointCloud`` (or a legacy ``o3d.geometry.PointCloud``).
        settings: ``MeshSettings``; ``**overrides`` by field over them (``method="tsdf"``,
            ``watertight=True``, ``poisson_depth=8``).

    Returns:
        An ``o3d.t.geometry.TriangleMesh`` (mm, the cloud's frame) with vertex normals.

    Raises:
        ValueError: not a cloud, or too few usable points to mesh.
    """
    o3d = open3d_lib()
    s = _settings(MeshSettings, settings, overrides, "mesh")
    if isinstance(cloud, o3d.t.geometry.PointCloud):
        legacy = cloud.to_legacy()
    elif isinstance(cloud, o3d.geometry.PointCloud):
        legacy = o3d.geometry.PointCloud(cloud)
    else:
        raise ValueError(f"mesh: expected an Open3D point cloud (ringscan.fuse returns one), got "
                         f"{type(cloud).__name__}")
    if not legacy.has_normals():
        legacy, _ = drop_unusable_points(legacy)
        if len(legacy.points) >= 3:
            orient_normals(legacy)
    res = mesh_cloud(legacy, settings=s)
    if s.watertight and not res.watertight:
        log.warning("mesh: the mesh is not watertight (%s)", res.info)
    return o3d.t.geometry.TriangleMesh.from_legacy(res.mesh)


def evaluate(cloud, truth, *, within_mm: float = 0.5) -> dict:
    """Measure a reconstruction against the truth.

    - Views (:func:`reconstruct`'s list, or one view) against a simulated scan: the figures of
      ``ringscan evaluate`` (:func:`~ringscan.pipeline.evaluate.metrics.evaluate_recon`): per view
      and for ``all``, the distances of the points to the truth surface at the view's turntable
      angle (median, mean, RMS, p95, max, share over 1 mm), the coverage of the lit surface, and
      the points' sigma against their errors.
    - A fused cloud (:func:`fuse`) against a truth mesh (an Open3D mesh, a mesh file, or a
      simulated scan's object), both in the object frame: the distances of its points to the
      truth surface (:func:`~ringscan.pipeline.evaluate.metrics.distance_stats`).
    - A mesh (:func:`mesh`) against a truth mesh: both ways (``ringscan fuse --truth``'s figures:
      means, 95th percentiles, chamfer, ``truth_within`` the share of the truth within ``within_mm``).

    Raises:
        ValueError: a cloud of another kind, or views with a truth that is not a simulated scan.
    """
    o3d = open3d_lib()
    if isinstance(cloud, ReconstructedView) or (isinstance(cloud, Sequence) and not isinstance(cloud, (str, bytes))):
        views = _check_views(cloud, "evaluate")
        if not isinstance(truth, (Scan, str, os.PathLike)):
            raise ValueError("evaluate: views are measured against a simulated scan (its folder, or "
                             f"ringscan.load_scan's), got {type(truth).__name__}")
        scan = _as_scan(truth, "evaluate")
        return evaluate_points(scan, ((v.name, v.cloud.point.positions.numpy().astype(np.float64),
                                       _column(v.cloud, "sigma")) for v in views))
    if isinstance(truth, o3d.t.geometry.TriangleMesh):
        truth = truth.to_legacy()
    if isinstance(truth, Scan):
        truth = truth.folder
    if not isinstance(truth, (o3d.geometry.TriangleMesh, str, os.PathLike)):
        raise ValueError(f"evaluate: truth must be a mesh, a mesh file or a simulated scan, got {type(truth).__name__}")
    truth_mesh = load_truth_mesh(truth if isinstance(truth, o3d.geometry.TriangleMesh) else Path(truth))
    if isinstance(cloud, (o3d.t.geometry.TriangleMesh, o3d.geometry.TriangleMesh)):
        legacy = cloud.to_legacy() if isinstance(cloud, o3d.t.geometry.TriangleMesh) else cloud
        return compare_to_truth(legacy, truth_mesh, within_mm=within_mm)
    if isinstance(cloud, o3d.t.geometry.PointCloud):
        pts = cloud.point.positions.numpy().astype(np.float64)
    elif isinstance(cloud, o3d.geometry.PointCloud):
        pts = np.asarray(cloud.points, np.float64)
    else:
        raise ValueError(f"evaluate: expected views (ringscan.reconstruct), a fused cloud or a mesh, got "
                         f"{type(cloud).__name__}")
    finite = np.all(np.isfinite(pts), axis=1)
    d = np.full(len(pts), np.nan)
    d[finite] = point_distances(truth_mesh, pts[finite])
    return {**distance_stats(d), "non_finite_points": int(np.count_nonzero(~finite))}
