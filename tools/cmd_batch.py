"""``ringscan batch ROOT --out OUT``: reconstruct every scan folder below ROOT (resumable)."""

from __future__ import annotations

from ringscan.pipeline.batch import batch_reconstruct
from ringscan.tools.cli import add_device_option
from ringscan.tools.cmd_reconstruct import load_settings


def add_parser(sub):
    p = sub.add_parser("batch", help="reconstruct every scan below a folder (resumable)",
                       description="Reconstruct each folder with a scan.json below ROOT into the same relative "
                                   "path below --out. Finished scans are skipped, so rerunning resumes a batch.")
    p.add_argument("root")
    p.add_argument("--out", required=True)
    p.add_argument("--settings", default=None, help="JSON settings file")
    p.add_argument("--no-progress", action="store_true")
    add_device_option(p)
    return p


def run(args) -> int:
    rep = batch_reconstruct(args.root, args.out, settings=load_settings(args.settings), device=args.device,
                            progress=not args.no_progress)
    failed = [s for s in rep["scans"] if s["status"] == "failed"]
    for s in rep["scans"]:
        redone = "; ".join(f"{n}: {why}" for n, why in s.get("redone", {}).items())
        print(f"{s['scan']}: {s['status']}" + (f" ({s['error']})" if s.get("error") else
                                                f", {s['points']} points" if "points" in s else "")
              + (f" [redone: {redone}]" if redone else ""))
    print(f"{len(rep['scans'])} scan(s), {len(failed)} failed; report: {args.out}/batch_report.json")
    return 1 if failed else 0
