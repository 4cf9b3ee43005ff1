"""Multi-view fusion: turntable views -> one cleaned point cloud in the object frame.

:func:`fuse_views` turns every view back by its turntable angle about the rig's axis,
cleans it (non-finite and low-confidence points, ground clip, outliers), orients its
normals toward the view's camera, refines the poses (point-to-plane ICP between
neighbouring views, loop closure, pose graph with the view nearest angle 0 fixed),
reports each view's residual and correction, and merges and downsamples the views. The
turntable pose is a prior that the refinement corrects only along the motions the views'
overlap fixes (:func:`overlap_information`, :func:`weak_motions`): a symmetric object (a
sphere, a cylinder) keeps its turntable angle, and a warning names its views.
Several poses of one object are aligned in :mod:`.poses`. Why: docs/design.md §17; the
steps, settings and figures: docs/fusion.md. Everything returned is an Open3D geometry
or a NumPy array, so a user's script can carry on with Open3D directly.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ringscan.pipeline.formats.meshes import open3d_lib
from ringscan.pipeline.formats.rig import Rig, Turntable, turntable_transform
from ringscan.pipeline.formats.settings import check_finite_settings
from ringscan.pipeline.fusion.overlap import (
    WEAK_MOTION_RATIO,
    _matches,
    _skew,
    _spectrum,
    overlap_information,
    weak_motions,
)
from ringscan.pipeline.fusion.threads import check_threads, open3d_threads

log = logging.getLogger(__name__)

__all__ = ["REPORT_NAME", "WEAK_MOTION_RATIO", "FuseSettings", "FusionView", "ViewResidual", "FuseResult",
           "check_fuse_settings", "fuse_views", "merge_clouds", "rotation_deg", "apply_transform",
           "overlap_information", "weak_motions"]

REPORT_NAME = "report.json"

LINE_RATIO = 0.05
"""A point's normal neighbourhood is a line, not a surface, where its second covariance
eigenvalue is below this fraction of its largest (the points spread across the line by
under ~22 % of their spread along it)."""


# ----------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class FuseSettings:
    """How views are cleaned, registered and merged (lengths in mm)."""

    min_confidence: float = 0.0
    """Points whose ``confidence`` is below this are dropped before anything else."""
    ground_clip_mm: float | None = 0.5
    """Drop points whose world z is below this: the reference plane z = 0 (docs/design.md §2),
    on which the object stands, would otherwise fuse into the object as a disc;
    None keeps every point."""
    statistical_neighbors: int = 20
    """Statistical outlier removal: neighbours averaged per point (0 turns it off)."""
    statistical_std_ratio: float = 4.0
    """Statistical outlier removal: drop points whose mean neighbour distance is
    more than this many standard deviations above the view's average."""
    radius_mm: float = 1.5
    """Radius outlier removal: search radius (0 turns it off)."""
    radius_min_points: int = 3
    """Radius outlier removal: a point needs this many neighbours within radius_mm."""
    normal_radius_mm: float = 2.5
    """Normal estimation: PCA neighbourhood radius; it must span several rings."""
    normal_max_nn: int = 40
    """Normal estimation: at most this many neighbours."""
    refine: bool = True
    """Refine the turntable poses with ICP and pose-graph optimisation."""
    icp_voxel_mm: float = 0.6
    """Views are downsampled to this voxel size for registration."""
    icp_coarse_mm: float = 3.0
    """Coarse ICP: largest point-pair distance (covers a few mm of axis error)."""
    icp_fine_mm: float = 1.0
    """Fine ICP, information matrices, pose graph and residuals: largest pair distance."""
    icp_iterations: int = 60
    """ICP iterations per stage."""
    neighbor_span: int = 2
    """Register each view with its next ``neighbor_span`` views in turntable order
    (1: a chain; 2 also links every other view, which stiffens the graph)."""
    loop_closure: bool = True
    """Close the loop: register the last views with the first ones (>= 3 views)."""
    edge_prune_threshold: float = 0.25
    """Pose graph: uncertain edges whose line-process weight falls below this are pruned."""
    min_edge_fitness: float = 0.2
    """Pairs whose fine ICP overlaps less than this fraction are left out of the graph."""
    voxel_mm: float = 0.3
    """Voxel size of the fused cloud (points and normals averaged per voxel; 0 keeps all)."""
    threads: int = 1
    """CPU threads Open3D may use (ICP, normals, outlier removal): 1 gives the same bytes
    from run to run; 0 (every core) is faster, with the last bits of the ICP poses
    varying (:mod:`ringscan.pipeline.fusion.threads`)."""


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True)
class FusionView:
    """One view's points in the world frame (docs/design.md §2)."""

    name: str
    """View name (e.g. ``view_000``)."""
    points: np.ndarray
    """(N, 3) float64 points in the world frame, mm."""
    turntable_deg: float
    """The turntable angle of the view (degrees, right-handed about the axis)."""
    camera_center: np.ndarray
    """(3,) camera centre in the world frame (mm); normals are oriented toward it."""
    normals: np.ndarray | None = None
    """(N, 3) normals in the world frame, or None to estimate them."""
    confidence: np.ndarray | None = None
    """(N,) per-point confidence, or None."""
    sigma: np.ndarray | None = None
    """(N,) per-point standard deviation (mm, a reconstruction's ``sigma``), or None."""


