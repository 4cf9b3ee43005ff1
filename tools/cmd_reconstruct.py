"""``ringscan reconstruct SCAN --out DIR``: one point cloud per view + report.json."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

from ringscan.kernels.triangulation import CONSTRAINTS
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.settings import apply_setting, check_finite_settings, settings_from_dict
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import RAYS, ReconstructSettings, check_setting_ranges
from ringscan.tools.cli import UsageError, add_device_option, basic_options


def add_parser(sub):
    p = sub.add_parser("reconstruct", help="reconstruct a scan folder into per-view point clouds",
                       description="Decode, sample and triangulate every view of a scan; write <view>.ply, "
                                   "report.json and settings.json into --out.")
    p.add_argument("scan", help="scan folder (with scan.json); or a URL: s3://bucket/prefix, gs://... "
                                "(docs/batch.md, \"Scans on S3\")")
    p.add_argument("--out", required=True, help="output folder, or a URL")
    p.add_argument("--views", default=None, help="comma-separated view names (default: all)")
    add_settings_options(p)
    p.add_argument("--resume", action="store_true",
                   help="keep views already done in --out (same inputs, same settings, files whole); "
                        "redo the others and say why")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_constraint_option(p)
    add_storage_option(p)
    add_device_option(p)
    basic_options(p, "--settings", "--set", "--min-confidence", "--resume", "--constraint", "--rays")
    return p


def add_storage_option(p) -> None:
    """``--storage-option KEY=VALUE``: fsspec options for scans and outputs given as URLs."""
    p.add_argument("--storage-option", dest="storage_options", action="append", default=[], metavar="KEY=VALUE",
                   help="an fsspec/s3fs option for URLs (s3://, gs://): endpoint_url=http://host:9000, "
                        "key=..., secret=..., anon=true, config_kwargs.connect_timeout=5; VALUE JSON or text; "
                        "repeatable (docs/batch.md)")


def storage_options_from_args(args) -> dict | None:
    """The ``--storage-option`` assignments as one dict (None when none were given)."""
    from ringscan.pipeline.formats.storage import parse_storage_options

    try:
        return parse_storage_options(args.storage_options) or None
    except ValueError as e:
        raise UsageError(str(e)) from None


def add_constraint_option(p) -> None:
    """``--constraint`` (which projector coordinates place a point) and ``--rays``
    (two cameras: which rays), over the settings file and --set."""
    p.add_argument("--constraint", choices=CONSTRAINTS, default=None,
                   help="which projector coordinates place each point: both (the ring and the polar angle, "
                        "weighted by their predicted errors), rings (the paper's ring surfaces alone), angle "
                        "(the angle alone, for comparison), auto (both where the codec decodes an angle, else "
                        "rings; the default); over the settings file's triangulate.constraint")
    p.add_argument("--rays", choices=RAYS, default=None,
                   help="two-camera scans: which rays place each point: camera-camera (the cameras matched by "
                        "projector coordinate; the projector needs no calibration), camera-projector (camera 1 "
                        "and the projector, camera 2 unused), all (both cameras and the calibrated projector), "
                        "auto (all where the projector is calibrated, else camera-camera; the default); "
                        "over the settings file's stereo.rays")


def with_constraint(settings: ReconstructSettings, constraint: str | None,
                    rays: str | None = None) -> ReconstructSettings:
    """The settings with ``--constraint`` and ``--rays`` applied (unchanged where not given)."""
    if constraint is not None:
        settings = replace(settings, triangulate=replace(settings.triangulate, constraint=constraint))
    if rays is not None:
        settings = replace(settings, stereo=replace(settings.stereo, rays=rays))
    return settings


def add_settings_options(p, *, file_option: str = "--settings") -> None:
    """The reconstruction settings options of reconstruct and batch: a file, then
    --set for any setting and --min-confidence (the most used)."""
    p.add_argument(file_option, dest="settings", default=None, metavar="JSON",
                   help="reconstruction settings file: any subset of a run's settings.json (default: built in)")
    p.add_argument("--set", dest="set_settings", action="append", default=[], metavar="KEY=VALUE",
                   help="one reconstruction setting, over the file's: KEY is its path in settings.json "
                        "(min_confidence, decode.min_contrast, triangulate.sector_margin, ...), VALUE JSON; "
                        "repeatable (docs/reconstruction.md)")
    p.add_argument("--min-confidence", type=float, default=None, metavar="C",
                   help=f"points whose confidence is below C (0..1) are not written; counted as low_confidence in "
                        f"report.json's dropped (default {ReconstructSettings.min_confidence}: all written)")


def load_settings(path, *, sets=(), min_confidence: float | None = None) -> ReconstructSettings:
    """The settings of a JSON file (a run's settings.json) or the defaults, with
    ``--set KEY=VALUE`` assignments and ``--min-confidence`` applied over them.

    Raises:
        FormatError: naming the file: unreadable, an unknown setting, a value of the wrong type, a NaN or
            infinite number.
        UsageError: the same found in a --set or --min-confidence.
    """
    d = read_json(path) if path else {}
    if not isinstance(d, dict):
        raise FormatError(path, f"expected an object of settings, got {type(d).__name__}")
    try:
        alone = settings_from_dict(ReconstructSettings, d)  # the file on its own first: its errors name it
        if 0 <= alone.min_confidence <= 1:  # else said below, as the file's or --min-confidence's
            check_setting_ranges(alone)
    except (TypeError, ValueError) as e:
        raise FormatError(path, str(e)) from None
    try:
        for a in sets:
            apply_setting(d, a)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if min_confidence is not None:
        d["min_confidence"] = min_confidence
    try:
        s = settings_from_dict(ReconstructSettings, d)
        check_finite_settings(s)
    except (TypeError, ValueError) as e:
        if path and not sets and min_confidence is None:
            raise FormatError(path, str(e)) from None
        raise UsageError(f"{'--set' if sets else '--min-confidence'}: {e}") from None
    if not 0 <= s.min_confidence <= 1:
        why = f"expected a confidence in 0..1, got {s.min_confidence}"
        if min_confidence is not None or any(a.split("=")[0].strip() == "min_confidence" for a in sets):
            raise UsageError(f"--min-confidence: {why}")
        raise FormatError(path, f"min_confidence: {why}")
    try:
        check_setting_ranges(s)
    except ValueError as e:
        raise UsageError(f"--set: {e}") from None
    return s


def settings_from_args(args) -> ReconstructSettings:
    """The settings of reconstruct's and batch's options: the file, --set, --min-confidence, then --constraint."""
    settings = load_settings(args.settings, sets=args.set_settings, min_confidence=args.min_confidence)
    return with_constraint(settings, getattr(args, "constraint", None), getattr(args, "rays", None))


def print_calibration_checks(views: list[dict]) -> None:
    """One line per view with its calibration check (report.json ``calibration_check``),
    and a warning line where the rig file does not fit the images; with three rays one more, the
    projector against the two cameras' points (``stereo.projector_check``)."""
    for v in views:
        c = v.get("calibration_check")
        if not c:
            continue
        what = ("epipolar distance of the camera matches" if c["kind"] == "epipolar"
                else "ray-ray residual (projector px)")
        print(f"{v['name']}: {v.get('rays', 'camera-projector')}: {what}: median {c['median_px']:.2f} px, "
              f"p95 {c['p95_px']:.2f} px ({c['samples']} samples)")
        if not c["fits"]:
            print(f"{v['name']}: warning: the rig file does not fit the images (median above 1 px): check the "
                  "calibration (docs/calibration.md)")
        p = v.get("stereo", {}).get("projector_check")
        if p:  # three rays: the projector against the two cameras' points
            said = f"; its ray discounted by {p['floor_px']:.2f} px" if p["floor_applied"] else ""
            print(f"{v['name']}: {v.get('rays')}: projector against the cameras' points: median "
                  f"{p['residual_px_median']:.2f} px, p95 {p['residual_px_p95']:.2f} px ({p['samples']} samples){said}")


def run(args) -> int:
    from ringscan.pipeline.formats.scan import load_scan
    from ringscan.pipeline.formats.storage import stage

    settings = settings_from_args(args)
    views = args.views.split(",") if args.views else None
    # a scan or output folder given as a URL is staged: frames downloaded, results uploaded whole at the end
    with stage(args.scan, args.out, options=storage_options_from_args(args), outputs=args.resume) as st:
        scan = load_scan(st.scan_dir, check_files=not st.remote_scan)
        st.check_scan(scan)
        st.fetch_frames(scan, views)
        rep = reconstruct_scan(scan, st.out_dir, settings=settings, device=args.device, views=views,
                               resume=args.resume, progress=not args.no_progress)
        st.commit()
    tot = rep["totals"]
    resumed = rep.get("resume")
    if resumed:
        if resumed["kept"]:
            print(f"kept {len(resumed['kept'])} view(s) done before with the same inputs and settings")
        for name, why in resumed["redone"].items():
            print(f"{name}: redone ({why})")
    print_calibration_checks(rep["views"])
    print(f"{len(rep['views'])} view(s): {tot['samples']} samples -> {tot['points']} points; dropped "
          + json.dumps(tot["dropped"]) + f"; {rep['time_s']:.2f} s on {rep['device']}; report: {args.out}/report.json")
    if rep["views"] and tot["points"] == 0:
        reasons = list(dict.fromkeys(v.get("no_points", "no points") for v in rep["views"]))
        more = f" (and {len(reasons) - 1} other reason(s), see above)" if len(reasons) > 1 else ""
        print(f"ringscan reconstruct: error: no view of {args.scan} gave any point: {reasons[0]}{more}",
              file=sys.stderr)
        return 1
    return 0
