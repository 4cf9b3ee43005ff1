"""Several poses of one object (flip and rescan): align whole turntable scans with
no known transform (FPFH + RANSAC, then ICP, then a pose graph) into one cloud.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ringscan.pipeline.formats.settings import check_finite_settings
from ringscan.pipeline.fusion.threads import check_threads, open3d_threads
from ringscan.pipeline.fusion.turntable import (FuseResult, apply_transform, merge_clouds, plane_residuals,
                                               rotation_deg)

log = logging.getLogger(__name__)

__all__ = ["PoseSettings", "PoseRegistration", "AlignmentError", "MultiPoseResult", "fuse_poses"]


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
    threads: int = 1
    """CPU threads Open3D may use (RANSAC, ICP, features): 1 gives the same bytes from run
    to run (RANSAC is seeded, ``seed``); 0 (every core) is faster, and then RANSAC's
    hypotheses and the ICP sums depend on scheduling (:mod:`ringscan.pipeline.fusion.threads`)."""


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
    point_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    """(M,) standard deviation (mm) of each merged point (the poses' errors independent:
    :func:`~ringscan.pipeline.fusion.turntable.merge_clouds`); NaN where unknown."""

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
    check_finite_settings(s)
    check_threads("PoseSettings", s.threads)
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
    res = plane_residuals(o3d, apply_transform(T, np.asarray(src.points)), np.asarray(dst.points),
                          np.asarray(dst.normals), dist)
    return float("inf") if res is None else res[1]


def _alignment_ok(fit: float, rmse: float, s: PoseSettings) -> str | None:
    if fit < s.min_fitness:
        return (f"failed to align to the reference pose: fitness {fit:.3f} < min_fitness {s.min_fitness} "
                f"(too little overlap within {s.icp_fine_mm} mm, or a wrong match)")
    if rmse > s.max_rmse_mm:
        return (f"failed to align to the reference pose: point-to-plane RMSE {rmse:.3f} mm > max_rmse_mm "
                f"{s.max_rmse_mm}")
    return None


def _prepare_pose(o3d, cloud, name: str, s: PoseSettings, *, check_points: bool) -> tuple:
    """A pose's registration inputs: (downsampled copy with normals for the global
    search, its FPFH features, downsampled copy for ICP)."""
    if check_points and len(cloud.points) < s.min_points:
        raise AlignmentError(name, f"too few points to align ({len(cloud.points)} < min_points {s.min_points})")
    g = _oriented_copy(o3d, cloud, s.global_voxel_mm, s.global_normal_radius_mm)
    f = o3d.pipelines.registration.compute_fpfh_feature(
        g, o3d.geometry.KDTreeSearchParamHybrid(radius=s.feature_radius_mm, max_nn=s.feature_max_nn))
    return g, f, _oriented_copy(o3d, cloud, s.icp_voxel_mm, None)


def _register_pairs(o3d, prepared: list, names: list[str], s: PoseSettings, progress: bool) -> tuple[list, dict]:
    """Register every further pose to the reference, and (pose graph) every pair of
    further poses too: a pose that shares little surface with the reference (upside
    down under a light along the axis) is placed via another.

    Returns:
        (edges, failures): edges ``(i, j, T, information, RANSAC fitness)`` of the pairs
        that pass the checks (T maps pose i onto pose j); per pose, why its first
        failed pair failed.
    """
    from ringscan.pipeline.formats.progress import progress_bar

    n = len(prepared)
    pairs = [(i, 0) for i in range(1, n)]
    if s.pose_graph and n >= 3:
        pairs += [(j, i) for i in range(1, n) for j in range(i + 1, n)]
    edges, failures = [], {}
    for i, j in progress_bar(pairs, desc="aligning poses", unit="pair", disable=not progress):
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
    return edges, failures


def _place_poses(edges: list, failures: dict, names: list[str]) -> tuple[list, dict, list]:
    """Place every pose by a spanning tree of the good pairs, breadth first from the
    reference; returns (transforms to the reference frame, parent of each pose, the
    RANSAC fitness of the pair that placed it). A pose the tree does not reach is an
    :class:`AlignmentError`."""
    n = len(names)
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
    return transforms, parent, gfits


def _optimise_pose_graph(o3d, transforms: list, edges: list, parent: dict, s: PoseSettings) -> tuple[list, object]:
    """Optimise the poses over every good pair (tree edges certain, the others may be
    pruned), the reference held fixed; returns (transforms, the optimised graph)."""
    reg = o3d.pipelines.registration
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
    return [P0_inv @ np.asarray(graph.nodes[i].pose) for i in range(len(transforms))], graph


def _check_against_others(o3d, prepared: list, transforms: list, names: list[str], s: PoseSettings, *,
                          optimised: bool) -> list[tuple]:
    """Check every further pose against all the other poses, merged; returns per pose
    (fitness, inlier RMSE, point-to-plane RMSE, fitness to the reference)."""
    reg = o3d.pipelines.registration
    n = len(prepared)
    fits: list[tuple] = [(1.0, 0.0, 0.0, 1.0)] * n
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
                                 + (" after the pose-graph optimisation" if optimised else ""))
    return fits


def fuse_poses(poses: Sequence, *, names: Sequence[str] | None = None, settings: PoseSettings = PoseSettings(),
               progress: bool = False) -> MultiPoseResult:
    """Align several poses of one object and merge them (see :func:`_fuse_poses`);
    Open3D runs on ``settings.threads`` threads meanwhile."""
    with open3d_threads(getattr(settings, "threads", 1)):
        return _fuse_poses(poses, names=names, settings=settings, progress=progress)


def _fuse_poses(poses: Sequence, *, names: Sequence[str] | None = None, settings: PoseSettings = PoseSettings(),
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

    _check_pose_settings(settings)
    s = settings
    if isinstance(poses, (str, bytes, os.PathLike)) or not isinstance(poses, Sequence) or len(poses) == 0:
        raise ValueError("poses: expected a non-empty sequence of FuseResults or point clouds")
    names = [f"pose_{i}" for i in range(len(poses))] if names is None else [str(n) for n in names]
    if len(names) != len(poses):
        raise ValueError(f"names: {len(names)} names for {len(poses)} poses")
    items = [_as_pose_cloud(o3d, p, i, names[i]) for i, p in enumerate(poses)]
    n = len(items)
    prepared = [_prepare_pose(o3d, cloud, name, s, check_points=n > 1) for (cloud, _, _), name in zip(items, names)]
    edges, failures = _register_pairs(o3d, prepared, names, s, progress)
    transforms, parent, gfits = _place_poses(edges, failures, names)
    graph = None
    if s.pose_graph and len(edges) > n - 1:
        transforms, graph = _optimise_pose_graph(o3d, transforms, edges, parent, s)
    fits = _check_against_others(o3d, prepared, transforms, names, s, optimised=graph is not None)

    regs, moved, confs = [], [], []
    for i, ((cloud, conf, _), name) in enumerate(zip(items, names)):
        T = transforms[i]
        regs.append(PoseRegistration(name=name, points=len(cloud.points), transform=T, global_fitness=gfits[i],
                                     fitness=fits[i][0], inlier_rmse_mm=fits[i][1], plane_rmse_mm=fits[i][2],
                                     fitness_to_reference=fits[i][3], aligned_with=names[parent[i]],
                                     rotation_deg=rotation_deg(T),
                                     translation_mm=float(np.linalg.norm(T[:3, 3]))))
        c = o3d.geometry.PointCloud(cloud).transform(T)  # normals turn with it: still outward
        moved.append(c)
        confs.append(conf if len(conf) == len(c.points) else np.ones(len(c.points)))
    sigmas = [np.asarray(fr.point_sigma, np.float64) if fr is not None and len(fr.point_sigma) == len(c.points)
              else np.full(len(c.points), np.nan) for (_, _, fr), c in zip(items, moved)]
    out, point_view, point_conf, point_sigma = merge_clouds(moved, confs, voxel_mm=s.voxel_mm, sigmas=sigmas)
    log.info("merged %d poses into %d points", n, len(out.points))
    return MultiPoseResult(cloud=out, poses=moved, names=names, transforms=np.stack(transforms), registrations=regs,
                           settings=s, fused=[it[2] for it in items if it[2] is not None]
                           if all(it[2] is not None for it in items) else [],
                           point_view=point_view, point_confidence=point_conf, pose_graph=graph,
                           point_sigma=point_sigma)
