"""Multi-view fusion: turntable views -> one cleaned point cloud in the object frame.

A turntable scan gives one point cloud per view, each in the world frame (DESIGN §2)
with the object turned by the view's ``turntable_deg``. Fusion

1. turns every view back by ``-turntable_deg`` about the rig's turntable axis
   (DESIGN §6), which puts all views in the object frame (the pose of angle 0);
2. cleans each view: non-finite and low-confidence points, a ground clip
   (the reference plane z = 0; on by default), statistical and radius outlier removal;
3. estimates normals (or rotates the ones the view carries) and orients them
   toward the view's camera centre, which turns with the view too;
4. refines the poses with Open3D: point-to-plane ICP between each view and its
   next neighbours in turntable order (coarse then fine), a loop-closure edge from
   the last view back to the first, and multiway pose-graph optimisation with the
   view nearest angle 0 held fixed (that view's pose does not depend on the axis);
5. reports each view's residual against all other views before and after the
   refinement, and the correction applied (mm, degrees);
6. merges the views and voxel-downsamples them into the fused cloud.

Several poses ("flip and rescan", :func:`fuse_poses`, :func:`fuse_recons`): each
pose's scan is fused as above into its own object frame; every further pose is
registered to the first (and, with three or more, to each other) with FPFH features
+ RANSAC on voxel-downsampled copies, then point-to-plane ICP (coarse, fine);
poses are placed along a spanning tree of the pairs that pass the fitness and
point-to-plane RMSE checks, a pose graph is optimised when there are more pairs,
every pose is checked against the others merged, and the clouds are merged in the
first pose's frame. A pose that cannot be aligned raises :class:`AlignmentError`
naming it.

Everything returned is an Open3D geometry or a NumPy array, so a user's script can
carry on with Open3D directly.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import FormatError
from .io import read_json, read_ply
from .rig import Rig, Turntable, parse_rig, turntable_transform

log = logging.getLogger(__name__)

__all__ = [
    "FuseSettings",
    "ViewCloud",
    "ViewResidual",
    "FuseResult",
    "fuse_views",
    "load_recon",
    "fuse_recon",
    "recon_folder",
    "PoseSettings",
    "PoseRegistration",
    "AlignmentError",
    "MultiPoseResult",
    "fuse_poses",
    "fuse_recons",
]

REPORT_NAME = "report.json"


# ----------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class FuseSettings:
    """How views are cleaned, registered and merged (lengths in mm)."""

    min_confidence: float = 0.0
    """Points whose ``confidence`` is below this are dropped before anything else."""
    ground_clip_mm: float | None = 0.5
    """Drop points whose world z is below this: the reference plane z = 0 (DESIGN §2),
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


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True)
class ViewCloud:
    """One view's points in the world frame (DESIGN §2)."""

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

    def report(self) -> dict:
        """A JSON-ready summary: per-view residuals and the resolved settings."""
        return {
            "points": len(self.cloud.points),
            "views": [r.to_dict() for r in self.residuals],
            "settings": dataclasses.asdict(self.settings),
            "axis": None if self.rig is None or self.rig.turntable is None else {
                "axis_point": self.rig.turntable.axis_point.tolist(),
                "axis_dir": self.rig.turntable.axis_dir.tolist()},
        }


# ----------------------------------------------------------------------------- geometry helpers


def _rotation_deg(T: np.ndarray) -> float:
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def _apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def _as_view(v, i: int) -> ViewCloud:
    if isinstance(v, ViewCloud):
        vc = v
    elif isinstance(v, Mapping):
        unknown = set(v) - {f.name for f in dataclasses.fields(ViewCloud)}
        if unknown:
            raise ValueError(f"views[{i}]: unknown keys {sorted(unknown)}")
        try:
            vc = ViewCloud(**{"name": f"view_{i:03d}", **v})
        except TypeError as e:
            raise ValueError(f"views[{i}]: {e}") from None
    else:
        raise ValueError(f"views[{i}]: expected a ViewCloud or a mapping, got {type(v).__name__}")
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
    cc = np.asarray(vc.camera_center, dtype=np.float64)
    if cc.shape != (3,) or not np.all(np.isfinite(cc)):
        raise ValueError(f"views[{i}] ({vc.name}): camera_center must be 3 finite numbers, got {vc.camera_center!r}")
    th = float(vc.turntable_deg)
    if not math.isfinite(th):
        raise ValueError(f"views[{i}] ({vc.name}): turntable_deg is not finite")
    return ViewCloud(name=str(vc.name), points=pts, turntable_deg=th, camera_center=cc, normals=nrm, confidence=conf)


def _check_settings(s: FuseSettings) -> None:
    if not isinstance(s, FuseSettings):
        raise ValueError(f"settings must be a FuseSettings, got {type(s).__name__}")
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