@dataclass(frozen=True)
class ViewResidual:
    """How well one view agrees with all the others (object frame)."""

    name: str
    turntable_deg: float
    points_in: int
    """Points given."""
    points_kept: int
    """Points left after confidence, ground clip and outlier removal."""
    fitness_before: float
    """Fraction of the view's points within icp_fine_mm of another view's points, before refinement."""
    rmse_before_mm: float
    """RMS point-to-plane distance of those points to the other views, before refinement."""
    fitness: float
    """The same fraction after refinement."""
    rmse_mm: float
    """The same RMS distance after refinement."""
    correction_mm: float
    """Translation of the refinement at the view's centroid (mm)."""
    correction_deg: float
    """Rotation angle of the refinement (degrees)."""
    angle_held: bool | None = None
    """True when the view's overlap with the other views does not fix its turn about the
    turntable axis (a shape symmetric about the axis: a sphere, a cylinder), so refinement
    kept the turntable's angle (:data:`WEAK_MOTION_RATIO`); None without refinement."""
    motions_held: int | None = None
    """How many of the view's 6 rigid motions (3 rotations, 3 translations) its overlap with
    the other views does not fix, kept at the turntable pose (0: all fixed; 6: no overlap);
    None without refinement."""

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class FuseResult:
    """The fused scan. Geometries are Open3D ``PointCloud``s in the object frame."""

    cloud: "o3d.geometry.PointCloud"  # noqa: F821
    """The fused, voxel-downsampled cloud with oriented normals."""
    views: list
    """Each view's cleaned cloud (full resolution, normals oriented) in the object frame."""
    names: list[str]
    """View names, in the order of ``views``."""
    turntable_deg: np.ndarray
    """(V,) turntable angles."""
    transforms: np.ndarray
    """(V, 4, 4) world -> object transforms, refinement included."""
    corrections: np.ndarray
    """(V, 4, 4) refinement alone (object frame; identity without refinement)."""
    camera_centers: np.ndarray
    """(V, 3) camera centres in the object frame."""
    residuals: list[ViewResidual]
    """Per-view residuals and corrections."""
    rig: Rig | None
    """The rig the views were taken with."""
    settings: FuseSettings
    """The settings used."""
    point_view: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    """(M,) for each fused point, the index of a view that contributed to it."""
    point_confidence: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    """(M,) mean confidence of the points merged into each fused point."""
    pose_graph: object = None
    """The optimised ``o3d.pipelines.registration.PoseGraph`` (None without refinement)."""
    point_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    """(M,) standard deviation (mm) of each fused point (:func:`merge_clouds`); NaN where a
    merged point had none."""

    def report(self) -> dict:
        """A JSON-ready summary: per-view residuals and the resolved settings."""
        return {
            "points": len(self.cloud.points),
            "views": [r.to_dict() for r in self.residuals],
            "angle_held": [r.name for r in self.residuals if r.angle_held],
            "settings": dataclasses.asdict(self.settings),
            "axis": None if self.rig is None or self.rig.turntable is None else {
                "axis_point": self.rig.turntable.axis_point.tolist(),
                "axis_dir": self.rig.turntable.axis_dir.tolist()},
        }


# ----------------------------------------------------------------------------- geometry helpers


