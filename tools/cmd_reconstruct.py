"""``ringscan reconstruct SCAN --out DIR``: one point cloud per view + report.json."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

from ringscan.kernels.triangulation import CONSTRAINTS
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.settings import check_finite_settings, settings_from_dict
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
    p.add_argument("--resume", action="store_true",
                   help="keep views already done in --out (same inputs, same settings, files whole); "
                        "redo the others and say why")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_constraint_option(p)
    add_device_option(p)
    return p


def add_constraint_option(p) -> None:
    """``--constraint``: which projector coordinates place a point (overrides the settings file)."""
    p.add_argument("--constraint", choices=CONSTRAINTS, default=None,
                   help="which projector coordinates place each point: both (the ring and the polar angle, "
                        "weighted by their predicted errors), rings (the paper's ring surfaces alone), angle "
                        "(the angle alone, for comparison), auto (both where the codec decodes an angle, else "
                        "rings; the default)")


def with_constraint(settings: ReconstructSettings, constraint: str | None) -> ReconstructSettings:
    """The settings with ``--constraint`` applied (unchanged when it was not given)."""
    if constraint is None:
        return settings
    return replace(settings, triangulate=replace(settings.triangulate, constraint=constraint))


def load_settings(path) -> ReconstructSettings:
    """The settings of a JSON file (a run's settings.json), or the defaults.

    Raises:
        FormatError: naming the file: unreadable, an unknown setting, a NaN or infinite number.
    """
    if not path:
        return ReconstructSettings()
    d = read_json(path)
    try:
        s = settings_from_dict(ReconstructSettings, d)
        check_finite_settings(s)
    except (TypeError, ValueError) as e:
        raise FormatError(path, str(e)) from None
    return s


def run(args) -> int:
    settings = with_constraint(load_settings(args.settings), args.constraint)
    rep = reconstruct_scan(args.scan, args.out, settings=settings, device=args.device,
                           views=args.views.split(",") if args.views else None, resume=args.resume,
                           progress=not args.no_progress)
    tot = rep["totals"]
    resumed = rep.get("resume")
    if resumed:
        if resumed["kept"]:
            print(f"kept {len(resumed['kept'])} view(s) done before with the same inputs and settings")
        for name, why in resumed["redone"].items():
            print(f"{name}: redone ({why})")
    print(f"{len(rep['views'])} view(s): {tot['samples']} samples -> {tot['points']} points; dropped "
          + json.dumps(tot["dropped"]) + f"; {rep['time_s']:.2f} s on {rep['device']}; report: {args.out}/report.json")
    if rep["views"] and tot["points"] == 0:
        reasons = list(dict.fromkeys(v.get("no_points", "no points") for v in rep["views"]))
        more = f" (and {len(reasons) - 1} other reason(s), see above)" if len(reasons) > 1 else ""
        print(f"ringscan reconstruct: error: no view of {args.scan} gave any point: {reasons[0]}{more}",
              file=sys.stderr)
        return 1
    return 0