def _clean_view(o3d, v: ViewCloud, T: np.ndarray, cam: np.ndarray, s: FuseSettings):
    """The view's cloud in the object frame, cleaned, with normals toward ``cam``."""
    keep = np.all(np.isfinite(v.points), axis=1)
    if v.confidence is not None:
        keep &= v.confidence >= s.min_confidence
    if s.ground_clip_mm is not None:
        keep &= v.points[:, 2] >= s.ground_clip_mm
    if v.normals is not None:
        keep &= np.all(np.isfinite(v.normals), axis=1)
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(_apply(T, v.points[keep]))
    if v.normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(v.normals[keep] @ T[:3, :3].T)
    conf = (v.confidence[keep] if v.confidence is not None else np.ones(int(keep.sum()))).astype(np.float64)
    idx = np.arange(len(pcd.points))
    if len(idx) and s.statistical_neighbors > 0 and len(idx) > s.statistical_neighbors:
        pcd, kept = pcd.remove_statistical_outlier(nb_neighbors=s.statistical_neighbors,
                                                   std_ratio=s.statistical_std_ratio)
        idx = idx[np.asarray(kept, dtype=np.int64)]
    if len(idx) and s.radius_mm > 0 and s.radius_min_points > 0:
        pcd, kept = pcd.remove_radius_outlier(nb_points=s.radius_min_points, radius=s.radius_mm)
        idx = idx[np.asarray(kept, dtype=np.int64)]
    conf = conf[idx]
    if len(pcd.points) >= 3:
        if not pcd.has_normals():
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=s.normal_radius_mm,
                                                                      max_nn=s.normal_max_nn))
        pcd.normalize_normals()
        pcd.orient_normals_towards_camera_location(cam)
    return pcd, conf


# ----------------------------------------------------------------------------- registration


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


def _residuals(o3d, downs: list, transforms: list[np.ndarray], dist: float) -> list[tuple[float, float]]:
    """Per view: (fraction of points within ``dist`` of another view, point-to-plane RMS of those)."""
    moved = [o3d.geometry.PointCloud(d).transform(T) for d, T in zip(downs, transforms)]
    out = []
    for i, d in enumerate(moved):
        others = [e for j, e in enumerate(moved) if j != i and len(e.points)]
        if len(d.points) == 0 or not others:
            out.append((0.0, 0.0))
            continue
        q_pts = np.concatenate([np.asarray(e.points) for e in others])
        q_nrm = np.concatenate([np.asarray(e.normals) for e in others])
        p = np.asarray(d.points)
        nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(q_pts))
        nns.knn_index()
        idx, d2 = nns.knn_search(o3d.core.Tensor(p), 1)
        idx = idx.numpy()[:, 0]
        inl = np.sqrt(d2.numpy()[:, 0]) < dist
        if not inl.any():
            out.append((0.0, 0.0))
            continue
        r = np.einsum("ij,ij->i", p[inl] - q_pts[idx[inl]], q_nrm[idx[inl]])
        out.append((float(inl.mean()), float(np.sqrt(np.mean(r * r)))))
    return out


def _refine(o3d, downs: list, angles: np.ndarray, s: FuseSettings, progress: bool):
    """Pose-graph refinement; returns per-view corrections (object frame) and the graph."""
    from tqdm import tqdm

    reg = o3d.pipelines.registration
    n = len(downs)
    order = np.argsort(np.mod(angles, 360.0), kind="stable")
    ref = int(np.argmin(np.abs((angles + 180.0) % 360.0 - 180.0)))
    graph = reg.PoseGraph()
    for _ in range(n):
        graph.nodes.append(reg.PoseGraphNode(np.eye(4)))
    pairs = _pairs(order, s)
    used = 0
    for i, j, uncertain in tqdm(pairs, desc="registering views", unit="pair", disable=not progress):
        if len(downs[i].points) < 10 or len(downs[j].points) < 10:
            continue
        fine, info = _icp_pair(o3d, downs[i], downs[j], s)
        if fine.fitness < s.min_edge_fitness:
            log.info("views %d -> %d overlap too little (fitness %.2f): edge left out", i, j, fine.fitness)
            continue
        log.debug("edge %d -> %d: fitness %.3f, rmse %.3f mm", i, j, fine.fitness, fine.inlier_rmse)
        graph.edges.append(reg.PoseGraphEdge(i, j, fine.transformation, info, uncertain=uncertain))
        used += 1
    if used == 0:
        log.warning("no pair of views overlaps enough to register: keeping the turntable poses")
        return [np.eye(4) for _ in range(n)], graph
    opt = reg.GlobalOptimizationOption(max_correspondence_distance=s.icp_fine_mm,
                                       edge_prune_threshold=s.edge_prune_threshold,
                                       preference_loop_closure=1.0, reference_node=ref)
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                            reg.GlobalOptimizationConvergenceCriteria(), opt)
    # Hold the reference view exactly where the turntable put it.
    P_ref_inv = np.linalg.inv(np.asarray(graph.nodes[ref].pose))
    poses = [P_ref_inv @ np.asarray(graph.nodes[i].pose) for i in range(n)]
    return poses, graph


# ----------------------------------------------------------------------------- public API