def rotation_deg(T: np.ndarray) -> float:
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def apply_transform(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def _as_view(v, i: int) -> FusionView:
    if isinstance(v, FusionView):
        vc = v
    elif isinstance(v, Mapping):
        unknown = set(v) - {f.name for f in dataclasses.fields(FusionView)}
        if unknown:
            raise ValueError(f"views[{i}]: unknown keys {sorted(unknown)}")
        try:
            vc = FusionView(**{"name": f"view_{i:03d}", **v})
        except TypeError as e:
            raise ValueError(f"views[{i}]: {e}") from None
    else:
        raise ValueError(f"views[{i}]: expected a FusionView or a mapping, got {type(v).__name__}")
    pts = np.asarray(vc.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"views[{i}] ({vc.name}): points must have shape (N, 3), got {pts.shape}")
    n = len(pts)
    nrm = None
    if vc.normals is not None:
        nrm = np.asarray(vc.normals, dtype=np.float64)
        if nrm.shape != (n, 3):
            raise ValueError(f"views[{i}] ({vc.name}): normals must have shape ({n}, 3), got {nrm.shape}")
    conf = None
    if vc.confidence is not None:
        conf = np.asarray(vc.confidence, dtype=np.float64)
        if conf.shape != (n,):
            raise ValueError(f"views[{i}] ({vc.name}): confidence must have shape ({n},), got {conf.shape}")
    sigma = None
    if vc.sigma is not None:
        sigma = np.asarray(vc.sigma, dtype=np.float64)
        if sigma.shape != (n,):
            raise ValueError(f"views[{i}] ({vc.name}): sigma must have shape ({n},), got {sigma.shape}")
    cc = np.asarray(vc.camera_center, dtype=np.float64)
    if cc.shape != (3,) or not np.all(np.isfinite(cc)):
        raise ValueError(f"views[{i}] ({vc.name}): camera_center must be 3 finite numbers, got {vc.camera_center!r}")
    th = float(vc.turntable_deg)
    if not math.isfinite(th):
        raise ValueError(f"views[{i}] ({vc.name}): turntable_deg is not finite")
    return FusionView(name=str(vc.name), points=pts, turntable_deg=th, camera_center=cc, normals=nrm, confidence=conf,
                      sigma=sigma)


def check_fuse_settings(s: FuseSettings) -> None:
    if not isinstance(s, FuseSettings):
        raise ValueError(f"settings must be a FuseSettings, got {type(s).__name__}")
    check_finite_settings(s)
    check_threads("FuseSettings", s.threads)
    for name in ("icp_voxel_mm", "icp_coarse_mm", "icp_fine_mm", "normal_radius_mm"):
        if not getattr(s, name) > 0:
            raise ValueError(f"FuseSettings.{name} must be > 0, got {getattr(s, name)}")
    for name in ("voxel_mm", "radius_mm", "min_confidence"):
        if getattr(s, name) < 0:
            raise ValueError(f"FuseSettings.{name} must be >= 0, got {getattr(s, name)}")
    if s.neighbor_span < 1:
        raise ValueError(f"FuseSettings.neighbor_span must be >= 1, got {s.neighbor_span}")
    if s.icp_iterations < 1:
        raise ValueError(f"FuseSettings.icp_iterations must be >= 1, got {s.icp_iterations}")


# ----------------------------------------------------------------------------- cleaning


def _clean_view(o3d, v: FusionView, T: np.ndarray, cam: np.ndarray, s: FuseSettings):
    """(the view's cloud in the object frame, cleaned, with normals toward ``cam``; its points'
    confidence; their sigma, NaN where the view has none)."""
    keep = np.all(np.isfinite(v.points), axis=1)
    if v.confidence is not None:
        keep &= v.confidence >= s.min_confidence
    if s.ground_clip_mm is not None:
        keep &= v.points[:, 2] >= s.ground_clip_mm
    if v.normals is not None:
        keep &= np.all(np.isfinite(v.normals), axis=1)
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(apply_transform(T, v.points[keep]))
    if v.normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(v.normals[keep] @ T[:3, :3].T)
    conf = (v.confidence[keep] if v.confidence is not None else np.ones(int(keep.sum()))).astype(np.float64)
    sigma = (v.sigma[keep] if v.sigma is not None else np.full(int(keep.sum()), np.nan)).astype(np.float64)
    idx = np.arange(len(pcd.points))
    if len(idx) and s.statistical_neighbors > 0 and len(idx) > s.statistical_neighbors:
        pcd, kept = pcd.remove_statistical_outlier(nb_neighbors=s.statistical_neighbors,
                                                   std_ratio=s.statistical_std_ratio)
        idx = idx[np.asarray(kept, dtype=np.int64)]
    if len(idx) and s.radius_mm > 0 and s.radius_min_points > 0:
        pcd, kept = pcd.remove_radius_outlier(nb_points=s.radius_min_points, radius=s.radius_mm)
        idx = idx[np.asarray(kept, dtype=np.int64)]
    conf, sigma = conf[idx], sigma[idx]
    if len(pcd.points) >= 3:
        if not pcd.has_normals():
            _estimate_surface_normals(o3d, pcd, s)
        pcd.normalize_normals()
        pcd.orient_normals_towards_camera_location(cam)
    return pcd, conf, sigma


def _estimate_surface_normals(o3d, pcd, s: FuseSettings) -> None:
    """Normals of ``pcd`` by PCA over ``normal_radius_mm`` (at most ``normal_max_nn``
    points); where that neighbourhood is a line, not a surface (it holds the points of one
    ring only: the paper's few rings, a coarse pattern, a far view), over the
    ``normal_max_nn`` nearest points instead, which reach the neighbouring rings. A line's
    PCA normal is any direction across it: on a symmetric object such normals hide the
    symmetry from the overlap check (:func:`overlap_information`), and refinement turned a
    6-view sphere of ring curves by ~60 degrees."""
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=s.normal_radius_mm, max_nn=s.normal_max_nn)
    pcd.estimate_normals(param)
    pcd.estimate_covariances(param)
    lam = np.linalg.eigvalsh(np.asarray(pcd.covariances))  # ascending, per point
    line = lam[:, 1] < LINE_RATIO * lam[:, 2]
    if not line.any():
        return
    from scipy.spatial import cKDTree

    P = np.asarray(pcd.points)
    k = min(s.normal_max_nn, len(P))
    _, idx = cKDTree(P).query(P[line], k=k)
    Q = P[idx.reshape(-1, k)] - P[line][:, None, :]  # neighbours about the point itself
    _, vec = np.linalg.eigh(np.einsum("mki,mkj->mij", Q, Q))
    # the plane's frame (e1, e2 in it, e3 its normal), then a quadric height
    # h = a x^2 + b xy + c y^2 + d x + e y through the neighbours: the surface's normal at
    # the point is (-d, -e, 1) in that frame (a plane's over a neighbourhood that spans
    # several rings of a curved surface leans toward the side that holds more of them)
    e1, e2, e3 = vec[:, :, 2], vec[:, :, 1], vec[:, :, 0]
    x, y, h = (np.einsum("mki,mi->mk", Q, e) for e in (e1, e2, e3))
    A = np.stack([x * x, x * y, y * y, x, y], axis=2)
    AtA = np.einsum("mki,mkj->mij", A, A) + 1e-9 * np.eye(5)
    coef = np.linalg.solve(AtA, np.einsum("mki,mk->mi", A, h)[..., None])[..., 0]
    n = -coef[:, 3:4] * e1 - coef[:, 4:5] * e2 + e3
    N = np.asarray(pcd.normals).copy()
    N[line] = n / np.linalg.norm(n, axis=1, keepdims=True)
    pcd.normals = o3d.utility.Vector3dVector(N)


