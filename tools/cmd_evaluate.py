"""``ringscan evaluate CLOUD --truth MESH_OR_SCAN``: accuracy against the virtual rig's truth (or a mesh)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ringscan.pipeline.evaluate.metrics import evaluate_against_mesh, evaluate_recon
from ringscan.pipeline.formats.atomic import atomic_write_json, check_no_overwrite, check_output_file
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.preview.plots import PLOT_FORMATS, error_histogram_figure, save_figure
from ringscan.tools.cli import UsageError, basic_options


def add_parser(sub):
    p = sub.add_parser("evaluate", help="point-to-surface error and coverage against ground truth",
                       description="CLOUD is a reconstruction folder (report.json + PLYs) or one PLY. The truth "
                                   "is a simulated scan folder (its truth/: each view's object placed at its "
                                   "table angle, and the coverage), or a mesh in the cloud's frame (distances "
                                   "only).")
    p.add_argument("cloud", help="reconstruction folder or PLY")
    p.add_argument("--truth", required=True, metavar="MESH_OR_SCAN",
                   help="a simulated scan folder (with truth/) or a truth mesh file (PLY/OBJ/STL)")
    p.add_argument("--coverage-radius", type=float, default=None, metavar="MM",
                   help="a truth pixel is covered when a point lies within this distance, mm (default: one band "
                        "width; scan-folder truth only)")
    p.add_argument("--report", default=None, metavar="JSON", help="also write the figures to this JSON file")
    p.add_argument("--json", dest="report", help=argparse.SUPPRESS)  # the old spelling (calibrate says --report)
    p.add_argument("--plot", default=None, metavar="PNG_OR_SVG",
                   help="also draw the histogram of the point-to-surface distances (all points, each view, the "
                        "median and p95) into this PNG or SVG file")
    basic_options(p, "--coverage-radius", "--report", "--plot")
    return p


def _fmt(x, scale=1.0, unit=""):
    return "-" if x is None else f"{x * scale:.4f}{unit}"


def run(args) -> int:
    r = args.coverage_radius
    if r is not None and not (r > 0 and r != float("inf")):
        raise UsageError(f"--coverage-radius: expected a finite number of mm > 0, got {r}")
    if args.plot:
        check_output_file(args.plot, extensions=PLOT_FORMATS, what="plot (--plot)")
    if args.report:
        out = check_output_file(args.report, what="JSON file (--report)")
        cloud = Path(args.cloud)
        inputs = [cloud / "report.json", *cloud.glob("*.ply")] if cloud.is_dir() else [cloud]
        truth_inputs = [Path(args.truth) / "scan.json"] if Path(args.truth).is_dir() else [Path(args.truth)]
        check_no_overwrite([out], [*inputs, *truth_inputs])
    if Path(args.truth).is_dir():
        with progress_step("evaluating against the scan's truth", enabled=not args.no_progress):
            res, dists = evaluate_recon(args.cloud, args.truth, coverage_radius_mm=args.coverage_radius,
                                        return_distances=True)
    else:
        with progress_step("evaluating against the truth mesh", enabled=not args.no_progress):
            res, dists = evaluate_against_mesh(args.cloud, args.truth, return_distances=True)
    print(f"{'view':<12}{'points':>9}{'median mm':>11}{'rms mm':>9}{'p95 mm':>9}{'>1mm %':>8}{'cover %':>9}{'object %':>9}")
    for name, v in res["views"].items():
        print(f"{name:<12}{v['points']:>9}{_fmt(v['median_mm']):>11}{_fmt(v['rms_mm']):>9}{_fmt(v['p95_mm']):>9}"
              f"{_fmt(v['frac_over_1mm'], 100):>8}{_fmt(v.get('coverage'), 100):>9}{_fmt(v.get('coverage_object'), 100):>9}")
    a = res["all"]
    print(f"{'all':<12}{a['points']:>9}{_fmt(a['median_mm']):>11}{_fmt(a['rms_mm']):>9}{_fmt(a['p95_mm']):>9}"
          f"{_fmt(a['frac_over_1mm'], 100):>8}{_fmt(a.get('coverage_mean'), 100):>9}")
    sg = a.get("sigma")
    if sg and sg["points"]:
        print(f"predicted sigma (along the camera ray, median {sg['median_sigma_mm']:.4f} mm): median |error|/sigma "
              f"{sg['median_ratio']:.2f} (a Gaussian: 0.67), {100 * sg['beyond_3']:.1f} % beyond 3 sigma (0.3 %)")
    if a["non_finite_points"]:
        print(f"left out {a['non_finite_points']} point(s) with a NaN or infinite coordinate")
    if args.report:
        atomic_write_json(args.report, res)
    if args.plot:
        save_figure(error_histogram_figure(dists, title=f"{Path(args.cloud).name}: distance to the truth"), args.plot)
        print(f"wrote {args.plot}")
    return 0
