"""``ringscan evaluate CLOUD --truth SCAN``: accuracy against the virtual rig's truth."""

from __future__ import annotations

from pathlib import Path

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.atomic import atomic_write_json, check_no_overwrite, check_output_file


def add_parser(sub):
    p = sub.add_parser("evaluate", help="point-to-surface error and coverage against ground truth",
                       description="CLOUD is a reconstruction folder (report.json + PLYs) or one view's PLY; "
                                   "SCAN is the simulated scan with its truth/.")
    p.add_argument("cloud", help="reconstruction folder or PLY")
    p.add_argument("--truth", required=True, help="simulated scan folder (with truth)")
    p.add_argument("--coverage-radius", type=float, default=None, help="mm (default: one band width)")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    return p


def _fmt(x, scale=1.0, unit=""):
    return "-" if x is None else f"{x * scale:.4f}{unit}"


def run(args) -> int:
    r = args.coverage_radius
    if r is not None and not (r > 0 and r != float("inf")):
        raise ValueError(f"--coverage-radius: expected a finite number of mm > 0, got {r}")
    if args.json:
        out = check_output_file(args.json, what="JSON file (--json)")
        cloud = Path(args.cloud)
        inputs = [cloud / "report.json", *cloud.glob("*.ply")] if cloud.is_dir() else [cloud]
        check_no_overwrite([out], [*inputs, Path(args.truth) / "scan.json"])
    res = evaluate_recon(args.cloud, args.truth, coverage_radius_mm=args.coverage_radius)
    print(f"{'view':<12}{'points':>9}{'median mm':>11}{'rms mm':>9}{'p95 mm':>9}{'>1mm %':>8}{'cover %':>9}{'object %':>9}")
    for name, v in res["views"].items():
        print(f"{name:<12}{v['points']:>9}{_fmt(v['median_mm']):>11}{_fmt(v['rms_mm']):>9}{_fmt(v['p95_mm']):>9}"
              f"{_fmt(v['frac_over_1mm'], 100):>8}{_fmt(v.get('coverage'), 100):>9}{_fmt(v.get('coverage_object'), 100):>9}")
    a = res["all"]
    print(f"{'all':<12}{a['points']:>9}{_fmt(a['median_mm']):>11}{_fmt(a['rms_mm']):>9}{_fmt(a['p95_mm']):>9}"
          f"{_fmt(a['frac_over_1mm'], 100):>8}{_fmt(a.get('coverage_mean'), 100):>9}")
    if a["non_finite_points"]:
        print(f"left out {a['non_finite_points']} point(s) with a NaN or infinite coordinate")
    if args.json:
        atomic_write_json(args.json, res)
    return 0