# ----------------------------------------------------------------------------- registration


def _rms_motion(T: np.ndarray, points: np.ndarray) -> float:
    """RMS distance (mm) the 4x4 ``T`` moves ``points`` (N, 3) by (0 for none)."""
    if not len(points):
        return 0.0
    return float(np.sqrt(np.mean(np.sum((apply_transform(T, points) - points) ** 2, axis=1))))


def _icp_pair(o3d, src, dst, s: FuseSettings):
    reg = o3d.pipelines.registration
    est = reg.TransformationEstimationPointToPlane()
    crit = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=s.icp_iterations)
    coarse = reg.registration_icp(src, dst, s.icp_coarse_mm, np.eye(4), est, crit)
    fine = reg.registration_icp(src, dst, s.icp_fine_mm, coarse.transformation, est, crit)
    info = reg.get_information_matrix_from_point_clouds(src, dst, s.icp_fine_mm, fine.transformation)
    return fine, info


def _pairs(order: np.ndarray, s: FuseSettings) -> list[tuple[int, int, bool]]:
    """(source, target, uncertain) index pairs along the turntable order."""
    n = len(order)
    out, seen = [], set()
    for a in range(n):
        for step in range(1, s.neighbor_span + 1):
            b = a + step
            if b >= n:
                if not (s.loop_closure and n >= 3):
                    continue
                b -= n
            i, j = int(order[a]), int(order[b])
            key = (min(i, j), max(i, j))
            if i == j or key in seen:
                continue
            seen.add(key)
            # Chain edges (next view, no wrap) are trusted; the rest may be pruned.
            out.append((i, j, not (step == 1 and a + step < n)))
    return out


