"""``ringscan bench``: stage timings against NumPy, as ratios measured in one run."""

from __future__ import annotations

from ringscan.tools.bench.core import run_bench
from ringscan.tools.bench.dense import bench_dense
from ringscan.tools.cli import basic_options


def add_parser(sub):
    p = sub.add_parser("bench", help="time decode, sampling and triangulation against NumPy",
                       description="Times each stage of one 1280x1024 view (28 frames by default) on the Warp CPU "
                                   "backend (and CUDA when present) against a vectorised NumPy implementation of the "
                                   "same stage, in one run, and prints the ratios and the memory-bandwidth floor.")
    p.add_argument("--scan", default=None, help="a gray-rings scan folder (default: simulate the default scan)")
    p.add_argument("--scene", default=None, help="scene for the default scan (default: Spot from ../shared, or sphere)")
    p.add_argument("--repeats", type=int, default=5, metavar="N",
                   help="timed runs of each stage; the shortest is reported (default 5)")
    p.add_argument("--device", action="append", default=None, help="device(s) to time (repeatable); default cpu (+cuda)")
    p.add_argument("--dense", action="store_true",
                   help="time the dense phase-rings path instead (decode, phase, smoothing, triangulation; "
                        "--scan then names a phase-rings scan)")
    basic_options(p, "--scan", "--scene", "--repeats", "--dense")
    return p


def run(args) -> int:
    if args.dense:

        bench_dense(scan_dir=args.scan, scene=args.scene, repeats=args.repeats, devices=args.device)
        return 0
    run_bench(scan_dir=args.scan, scene=args.scene, repeats=args.repeats, devices=args.device)
    return 0
