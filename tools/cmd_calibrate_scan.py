"""``ringscan calibrate refine | projector-from-scan``: calibrations from a scan's own matches
(docs/calibration.md).

- ``refine SCAN``: the extrinsics re-estimated from a scan's own matches (two cameras, or camera and projector);
- ``projector-from-scan SCAN``: the projector fitted to a two-camera scan's points (a procam rig).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.opencv_files import write_opencv_procam, write_opencv_stereo
from ringscan.pipeline.calibrate.projector_fit import (
    DISTORTION_CHOICES,
    ProjectorSettings,
    fit_projector,
    no_pinhole_projector,
    procam_rig_from_fit,
    triangulation_covariance,
)
from ringscan.pipeline.calibrate.rig_refine import MAX_MATCHES
from ringscan.pipeline.calibrate.scan_matches import (
    OPENCV_EXTENSIONS,
    gather_matches,
    load_scan_with_rig,
    refine_rig_from_matches,
    two_camera_points,
)
from ringscan.pipeline.formats.atomic import atomic_write_json, check_output_file
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.formats.rig import PerspectiveLight, save_rig
from ringscan.tools.calibrate_options import add_force_option, check_outputs, parse_size, refuse_unless_forced
from ringscan.tools.cli import UsageError, add_device_option, basic_options


# ----------------------------------------------------------------------------- refine, projector-from-scan

def add_scan_match_options(p, *, out_help: str) -> None:
    p.add_argument("scan", metavar="SCAN", help="the scan folder whose matches to use")
    p.add_argument("--rig", default=None, metavar="RIG",
                   help="the rig file (ringscan JSON) to start from (default: the scan's own rig.json)")
    p.add_argument("--out", required=True, metavar="RIG2", help=out_help)
    p.add_argument("--opencv", default=None, metavar="FILE.yml",
                   help="where to write it as OpenCV FileStorage as well (default: --out with .yml)")
    p.add_argument("--view", action="append", default=None, metavar="NAME",
                   help="use this view's matches (repeatable; default: every view)")
    p.add_argument("--max-matches", type=int, default=200_000, metavar="N",
                   help="use at most N matches over all views (a seeded random subset; default 200000)")
    p.add_argument("--report", default=None, metavar="JSON", help="also write the figures as JSON")
    p.add_argument("--ring-curvature", choices=("on", "off"), default="on",
                   help="decode ring-edge samples with the blurred edge's inward shift removed "
                        "(SampleSettings.ring_curvature: on, the default here, since a fit of intrinsics or a pose "
                        "takes a bias that grows toward the pattern centre for a change of focal length and "
                        "distance; reconstruct leaves it off by default; docs/calibration.md)")
    add_force_option(p)
    add_device_option(p)


def match_outputs(args) -> dict:
    """The output files of a refine / projector-from-scan run, checked before anything is read."""
    if not 100 <= args.max_matches <= MAX_MATCHES:
        raise UsageError(f"--max-matches: expected 100 to {MAX_MATCHES}, got {args.max_matches}")
    check_output_file(args.out, extensions=(".json",), what="rig file --out writes")
    yml = args.opencv or str(Path(args.out).with_suffix(".yml"))
    check_output_file(yml, extensions=OPENCV_EXTENSIONS, what="OpenCV file --opencv writes")
    outs = {"--out": args.out, "--opencv": yml, "--report": args.report}
    if getattr(args, "stereo_out", None):
        check_output_file(args.stereo_out, extensions=(".json",), what="rig file --stereo-out writes")
        outs["--stereo-out"] = args.stereo_out
    scan = Path(args.scan)
    check_outputs(outs, [scan / "scan.json", scan / "rig.json", *([args.rig] if args.rig else [])])
    return outs



def view_matches(scan, view, *, device, ring_curvature: bool = True):
    """(uv1, uv2, proj, sigmas) of one two-camera view (``ringscan.pipeline.reconstruct.stereo.match_view``);
    sigmas: (n, 5) predicted standard deviations of uv1, uv2 (px), proj (projector px, the mean of its
    two axes) and proj along u_p and v_p, or None. ``ring_curvature``: SampleSettings.ring_curvature."""
    from ringscan.pipeline.reconstruct.settings import ReconstructSettings
    from ringscan.pipeline.reconstruct.stereo import match_view

    settings = ReconstructSettings()
    settings = dataclasses.replace(settings,
                                   sample=dataclasses.replace(settings.sample, ring_curvature=ring_curvature))
    m = match_view(scan, view, device=device, settings=settings)
    sp = np.asarray(m.sigma_proj, float)
    sig = np.stack([m.sigma1, m.sigma2, np.mean(sp, axis=1), sp[:, 0], sp[:, 1]], 1).astype(float)
    return np.asarray(m.uv1, float), np.asarray(m.uv2, float), np.asarray(m.proj, float), sig



def scan_matches(scan, views, args, *, need: str):
    """:func:`~ringscan.pipeline.calibrate.scan_matches.gather_matches` with the options (--max-matches,
    --device, --ring-curvature), each view's count printed."""
    curvature = getattr(args, "ring_curvature", "on") == "on"
    return gather_matches(scan, views, need=need, max_matches=args.max_matches, progress=not args.no_progress,
                          match_view=lambda s, v: view_matches(s, v, device=args.device, ring_curvature=curvature),
                          on_view=lambda name, n: print(f"  {name}: {n} matches"))


