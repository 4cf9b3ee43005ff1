"""``ringscan demo``: the whole chain on an embedded default scene.

Simulates a turntable scan with the virtual rig (default rig: 1280x1024 camera,
parallel light, gray-rings 7 bits at a pitch of 4 px with 9 sector bits and the angle code),
reconstructs every view, measures the points against the ground truth, fuses the
views, meshes them and writes a preview PNG.
"""

from __future__ import annotations

import json
import logging
import time

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.atomic import atomic_write_json, check_output_folder
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.fusion.workflow import fuse_and_mesh
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.tools.cli import UsageError, add_device_option

log = logging.getLogger(__name__)

DEMO_PATTERNS = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                 "rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 9,
                 "angle_steps": 4, "angle_period": 8.0}  # gray-rings' defaults (docs/dense.md, "How sharp")


def add_parser(sub):
    p = sub.add_parser("demo", help="simulate, reconstruct, evaluate, fuse, mesh and preview a default scan",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--scene", default="sphere", help="procedural scene or mesh file (default sphere)")
    p.add_argument("--views", type=int, default=8, help="turntable views (default 8)")
    p.add_argument("--size-mm", type=float, default=80.0, metavar="MM",
                   help="longest side of the object in mm (default 80)")
    add_device_option(p)
    return p


def run(args) -> int:

    if args.views < 1:
        raise UsageError("--views must be at least 1")
    out = check_output_folder(args.out, what="demo's output folder (--out)")
    t0 = time.perf_counter()
    spec = parse_patterns(DEMO_PATTERNS)
    print(f"[1/4] simulating {args.views} view(s) of '{args.scene}' with the virtual rig -> {out / 'scan'}")
    scan = simulate_scan(out / "scan", scene=args.scene, patterns=spec, views=args.views, device=args.device,
                         size_mm=args.size_mm, progress=not args.no_progress)
    print(f"[2/4] reconstructing -> {out / 'recon'}")
    rep = reconstruct_scan(scan, out / "recon", device=args.device, progress=not args.no_progress)
    tot = rep["totals"]
    print(f"      {tot['samples']} ring samples -> {tot['points']} points; dropped {json.dumps(tot['dropped'])}")
    print("[3/4] evaluating against the ground truth")
    with progress_step("evaluating", enabled=not args.no_progress):
        ev = evaluate_recon(out / "recon", scan)
    atomic_write_json(out / "evaluation.json", ev)
    a = ev["all"]
    print(f"      median {a['median_mm']:.4f} mm, RMS {a['rms_mm']:.4f} mm, p95 {a['p95_mm']:.4f} mm, "
          f"{100 * a['frac_over_1mm']:.3f} % over 1 mm, coverage {100 * a['coverage_mean']:.1f} %")
    print(f"[4/4] fusing the views and meshing -> {out / 'model'}")
    fr = fuse_and_mesh(out / "recon", out / "model", formats=(".ply", ".obj", ".stl"), preview=True, truth=scan.folder,
                       device=args.device, progress=not args.no_progress)
    truth = fr.get("truth") or {}
    if "mesh_to_truth_mean" in truth:
        print(f"      mesh -> truth surface: mean {truth['mesh_to_truth_mean']:.4f} mm, "
              f"p95 {truth['mesh_to_truth_p95']:.4f} mm (the light never reaches the underside, so the "
              f"truth -> mesh figures in model/fuse_report.json count it as missing)")
    print(f"done in {time.perf_counter() - t0:.0f} s:")
    for name in ("model/preview.png", "model/mesh.ply", "model/mesh.obj", "model/mesh.stl", "model/fused.ply",
                 "recon/report.json", "evaluation.json"):
        if (out / name).exists():
            print(f"  {out / name}")
    return 0
