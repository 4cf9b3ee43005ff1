"""Accuracy against the virtual rig's ground truth (``ringscan evaluate``, docs/design.md §16).

For each view the truth surface is the placed object (turned to the view's
turntable angle) plus the reference plane z = 0. Figures:

- point-to-surface distance of every reconstructed point (mm): median, mean, RMS,
  95th percentile, max, and the fraction of points more than 1 mm off;
- coverage: of the camera pixels that saw the surface lit (truth ``lit`` mask)
  inside the coded annulus, the fraction whose truth point has a reconstructed
  point within r = ``coverage_radius_mm`` / max(cos theta, 0.25), theta being the
  angle between the surface normal and the light. The ring codecs sample the
  surface along curves one band apart in the light's cross-section (default
  radius: one band width, s * pitch for the parallel light, or two camera pixels
  for the dense codec, whichever is larger); on a slope the curves lie 1 / cos theta
  farther apart on the surface, so a point between two sampled rings is covered
  and a ring that was not sampled is not. Reported for the whole view and for the
  object alone (truth points more than 0.5 mm off the plane, and off the wall of a
  scan simulated with one, truth ``wall_z``). A two-camera scan is measured
  against camera 1's truth. The annulus and the light's angle come from the rig's
  light, or, where its projector is ``uncalibrated``, from the light the simulator
  rendered with (``truth.light``); without either (and for the ``decoded`` codec,
  which has no rings), coverage is of all of camera 1's lit pixels.

Points with a NaN or infinite coordinate are left out of every figure and
counted (``non_finite_points``); a cloud with no finite point has no error
figures (null) and covers nothing.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.limits import check_image_header
from ringscan.pipeline.formats.meshes import open3d_lib, read_mesh
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import (ParallelLight, Rig, has_calibrated_light, parse_rig, rig_to_dict,
                                          turntable_transform)
from ringscan.pipeline.formats.scan import Scan, check_truth, load_scan
from ringscan.pipeline.geometry import light_directions, projector_polar, undistort_normalized

log = logging.getLogger(__name__)




__all__ = ["truth_surface", "distance_stats", "point_distances", "surface_normals", "truth_points", "coverage_radius", "evaluate_view", "evaluate_recon", "evaluate_points", "sigma_stats", "ray_errors", "evaluate_against_mesh", "truth_rho_at",
           "light_rig",
           "check_coverage_radius"]




def truth_surface(scan: Scan, turntable_deg: float):
    """Open3D triangle mesh of the truth for a view: the object at the view's
    angle plus a reference-plane quad, in world coordinates."""
    o3d = open3d_lib()
    truth = check_truth(scan)
    mesh_path = scan.folder / truth["mesh"]
    if not mesh_path.is_file():
        raise FormatError(mesh_path, "truth mesh not found")
    # a scene of bare planes has an empty object mesh: no warning for it (the plane is added below)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(mesh_path))
    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.triangles, np.int64)
    if len(V):
        T = turntable_transform(scan.rig.turntable, turntable_deg)
        V = V @ T[:3, :3].T + T[:3, 3]
    zp = truth["reference_plane_z"]
    if truth["reference_plane"]:
        r = 4.0 * scan.rig.volume.r_max
        PV = np.array([[-r, -r, zp], [r, -r, zp], [r, r, zp], [-r, r, zp]])
        PF = np.array([[0, 1, 2], [0, 2, 3]]) + len(V)
        V = np.vstack([V, PV]) if len(V) else PV
        F = np.vstack([F, PF]) if len(F) else PF - len(V) + 4
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F.astype(np.int32)))
    return out


def distance_stats(d: np.ndarray, *, over_mm: float = 1.0) -> dict:
    """Summary of point-to-surface distances (mm); NaN distances are left out."""
    d = np.asarray(d, np.float64)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"points": 0, "median_mm": None, "mean_mm": None, "rms_mm": None, "p95_mm": None, "max_mm": None,
                "frac_over_1mm": None}
    return {"points": int(d.size), "median_mm": float(np.median(d)), "mean_mm": float(d.mean()),
            "rms_mm": float(np.sqrt(np.mean(d * d))), "p95_mm": float(np.percentile(d, 95)),
            "max_mm": float(d.max()), "frac_over_1mm": float(np.mean(d > over_mm))}


def sigma_stats(error_mm: np.ndarray, sigma_mm: np.ndarray) -> dict:
    """Whether predicted standard deviations mean what they say: ``median_ratio``,
    the median of |error| / sigma (a Gaussian gives 0.674), and ``beyond_3``, the
    share of points more than three of their sigmas off (0.27 %); points without a
    finite error or a sigma > 0 are left out (``points`` counts the rest)."""
    e = np.abs(np.asarray(error_mm, np.float64))
    s = np.asarray(sigma_mm, np.float64)
    m = np.isfinite(e) & np.isfinite(s) & (s > 0)
    if not m.any():
        return {"points": 0, "median_ratio": None, "beyond_3": None, "median_sigma_mm": None}
    r = e[m] / s[m]
    return {"points": int(m.sum()), "median_ratio": float(np.median(r)), "beyond_3": float(np.mean(r > 3.0)),
            "median_sigma_mm": float(np.median(s[m]))}


def ray_errors(mesh, points: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Signed error of each point along its camera ray (mm): its distance from the
    camera centre less the distance at which the ray first meets the truth (NaN
    where the ray misses it). The predicted ``sigma`` of a point is along this ray."""
    o3d = open3d_lib()
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0)
    d = pts - np.asarray(center, np.float64)
    length = np.linalg.norm(d, axis=1)
    d /= np.maximum(length, 1e-12)[:, None]
    rays = np.concatenate([np.broadcast_to(np.asarray(center, np.float64), pts.shape), d], axis=1)
    hit = _scene(mesh).cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy().astype(np.float64)
    return np.where(np.isfinite(hit), length - hit, np.nan)


