"""Flip and rescan: accuracy of several poses fused into one object (virtual rig).

The virtual rig's light is parallel to the turntable axis, so lighting does not
change with the turntable angle: a surface point unlit at angle 0 is never lit, and
one turntable scan covers only the upward-facing surface. This benchmark simulates
a mesh (default: Keenan Crane's Spot from ../shared/data/models) in several resting
poses (default ``upright``, ``tetra-1``, ``tetra-2``, ``tetra-3``), each an N-view turntable
scan, reconstructs and fuses each pose, aligns the poses to the first one
(FPFH + RANSAC, then ICP; :func:`ringscan.pipeline.fusion.poses.fuse_poses`), meshes
(Poisson) and measures against the *whole* truth mesh of the first pose:

- mesh -> truth and truth -> mesh mean distance, and the fraction of the truth
  surface within 0.5 mm of the mesh, for the first 1, 2, ... poses;
- each pose's recovered transform against the known one (the simulator writes the
  pose transform into scan.json ``truth.pose``).

Usage::

    python benchmarks/multipose_accuracy.py [--model PATH] [--views 8]
        [--poses upright,upside-down,side-x] [--work DIR] [--device cpu] [--json OUT.json]

Takes ~1 min per pose on a 2-core CPU at 8 views (simulation ~40 s, reconstruction
~15 s), then ~30 s per fusion + Poisson.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = REPO.parent / "shared" / "data" / "models" / "odedstein_spot.obj"
DEFAULT_POSES = "upright,tetra-1,tetra-2,tetra-3"


def _rot_err_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(R) - 1.0) / 2.0))))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=str(DEFAULT_MODEL), help="mesh file or scene name (default: Spot)")
    ap.add_argument("--size-mm", type=float, default=80.0, help="longest side of the object (default 80)")
    ap.add_argument("--views", type=int, default=8, help="turntable views per pose (default 8)")
    ap.add_argument("--poses", default=DEFAULT_POSES, help=f"comma-separated poses ';'-free (default {DEFAULT_POSES}); "
                                                           "general specs AXIS:DEG use '+' between turns")
    ap.add_argument("--work", default=None, help="work folder (default: a temporary one); existing scans and "
                                                 "reconstructions there are reused")
    ap.add_argument("--device", default=None, help="Warp device for simulation and reconstruction")
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args(argv)

    from ringscan.pipeline.formats.atomic import read_json
    from ringscan.pipeline.formats.meshes import read_mesh
    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.fusion.mesh import MeshSettings, compare_to_truth
    from ringscan.pipeline.fusion.poses import AlignmentError, PoseSettings, fuse_poses
    from ringscan.pipeline.fusion.turntable import FuseSettings, fuse_views
    from ringscan.pipeline.fusion.meshing import mesh_cloud
    from ringscan.pipeline.fusion.recon import load_recon
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan
    from ringscan.pipeline.simulate.scan import simulate_scan

    poses = [p.strip().replace("+", ",") for p in args.poses.split(",") if p.strip()]
    work = Path(args.work or tempfile.mkdtemp(prefix="ringscan-multipose-"))
    if str(args.model) == str(DEFAULT_MODEL) and not DEFAULT_MODEL.is_file():
        print(f"model {DEFAULT_MODEL} not found (../shared/data); pass --model", file=sys.stderr)
        return 2
    spec = parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 6})
    fs = FuseSettings()
    fused, truths, pose_T, times = [], [], [], []
    for k, pose in enumerate(poses):
        scan_dir = work / f"scan_{k}"
        recon_dir = work / f"recon_{k}"
        t0 = time.perf_counter()
        if not (scan_dir / "scan.json").is_file():
            simulate_scan(scan_dir, scene=args.model, patterns=spec, views=args.views, device=args.device,
                          progress=False, size_mm=args.size_mm, pose=pose)
        t1 = time.perf_counter()
        if not (recon_dir / "report.json").is_file():
            reconstruct_scan(scan_dir, recon_dir, device=args.device, progress=False)
        t2 = time.perf_counter()
        views, rig, _ = load_recon(recon_dir)
        fused.append(fuse_views(views, rig, settings=fs))
        t3 = time.perf_counter()
        tj = read_json(scan_dir / "scan.json")["truth"]
        truths.append(read_mesh(scan_dir / tj["mesh"]))
        pose_T.append(np.asarray(tj["pose"]["transform"], float))
        times.append((t1 - t0, t2 - t1, t3 - t2))
        print(f"pose {k} {pose}: simulate {t1 - t0:.0f} s, reconstruct {t2 - t1:.0f} s, fuse {t3 - t2:.0f} s, "
              f"{len(fused[-1].cloud.points)} points", flush=True)

    truth = truths[0]
    results = {}
    ps = PoseSettings()
    failed = {}
    for n in range(1, len(poses) + 1):
        t = time.perf_counter()
        try:
            mp = fuse_poses(fused[:n], names=poses[:n], settings=ps)
        except AlignmentError as e:
            # e.g. upright + upside-down alone: under a light along the axis they share
            # almost no lit surface; a side pose links them.
            failed["+".join(poses[:n])] = str(e)
            continue
        m = mesh_cloud(mp.cloud, settings=MeshSettings())
        f = compare_to_truth(m.mesh, truth, samples=300_000, within_mm=0.5)
        f["seconds"] = round(time.perf_counter() - t, 1)
        f["poses"] = []
        for i, r in enumerate(mp.registrations):
            known = pose_T[0] @ np.linalg.inv(pose_T[i])      # pose i's frame -> pose 0's frame
            dT = np.linalg.inv(known) @ r.transform
            c = np.asarray(fused[i].cloud.points).mean(axis=0)  # error measured at the pose's centroid
            f["poses"].append({"name": r.name, "fitness": r.fitness, "inlier_rmse_mm": r.inlier_rmse_mm,
                               "plane_rmse_mm": r.plane_rmse_mm, "fitness_to_reference": r.fitness_to_reference,
                               "aligned_with": r.aligned_with,
                               "rotation_error_deg": _rot_err_deg(dT[:3, :3]),
                               "translation_error_mm": float(np.linalg.norm(
                                   (r.transform[:3, :3] - known[:3, :3]) @ c + r.transform[:3, 3] - known[:3, 3]))})
        results["+".join(poses[:n])] = f

    print(f"model {args.model}, {args.views} views per pose, poses {', '.join(poses)}; against the whole truth "
          f"mesh of pose 0")
    print(f"{'poses':<40}{'mesh->T':>9}{'T->mesh':>9}{'T<=0.5':>9}{'T->m p95':>10}{'s':>6}")
    for name, f in results.items():
        print(f"{name:<40}{f['mesh_to_truth_mean']:>9.4f}{f['truth_to_mesh_mean']:>9.4f}"
              f"{100 * f['truth_within']:>8.2f}%{f['truth_to_mesh_p95']:>10.4f}{f['seconds']:>6.0f}")
    for name, why in failed.items():
        print(f"{name:<40}does not align: {why}")
    print("pose alignment (all poses) against the known transforms:")
    for p in list(results.values())[-1]["poses"][1:]:
        print(f"  {p['name']:<20} fitness {p['fitness']:.3f} (to pose 0 {p['fitness_to_reference']:.3f}), "
              f"point-to-plane rmse {p['plane_rmse_mm']:.4f} mm, via {p['aligned_with']}, "
              f"rotation error {p['rotation_error_deg']:.4f} deg, translation error {p['translation_error_mm']:.4f} mm")
    if args.json:
        from ringscan.pipeline.formats.atomic import atomic_write_json

        atomic_write_json(args.json, {"model": str(args.model), "views": args.views, "poses": poses,
                                      "results": results, "failed": failed})
    print(f"work folder: {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
