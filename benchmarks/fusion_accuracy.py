"""Fusion and meshing accuracy on the virtual rig (issue 5's figures).

Simulates an 8-view turntable scan of a mesh (default: Keenan Crane's Spot from
../shared/data/models), reconstructs it, fuses and meshes it, and measures the mesh
against the placed truth mesh (``truth/object.ply``, object frame):

- mesh -> truth and truth -> mesh mean distance (chamfer, both ways), and the
  fraction of the truth surface within 0.5 mm of the mesh;
- the same against the *observed* truth: the surface points that some view's
  camera saw lit by the projector (truth depth + lit masks), above the 0.5 mm
  ground clip. A parallel light along z never lights vertical or downward-facing
  surfaces, whatever the turntable angle, so the rest of the truth cannot be
  measured by this rig;
- all of it again with the rig's turntable axis wrong by 0.5 degrees and 1 mm,
  with and without the ICP / pose-graph refinement.

Usage::

    python benchmarks/fusion_accuracy.py [--model PATH|sphere|cube|terrain] [--views 8]
        [--work DIR] [--scan EXISTING_SCAN] [--device cpu] [--json OUT.json]

Takes a few minutes on the CPU (simulation ~1 min, each fusion + Poisson ~20 s).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = REPO.parent / "shared" / "data" / "models" / "odedstein_spot.obj"


def observed_truth(scan, ground_clip_mm: float) -> np.ndarray:
    """Object-frame truth points that some view saw lit (above the ground clip)."""
    from ringscan.pipeline.evaluate.metrics import truth_points
    from ringscan.pipeline.formats.rig import turntable_transform

    pts = []
    for v in scan.views:
        Xw, _ = truth_points(scan, v.name)
        Xw = Xw[Xw[:, 2] >= ground_clip_mm]
        T = turntable_transform(scan.rig.turntable, -v.turntable_deg)
        pts.append(Xw @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(pts)


def measure(mesh, truth, seen: np.ndarray, cloud=None) -> dict:
    import open3d as o3d

    from ringscan.pipeline.fusion.mesh import compare_to_truth

    f = compare_to_truth(mesh, truth, samples=300_000, within_mm=0.5)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    rng = np.random.default_rng(0)
    sub = seen[rng.choice(len(seen), min(len(seen), 300_000), replace=False)]
    d = scene.compute_distance(o3d.core.Tensor(sub.astype(np.float32))).numpy()
    f["seen_to_mesh_mean"] = float(d.mean())
    f["seen_within"] = float(np.mean(d <= 0.5))
    if cloud is not None:
        ts = o3d.t.geometry.RaycastingScene()
        ts.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(truth))
        dc = ts.compute_distance(o3d.core.Tensor(np.asarray(cloud.points, np.float32))).numpy()
        f["cloud_to_truth_mean"] = float(dc.mean())
    return f


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=str(DEFAULT_MODEL), help="mesh file or scene name (default: Spot)")
    ap.add_argument("--size-mm", type=float, default=80.0, help="longest side of the object (default 80)")
    ap.add_argument("--views", type=int, default=8, help="turntable views (default 8)")
    ap.add_argument("--work", default=None, help="work folder (default: a temporary one)")
    ap.add_argument("--scan", default=None, help="use this simulated scan instead of simulating one")
    ap.add_argument("--device", default=None, help="Warp device for simulation and reconstruction")
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args(argv)

    from ringscan.pipeline.formats.meshes import read_mesh
    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.formats.rig import Turntable
    from ringscan.pipeline.formats.scan import load_scan
    from ringscan.pipeline.fusion.mesh import MeshSettings
    from ringscan.pipeline.fusion.turntable import FuseSettings, fuse_views
    from ringscan.pipeline.fusion.meshing import mesh_fused
    from ringscan.pipeline.fusion.recon import load_recon
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan
    from ringscan.pipeline.simulate.scan import simulate_scan

    work = Path(args.work or tempfile.mkdtemp(prefix="ringscan-fusion-"))
    t0 = time.perf_counter()
    if args.scan:
        scan_dir = Path(args.scan)
    else:
        scan_dir = work / "scan"
        if str(args.model) == str(DEFAULT_MODEL) and not DEFAULT_MODEL.is_file():
            print(f"model {DEFAULT_MODEL} not found (../shared/data); pass --model", file=sys.stderr)
            return 2
        spec = parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                               "rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 6})
        simulate_scan(scan_dir, scene=args.model, patterns=spec, views=args.views, device=args.device,
                      progress=False, size_mm=args.size_mm)
    t_sim = time.perf_counter() - t0
    recon_dir = work / "recon"
    t = time.perf_counter()
    reconstruct_scan(scan_dir, recon_dir, device=args.device, progress=False)
    t_rec = time.perf_counter() - t
    scan = load_scan(scan_dir)
    truth = read_mesh(scan_dir / scan.extra["truth"]["mesh"])
    fs = FuseSettings()
    seen = observed_truth(scan, fs.ground_clip_mm)
    views, rig, _ = load_recon(recon_dir)
    a = math.radians(0.5)
    tt = rig.turntable
    ex = np.cross(tt.axis_dir, [0.0, 1.0, 0.0] if abs(tt.axis_dir[1]) < 0.9 else [1.0, 0.0, 0.0])
    ex /= np.linalg.norm(ex)
    wrong = dataclasses.replace(rig, turntable=Turntable(axis_point=tt.axis_point + 1.0 * ex,
                                                         axis_dir=math.cos(a) * tt.axis_dir + math.sin(a) * ex))
    cases = [("right axis", rig, fs, MeshSettings()),
             ("wrong axis, refined", wrong, fs, MeshSettings()),
             ("wrong axis, not refined", wrong, dataclasses.replace(fs, refine=False), MeshSettings()),
             ("right axis, watertight", rig, fs, MeshSettings(watertight=True)),
             ("right axis, TSDF", rig, fs, MeshSettings(method="tsdf"))]
    results = {}
    for name, r, s, ms in cases:
        t = time.perf_counter()
        fused = fuse_views(views, r, settings=s)
        m = mesh_fused(fused, settings=ms)
        f = measure(m.mesh, truth, seen, fused.cloud)
        f["seconds"] = round(time.perf_counter() - t, 1)
        f["max_correction_mm"] = max(v.correction_mm for v in fused.residuals)
        if ms.watertight:
            f["watertight"] = m.watertight
        results[name] = f
    print(f"model {args.model}, {len(views)} views; simulate {t_sim:.0f} s, reconstruct {t_rec:.0f} s; "
          f"observed truth: {len(seen)} points")
    hdr = (f"{'case':<26}{'cloud->T':>9}{'mesh->T':>9}{'T->mesh':>9}{'T<=0.5':>8}{'seen->m':>9}{'seen<=0.5':>10}"
           f"{'corr mm':>9}{'s':>6}")
    print(hdr)
    for name, f in results.items():
        print(f"{name:<26}{f['cloud_to_truth_mean']:>9.4f}{f['mesh_to_truth_mean']:>9.4f}"
              f"{f['truth_to_mesh_mean']:>9.4f}{100 * f['truth_within']:>7.2f}%{f['seen_to_mesh_mean']:>9.4f}"
              f"{100 * f['seen_within']:>9.2f}%{f['max_correction_mm']:>9.3f}{f['seconds']:>6.0f}"
              + (f"  watertight {f['watertight']}" if "watertight" in f else ""))
    r0, r1 = results["right axis"], results["wrong axis, refined"]
    print("wrong/right axis ratio (refined): mesh->truth "
          f"{r1['mesh_to_truth_mean'] / r0['mesh_to_truth_mean']:.2f}, seen->mesh "
          f"{r1['seen_to_mesh_mean'] / r0['seen_to_mesh_mean']:.2f}")
    if args.json:
        from ringscan.pipeline.formats.atomic import atomic_write_json

        atomic_write_json(args.json, {"model": str(args.model), "views": len(views), "results": results})
    print(f"work folder: {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