def _scene(mesh):
    o3d = open3d_lib()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def point_distances(mesh, points: np.ndarray) -> np.ndarray:
    """Unsigned distance of each point to the mesh (Open3D raycasting scene)."""
    o3d = open3d_lib()
    if len(points) == 0:
        return np.zeros(0)
    q = o3d.core.Tensor(np.asarray(points, np.float32))
    return _scene(mesh).compute_distance(q).numpy().astype(np.float64)


def surface_normals(mesh, points: np.ndarray) -> np.ndarray:
    """Unit normal of the mesh triangle closest to each point."""
    o3d = open3d_lib()
    if len(points) == 0:
        return np.zeros((0, 3))
    ans = _scene(mesh).compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))
    n = ans["primitive_normals"].numpy().astype(np.float64)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def truth_points(scan: Scan, view_name: str) -> tuple[np.ndarray, np.ndarray]:
    """World points of the pixels that saw the surface lit, and their pixel index."""
    import cv2

    tv = check_truth(scan)["views"].get(view_name)
    if not tv:
        raise FormatError(scan.path, f"truth.views: no ground truth for view {view_name!r}")
    dpath = scan.folder / tv["depth"]
    check_image_header(dpath)
    depth = cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED)
    if depth is None or depth.ndim != 2 or depth.dtype != np.float32:
        raise FormatError(dpath, "cannot read truth depth (expected a single-channel float32 TIFF)")
    if depth.shape != (scan.rig.camera.height, scan.rig.camera.width):
        raise FormatError(dpath, f"truth depth is {depth.shape[1]}x{depth.shape[0]}, but the camera is "
                                 f"{scan.rig.camera.width}x{scan.rig.camera.height}")
    lit = read_image(scan.folder / tv["lit"]) > 0
    if lit.shape != depth.shape:
        raise FormatError(scan.folder / tv["lit"], f"truth lit mask is {lit.shape[1]}x{lit.shape[0]}, but the "
                                                   f"depth is {depth.shape[1]}x{depth.shape[0]}")
    ok = lit & np.isfinite(depth)
    vv, uu = np.nonzero(ok)
    cam = scan.rig.camera
    x, y = undistort_normalized(cam, uu, vv)
    z = depth[vv, uu].astype(np.float64)
    Xc = np.stack([x * z, y * z, z], -1)
    Xw = (Xc - cam.t) @ cam.R
    return Xw, vv * cam.width + uu


def light_rig(scan: Scan) -> Rig | None:
    """The scan's rig with a calibrated light for the coverage figures: its own, or,
    where its projector is ``uncalibrated`` (a two-camera scan), the light the
    virtual rig rendered with (``truth.light``, written by ``ringscan simulate``);
    None where neither is known."""
    if has_calibrated_light(scan.rig):
        return scan.rig
    li = scan.extra.get("truth", {}).get("light")
    if not isinstance(li, dict):
        return None
    return parse_rig({**rig_to_dict(scan.rig), "light": li}, source=f"{scan.path} (truth.light)")


