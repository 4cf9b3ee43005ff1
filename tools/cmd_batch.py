"""``ringscan batch ROOT --out OUT``: reconstruct every scan folder below ROOT on worker processes or a
Ray cluster (resumable; see docs/batch.md)."""

from __future__ import annotations

from ringscan.pipeline.batch import batch_reconstruct, format_table, plan_batch
from ringscan.pipeline.batch.report import format_calibration_checks
from ringscan.tools.cli import UsageError, add_device_option, basic_options
from ringscan.tools.cmd_reconstruct import (
    add_constraint_option,
    add_settings_options,
    add_storage_option,
    settings_from_args,
    storage_options_from_args,
)


def _workers(text: str, *, option: str = "--workers") -> int:
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise UsageError(f"{option} {text!r}: expected a whole number >= 0" + (" (0: in this process)"
                                                                              if option == "--workers" else ""))
    return n


def add_parser(sub):
    p = sub.add_parser("batch", help="reconstruct every scan below a folder, in parallel (resumable)",
                       description="Reconstruct each folder with a scan.json below ROOT into the same relative "
                                   "path below --out, on worker processes (or a Ray cluster). Finished scans are "
                                   "skipped, so rerunning resumes a batch. Exit status 1 when a scan failed.")
    p.add_argument("root", help="folder searched for scan folders (each with a scan.json), at any depth; or a URL "
                                "(s3://bucket/prefix, gs://...: docs/batch.md, \"Scans on S3\")")
    p.add_argument("--out", required=True,
                   help="output root (a folder or a URL): each scan's results go to the same relative path below it")
    add_settings_options(p)
    add_constraint_option(p)
    p.add_argument("--workers", default=None,
                   help="worker processes (default: one per CUDA device where there are GPUs, else one per CPU "
                        "core; 0: in this process)")
    p.add_argument("--cpu-threads", default=None,
                   help="CPU threads of each local worker (default: the cores shared out among the workers); "
                        "results do not depend on it")
    p.add_argument("--backend", choices=("local", "ray"), default="local",
                   help="local: a process pool on this machine; ray: a Ray cluster (needs Ray: pip install ray)")
    p.add_argument("--address", default=None,
                   help="the Ray cluster's address (default: RAY_ADDRESS, else a local cluster)")
    p.add_argument("--fuse", action="store_true", help="also fuse each scan's views (<out>/<scan>/fused/)")
    p.add_argument("--mesh", action="store_true", help="also fuse and mesh each scan (<out>/<scan>/mesh/)")
    p.add_argument("--dry-run", action="store_true", help="list what would run and why; write nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_storage_option(p)
    add_device_option(p)
    basic_options(p, "--settings", "--set", "--workers", "--backend", "--address", "--fuse", "--mesh", "--dry-run")
    return p


def run(args) -> int:
    settings = settings_from_args(args)
    if args.address and args.backend != "ray":
        raise UsageError("--address: only with --backend ray")
    storage = storage_options_from_args(args)
    if args.dry_run:
        skipped: list = []
        plans = plan_batch(args.root, args.out, settings=settings, skipped=skipped, storage_options=storage)
        w = max(len(p.scan) for p in plans)
        for p in plans:
            print(f"{p.scan:<{w}}  {p.action:<4}  {p.why}" + (f"  ({p.detail})" if p.detail else ""))
        todo = sum(p.action == "run" for p in plans)
        print(f"{len(plans)} scan(s): {todo} to run, {len(plans) - todo} done")
        for s in skipped:
            print(f"not searched: {s['path']}: {s['why']}")
        return 0
    workers = None if args.workers is None else _workers(args.workers)
    cpu_threads = None
    if args.cpu_threads is not None:
        cpu_threads = _workers(args.cpu_threads, option="--cpu-threads")
        if cpu_threads < 1:
            raise UsageError(f"--cpu-threads {args.cpu_threads!r}: expected a whole number >= 1")
    rep = batch_reconstruct(args.root, args.out, settings=settings, device=args.device, workers=workers,
                            backend=args.backend, address=args.address, fuse=args.fuse, mesh=args.mesh,
                            cpu_threads=cpu_threads, progress=not args.no_progress, storage_options=storage)
    print(format_table(rep["scans"], rep["totals"]))
    for line in format_calibration_checks(rep["scans"]):
        print(line)
    for s in rep.get("not_searched", []):
        print(f"not searched: {s['path']}: {s['why']}")
    failed = rep["totals"]["status"].get("failed", 0)
    print(f"report: {args.out.rstrip('/')}/batch_report.json")
    return 1 if failed else 0