def _held_icp(o3d, src, dst, s: FuseSettings, H: np.ndarray, matched: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Point-to-plane ICP of ``src`` onto ``dst`` from the turntable pose that moves only along
    the motions their overlap fixes: the eigenvectors of the overlap's information ``H`` (at
    its ``matched`` points, :func:`overlap_information`) above :data:`WEAK_MOTION_RATIO`,
    found once, so that no step can slide along a free motion (a coarse pass's stray matches
    at the overlap's edge make one look fixed). Coarse then fine, like :func:`_icp_pair`.
    Returns (4x4 source -> target, fitness, inlier RMS point-to-plane mm)."""
    w, V, c, scale = _spectrum(H, matched)
    B = V[:, w >= WEAK_MOTION_RATIO * w[-1]]
    P = np.asarray(src.points, np.float64)
    Q = np.asarray(dst.points, np.float64)
    N = np.asarray(dst.normals, np.float64)
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(Q))
    nns.knn_index()
    T = np.eye(4)
    for dist in (s.icp_coarse_mm, s.icp_fine_mm):
        for _ in range(s.icp_iterations):
            X = apply_transform(T, P)
            ok, idx = _matches(o3d, nns, X, dist)
            if len(ok) < 6:
                break
            p, n = X[ok], N[idx]
            J = np.concatenate([np.cross((p - c) / scale, n), n], axis=1) @ B
            r = np.einsum("ij,ij->i", p - Q[idx], n)
            xi = B @ np.linalg.lstsq(J, -r, rcond=None)[0]
            step = np.eye(4)
            step[:3, :3] = _rotation(xi[:3] / scale)
            step[:3, 3] = c + xi[3:] - step[:3, :3] @ c  # turned about c, then c moved by xi[3:]
            T = step @ T
            # a micrometre: far below any scan's noise (and matches may flip back and forth)
            if np.linalg.norm(xi) < 1e-3:
                break
    X = apply_transform(T, P)
    ok, idx = _matches(o3d, nns, X, s.icp_fine_mm)
    if len(ok) == 0:
        return T, 0.0, 0.0
    r = np.einsum("ij,ij->i", X[ok] - Q[idx], N[idx])
    return T, len(ok) / max(len(P), 1), float(np.sqrt(np.mean(r * r)))


def _rotation(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``omega`` (Rodrigues)."""
    th = float(np.linalg.norm(omega))
    if th < 1e-12:
        return np.eye(3) + _skew(omega)
    K = _skew(omega / th)
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * K @ K


def plane_residuals(o3d, p: np.ndarray, q: np.ndarray, q_normals: np.ndarray,
                    dist: float) -> tuple[float, float] | None:
    """Points ``p`` (N, 3) against the cloud ``q`` (M, 3) with unit normals ``q_normals`` (M, 3):
    (the fraction of ``p`` whose nearest point of ``q`` lies within ``dist``, the RMS point-to-plane
    distance of those pairs); None when there is no such pair."""
    if len(p) == 0 or len(q) == 0:
        return None
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(q))
    nns.knn_index()
    idx, d2 = nns.knn_search(o3d.core.Tensor(p), 1)
    idx = idx.numpy()[:, 0]
    inl = np.sqrt(d2.numpy()[:, 0]) < dist
    if not inl.any():
        return None
    r = np.einsum("ij,ij->i", p[inl] - q[idx[inl]], q_normals[idx[inl]])
    return float(inl.mean()), float(np.sqrt(np.mean(r * r)))


def _residuals(o3d, downs: list, transforms: list[np.ndarray], dist: float) -> list[tuple[float, float]]:
    """Per view: (fraction of points within ``dist`` of another view, point-to-plane RMS of those)."""
    moved = [o3d.geometry.PointCloud(d).transform(T) for d, T in zip(downs, transforms)]
    out = []
    for i, d in enumerate(moved):
        # a view too small for normals (< 3 points after cleaning) cannot be a plane to measure against
        others = [e for j, e in enumerate(moved) if j != i and len(e.points) and len(e.normals) == len(e.points)]
        if len(d.points) == 0 or not others:
            out.append((0.0, 0.0))
            continue
        q_pts = np.concatenate([np.asarray(e.points) for e in others])
        q_nrm = np.concatenate([np.asarray(e.normals) for e in others])
        res = plane_residuals(o3d, np.asarray(d.points), q_pts, q_nrm, dist)
        out.append((0.0, 0.0) if res is None else res)
    return out