def coverage_radius(scan: Scan) -> float:
    """Default coverage radius (mm): one band width at the object, or two camera
    pixels where that is larger; two camera pixels for a dense codec (a sample at
    every pixel: no band spacing at the object) or an unknown projector."""
    spec = scan.patterns
    cam_px = np.linalg.norm(scan.rig.camera.center) / scan.rig.camera.K[0, 0]
    rig = light_rig(scan)
    if rig is None or spec.layout.dense:
        return float(2.0 * cam_px)
    li = rig.light
    if isinstance(li, ParallelLight):
        px = li.pixel_pitch_mm
    else:
        d = np.linalg.norm(li.center - np.array([0, 0, 0.5 * (rig.volume.z_min + rig.volume.z_max)]))
        px = d / li.K[0, 0]
    return float(max(spec.pitch * px, 2.0 * cam_px))


def evaluate_view(scan: Scan, view_name: str, points: np.ndarray, *, coverage_radius_mm: float | None = None,
                  sigma: np.ndarray | None = None, return_distances: bool = False):
    """Accuracy and coverage of one view's points against the truth.

    With ``sigma`` ((n,) mm, the points' predicted standard deviations along
    camera 1's ray, the PLY's ``sigma``), ``out["sigma"]`` checks them
    (:func:`sigma_stats` of each point's error along the same ray).

    Returns the figures (dict), and with ``return_distances`` also each point's
    distance to the truth surface (mm; NaN for a point with a non-finite coordinate).

    Raises:
        ValueError: ``coverage_radius_mm`` is not a finite number > 0.
    """
    out, d, _ = _evaluate_view(scan, view_name, points, coverage_radius_mm=coverage_radius_mm, sigma=sigma)
    return (out, d) if return_distances else out


def _evaluate_view(scan: Scan, view_name: str, points: np.ndarray, *, coverage_radius_mm: float | None,
                   sigma: np.ndarray | None):
    """:func:`evaluate_view`'s (figures, distances, |error| / sigma or None)."""
    o3d = open3d_lib()
    check_coverage_radius(coverage_radius_mm)
    view = next((v for v in scan.views if v.name == view_name), None)
    if view is None:
        raise FormatError(scan.path, f"no view named {view_name!r}")
    mesh = truth_surface(scan, view.turntable_deg)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(pts), axis=1)
    d = np.full(len(pts), np.nan)
    d[finite] = point_distances(mesh, pts[finite])
    points = pts[finite]
    out = distance_stats(d)
    out["non_finite_points"] = int(np.count_nonzero(~finite))
    if sigma is not None:
        if np.size(sigma) != len(pts):
            raise ValueError(f"evaluate_view: {np.size(sigma)} sigmas for {len(pts)} points")
        cam = scan.rig.camera
        center = -np.asarray(cam.R, np.float64).T @ np.asarray(cam.t, np.float64)
        e = np.full(len(pts), np.nan)
        e[finite] = ray_errors(mesh, pts[finite], center)
        sigma = np.asarray(sigma, np.float64).reshape(-1)
        out["sigma"] = sigma_stats(e, sigma)
        ratios = np.abs(e) / np.where(sigma > 0, sigma, np.nan)
    else:
        ratios = None
    # Coverage of camera 1's lit, seen surface inside the coded annulus (the decoded
    # codec, or an unknown projector: all of camera 1's lit pixels).
    X, _ = truth_points(scan, view_name)
    spec = scan.patterns
    rig = light_rig(scan)
    # from the first sampled ring to the last (band boundaries 1..2**bits-1 of the binary
    # codecs); the decoded codec has no rings
    radii = spec.ring_radii()
    if rig is not None and radii.size:
        rho = projector_polar(rig, X, spec.center)
        lo, hi = radii[0], radii[-1]
        X = X[(rho >= lo) & (rho <= hi)]
    r = coverage_radius(scan) if coverage_radius_mm is None else float(coverage_radius_mm)
    out["coverage_radius_mm"] = r
    if len(X) and len(points):
        tp = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(X))
        rp = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
        dn = np.asarray(tp.compute_point_cloud_distance(rp))
        if rig is not None:
            light_dir = light_directions(rig, X)
            cos_t = np.abs(np.sum(surface_normals(mesh, X) * light_dir, axis=1))
        else:
            cos_t = np.ones(len(X))  # the light's direction unknown: no allowance for slopes
        near = dn <= r / np.maximum(cos_t, 0.25)
        tr = scan.extra["truth"]
        obj = np.abs(X[:, 2] - check_truth(scan)["reference_plane_z"]) > 0.5
        if isinstance(tr.get("wall_z"), (int, float)):          # a simulated wall is not the object
            obj &= np.abs(X[:, 2] - float(tr["wall_z"])) > 0.5
        out["coverage"] = float(near.mean())
        out["coverage_object"] = float(near[obj].mean()) if obj.any() else None
    else:
        out["coverage"] = 0.0 if len(X) else None
        out["coverage_object"] = None
    out["truth_pixels"] = int(len(X))
    return out, d, ratios


