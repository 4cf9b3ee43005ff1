"""``ringscan reconstruct SCAN --out DIR``: one point cloud per view + report.json."""

from __future__ import annotations

import json

from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.settings import settings_from_dict
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.tools.cli import add_device_option


def add_parser(sub):
    p = sub.add_parser("reconstruct", help="reconstruct a scan folder into per-view point clouds",
                       description="Decode, sample and triangulate every view of a scan; write <view>.ply, "
                                   "report.json and settings.json into --out.")
    p.add_argument("scan", help="scan folder (with scan.json)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--views", default=None, help="comma-separated view names (default: all)")
    p.add_argument("--settings", default=None, help="JSON file of settings (see settings.json of a run)")
    p.add_argument("--resume", action="store_true", help="skip views already done in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_device_option(p)
    return p


def load_settings(path) -> ReconstructSettings:
    return settings_from_dict(ReconstructSettings, read_json(path)) if path else ReconstructSettings()


def run(args) -> int:
    rep = reconstruct_scan(args.scan, args.out, settings=load_settings(args.settings), device=args.device,
                           views=args.views.split(",") if args.views else None, resume=args.resume,
                           progress=not args.no_progress)
    tot = rep["totals"]
    print(f"{len(rep['views'])} view(s): {tot['samples']} samples -> {tot['points']} points; dropped "
          + json.dumps(tot["dropped"]) + f"; {rep['time_s']:.2f} s on {rep['device']}; report: {args.out}/report.json")
    return 0