def _refine(o3d, downs: list, angles: np.ndarray, s: FuseSettings, progress: bool, axis):
    """Pose-graph refinement; returns per-view corrections (object frame), the graph, and per
    view (motions its overlaps leave free, whether its turn about ``axis`` is free) or None
    when no pair was registered.

    A pair whose overlap leaves a motion free (:func:`weak_motions`: a sphere's rotations,
    a cylinder's spin) is registered by :func:`_held_icp` instead, which keeps the turntable
    pose along the free motions: ICP would otherwise slide the views along them as far as
    the points' noise takes it (tens of degrees on a sphere)."""
    from ringscan.pipeline.formats.progress import progress_bar

    reg = o3d.pipelines.registration
    n = len(downs)
    order = np.argsort(np.mod(angles, 360.0), kind="stable")
    ref = int(np.argmin(np.abs((angles + 180.0) % 360.0 - 180.0)))
    graph = reg.PoseGraph()
    for _ in range(n):
        graph.nodes.append(reg.PoseGraphNode(np.eye(4)))
    pairs = _pairs(order, s)
    used, slid = [], []
    for i, j, uncertain in progress_bar(pairs, desc="registering views", unit="pair", disable=not progress):
        if len(downs[i].points) < 10 or len(downs[j].points) < 10:
            continue
        fine, info = _icp_pair(o3d, downs[i], downs[j], s)
        T, fitness, rmse = fine.transformation, fine.fitness, fine.inlier_rmse
        dst_pts, dst_nrm = np.asarray(downs[j].points), np.asarray(downs[j].normals)
        src_pts = np.asarray(downs[i].points)
        H, matched = overlap_information(apply_transform(T, src_pts), dst_pts, dst_nrm,
                                         max_distance_mm=s.icp_fine_mm)
        free = weak_motions(H, matched)[0] if len(matched) >= 6 else 0
        if free:
            T, fitness, rmse = _held_icp(o3d, downs[i], downs[j], s, H, matched)
            info = reg.get_information_matrix_from_point_clouds(downs[i], downs[j], s.icp_fine_mm, T)
            H, matched = overlap_information(apply_transform(T, src_pts), dst_pts, dst_nrm,
                                             max_distance_mm=s.icp_fine_mm)
            log.debug("views %d -> %d: their overlap leaves %d motion(s) free, kept at the turntable pose", i, j,
                      free)
        moved = _rms_motion(T, src_pts)
        if moved > s.icp_coarse_mm:
            # ICP starts at the turntable pose and matches within icp_coarse_mm: a pair it
            # carries further than that slid along a near-symmetry (sparse ring curves on
            # a rounded shape snap onto the neighbour view's curves), not back to a truth it
            # could see; the pair keeps the turntable's relative pose
            slid.append((i, j, moved))
            T = np.eye(4)
            ev = reg.evaluate_registration(downs[i], downs[j], s.icp_fine_mm, T)
            fitness, rmse = ev.fitness, ev.inlier_rmse
            info = reg.get_information_matrix_from_point_clouds(downs[i], downs[j], s.icp_fine_mm, T)
            H, matched = overlap_information(src_pts, dst_pts, dst_nrm, max_distance_mm=s.icp_fine_mm)
        if fitness < s.min_edge_fitness:
            log.info("views %d -> %d overlap too little (fitness %.2f): edge left out", i, j, fitness)
            continue
        log.debug("edge %d -> %d: fitness %.3f, rmse %.3f mm", i, j, fitness, rmse)
        graph.edges.append(reg.PoseGraphEdge(i, j, T, info, uncertain=uncertain))
        used.append((i, j, H, matched))
    if slid:
        log.warning("ICP carried %d of %d view pairs further than its %.3g mm matching window (up to %.1f mm): "
                    "kept at the turntable's relative pose (a shape near-symmetric about the turntable axis, "
                    "or views too sparse to fix each other: docs/fusion.md, \"Symmetric objects\")",
                    len(slid), len(pairs), s.icp_coarse_mm, max(m for _, _, m in slid))
    if not used:
        log.warning("no pair of views overlaps enough to register: keeping the turntable poses")
        return [np.eye(4) for _ in range(n)], graph, None
    opt = reg.GlobalOptimizationOption(max_correspondence_distance=s.icp_fine_mm,
                                       edge_prune_threshold=s.edge_prune_threshold,
                                       preference_loop_closure=1.0, reference_node=ref)
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                            reg.GlobalOptimizationConvergenceCriteria(), opt)
    # Hold the reference view exactly where the turntable put it.
    P_ref_inv = np.linalg.inv(np.asarray(graph.nodes[ref].pose))
    poses = [P_ref_inv @ np.asarray(graph.nodes[i].pose) for i in range(n)]
    # What each view's overlaps fix together (its edges' information summed).
    held = []
    for k in range(n):
        mine = [(h, q) for i, j, h, q in used if k in (i, j)]
        H = sum((h for h, _ in mine), np.zeros((6, 6)))
        held.append(weak_motions(H, np.concatenate([q for _, q in mine] or [np.zeros((0, 3))]), axis=axis))
    return poses, graph, held


# ----------------------------------------------------------------------------- public API