def check_coverage_radius(r: float | None) -> None:
    """None (the default radius) or a finite number of mm > 0; else ValueError."""
    if r is None:
        return
    if isinstance(r, bool) or not isinstance(r, (int, float, np.integer, np.floating)) or not math.isfinite(r) \
            or r <= 0:
        raise ValueError(f"coverage radius: expected a finite number of mm > 0, got {r!r}")


def _recon_views(p: Path) -> list[tuple[str, Path]]:
    """(view name, PLY) of each view of a reconstruction folder's report.json."""
    rpath = p / "report.json"
    rep = read_json(rpath)
    views = rep.get("views")
    if not isinstance(views, list):
        raise FormatError(rpath, "views: expected a list")
    items = []
    for i, v in enumerate(views):
        if not isinstance(v, dict) or not isinstance(v.get("name"), str) or not isinstance(v.get("ply"), str):
            raise FormatError(rpath, f"views[{i}]: expected an object with a name and a ply")
        items.append((v["name"], p / v["ply"]))
    return items


def _ply_points(ply_path: Path, ply: dict | None = None) -> np.ndarray:
    ply = read_ply(ply_path) if ply is None else ply
    missing = [k for k in ("x", "y", "z") if k not in ply]
    if missing:
        raise FormatError(ply_path, f"vertex property {missing[0]!r} missing")
    return np.stack([ply["x"], ply["y"], ply["z"]], -1).astype(np.float64)


def evaluate_against_mesh(cloud_or_dir: str | os.PathLike, truth_mesh, *, return_distances: bool = False):
    """Distances of a reconstruction's points to a truth mesh in the same frame.

    For a cloud and a mesh that share a frame (a fused cloud and its object, or a
    real scan and a CAD model aligned to it): point-to-surface distances only, no
    coverage (a bare mesh says nothing about which pixels saw it). A simulated scan
    folder as the truth (:func:`evaluate_recon`) also gives the coverage and places
    the object at each view's table angle.

    Args:
        cloud_or_dir: a reconstruction folder (report.json + PLYs) or one PLY.
        truth_mesh: an ``o3d.geometry.TriangleMesh`` or a mesh file (PLY/OBJ/STL).
        return_distances: also return each view's point distances ({name: (N,) mm, NaN
            for a non-finite point}).
    """
    mesh = read_mesh(truth_mesh) if isinstance(truth_mesh, (str, os.PathLike)) else truth_mesh
    p = Path(cloud_or_dir)
    items = _recon_views(p) if p.is_dir() else [(p.stem, p)]
    result = {"views": {}}
    all_d = []
    dists = {}
    for name, ply_path in items:
        pts = _ply_points(ply_path)
        finite = np.all(np.isfinite(pts), axis=1)
        d = np.full(len(pts), np.nan)
        d[finite] = point_distances(mesh, pts[finite])
        result["views"][name] = {**distance_stats(d), "non_finite_points": int((~finite).sum()), "coverage": None}
        all_d.append(d)
        dists[name] = d
    result["all"] = distance_stats(np.concatenate(all_d) if all_d else np.zeros(0))
    result["all"]["non_finite_points"] = sum(v["non_finite_points"] for v in result["views"].values())
    result["all"]["coverage_mean"] = None
    return (result, dists) if return_distances else result