def fuse_views(views: Sequence, rig: Rig | None, *, settings: FuseSettings = FuseSettings(),
               progress: bool = False) -> FuseResult:
    """Fuse turntable views into one cloud in the object frame.

    Args:
        views: :class:`ViewCloud`s, or mappings with the same keys (``points``,
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

    _check_settings(settings)
    s = settings
    if isinstance(views, (str, bytes, os.PathLike)) or not isinstance(views, Sequence) or len(views) == 0:
        raise ValueError("views: expected a non-empty sequence of views")
    vs = [_as_view(v, i) for i, v in enumerate(views)]
    angles = np.array([v.turntable_deg for v in vs])
    turntable = rig.turntable if rig is not None else None
    if turntable is None:
        if np.any(np.abs((angles + 180.0) % 360.0 - 180.0) > 1e-9):
            raise ValueError("views are turned (turntable_deg != 0) but the rig has no turntable axis")
        turntable = Turntable(axis_point=np.zeros(3), axis_dir=np.array([0.0, 0.0, 1.0]))

    T0 = [turntable_transform(turntable, -v.turntable_deg) for v in vs]
    clouds, confs, cams = [], [], []
    for v, T in zip(vs, T0):
        cam = _apply(T, v.camera_center[None])[0]
        pcd, conf = _clean_view(o3d, v, T, cam, s)
        clouds.append(pcd)
        confs.append(conf)
        cams.append(cam)
        log.info("%s: %d of %d points kept", v.name, len(pcd.points), len(v.points))
    if sum(len(c.points) for c in clouds) == 0:
        raise ValueError("no points left in any view after cleaning (check min_confidence and ground_clip_mm)")

    downs = [c.voxel_down_sample(s.icp_voxel_mm) for c in clouds]
    for d, cam in zip(downs, cams):
        if len(d.points) >= 3:
            d.normalize_normals()
            d.orient_normals_towards_camera_location(cam)
    before = _residuals(o3d, downs, [np.eye(4)] * len(vs), s.icp_fine_mm)
    graph = None
    poses = [np.eye(4) for _ in vs]
    if s.refine and len(vs) >= 2:
        poses, graph = _refine(o3d, downs, angles, s, progress)
    after = _residuals(o3d, downs, poses, s.icp_fine_mm) if graph is not None else before

    residuals = []
    for i, v in enumerate(vs):
        P = poses[i]
        c = np.asarray(clouds[i].points).mean(axis=0) if len(clouds[i].points) else np.zeros(3)
        residuals.append(ViewResidual(
            name=v.name, turntable_deg=v.turntable_deg, points_in=len(v.points), points_kept=len(clouds[i].points),
            fitness_before=before[i][0], rmse_before_mm=before[i][1], fitness=after[i][0], rmse_mm=after[i][1],
            correction_mm=float(np.linalg.norm(_apply(P, c[None])[0] - c)), correction_deg=_rotation_deg(P)))
        if graph is not None:
            clouds[i].transform(P)
            cams[i] = _apply(P, cams[i][None])[0]

    merged = o3d.geometry.PointCloud()
    labels, conf_all = [], []
    for i, c in enumerate(clouds):
        merged += c
        labels.append(np.full(len(c.points), i, np.int32))
        conf_all.append(confs[i])
    labels = np.concatenate(labels)
    conf_all = np.concatenate(conf_all)
    if s.voxel_mm > 0 and len(merged.points):
        lo = merged.get_min_bound() - s.voxel_mm
        hi = merged.get_max_bound() + s.voxel_mm
        fused, _, traces = merged.voxel_down_sample_and_trace(s.voxel_mm, lo, hi, False)
        point_view = np.array([labels[t[0]] for t in traces], np.int32)
        point_conf = np.array([conf_all[np.asarray(t)].mean() for t in traces], np.float32)
        fused.normalize_normals()
    else:
        fused, point_view, point_conf = merged, labels, conf_all.astype(np.float32)
    log.info("fused %d views into %d points", len(vs), len(fused.points))
    return FuseResult(
        cloud=fused, views=clouds, names=[v.name for v in vs], turntable_deg=angles,
        transforms=np.stack([P @ T for P, T in zip(poses, T0)]), corrections=np.stack(poses),
        camera_centers=np.stack(cams), residuals=residuals, rig=rig, settings=s,
        point_view=point_view, point_confidence=point_conf, pose_graph=graph)


def load_recon(recon_dir: str | os.PathLike) -> tuple[list[ViewCloud], Rig | None, dict]:
    """Read a reconstruction folder: ``report.json`` and one PLY per view.

    Returns:
        (views, rig, report): the views in the world frame, the rig from the report
        (None if it has none) and the report dictionary itself.

    Raises:
        FormatError: naming the file and field that is missing or wrong.
    """
    recon_dir = Path(recon_dir)
    rpath = recon_dir / REPORT_NAME
    report = read_json(rpath)
    rig = None
    if report.get("rig") is not None:
        rig_d = report["rig"]
        if isinstance(rig_d, str):
            from .rig import load_rig

            rig = load_rig(recon_dir / rig_d)
        else:
            rig = parse_rig(rig_d, source=f"{rpath}: rig")
    vlist = report.get("views")
    if not isinstance(vlist, list) or not vlist:
        raise FormatError(rpath, "views: missing or empty")
    views = []
    for i, vd in enumerate(vlist):
        where = f"views[{i}]"
        if not isinstance(vd, dict):
            raise FormatError(rpath, f"{where}: expected an object")
        name = vd.get("name", f"view_{i:03d}")
        ply = vd.get("ply")
        if not isinstance(ply, str):
            raise FormatError(rpath, f"{where}.ply: missing or not a string")
        th = vd.get("turntable_deg", 0.0)
        if isinstance(th, bool) or not isinstance(th, (int, float)):
            raise FormatError(rpath, f"{where}.turntable_deg: expected a number, got {th!r}")
        cc = vd.get("camera_center")
        if cc is None and rig is not None:
            cc = rig.camera.center.tolist()
        try:
            cc = np.asarray(cc, dtype=np.float64)
        except (TypeError, ValueError):
            cc = None
        if cc is None or cc.shape != (3,):
            raise FormatError(rpath, f"{where}.camera_center: expected 3 numbers (or a rig with a camera)")
        f = read_ply(recon_dir / ply)
        for k in ("x", "y", "z"):
            if k not in f:
                raise FormatError(recon_dir / ply, f"vertex property {k!r} missing")
        pts = np.stack([f["x"], f["y"], f["z"]], axis=1).astype(np.float64)
        nrm = None
        if all(k in f for k in ("nx", "ny", "nz")):
            nrm = np.stack([f["nx"], f["ny"], f["nz"]], axis=1).astype(np.float64)
        conf = f["confidence"].astype(np.float64) if "confidence" in f else None
        views.append(ViewCloud(name=str(name), points=pts, turntable_deg=float(th), camera_center=cc,
                               normals=nrm, confidence=conf))
    return views, rig, report


def recon_folder(path: str | os.PathLike, *, work_dir: str | os.PathLike | None = None, device: str | None = None,
                 progress: bool = False) -> Path:
    """The reconstruction folder for ``path``.

    A folder with ``report.json`` is returned as it is. A scan folder (with
    ``scan.json``) is reconstructed first, into ``work_dir`` (required then), with
    :func:`ringscan.pipeline.reconstruct.reconstruct_scan`.

    Raises:
        FormatError: ``path`` is neither.
        ValueError: a scan folder without ``work_dir``.
    """
    path = Path(path)
    if (path / REPORT_NAME).is_file():
        return path
    if (path / "scan.json").is_file():
        if work_dir is None:
            raise ValueError(f"{path} is a scan folder: give a folder to reconstruct it into")
        try:
            from .reconstruct import reconstruct_scan
        except ImportError as e:  # pragma: no cover - only in partial checkouts
            raise ValueError(f"{path} is a scan folder, but this install cannot reconstruct scans ({e}); "
                             "run `ringscan reconstruct` first and fuse its output folder") from None
        log.info("reconstructing scan %s into %s", path, work_dir)
        reconstruct_scan(path, work_dir, device=device, progress=progress)
        return Path(work_dir)
    if not path.exists():
        raise FormatError(path, "not found")
    raise FormatError(path, f"neither a reconstruction folder ({REPORT_NAME}) nor a scan folder (scan.json)")


def fuse_recon(path: str | os.PathLike, *, settings: FuseSettings = FuseSettings(), rig: Rig | None = None,
               work_dir: str | os.PathLike | None = None, device: str | None = None,
               progress: bool = False) -> FuseResult:
    """Fuse a reconstruction folder (``report.json`` + per-view PLYs) or a scan folder.

    Args:
        path: the reconstruction folder, or a scan folder (reconstructed first into
            ``work_dir``, see :func:`recon_folder`).
        settings: fusion settings.
        rig: use this rig instead of the one in the report (e.g. a corrected axis).
        work_dir: where a scan folder is reconstructed.
        device: Warp device for that reconstruction.
        progress: show progress bars.
    """
    folder = recon_folder(path, work_dir=work_dir, device=device, progress=progress)
    views, rep_rig, _ = load_recon(folder)
    return fuse_views(views, rig if rig is not None else rep_rig, settings=settings, progress=progress)


# ----------------------------------------------------------------------------- several poses


@dataclass(frozen=True)
class PoseSettings:
    """How the fused clouds of several poses ("flip and rescan") are aligned and merged
    (lengths in mm). Every further pose is registered to the first (reference) pose:
    FPFH features + RANSAC on voxel-downsampled copies (global, no initial guess),
    then point-to-plane ICP (coarse, then fine) on finer copies."""

    global_voxel_mm: float = 1.5
    """Voxel size of the copies used for FPFH features and RANSAC."""
    feature_radius_mm: float = 7.5
    """FPFH feature radius (about 5 x global_voxel_mm)."""
    feature_max_nn: int = 100
    """FPFH: at most this many neighbours."""
    global_normal_radius_mm: float = 3.0
    """Normals of the global copies are re-estimated at this radius (then oriented
    like the full cloud's normals, which point out of the object)."""
    ransac_distance_mm: float = 2.25
    """RANSAC: largest distance of an inlier pair (about 1.5 x global_voxel_mm)."""
    ransac_iterations: int = 200_000
    """RANSAC: most hypotheses per trial."""
    ransac_confidence: float = 0.999
    """RANSAC: stop early at this confidence."""
    ransac_trials: int = 3
    """Run global registration (and ICP) this many times with different random
    seeds and keep the alignment with the best fine ICP fitness."""
    edge_length_ratio: float = 0.9
    """RANSAC checker: corresponding edge lengths must agree to this ratio."""
    seed: int = 0
    """Random seed of the first RANSAC trial (trial k uses seed + k)."""
    icp_voxel_mm: float = 0.6
    """Voxel size of the copies used for ICP and the overlap figures."""
    icp_coarse_mm: float = 3.0
    """Coarse ICP: largest point-pair distance."""
    icp_fine_mm: float = 1.0
    """Fine ICP, fitness, inlier RMSE and pose graph: largest point-pair distance."""
    icp_iterations: int = 80
    """ICP iterations per stage."""
    pose_graph: bool = True
    """With 3 or more poses, also register every pair of further poses and optimise a
    pose graph (reference pose fixed); a pair that fails the checks is left out."""
    min_fitness: float = 0.1
    """A pose whose fine ICP fitness (fraction of its points within icp_fine_mm of
    the reference pose's points) is below this has failed to align: an error."""
    max_rmse_mm: float = 0.15
    """A pose whose point-to-plane RMS distance to the reference pose (over the pairs
    within icp_fine_mm, ``plane_rmse_mm``) is above this has failed to align: an
    error. (Open3D's inlier RMSE is point-to-point, dominated by the point spacing,
    so it is reported but not checked.)"""
    min_points: int = 1000
    """A pose whose cloud has fewer points than this cannot be aligned reliably (a
    few points fit anywhere): an error."""
    voxel_mm: float = 0.3
    """Voxel size of the merged cloud (points and normals averaged per voxel; 0 keeps all)."""


@dataclass(frozen=True)
class PoseRegistration:
    """How one pose was aligned to the reference pose."""

    name: str
    """The pose's name (its source)."""
    points: int
    """Points of the pose's fused cloud."""
    transform: np.ndarray
    """(4, 4) the pose's object frame -> the reference pose's object frame."""
    global_fitness: float
    """RANSAC fitness (on the global copies) of the kept trial of the pair that placed the pose."""
    fitness: float
    """Final fitness: fraction of the pose's (ICP-copy) points within icp_fine_mm of
    the other poses' points, all in the reference frame (checked against min_fitness)."""
    inlier_rmse_mm: float
    """Open3D's inlier RMSE of those pairs (point-to-point, mm)."""
    plane_rmse_mm: float
    """RMS point-to-plane distance of those pairs (mm): the alignment error plus the
    scan noise (checked against max_rmse_mm)."""
    fitness_to_reference: float
    """The same fraction against the reference pose alone (an upside-down pose may
    share almost nothing with an upright one and be placed via a side pose)."""
    aligned_with: str
    """The pose this one was registered to first (spanning tree of the good pairs)."""
    rotation_deg: float
    """Rotation angle of ``transform`` (degrees)."""
    translation_mm: float
    """Length of the translation of ``transform`` (mm)."""

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["transform"] = np.asarray(self.transform).tolist()
        return d


class AlignmentError(ValueError):
    """A pose could not be aligned to the reference pose (low fitness or high RMSE)."""

    def __init__(self, name: str, message: str):
        super().__init__(f"pose {name!r}: {message}")
        self.name = name


@dataclass
class MultiPoseResult:
    """Several poses merged in the reference (first) pose's object frame."""

    cloud: "o3d.geometry.PointCloud"  # noqa: F821
    """The merged, voxel-downsampled cloud with outward normals."""
    poses: list
    """Each pose's cloud, transformed into the reference frame (full resolution)."""
    names: list[str]
    """Pose names, in the order of ``poses`` (the first is the reference)."""
    transforms: np.ndarray
    """(P, 4, 4) each pose's object frame -> the reference object frame (identity first)."""
    registrations: list[PoseRegistration]
    """One per pose (the reference pose's with fitness 1 and the identity)."""
    settings: PoseSettings
    """The settings used."""
    fused: list = field(default_factory=list)
    """Each pose's :class:`FuseResult` when the poses came from turntable scans (else empty)."""
    point_view: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    """(M,) for each merged point, the index of a pose that contributed to it."""
    point_confidence: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    """(M,) mean confidence of the points merged into each point."""
    pose_graph: object = None
    """The optimised ``o3d.pipelines.registration.PoseGraph`` (None without one)."""

    @property
    def rig(self):
        """The reference pose's rig (None for bare clouds)."""
        return self.fused[0].rig if self.fused else None

    def report(self) -> dict:
        """A JSON-ready summary: per-pose registration (and per-view residuals of each pose)."""
        out = {"points": len(self.cloud.points), "reference": self.names[0],
               "poses": [], "pose_settings": dataclasses.asdict(self.settings),
               "pose_graph": self.pose_graph is not None}
        for i, r in enumerate(self.registrations):
            d = r.to_dict()
            if self.fused:
                d["fusion"] = self.fused[i].report()
            out["poses"].append(d)
        if self.fused:
            out["views"] = [dict(v, pose=self.names[i]) for i, f in enumerate(self.fused)
                            for v in f.report()["views"]]
            out["settings"] = self.fused[0].report()["settings"]
        return out


def _check_pose_settings(s: PoseSettings) -> None:
    if not isinstance(s, PoseSettings):
        raise ValueError(f"settings must be a PoseSettings, got {type(s).__name__}")
    for name in ("global_voxel_mm", "feature_radius_mm", "global_normal_radius_mm", "ransac_distance_mm",
                 "icp_voxel_mm", "icp_coarse_mm", "icp_fine_mm", "max_rmse_mm"):
        if not getattr(s, name) > 0:
            raise ValueError(f"PoseSettings.{name} must be > 0, got {getattr(s, name)}")
    for name in ("ransac_iterations", "ransac_trials", "icp_iterations", "feature_max_nn", "min_points"):
        if getattr(s, name) < 1:
            raise ValueError(f"PoseSettings.{name} must be >= 1, got {getattr(s, name)}")
    if not 0 <= s.min_fitness <= 1:
        raise ValueError(f"PoseSettings.min_fitness must be in [0, 1], got {s.min_fitness}")
    if not 0 < s.ransac_confidence <= 1 or not 0 < s.edge_length_ratio < 1:
        raise ValueError("PoseSettings.ransac_confidence must be in (0, 1] and edge_length_ratio in (0, 1)")
    if s.voxel_mm < 0:
        raise ValueError(f"PoseSettings.voxel_mm must be >= 0, got {s.voxel_mm}")


def _as_pose_cloud(o3d, src, i: int, name: str):
    """(cloud with outward normals, per-point confidence, FuseResult or None)."""
    if isinstance(src, FuseResult):
        return src.cloud, np.asarray(src.point_confidence, np.float64), src
    if isinstance(src, o3d.geometry.PointCloud):
        if len(src.points) == 0:
            raise ValueError(f"poses[{i}] ({name}): the cloud is empty")
        if not src.has_normals():
            raise ValueError(f"poses[{i}] ({name}): the cloud has no normals (they must point out of the object)")
        return src, np.ones(len(src.points)), None
    raise ValueError(f"poses[{i}] ({name}): expected a FuseResult or an o3d.geometry.PointCloud, "
                     f"got {type(src).__name__}")


def _oriented_copy(o3d, pcd, voxel: float, radius: float | None, max_nn: int = 30):
    """A voxel-downsampled copy; normals re-estimated at ``radius`` (if given) and
    flipped to agree with the (outward) averaged normals."""
    d = pcd.voxel_down_sample(voxel)
    if len(d.points) < 3:
        return d
    d.normalize_normals()
    if radius is not None:
        ref = np.asarray(d.normals).copy()
        d.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
        n = np.asarray(d.normals)
        flip = np.einsum("ij,ij->i", n, ref) < 0
        n[flip] *= -1.0
        d.normals = o3d.utility.Vector3dVector(n)
    return d


def _register_pair(o3d, src: tuple, dst: tuple, s: PoseSettings, name: str):
    """Global (FPFH + RANSAC, best of ``ransac_trials``) then coarse and fine ICP.

    ``src``/``dst`` are (global copy, FPFH feature, ICP copy). Returns
    (fine ICP result, RANSAC fitness, information matrix).
    """
    reg = o3d.pipelines.registration
    g_src, f_src, i_src = src
    g_dst, f_dst, i_dst = dst
    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(s.edge_length_ratio),
                reg.CorrespondenceCheckerBasedOnDistance(s.ransac_distance_mm)]
    est = reg.TransformationEstimationPointToPlane()
    crit = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=s.icp_iterations)
    best = None
    for k in range(s.ransac_trials):
        o3d.utility.random.seed(s.seed + k)
        glob = reg.registration_ransac_based_on_feature_matching(
            g_src, g_dst, f_src, f_dst, True, s.ransac_distance_mm,
            reg.TransformationEstimationPointToPoint(False), 3, checkers,
            reg.RANSACConvergenceCriteria(s.ransac_iterations, s.ransac_confidence))
        coarse = reg.registration_icp(i_src, i_dst, s.icp_coarse_mm, glob.transformation, est, crit)
        fine = reg.registration_icp(i_src, i_dst, s.icp_fine_mm, coarse.transformation, est, crit)
        log.debug("%s trial %d: RANSAC fitness %.3f, fine ICP fitness %.3f, rmse %.3f mm", name, k,
                  glob.fitness, fine.fitness, fine.inlier_rmse)
        # The best trial: the highest fitness among those that pass the RMSE check
        # (a wrong match of two smooth caps can overlap more than the right one).
        prmse = _plane_rmse(o3d, i_src, i_dst, np.asarray(fine.transformation), s.icp_fine_mm)
        score = fine.fitness - (0.0 if prmse <= s.max_rmse_mm else 2.0)
        if best is None or score > best[2]:
            best = (fine, glob.fitness, score)
    fine, gfit, _ = best
    info = reg.get_information_matrix_from_point_clouds(i_src, i_dst, s.icp_fine_mm, fine.transformation)
    return fine, gfit, info


