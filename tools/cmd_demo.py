"""``ringscan demo``: the whole chain on the object the package ships.

Simulates a turntable scan of Spot the cow (Keenan Crane, public domain; 80 mm long) with
the virtual rig (default rig: 1280x1024 camera, parallel light, gray-rings 7 bits at a pitch
of 4 px with 9 sector bits and the angle code), reconstructs every view, measures the points
against the ground truth, fuses the views, meshes them and writes a shaded preview PNG with a
scale bar.
"""

from __future__ import annotations

import json
import logging
import time

from ringscan.pipeline.codecs import DEFAULT_CODEC
from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.atomic import atomic_write_json, check_output_folder
from ringscan.pipeline.formats.patterns import CODEC_DEFAULTS, parse_patterns
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.fusion.workflow import fuse_and_mesh
from ringscan.pipeline.preview.render import ViewSettings
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.tools.cli import UsageError, add_device_option, basic_options

log = logging.getLogger(__name__)

DEMO_PATTERNS = {"codec": DEFAULT_CODEC, "width": 1024, "height": 768, "center": [511.5, 383.5],
                 **CODEC_DEFAULTS[DEFAULT_CODEC]}  # the default codec's defaults (docs/dense.md, "How sharp")
DEMO_SCENE = "spot"
"""The demo's default object: the mesh the package ships (pipeline/simulate/data/spot.obj, with its licence)."""
DEMO_VIEW = ViewSettings(azimuth_deg=-30.0, elevation_deg=25.0)
"""The preview's view: Spot in three-quarter view, 25 degrees above (head, ears, back and legs in sight)."""
DEMO_KERNELS = ("raytrace", "ring_labels", "ring_sampling", "angle", "sample_light", "compact", "error_terms",
                "calibration_floor", "triangulation", "point_filter")
"""The Warp modules of ringscan.kernels a demo run launches (what Warp compiled into an empty kernel cache,
2026-12-07)."""
COLD_COMPILE_S = 10
"""What compiling them adds to a demo run on the 2-core development machine, measured: 60 s from an
empty kernel cache against 53 s with it filled (docs/demo.md); a first run announces it."""


def add_parser(sub):
    p = sub.add_parser("demo", help="simulate, reconstruct, evaluate, fuse, mesh and preview a default scan",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--scene", default=DEMO_SCENE,
                   help=f"spot (the shipped mesh), a procedural scene (sphere, cube, terrain) or a mesh file "
                        f"(default {DEMO_SCENE}: Spot the cow, public domain)")
    p.add_argument("--views", type=int, default=6, help="turntable views, every 360/N degrees (default 6)")
    p.add_argument("--size-mm", type=float, default=80.0, metavar="MM",
                   help="longest side of the object in mm (default 80)")
    add_device_option(p)
    basic_options(p, "--scene", "--views", "--size-mm")
    return p


def run(args) -> int:

    if args.views < 1:
        raise UsageError("--views must be at least 1")
    out = check_output_folder(args.out, what="demo's output folder (--out)")
    t0 = time.perf_counter()
    spec = parse_patterns(DEMO_PATTERNS)
    _announce_kernel_compile(args.device)
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
                       device=args.device, progress=not args.no_progress, preview_scale_bar=True,
                       preview_view=DEMO_VIEW)
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


def _announce_kernel_compile(device) -> None:
    """One line before a first run's Warp compile (a fresh machine, a new Warp or changed kernels):
    it is silent and takes half a minute on two cores; later runs load the kernels from Warp's cache."""
    from ringscan.kernels.runtime import resolve_device, uncached_kernel_modules

    try:
        resolved = resolve_device(device)
    except ValueError as e:
        raise UsageError(str(e)) from None
    cold = uncached_kernel_modules(resolved, DEMO_KERNELS)
    if not cold:
        return
    import warp as wp

    where = "the CPU" if resolved == "cpu" else resolved
    print(f"[0/4] first run: compiling {len(cold)} Warp kernel module(s) for {where} as they are first used "
          f"(about {COLD_COMPILE_S} s on 2 CPU cores, once: later runs load them from {wp.config.kernel_cache_dir})",
          flush=True)