def merge_clouds(clouds: Sequence, confidences: Sequence[np.ndarray], *, voxel_mm: float,
                 sigmas: Sequence[np.ndarray] | None = None):
    """Merge clouds (already in one frame) into one, thinned on a voxel grid.

    Args:
        clouds: Open3D point clouds.
        confidences: one (n_i,) confidence array per cloud.
        voxel_mm: voxel size; 0 keeps every point.
        sigmas: one (n_i,) standard deviation array (mm) per cloud (NaN: unknown), or None.

    Returns:
        (cloud, source, confidence, sigma): the merged cloud, each point's source cloud
        index (the first point in its voxel), its mean confidence over the voxel, and the
        standard deviation of the voxel's mean position: the points of one source in a voxel
        are taken to share one error (neighbouring pixels of one view: the same calibration,
        the same ring), of their RMS sigma, and the sources' errors to be independent, so
        sigma = sqrt(sum over sources of (n_s * sigma_s)^2) / n for n points, n_s of source s
        (one source: its RMS sigma; k sources of equal sigma and count: sigma / sqrt(k)).
        NaN where a merged point has no sigma.
    """
    o3d = open3d_lib()
    merged = o3d.geometry.PointCloud()
    for c in clouds:
        merged += c
    labels = np.concatenate([np.full(len(c.points), i, np.int32) for i, c in enumerate(clouds)] or
                            [np.zeros(0, np.int32)])
    conf_all = np.concatenate([np.asarray(c, np.float64) for c in confidences] or [np.zeros(0)])
    if sigmas is None:
        sig_all = np.full(len(labels), np.nan)
    else:
        sig_all = np.concatenate([np.asarray(x, np.float64) for x in sigmas] or [np.zeros(0)])
    if len(sig_all) != len(labels):
        raise ValueError(f"merge_clouds: {len(sig_all)} sigmas for {len(labels)} points")
    if voxel_mm > 0 and len(merged.points):
        lo = merged.get_min_bound() - voxel_mm
        hi = merged.get_max_bound() + voxel_mm
        out, _, traces = merged.voxel_down_sample_and_trace(voxel_mm, lo, hi, False)
        source = np.array([labels[t[0]] for t in traces], np.int32)
        conf = np.array([conf_all[np.asarray(t)].mean() for t in traces], np.float32)
        out.normalize_normals()
        return out, source, conf, _voxel_sigma(traces, labels, sig_all, len(clouds))
    return merged, labels, conf_all.astype(np.float32), sig_all.astype(np.float32)


def _voxel_sigma(traces, labels: np.ndarray, sigma: np.ndarray, n_sources: int) -> np.ndarray:
    """:func:`merge_clouds`'s sigma of each voxel's mean (float32)."""
    lens = np.array([len(t) for t in traces], np.int64)
    flat = np.concatenate([np.asarray(t, np.int64) for t in traces])
    vox = np.repeat(np.arange(len(traces)), lens)
    groups, inv = np.unique(vox * max(n_sources, 1) + labels[flat], return_inverse=True)
    n_g = np.bincount(inv)
    s2_g = np.bincount(inv, weights=sigma[flat] ** 2)  # NaN stays NaN
    var = np.bincount(groups // max(n_sources, 1), weights=n_g * s2_g, minlength=len(traces)) / lens.astype(
        np.float64) ** 2
    return np.sqrt(var).astype(np.float32)


def fuse_views(views: Sequence, rig: Rig | None, *, settings: FuseSettings = FuseSettings(),
               progress: bool = False) -> FuseResult:
    """Fuse turntable views into one cloud in the object frame (see :func:`_fuse_views`);
    Open3D runs on ``settings.threads`` threads meanwhile."""
    with open3d_threads(getattr(settings, "threads", 1)):
        return _fuse_views(views, rig, settings=settings, progress=progress)


def _turntable_of(rig: Rig | None, angles: np.ndarray) -> Turntable:
    """The rig's turntable; without one, the world z axis, for views that are all at angle 0.

    Raises:
        ValueError: turned views and no turntable axis.
    """
    turntable = rig.turntable if rig is not None else None
    if turntable is None:
        if np.any(np.abs((angles + 180.0) % 360.0 - 180.0) > 1e-9):
            raise ValueError("views are turned (turntable_deg != 0) but the rig has no turntable axis")
        turntable = Turntable(axis_point=np.zeros(3), axis_dir=np.array([0.0, 0.0, 1.0]))
    return turntable


def _clean_views(o3d, vs: list, T0: list, s: FuseSettings) -> tuple[list, list, list, list]:
    """Each view cleaned in the object frame (:func:`_clean_view`): (clouds, confidences,
    sigmas, camera centres), one each a view.

    Raises:
        ValueError: no view keeps a point.
    """
    clouds, confs, sigmas, cams = [], [], [], []
    for v, T in zip(vs, T0):
        cam = apply_transform(T, v.camera_center[None])[0]
        pcd, conf, sigma = _clean_view(o3d, v, T, cam, s)
        clouds.append(pcd)
        confs.append(conf)
        sigmas.append(sigma)
        cams.append(cam)
        log.info("%s: %d of %d points kept", v.name, len(pcd.points), len(v.points))
    if sum(len(c.points) for c in clouds) == 0:
        raise ValueError("no points left in any view after cleaning (check min_confidence and ground_clip_mm)")
    return clouds, confs, sigmas, cams