def _plane_rmse(o3d, src, dst, T: np.ndarray, dist: float) -> float:
    """RMS point-to-plane distance of ``src`` (moved by T) to ``dst`` over pairs within ``dist``."""
    p = _apply(T, np.asarray(src.points))
    q = np.asarray(dst.points)
    if len(p) == 0 or len(q) == 0:
        return float("inf")
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(q))
    nns.knn_index()
    idx, d2 = nns.knn_search(o3d.core.Tensor(p), 1)
    idx = idx.numpy()[:, 0]
    inl = np.sqrt(d2.numpy()[:, 0]) < dist
    if not inl.any():
        return float("inf")
    r = np.einsum("ij,ij->i", p[inl] - q[idx[inl]], np.asarray(dst.normals)[idx[inl]])
    return float(np.sqrt(np.mean(r * r)))


def _alignment_ok(fit: float, rmse: float, s: PoseSettings) -> str | None:
    if fit < s.min_fitness:
        return (f"failed to align to the reference pose: fitness {fit:.3f} < min_fitness {s.min_fitness} "
                f"(too little overlap within {s.icp_fine_mm} mm, or a wrong match)")
    if rmse > s.max_rmse_mm:
        return (f"failed to align to the reference pose: point-to-plane RMSE {rmse:.3f} mm > max_rmse_mm "
                f"{s.max_rmse_mm}")
    return None