def print_refinement(what: str, ref) -> None:
    print(f"{what}: {ref.used} matches used, {ref.inliers} fit within 3 px (start: {ref.start})")
    print(f"  epipolar distance  before: {ref.epipolar_before.line()}")
    print(f"                     after:  {ref.epipolar_after.line()}")
    print(f"  reprojection error before: {ref.reprojection_before.line()}")
    print(f"                     after:  {ref.reprojection_after.line()}")
    print(f"  rotation changed by {ref.rotation_change_deg:.3f} deg (+- {ref.rotation_std_deg:.4f}), baseline "
          f"direction by {ref.direction_change_deg:.3f} deg (+- {ref.direction_std_deg:.4f}); baseline "
          f"{ref.baseline_mm:.2f} mm")
    if math.isfinite(ref.scale_std):
        print(f"  scale (vergence): +- {100 * ref.scale_std:.2f} % of the depths (a turn of +- {ref.vergence_std_deg:.4f} "
              "deg about the vergence axis; noise and the spread over the image's quarters)")
    if ref.light_epipolar is not None:
        print(f"  {ref.third or 'projector'} against camera 1 (held): epipolar distance {ref.light_epipolar.line()}")
    if ref.method == "three-device":
        print(f"  bundle adjustment over camera 1, camera 2 and the projector ({ref.third} held): {ref.bundle_used} "
              "matches, weighted by their predicted standard deviations")
    for note in ref.notes:
        print(f"  note: {note}")


def add_refine_parser(calsub) -> None:
    p = calsub.add_parser("refine", help="re-estimate the extrinsics from a scan's own matches",
                          description="Matches the scan's pixels (two cameras by equal projector coordinate, or an "
                                      "imported camera-projector scan's decoded pixels) without the rig's extrinsics, "
                                      "then re-estimates the second device's pose: an essential matrix (RANSAC) and a "
                                      "bundle adjustment over the matches, keeping the rig's baseline length (or "
                                      "--baseline); on a two-camera rig the third device (the calibrated projector "
                                      "when camera 2 is refined, camera 2 when the projector is) then joins a bundle "
                                      "adjustment of the reprojection errors in all three devices (its pose held; "
                                      "--two-view leaves it out). Prints the epipolar distance and the reprojection "
                                      "error before and after; writes the rig (JSON) and the pair as OpenCV "
                                      "FileStorage.")
    add_scan_match_options(p, out_help="the refined rig file to write (JSON)")
    p.add_argument("--pair", choices=("auto", "cameras", "projector"), default="auto",
                   help="what to refine: camera 2 against camera 1, or the projector against camera 1 (auto: the "
                        "cameras of a two-camera rig, the projector of a one-camera rig)")
    p.add_argument("--baseline", type=float, default=None, metavar="MM",
                   help="the baseline length in mm (a measured one; default: the rig's)")
    p.add_argument("--two-view", action="store_true",
                   help="on a two-camera rig, leave the third device (the calibrated projector for --pair cameras, "
                        "camera 2 for --pair projector) out of the adjustment (by default it joins it, its pose held, "
                        "where it fits camera 1's matches)")
    basic_options(p, "--rig", "--opencv", "--report", "--pair")
    p.set_defaults(_calibrate=run_refine)