def _view_residual(v: FusionView, cloud, P: np.ndarray, before: tuple, after: tuple, held) -> ViewResidual:
    """A view's :class:`ViewResidual`: its points, its fit to the others before and after
    refinement, its correction ``P`` (at its cleaned ``cloud``'s centroid) and what its
    overlaps left free (``held``: (motions, angle) or None)."""
    c = np.asarray(cloud.points).mean(axis=0) if len(cloud.points) else np.zeros(3)
    return ViewResidual(
        name=v.name, turntable_deg=v.turntable_deg, points_in=len(v.points), points_kept=len(cloud.points),
        fitness_before=before[0], rmse_before_mm=before[1], fitness=after[0], rmse_mm=after[1],
        correction_mm=float(np.linalg.norm(apply_transform(P, c[None])[0] - c)), correction_deg=rotation_deg(P),
        motions_held=None if held is None else held[0], angle_held=None if held is None else held[1])


def _fuse_views(views: Sequence, rig: Rig | None, *, settings: FuseSettings = FuseSettings(),
                progress: bool = False) -> FuseResult:
    """Fuse turntable views into one cloud in the object frame.

    Args:
        views: :class:`FusionView`s, or mappings with the same keys (``points``,
            ``turntable_deg``, ``camera_center``, optional ``name``, ``normals``,
            ``confidence``), all in the world frame.
        rig: the rig; its turntable axis turns the views into the object frame. May
            be None (or have no turntable) only if every view is at angle 0.
        settings: cleaning, registration and merging settings.
        progress: show a progress bar during registration.

    Returns:
        A :class:`FuseResult` whose ``cloud`` is the fused ``o3d.geometry.PointCloud``.

    Raises:
        ValueError: no views, bad shapes, or turned views without a turntable axis.
    """
    import open3d as o3d

    check_fuse_settings(settings)
    s = settings
    if isinstance(views, (str, bytes, os.PathLike)) or not isinstance(views, Sequence) or len(views) == 0:
        raise ValueError("views: expected a non-empty sequence of views")
    vs = [_as_view(v, i) for i, v in enumerate(views)]
    angles = np.array([v.turntable_deg for v in vs])
    turntable = _turntable_of(rig, angles)
    T0 = [turntable_transform(turntable, -v.turntable_deg) for v in vs]
    clouds, confs, sigmas, cams = _clean_views(o3d, vs, T0, s)

    downs = [c.voxel_down_sample(s.icp_voxel_mm) for c in clouds]
    for d, cam in zip(downs, cams):
        if len(d.points) >= 3:
            d.normalize_normals()
            d.orient_normals_towards_camera_location(cam)
    before = _residuals(o3d, downs, [np.eye(4)] * len(vs), s.icp_fine_mm)
    graph = held = None
    poses = [np.eye(4) for _ in vs]
    if s.refine and len(vs) >= 2:
        poses, graph, held = _refine(o3d, downs, angles, s, progress, (turntable.axis_point, turntable.axis_dir))
    after = _residuals(o3d, downs, poses, s.icp_fine_mm) if graph is not None else before

    residuals = [_view_residual(v, clouds[i], poses[i], before[i], after[i], None if held is None else held[i])
                 for i, v in enumerate(vs)]
    if graph is not None:
        for i, P in enumerate(poses):
            clouds[i].transform(P)
            cams[i] = apply_transform(P, cams[i][None])[0]

    kept = [r.name for r in residuals if r.angle_held]
    if kept:
        log.warning("the views' overlap does not fix the turntable angle of %d of %d views (%s): kept at the "
                    "turntable's; a shape symmetric about the turntable axis (a sphere, a cylinder) does not show "
                    "its own turn (docs/fusion.md, \"Symmetric objects\")", len(kept), len(vs), ", ".join(kept))
    fused, point_view, point_conf, point_sigma = merge_clouds(clouds, confs, voxel_mm=s.voxel_mm, sigmas=sigmas)
    log.info("fused %d views into %d points", len(vs), len(fused.points))
    return FuseResult(
        cloud=fused, views=clouds, names=[v.name for v in vs], turntable_deg=angles,
        transforms=np.stack([P @ T for P, T in zip(poses, T0)]), corrections=np.stack(poses),
        camera_centers=np.stack(cams), residuals=residuals, rig=rig, settings=s,
        point_view=point_view, point_confidence=point_conf, pose_graph=graph, point_sigma=point_sigma)


# ----------------------------------------------------------------------------- several poses