def fuse_poses(poses: Sequence, *, names: Sequence[str] | None = None, settings: PoseSettings = PoseSettings(),
               progress: bool = False) -> MultiPoseResult:
    """Align the clouds of several poses of one object to the first and merge them.

    Args:
        poses: per pose, a :class:`FuseResult` (a fused turntable scan) or an
            ``o3d.geometry.PointCloud`` with outward normals, each in its own object
            frame. The first is the reference pose: the result is in its frame.
        names: pose names for the report and errors (default ``pose_0``, ...).
        settings: registration and merging settings.
        progress: show a progress bar.

    Returns:
        A :class:`MultiPoseResult`; ``transforms[i]`` maps pose i's object frame to
        the reference frame.

    Raises:
        AlignmentError: a pose's final fitness is below ``min_fitness`` or its RMSE
            above ``max_rmse_mm`` (the message names the pose).
        ValueError: no poses, bad types, empty clouds, bad settings.
    """
    import open3d as o3d
    from tqdm import tqdm

    _check_pose_settings(settings)
    s = settings
    if isinstance(poses, (str, bytes, os.PathLike)) or not isinstance(poses, Sequence) or len(poses) == 0:
        raise ValueError("poses: expected a non-empty sequence of FuseResults or point clouds")
    names = [f"pose_{i}" for i in range(len(poses))] if names is None else [str(n) for n in names]
    if len(names) != len(poses):
        raise ValueError(f"names: {len(names)} names for {len(poses)} poses")
    items = [_as_pose_cloud(o3d, p, i, names[i]) for i, p in enumerate(poses)]
    reg = o3d.pipelines.registration
    n = len(items)

    prepared = []
    for (cloud, _, _), name in zip(items, names):
        if n > 1 and len(cloud.points) < s.min_points:
            raise AlignmentError(name, f"too few points to align ({len(cloud.points)} < min_points {s.min_points})")
        g = _oriented_copy(o3d, cloud, s.global_voxel_mm, s.global_normal_radius_mm)
        f = reg.compute_fpfh_feature(g, o3d.geometry.KDTreeSearchParamHybrid(radius=s.feature_radius_mm,
                                                                            max_nn=s.feature_max_nn))
        prepared.append((g, f, _oriented_copy(o3d, cloud, s.icp_voxel_mm, None)))

    # Register pairs: every further pose to the reference, and (pose graph) every
    # pair of further poses too: a pose that shares little surface with the
    # reference (upside down under a light along the axis) is placed via another.
    pairs = [(i, 0) for i in range(1, n)]
    if s.pose_graph and n >= 3:
        pairs += [(j, i) for i in range(1, n) for j in range(i + 1, n)]
    edges, failures = [], {}
    for i, j in tqdm(pairs, desc="aligning poses", unit="pair", disable=not progress):
        fine, gfit, info = _register_pair(o3d, prepared[i], prepared[j], s, names[i])
        T = np.asarray(fine.transformation).copy()
        prmse = _plane_rmse(o3d, prepared[i][2], prepared[j][2], T, s.icp_fine_mm)
        log.info("pose %s -> %s: RANSAC fitness %.3f, ICP fitness %.3f, inlier rmse %.4f mm, point-to-plane "
                 "%.4f mm", names[i], names[j], gfit, fine.fitness, fine.inlier_rmse, prmse)
        bad = _alignment_ok(float(fine.fitness), prmse, s)
        if bad:
            failures.setdefault(i, bad.replace("the reference pose", repr(names[j])))
            failures.setdefault(j, bad.replace("the reference pose", repr(names[i])))
            continue
        edges.append((i, j, T, info, float(gfit)))

    # Place every pose by a spanning tree of the good pairs, from the reference.
    transforms: list = [np.eye(4)] + [None] * (n - 1)
    parent = {0: 0}
    gfits = [1.0] * n
    frontier = [0]
    while frontier:
        k = frontier.pop(0)
        for i, j, T, _, gfit in edges:
            if j == k and i not in parent:        # T: i -> j
                transforms[i], parent[i], gfits[i] = transforms[j] @ T, j, gfit
                frontier.append(i)
            elif i == k and j not in parent:
                transforms[j], parent[j], gfits[j] = transforms[i] @ np.linalg.inv(T), i, gfit
                frontier.append(j)
    for i in range(1, n):
        if i not in parent:
            why = failures.get(i, "no pair with it passed the checks")
            raise AlignmentError(names[i], why.replace("failed to align to", "failed to align with")
                                 + ("" if n == 2 else " (nor with any other pose)"))

    graph = None
    if s.pose_graph and len(edges) > n - 1:
        graph = reg.PoseGraph()
        for T in transforms:
            graph.nodes.append(reg.PoseGraphNode(np.asarray(T)))
        for i, j, T, info, _ in edges:
            tree = parent.get(i) == j or parent.get(j) == i
            graph.edges.append(reg.PoseGraphEdge(i, j, T, info, uncertain=not tree))
        opt = reg.GlobalOptimizationOption(max_correspondence_distance=s.icp_fine_mm, edge_prune_threshold=0.25,
                                           preference_loop_closure=1.0, reference_node=0)
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), opt)
        P0_inv = np.linalg.inv(np.asarray(graph.nodes[0].pose))
        transforms = [P0_inv @ np.asarray(graph.nodes[i].pose) for i in range(n)]

    # Final check of every further pose against all the other poses, merged.
    fits: list[tuple] = [(1.0, 0.0, 0.0, 1.0)] * n  # (fitness, inlier rmse, plane rmse, fitness to the reference)
    moved_icp = [o3d.geometry.PointCloud(p[2]).transform(T) for p, T in zip(prepared, transforms)]
    for i in range(1, n):
        others = o3d.geometry.PointCloud()
        for k, c in enumerate(moved_icp):
            if k != i:
                others += c
        ev = reg.evaluate_registration(moved_icp[i], others, s.icp_fine_mm, np.eye(4))
        prmse = _plane_rmse(o3d, moved_icp[i], others, np.eye(4), s.icp_fine_mm)
        ev0 = reg.evaluate_registration(moved_icp[i], moved_icp[0], s.icp_fine_mm, np.eye(4))
        fits[i] = (float(ev.fitness), float(ev.inlier_rmse), prmse, float(ev0.fitness))
        bad = _alignment_ok(fits[i][0], prmse, s)
        if bad:
            raise AlignmentError(names[i], bad.replace("the reference pose", "the other poses")
                                 + (" after the pose-graph optimisation" if graph is not None else ""))

    regs, moved, labels, confs = [], [], [], []
    for i, ((cloud, conf, _), name) in enumerate(zip(items, names)):
        T = transforms[i]
        regs.append(PoseRegistration(name=name, points=len(cloud.points), transform=T, global_fitness=gfits[i],
                                     fitness=fits[i][0], inlier_rmse_mm=fits[i][1], plane_rmse_mm=fits[i][2],
                                     fitness_to_reference=fits[i][3], aligned_with=names[parent[i]],
                                     rotation_deg=_rotation_deg(T),
                                     translation_mm=float(np.linalg.norm(T[:3, 3]))))
        c = o3d.geometry.PointCloud(cloud).transform(T)  # normals turn with it: still outward
        moved.append(c)
        labels.append(np.full(len(c.points), i, np.int32))
        confs.append(conf if len(conf) == len(c.points) else np.ones(len(c.points)))
    merged = o3d.geometry.PointCloud()
    for c in moved:
        merged += c
    labels = np.concatenate(labels)
    conf_all = np.concatenate(confs)
    if s.voxel_mm > 0 and len(merged.points):
        lo = merged.get_min_bound() - s.voxel_mm
        hi = merged.get_max_bound() + s.voxel_mm
        out, _, traces = merged.voxel_down_sample_and_trace(s.voxel_mm, lo, hi, False)
        point_view = np.array([labels[t[0]] for t in traces], np.int32)
        point_conf = np.array([conf_all[np.asarray(t)].mean() for t in traces], np.float32)
        out.normalize_normals()
    else:
        out, point_view, point_conf = merged, labels, conf_all.astype(np.float32)
    log.info("merged %d poses into %d points", n, len(out.points))
    return MultiPoseResult(cloud=out, poses=moved, names=names, transforms=np.stack(transforms), registrations=regs,
                           settings=s, fused=[it[2] for it in items if it[2] is not None]
                           if all(it[2] is not None for it in items) else [],
                           point_view=point_view, point_confidence=point_conf, pose_graph=graph)


def fuse_recons(paths: Sequence, *, settings: FuseSettings = FuseSettings(),
                pose_settings: PoseSettings = PoseSettings(), work_dir: str | os.PathLike | None = None,
                device: str | None = None, progress: bool = False) -> MultiPoseResult:
    """Fuse several scans of one object in different poses (flip and rescan).

    Each path (a reconstruction folder or a scan folder, see :func:`fuse_recon`) is
    fused on its own, then :func:`fuse_poses` aligns them to the first and merges.
    Scan folders are reconstructed into ``work_dir/pose_<i>``.

    Raises:
        AlignmentError: naming the source whose alignment failed.
    """
    if isinstance(paths, (str, bytes, os.PathLike)) or not isinstance(paths, Sequence) or len(paths) == 0:
        raise ValueError("paths: expected a non-empty sequence of folders")
    results = []
    for i, p in enumerate(paths):
        wd = None if work_dir is None else Path(work_dir) / f"pose_{i}"
        log.info("pose %d: fusing %s", i, p)
        results.append(fuse_recon(p, settings=settings, work_dir=wd, device=device, progress=progress))
    return fuse_poses(results, names=[str(p) for p in paths], settings=pose_settings, progress=progress)