def run_refine(args) -> int:
    if args.baseline is not None and not (np.isfinite(args.baseline) and 0 < args.baseline <= 1e5):
        raise UsageError(f"--baseline: expected mm from 0 to 100000, got {args.baseline:g}")
    outs = match_outputs(args)
    scan, views = load_scan_with_rig(args.scan, rig_path=args.rig, view_names=args.view)
    rig = scan.rig
    pair = args.pair if args.pair != "auto" else ("cameras" if rig.camera2 is not None else "projector")
    if pair == "cameras" and rig.camera2 is None:
        raise FormatError(args.rig or scan.path, "has one camera: --pair cameras needs a two-camera rig")
    if pair == "projector" and not isinstance(rig.light, PerspectiveLight):
        raise FormatError(args.rig or scan.path, f"its projector is not calibrated (model {rig.light.model!r}): "
                                                 "refining it needs a perspective projector (a two-camera rig's "
                                                 "projector: `ringscan calibrate projector-from-scan`)")
    uv1, uv2, proj, sig = scan_matches(scan, views, args, need=pair)
    with progress_step("refining", enabled=not args.no_progress):
        new, ref = refine_rig_from_matches(rig, uv1, uv2, proj, sig, pair=pair, baseline_mm=args.baseline,
                                           two_view=args.two_view)
    print_refinement("camera 2 against camera 1" if pair == "cameras" else "projector against camera 1"
                     if rig.camera2 is not None else "camera against the projector", ref)
    refuse_unless_forced(args, ref.problems, args.out)
    save_rig(args.out, new)
    if pair == "cameras":
        write_opencv_stereo(outs["--opencv"], new)
    else:
        write_opencv_procam(outs["--opencv"], new)
    print(f"wrote {args.out} and {outs['--opencv']}")
    if args.report:
        atomic_write_json(args.report, {"pair": pair, **ref.report()})
    return 0


def add_projector_from_scan_parser(calsub) -> None:
    p = calsub.add_parser("projector-from-scan", help="the projector fitted to a two-camera scan's points",
                          description="Triangulates the two cameras' matches with the rig (its projector may be "
                                      "uncalibrated), then fits a perspective projector (intrinsics, pose, and the "
                                      "lens distortion terms the points determine: --radial, --tangential) to the "
                                      "points and their projector pixels, each pair weighted by its predicted "
                                      "uncertainty (--weights): a normalised DLT, then OpenCV's calibrateCamera on "
                                      "the non-planar point set. Prints the RMS reprojection error, the fit's "
                                      "standard deviations (with the residuals' correlation, and without), its "
                                      "condition, the points' depth along the projector's axis, and refuses a fit "
                                      "the points do not determine (a flat scene: give --principal-point). Writes a "
                                      "one-camera procam rig (camera 1 and the projector), as JSON and OpenCV "
                                      "FileStorage.")
    add_scan_match_options(p, out_help="the procam rig file to write (JSON: camera 1 and the fitted projector)")
    p.add_argument("--stereo-out", default=None, metavar="RIG3",
                   help="also write the two-camera rig with the fitted projector (for three-ray triangulation)")
    p.add_argument("--projector", default=None, metavar="WxH",
                   help="the projector's size in pixels (default: the rig's)")
    p.add_argument("--principal-point", nargs=2, type=float, default=None, metavar=("CX", "CY"),
                   help="hold the projector's principal point here (px): lets a nearly flat scene fit the focal "
                        "length")
    p.add_argument("--tangential", default="auto", metavar="|".join(DISTORTION_CHOICES),
                   help="the projector's tangential distortion p1, p2: fitted where the points determine them "
                        "(auto, the default: a significance test against the residuals), always (fit) or held at 0 "
                        "(hold)")
    p.add_argument("--weights", default="predicted", metavar="predicted|none",
                   help="weight each point-pixel pair by its predicted uncertainty (the two cameras' triangulation "
                        "mapped into the projector, plus the decoded pixel's; predicted, the default) or not (none)")
    p.add_argument("--radial", default="auto", metavar="|".join(DISTORTION_CHOICES),
                   help="its radial distortion: k1, and k2, k3 where the points determine them (auto, the "
                        "default), k1 and k2 (fit) or none (hold)")
    basic_options(p, "--rig", "--stereo-out", "--opencv", "--report", "--projector")
    p.set_defaults(_calibrate=run_projector_from_scan)



