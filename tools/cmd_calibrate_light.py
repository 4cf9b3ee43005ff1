"""``ringscan calibrate response | pose | light | latency | turntable``: the projector's response, the camera's
pose over the reference plane, the parallel light, the display projector's latency and the turntable axis
(docs/calibration.md).

- ``response CAPTURE_DIR...``: the projector's response curve;
- ``pose IMAGE``: the camera's pose over the reference plane from a board lying on it;
- ``light SCAN... --heights ...``: the parallel light from ring captures of a plane at known heights;
- ``latency --projector display:N --camera SPEC``: how long after a frame's swap the camera sees it in full;
- ``turntable SCAN | IMAGES... --angles ...``: the turntable axis from a board at several table angles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ringscan.hardware.capture.latency import LatencySettings, latency_frames, measure_latency, write_rig_latency
from ringscan.hardware.devices.camera import open_camera
from ringscan.hardware.devices.display import DisplayProjector, choose_display, list_displays, parse_display_spec
from ringscan.pipeline.calibrate.board import detect_board, view_name
from ringscan.pipeline.calibrate.capture_reader import expand_capture_frame
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.light import (
    LightSettings,
    calibrate_parallel_light,
    camera_pose_on_plane,
    rig_file_with_camera_pose,
    rig_with_light,
)
from ringscan.pipeline.calibrate.response import estimate_light_gamma, repeated_frames, response_problems
from ringscan.pipeline.calibrate.turntable import (
    TurntableSettings,
    board_views_of_scan,
    calibrate_turntable,
    rig_with_turntable,
)
from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import few_bits_hint, read_image
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.formats.rig import load_rig, parse_rig, save_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.scan import scan_inputs
from ringscan.tools.calibrate_options import (
    add_board_options,
    add_force_option,
    board_from_args,
    board_settings_from_args,
    check_outputs,
    print_views,
    refuse_unless_forced,
)
from ringscan.tools.cli import UsageError, add_device_option, basic_options, check_frame_bits_option


# ----------------------------------------------------------------------------- response


def add_response_parser(calsub) -> None:
    p = calsub.add_parser("response", help="the projector's response curve (gamma) from a projected grey ramp",
                          description="FRAMES are camera images of the projector showing uniform grey values "
                                      "--levels (0..255, one per frame, including 0 and 255). The light's gamma "
                                      "(emitted = (value/255)^gamma) goes into the rig's light.response.")
    p.add_argument("frames", nargs="+", metavar="FRAME", help="camera frames of the ramp, in --levels order")
    p.add_argument("--levels", type=float, nargs="+", required=True, help="projected values 0..255, one per frame")
    p.add_argument("--rig", required=True, metavar="RIG", help="rig file to update (its camera gamma linearises)")
    p.add_argument("--frame-bits", type=int, default=None, metavar="N",
                   help="bits the 16-bit frames hold (10, 12: a 10- or 12-bit camera's values 0..1023, 0..4095), "
                        "scaled to 16 bits as they are read, so that contrast and saturation are judged on the "
                        "camera's range (default: the frames' own bits)")
    add_force_option(p)
    basic_options(p, "--frame-bits", "--force")
    p.set_defaults(_calibrate=run_response)


def run_response(args) -> int:
    for f in args.frames:
        if not Path(f).exists() and any(c in f for c in "*?["):
            raise FormatError(f, "no file matches this pattern (the shell passed it on as it was)")
    if len(args.levels) != len(args.frames):
        raise UsageError(f"--levels: {len(args.levels)} values for {len(args.frames)} frames")
    bad = [v for v in args.levels if not (np.isfinite(v) and 0 <= v <= 255)]
    if bad:
        raise UsageError(f"--levels: values must be finite and in 0..255, got {', '.join(f'{v:g}' for v in bad)}")
    check_frame_bits_option(args.frame_bits)
    d = read_json(args.rig)
    rig = parse_rig(d, source=args.rig)
    imgs = [read_image(f) for f in args.frames]
    for f, im in zip(args.frames, imgs):
        if im.shape != imgs[0].shape or im.dtype != imgs[0].dtype:
            raise FormatError(f, "frame differs in size or bit depth from the first frame")
        if args.frame_bits is not None:
            expand_capture_frame(Path(f), im, args.frame_bits)
    stack = np.stack(imgs)
    problems = [f"{args.frames[j]} is the same image as {args.frames[i]}, but --levels gives "
                f"{args.levels[i]:g} and {args.levels[j]:g}" for i, j in repeated_frames(stack, args.levels)]
    try:
        gamma, curve = estimate_light_gamma(stack, np.asarray(args.levels) / 255.0, camera_gamma=rig.camera.gamma)
    except CalibrationError as e:
        hint = ""
        if stack.dtype == np.uint16 and args.frame_bits is None and stack.size:
            hint = few_bits_hint(int(stack.max()), "give their bits (--frame-bits)")
        if hint:
            raise CalibrationError(e.path, e.message + hint) from None
        raise
    print(f"light gamma {gamma:.3f} (camera gamma {rig.camera.gamma:g} undone first)")
    for x, y in curve.items():
        print(f"  level {255 * x:5.1f}: response {y:.4f} (model {x ** gamma:.4f})")
    refuse_unless_forced(args, problems + response_problems(curve, gamma), args.rig)
    d["light"]["response"] = {"gamma": gamma}
    save_rig(args.rig, parse_rig(d, source=args.rig))
    print(f"updated light.response.gamma of {args.rig}")
    return 0



# ----------------------------------------------------------------------------- pose (the paper's rig)


def add_pose_parser(calsub) -> None:
    p = calsub.add_parser("pose", help="the camera's pose over the reference plane, from a board lying on it",
                          description="IMAGE shows the board lying flat on the reference plane, where the light "
                                      "axis will be (roughly). Its pose sets the world frame (origin on the plane "
                                      "under the middle of the board's corners, x along its columns, z up toward "
                                      "the camera) and the camera's R, t in the rig file (updated in place; its "
                                      "intrinsics are used). Then calibrate the light and the turntable in that "
                                      "frame (docs/calibration.md).")
    p.add_argument("image", metavar="IMAGE", help="an image of the board lying on the reference plane")
    add_board_options(p)
    p.add_argument("--thickness", type=float, default=0.0, metavar="MM",
                   help="the board's thickness: its printed face lies this far above the plane (default 0)")
    p.add_argument("--rig", required=True, metavar="RIG", help="rig file to update (its camera's intrinsics are used)")
    basic_options(p, "--thickness", "--board", "--charuco")
    p.set_defaults(_calibrate=run_pose)


def run_pose(args) -> int:
    board = board_from_args(args)
    d = read_json(args.rig)
    rig = parse_rig(d, source=args.rig)
    img = read_image(args.image)
    cam = rig.camera
    if img.shape != (cam.height, cam.width):
        raise FormatError(args.image, f"image is {img.shape[1]}x{img.shape[0]}, the rig's camera is "
                                      f"{cam.width}x{cam.height}")
    view = detect_board(img, board=board, name=view_name(args.image), settings=board_settings_from_args(args))
    R, t, rms = camera_pose_on_plane(view, board=board, camera=cam, thickness_mm=args.thickness)
    C = -R.T @ t
    print(f"camera pose: centre ({C[0]:.2f}, {C[1]:.2f}, {C[2]:.2f}) in the board's world frame, "
          f"{np.degrees(np.arccos(min(1.0, abs(float(R[2, 2]))))):.2f} deg off the plane's normal; "
          f"RMS reprojection error {rms:.3f} px")
    new, baseline = rig_file_with_camera_pose(d, rig=rig, R=R, t=t, source=args.rig)
    if baseline is not None:
        print(f"the projector moves with the camera (baseline {baseline:.1f} kept)")
    save_rig(args.rig, new)
    print(f"updated the camera pose of {args.rig}")
    return 0



# ----------------------------------------------------------------------------- light (parallel)


def add_light_parser(calsub) -> None:
    p = calsub.add_parser("light", help="the parallel light (axis pixel, pitch, rotation) from plane captures",
                          description="Each SCAN is a scan folder (gray-rings or phase-rings, with sector bits) of "
                                      "the flat reference plane, or of a flat plate on it, at a known height (world "
                                      "z in mm, one per SCAN in --heights; two heights at least). The camera must be "
                                      "calibrated in the world frame (--rig, or the scans' own rig). Writes that rig "
                                      "with the fitted parallel light (docs/calibration.md).")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan folders of the plane, one height each")
    p.add_argument("--heights", type=float, nargs="+", required=True, metavar="MM",
                   help="the plane's height (world z, mm) in each SCAN, in order")
    p.add_argument("--rig", default=None, metavar="RIG", help="rig file whose camera to use (default: the first scan's)")
    p.add_argument("--out", required=True, metavar="RIG", help="rig file to write (the rig with this light)")
    p.add_argument("--max-residual", type=float, default=LightSettings.max_residual_px, metavar="PX",
                   help="drop samples whose ring residual exceeds this after the robust fit "
                        f"(projector px, default {LightSettings.max_residual_px:g})")
    p.add_argument("--report", default=None, metavar="JSON", help="also write the figures as JSON")
    add_device_option(p)
    basic_options(p, "--rig", "--report")
    p.set_defaults(_calibrate=run_light)


def run_light(args) -> int:
    if len(args.heights) != len(args.scans):
        raise UsageError(f"--heights: {len(args.heights)} height(s) for {len(args.scans)} scan(s); give one per scan")
    rig = load_rig(args.rig) if args.rig else None
    scans = [load_scan(s) for s in args.scans]
    check_outputs({"--out": args.out, "--report": args.report},
                  [*(f for s in scans for f in scan_inputs(s)), *([args.rig] if args.rig else [])])
    with progress_step(f"fitting the light to {len(scans)} plane scan(s)", enabled=not args.no_progress):
        cal = calibrate_parallel_light(scans, args.heights, rig=rig, device=args.device,
                                       settings=LightSettings(max_residual_px=args.max_residual))
    li = cal.light
    print(f"parallel light: pitch {li.pixel_pitch_mm:.6f} mm/px, axis pixel ({li.axis_px[0]:.2f}, "
          f"{li.axis_px[1]:.2f}), tilt {cal.tilt_deg:.3f} deg from z, roll {cal.roll_deg:.3f} deg; "
          f"ring RMS {cal.rms_px:.3f} px")
    for name, c in cal.captures.items():
        print(f"  {name} (z = {c['height_mm']:g} mm): {c['samples']} samples ({c['dropped']} dropped), "
              f"RMS {c['rms_px']:.3f} px, sectors agree {100 * c['sector_agreement']:.1f} %")
    save_rig(args.out, rig_with_light(rig or scans[0].rig, li))
    print(f"wrote {args.out}")
    if args.report:
        atomic_write_json(args.report, cal.report())
    return 0



# ----------------------------------------------------------------------------- latency (display projector)


def add_latency_parser(calsub) -> None:
    p = calsub.add_parser("latency", help="the projector's latency: how long after a frame's swap the camera sees it",
                          description="Shows black and white full-screen on the projector's display and grabs with "
                                      "the camera after delays from 0 upward: the first delay from which every grab "
                                      "shows the new frame in full (plus a margin of one refresh) goes into the rig "
                                      "file as light.latency_s, and `ringscan capture --projector display` waits that "
                                      "long after each frame. Aim the camera at the projected light; use the exposure "
                                      "and flush of the capture (docs/hardware.md).")
    p.add_argument("--projector", required=True, metavar="display[:N]",
                   help="the projector's display: display (= display:0), display:N or display:NAME")
    p.add_argument("--camera", required=True, metavar="SPEC", help="camera, as for `ringscan capture`")
    p.add_argument("--rig", default=None, metavar="RIG", help="rig file to write light.latency_s into")
    p.add_argument("--exposure", type=float, default=None, metavar="E", help="manual camera exposure (backend units)")
    p.add_argument("--gain", type=float, default=None, metavar="G", help="camera gain (backend units)")
    p.add_argument("--flush", type=int, default=None, metavar="N",
                   help="frames dropped before each grab (default 4 for live cameras)")
    d = LatencySettings()
    p.add_argument("--trials", type=int, default=d.trials, help=f"switches per delay (default {d.trials})")
    p.add_argument("--max-delay", type=float, default=d.max_s, metavar="S",
                   help=f"longest delay tried, s (default {d.max_s:g})")
    p.add_argument("--rest", type=float, default=d.rest_s, metavar="S",
                   help=f"time the old frame stays up before a switch, s (default {d.rest_s:g})")
    p.add_argument("--step", type=float, default=None, metavar="S", help="delay step, s (default half a refresh)")
    p.add_argument("--report", default=None, metavar="JSON", help="also write every grab's verdict as JSON")
    basic_options(p, "--rig", "--exposure", "--report")
    p.set_defaults(_calibrate=run_latency)


def run_latency(args) -> int:
    spec = parse_display_spec(args.projector)
    if spec is None:
        raise UsageError(f"--projector: expected display, display:N or display:NAME, got {args.projector!r}")
    settings = LatencySettings(trials=args.trials, max_s=args.max_delay, rest_s=args.rest, step_s=args.step)
    disp = choose_display(list_displays(), spec)
    with DisplayProjector(latency_frames(disp.width, disp.height), display=disp.index) as projector, \
            open_camera(args.camera, flush_frames=args.flush, exposure=args.exposure, gain=args.gain) as camera:
        res = measure_latency(projector, camera, settings=settings)
    print(f"display {disp.describe()}: refresh period {res.frame_period_s * 1e3:.1f} ms, {res.lit_pixels} lit "
          f"camera pixels")
    for row in res.delays:
        seen = " ".join(g["verdict"] + ("+again" if g["regrabs"] else "") for g in row["grabs"])
        print(f"  {row['delay_s'] * 1e3:6.1f} ms: {seen}")
    if res.mixed_frames:
        print(f"{res.mixed_frames} torn frame(s) (part old, part new) seen and grabbed again")
    print(f"the camera sees a new frame in full {res.measured_s * 1e3:.1f} ms after the swap; latency with margin "
          f"{res.latency_s * 1e3:.1f} ms")
    if args.rig:
        write_rig_latency(args.rig, res.latency_s)
        print(f"updated light.latency_s of {args.rig}")
    if args.report:
        atomic_write_json(args.report, res.to_dict())
    return 0



# ----------------------------------------------------------------------------- turntable


def add_turntable_parser(calsub) -> None:
    p = calsub.add_parser("turntable", help="the turntable axis from a board seen at several table angles",
                          description="A board lies (or stands) on the turntable, seen at several table angles. "
                                      "Give a scan folder whose views show it at their turntable_deg (the --frame "
                                      "frame of each view is used), or board images with --angles. The camera must "
                                      "be calibrated in the world frame (--rig, or the scan's rig). Writes that rig "
                                      "with the fitted turntable axis (docs/calibration.md).")
    p.add_argument("inputs", nargs="+", metavar="SCAN_OR_IMAGE", help="one scan folder, or board images")
    p.add_argument("--angles", type=float, nargs="+", default=None, metavar="DEG",
                   help="table angle of each image (degrees, right-handed about the axis); images only")
    p.add_argument("--frame", default="white", help="which frame of each scan view shows the board (default white)")
    add_board_options(p)
    p.add_argument("--rig", default=None, metavar="RIG",
                   help="rig file whose camera to use (default: the scan's); its turntable, if any, only tells "
                        "the rough axis line")
    p.add_argument("--out", required=True, metavar="RIG", help="rig file to write (the rig with this turntable)")
    p.add_argument("--report", default=None, metavar="JSON", help="also write the figures as JSON")
    add_force_option(p)
    basic_options(p, "--angles", "--rig", "--board", "--charuco", "--report")
    p.set_defaults(_calibrate=run_turntable)


def run_turntable(args) -> int:
    board = board_from_args(args)
    rig = load_rig(args.rig) if args.rig else None
    inputs = [*(scan_inputs(load_scan(args.inputs[0])) if len(args.inputs) == 1 and Path(args.inputs[0]).is_dir()
                else args.inputs), *([args.rig] if args.rig else [])]
    check_outputs({"--out": args.out, "--report": args.report}, inputs)
    prior = (0.0, 0.0, 1.0) if rig is None or rig.turntable is None else tuple(rig.turntable.axis_dir)
    settings = TurntableSettings(board=board_settings_from_args(args), prior_axis=prior)
    if len(args.inputs) == 1 and Path(args.inputs[0]).is_dir():
        if args.angles is not None:
            raise UsageError("--angles: a scan's views carry their own table angles (turntable_deg)")
        scan = load_scan(args.inputs[0])
        if rig is not None and (scan.rig.camera.width, scan.rig.camera.height) != (rig.camera.width,
                                                                                rig.camera.height):
            raise FormatError(args.inputs[0], f"the scan's frames are {scan.rig.camera.width}x"
                                              f"{scan.rig.camera.height}, the camera of {args.rig} is "
                                              f"{rig.camera.width}x{rig.camera.height}")
        rig = scan.rig if rig is None else rig
        if args.rig is None and rig.turntable is not None:
            settings = TurntableSettings(board=settings.board, prior_axis=tuple(rig.turntable.axis_dir))
        views, angles = board_views_of_scan(scan, board=board, frame=args.frame, settings=settings)
    else:
        if args.angles is None or len(args.angles) != len(args.inputs):
            n = 0 if args.angles is None else len(args.angles)
            raise UsageError(f"--angles: {n} angle(s) for {len(args.inputs)} image(s); give one per image")
        if rig is None:
            raise UsageError("--rig: images need the rig file of the calibrated camera")
        views = []
        for path in args.inputs:
            img = read_image(path)
            if img.shape[:2] != (rig.camera.height, rig.camera.width):
                raise FormatError(path, f"image is {img.shape[1]}x{img.shape[0]}, the camera of {args.rig} is "
                                        f"{rig.camera.width}x{rig.camera.height}")
            views.append(detect_board(img, board=board, name=view_name(path), settings=settings.board))
        angles = list(args.angles)
    print(f"board {board.cols}x{board.rows} found in {sum(v.found for v in views)} of {len(views)} views:")
    print_views(views)
    with progress_step("fitting the turntable axis", enabled=not args.no_progress):
        cal = calibrate_turntable(views, angles, board=board, camera=rig.camera, volume=rig.volume, settings=settings)
    tt = cal.turntable
    print(f"turntable axis: through ({', '.join(f'{x:.3f}' for x in tt.axis_point)}) along "
          f"({', '.join(f'{x:.5f}' for x in tt.axis_dir)}); RMS reprojection error {cal.rms_px:.3f} px "
          f"over {len(cal.names)} views")
    for n, a, e, d in zip(cal.names, cal.angles_deg, cal.per_view_px, cal.angle_error_deg):
        print(f"  {n} at {a:g} deg: {e:.3f} px, board turned {d:+.3f} deg from the table's angle")
    for n in cal.outliers:
        print(f"  {n}: spoils the fit, left out")
    refuse_unless_forced(args, cal.problems, args.out)
    save_rig(args.out, rig_with_turntable(rig, tt))
    print(f"wrote {args.out}")
    if args.report:
        atomic_write_json(args.report, cal.report())
    return 0