def evaluate_recon(cloud_or_dir: str | os.PathLike, truth_scan: str | os.PathLike | Scan, *,
                   coverage_radius_mm: float | None = None, return_distances: bool = False):
    """Evaluate a reconstruction folder (report.json + PLYs) or one view's PLY.

    Returns the figures (dict), and with ``return_distances`` also each view's point
    distances to its truth surface ({name: (N,) mm, NaN for a non-finite point}).
    """
    check_coverage_radius(coverage_radius_mm)
    scan = truth_scan if isinstance(truth_scan, Scan) else load_scan(truth_scan, check_files=False)
    check_truth(scan)
    p = Path(cloud_or_dir)
    items = []
    if p.is_dir():
        items = _recon_views(p)
    else:
        ply = read_ply(p)
        vi = int(ply["view"][0]) if "view" in ply and len(ply["view"]) else 0
        if not 0 <= vi < len(scan.views):
            raise FormatError(p, f"its points are of view {vi}, but {scan.path} has {len(scan.views)} view(s)")
        items.append((scan.views[vi].name, p))

    def views():
        for name, ply_path in items:
            ply = read_ply(ply_path)
            sigma = np.asarray(ply["sigma"], np.float64) if "sigma" in ply else None
            yield name, _ply_points(ply_path, ply), sigma

    return evaluate_points(scan, views(), coverage_radius_mm=coverage_radius_mm, return_distances=return_distances)


def evaluate_points(scan: Scan, views, *, coverage_radius_mm: float | None = None, return_distances: bool = False):
    """:func:`evaluate_recon`'s figures of views' points held in memory.

    Args:
        scan: the simulated scan whose truth the points are measured against.
        views: (view name, (N, 3) world points, (N,) sigma mm or None) for each view.

    Returns:
        As :func:`evaluate_recon`: the figures, per view and for ``all`` views (and with
        ``return_distances`` each view's point distances).
    """
    check_coverage_radius(coverage_radius_mm)
    check_truth(scan)
    result = {"views": {}}
    all_d = []
    dists = {}
    ratios, sigmas = [], []
    for name, pts, sigma in views:
        result["views"][name], d, r = _evaluate_view(scan, name, pts, coverage_radius_mm=coverage_radius_mm,
                                                     sigma=sigma)
        if r is not None:
            ratios.append(r)
            sigmas.append(sigma)
        all_d.append(d)
        dists[name] = d
    result["all"] = distance_stats(np.concatenate(all_d) if all_d else np.zeros(0))
    result["all"]["non_finite_points"] = sum(v["non_finite_points"] for v in result["views"].values())
    if ratios:
        # the ratios already carry each point's sigma: pooled with sigma 1
        r = np.concatenate(ratios)
        result["all"]["sigma"] = sigma_stats(r, np.ones(r.size))
        s = np.concatenate(sigmas)
        result["all"]["sigma"]["median_sigma_mm"] = float(np.median(s[np.isfinite(r)])) if np.isfinite(r).any() \
            else None
    covs = [v["coverage"] for v in result["views"].values() if v.get("coverage") is not None]
    result["all"]["coverage_mean"] = float(np.mean(covs)) if covs else None
    return (result, dists) if return_distances else result


def truth_rho_at(scan: Scan, view_name: str, uv: np.ndarray, *, max_step_mm: float = 0.5) -> np.ndarray:
    """Ring radius (projector px) of the truth surface at sub-pixel camera positions.

    The truth world points of the four pixel centres around each position (from
    the virtual rig's depth map) are interpolated bilinearly and projected onto the
    pattern. NaN where a neighbour saw nothing or the four points are more than
    ``max_step_mm`` apart (a depth edge): there the truth is not smooth enough to
    judge a label. Used to count mislabelled ring samples (a sample of ring k whose
    truth radius is nearer another ring).
    """

    cam = scan.rig.camera
    w, h = cam.width, cam.height
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    X, pix = truth_points(scan, view_name)
    grid = np.full((h * w, 3), np.nan)
    grid[pix] = X
    x0 = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, h - 2)
    fx = (uv[:, 0] - x0)[:, None]
    fy = (uv[:, 1] - y0)[:, None]
    p00, p10 = grid[y0 * w + x0], grid[y0 * w + x0 + 1]
    p01, p11 = grid[(y0 + 1) * w + x0], grid[(y0 + 1) * w + x0 + 1]
    Xi = (1 - fy) * ((1 - fx) * p00 + fx * p10) + fy * ((1 - fx) * p01 + fx * p11)
    corners = np.stack([p00, p10, p01, p11], 1)
    spread = np.max(np.linalg.norm(corners - corners.mean(1, keepdims=True), axis=2), axis=1)
    ok = np.isfinite(spread) & (spread <= max_step_mm)
    rho = np.full(uv.shape[0], np.nan)
    if ok.any():
        rho[ok] = projector_polar(scan.rig, Xi[ok], scan.patterns.center)
    return rho