def run_projector_from_scan(args) -> int:
    size = parse_size(args.projector, "--projector") if args.projector is not None else None
    if args.principal_point is not None and not all(np.isfinite(args.principal_point)):
        raise UsageError("--principal-point: expected two finite numbers")
    for flag, value in (("--tangential", args.tangential), ("--radial", args.radial)):
        if value not in DISTORTION_CHOICES:
            raise UsageError(f"{flag}: expected {', '.join(DISTORTION_CHOICES)}, got {value!r}")
    if args.weights not in ("predicted", "none"):
        raise UsageError(f"--weights: expected predicted or none, got {args.weights!r}")
    match_outputs(args)
    scan, views = load_scan_with_rig(args.scan, rig_path=args.rig, view_names=args.view)
    rig = scan.rig
    if rig.camera2 is None:
        raise FormatError(args.rig or scan.path, "has one camera: projector-from-scan needs a two-camera rig "
                                                 "(camera2) and a two-camera scan")
    if size is None:
        size = (getattr(rig.light, "width", 0), getattr(rig.light, "height", 0))
        if not min(size) > 0:
            raise UsageError("--projector: the rig does not give the projector's size; give --projector WxH")
    uv1, uv2, proj, sig = scan_matches(scan, views, args, need="cameras")
    c1, c2 = rig.camera, rig.camera2
    Xw, keep, err = two_camera_points(c1, c2, uv1, uv2)
    print(f"two-camera points: reprojection error median {np.median(err):.3f} px, p95 "
          f"{np.percentile(err, 95):.3f} px over {err.size} matches")
    problems = []
    if not np.median(err) <= 1.0:
        problems.append(f"the rig's cameras do not fit the matches (reprojection median {np.median(err):.2f} px > "
                        "1 px): run `ringscan calibrate refine` first")
    pp = tuple(args.principal_point) if args.principal_point is not None else None
    weighted = args.weights == "predicted" and sig is not None
    with progress_step("fitting the projector", enabled=not args.no_progress):
        cov = triangulation_covariance(c1, c2, Xw, sig[keep, 0], sig[keep, 1]) if weighted else None
        try:
            fit = fit_projector(Xw, proj[keep], size=size, settings=ProjectorSettings(
                principal_point=pp, radial=args.radial, tangential=args.tangential), point_cov=cov,
                pixel_sigma=sig[keep, 3:5] if weighted else None)
        except CalibrationError as e:
            if "Principal point must be within the image" not in e.message:
                raise
            raise CalibrationError(args.rig or scan.path, no_pinhole_projector(Xw, proj[keep])) from None
    K = fit.light.K
    sd = fit.std
    print(f"projector: RMS reprojection error {fit.rms_px:.3f} px over {fit.used} points ({fit.outliers} left out); "
          f"{fit.residuals.line()}; "
          + ("each pair weighted by its predicted uncertainty" if weighted else "unweighted"))
    dist = fit.light.dist
    print(f"  fx {K[0, 0]:.2f} +- {sd['fx']:.2f}, fy {K[1, 1]:.2f} +- {sd['fy']:.2f}, cx {K[0, 2]:.2f} +- "
          f"{sd['cx']:.2f}, cy {K[1, 2]:.2f} +- {sd['cy']:.2f} px; k1 {dist[0]:.4f}, k2 {dist[1]:.4f}, p1 "
          f"{dist[2]:.5f}, p2 {dist[3]:.5f}, k3 {dist[4]:.4f}; fixed: {', '.join(fit.fixed) or 'none'}")
    print(f"  pose +- {sd['rotation_deg']:.4f} deg, +- {sd['position']:.3f} mm; condition {fit.condition:.3g}; "
          f"point set thickness {fit.thickness:.3f}")
    nz = fit.std_noise
    print(f"  (+- the residuals' correlation, {fit.correlation:.1f}x their variance: independent residuals would "
          f"give fx +- {nz['fx']:.2f} px, pose +- {nz['rotation_deg']:.4f} deg, +- {nz['position']:.3f} mm)")
    print(f"  depth along the projector's axis {fit.depth_range[0]:.0f} to {fit.depth_range[1]:.0f} mm (5-95 %): "
          f"{100 * fit.depth_ratio:.1f} % of the distance; focal length-distance correlation "
          f"{fit.focal_distance_correlation:+.4f}")
    for line in fit.decisions:
        print(f"  distortion {line}")
    for note in fit.notes:
        print(f"  note: {note}")
    refuse_unless_forced(args, problems + fit.problems, args.out)
    procam = procam_rig_from_fit(c1, fit.light, Xw)
    save_rig(args.out, procam)
    yml = args.opencv or str(Path(args.out).with_suffix(".yml"))
    write_opencv_procam(yml, procam)
    print(f"wrote {args.out} and {yml} (camera 1 and the projector)")
    if args.stereo_out:
        save_rig(args.stereo_out, dataclasses.replace(rig, light=fit.light))
        print(f"wrote {args.stereo_out} (both cameras and the projector)")
    if args.report:
        atomic_write_json(args.report, {"two_camera_reprojection_px": {"median": float(np.median(err)),
                                                                       "p95": float(np.percentile(err, 95))},
                                        "projector": fit.report(), "problems": problems + fit.problems})
    return 0

