"""``ringscan calibrate <what> ...``: calibration of a real rig (docs/calibration.md).

Sub-commands register themselves: each ``add_<name>_parser(calsub)`` adds one
sub-command and sets ``_calibrate`` to its run function; :func:`run` dispatches.

- ``camera IMAGES...``: camera intrinsics from chessboard or ChArUco images;
- ``stereo --cam1 IMAGES... --cam2 IMAGES...``: two cameras and their pose from board image pairs;
- ``procam CAPTURE_DIR...``: camera + perspective projector from Gray-code captures;
- ``response CAPTURE_DIR...``: the projector's response curve;
- ``pose IMAGE``: the camera's pose over the reference plane from a board lying on it;
- ``light SCAN... --heights ...``: the parallel light from ring captures of a plane at known heights;
- ``turntable SCAN | IMAGES... --angles ...``: the turntable axis from a board at several table angles.
- ``latency --projector display:N --camera SPEC``: how long after a frame's swap the camera sees it in full.
- ``refine SCAN``: the extrinsics re-estimated from a scan's own matches (two cameras, or camera and projector);
- ``projector-from-scan SCAN``: the projector fitted to a two-camera scan's points (a procam rig).

New sub-commands are found by name: any module-level ``add_<name>_parser`` function
is called by :func:`add_parser`, in definition order.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
from pathlib import Path

import cv2
import numpy as np

from ringscan.hardware.capture.latency import LatencySettings, latency_frames, measure_latency, write_rig_latency
from ringscan.hardware.devices.camera import open_camera
from ringscan.hardware.devices.display import DisplayProjector, choose_display, list_displays, parse_display_spec
from ringscan.pipeline.calibrate.board import (
    ARUCO_DICTIONARIES,
    Board,
    BoardSettings,
    charuco_dictionary,
    detect_board,
)
from ringscan.pipeline.calibrate.camera import (
    LENS_MODELS,
    CameraSettings,
    calibrate_camera,
    calibration_report,
    camera_block,
    reprojection_residuals,
)
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import LAYOUTS, expand_capture_frame, read_capture
from ringscan.pipeline.calibrate.light import (
    LightSettings,
    calibrate_parallel_light,
    camera_pose_on_plane,
    rig_with_light,
)
from ringscan.pipeline.calibrate.procam import (
    ProcamSettings,
    calibrate_procam,
    capture_corners,
    depth_range,
    principal_point_inside,
    procam_rig,
)
from ringscan.pipeline.calibrate.opencv_files import (
    write_opencv_procam,
    write_opencv_stereo,
    write_opencv_stereo_cameras,
)
from ringscan.pipeline.calibrate.projector_fit import (
    DISTORTION_CHOICES,
    ProjectorSettings,
    decoded_pairs,
    fit_projector,
    procam_rig_from_fit,
    triangulation_covariance,
)
from ringscan.pipeline.calibrate.rig_refine import (
    MAX_MATCHES,
    refine_procam_rig,
    refine_stereo_rig,
    relative_pose,
    reprojection_errors,
    triangulate_pair,
)
from ringscan.pipeline.calibrate.stereo_boards import calibrate_stereo_boards
from ringscan.pipeline.calibrate.response import estimate_light_gamma, repeated_frames, response_problems
from ringscan.pipeline.calibrate.turntable import (
    TurntableSettings,
    board_views_of_scan,
    calibrate_turntable,
    rig_with_turntable,
)
from ringscan.pipeline.formats.atomic import atomic_write_json, check_no_overwrite, check_output_file, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import few_bits_hint, read_image
from ringscan.pipeline.formats.progress import progress_bar, progress_step
from ringscan.pipeline.formats.rig import PerspectiveLight, load_rig, parse_rig, save_rig
from ringscan.pipeline.formats.scan import check_frame_bits, load_scan
from ringscan.pipeline.preview.plots import PLOT_FORMATS, residuals_figure, save_figure
from ringscan.pipeline.reconstruct.scan import scan_inputs
from ringscan.tools.cli import UsageError, add_device_option


MAX_SIZE = 65536
"""Largest width or height ``parse_size`` accepts (the rig file's limit)."""

MAX_WINDOW_PX = 200
"""Largest ``calibrate procam --window`` (camera px): a homography is fitted to the (2w+1)^2 pixels around each
corner, so the time grows with its square (100000 ran for minutes)."""


def parse_size(text: str, what: str) -> tuple[int, int]:
    """'9x7' -> (9, 7); a clear error otherwise (each side 1..65536)."""
    if not isinstance(text, str):  # argparse gives `--board=--` as an empty list
        text = " ".join(map(str, text)) if isinstance(text, (list, tuple)) else str(text)
        text = text or "--"
    shown = text if len(text) <= 40 else text[:37] + "..."
    try:
        a, b = text.lower().split("x")
        if not (a.strip().isdigit() and b.strip().isdigit()) or len(a.strip()) > 6 or len(b.strip()) > 6:
            raise ValueError
        w, h = int(a), int(b)
    except ValueError:
        raise UsageError(f"{what}: expected WxH (e.g. 9x7), got {shown!r}") from None
    if not (0 < w <= MAX_SIZE and 0 < h <= MAX_SIZE):
        raise UsageError(f"{what}: sizes must be from 1 to {MAX_SIZE}, got {shown!r}")
    return w, h


def check_outputs(outputs: dict, inputs) -> None:
    """Refuse output files (option -> path; None: not given) that are the same file, that would overwrite an input,
    or that cannot be written as files, before anything is computed.

    Raises:
        FormatError: naming the output.
    """
    given = {opt: p for opt, p in outputs.items() if p}
    seen: dict = {}
    for opt, p in given.items():
        check_output_file(p, what=f"file {opt} writes")
        key = os.path.realpath(p)
        if key in seen:
            raise FormatError(p, f"given to both {seen[key]} and {opt}: one would overwrite the other")
        seen[key] = opt
    check_no_overwrite(list(given.values()), [str(i) for i in inputs])


def folder_files(folders) -> list[Path]:
    """The regular files directly in each folder (a capture's frames): outputs must not overwrite them."""
    out = []
    for f in folders:
        with contextlib.suppress(OSError):
            out += [Path(e.path) for e in os.scandir(f) if e.is_file()]
    return out


def view_name(path) -> str:
    """An image's name in messages: its folder and file name (captures share file names)."""
    return "/".join(Path(path).parts[-2:])


def _charuco_arg(text: str) -> str:
    import argparse

    try:
        return charuco_dictionary(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_board_options(p) -> None:
    g = p.add_argument_group("board")
    g.add_argument("--board", default="9x7", metavar="COLSxROWS", help="inner corners of the chessboard (default 9x7)")
    g.add_argument("--square", type=float, required=True, help="square size in mm (the rig's units)")
    g.add_argument("--charuco", type=_charuco_arg, default=None, metavar="DICT",
                   help="a ChArUco board with this predefined ArUco dictionary, any case (--board counts its inner "
                        "corners; OpenCV's layout before 4.6.0 is recognised by itself): "
                        + ", ".join(ARUCO_DICTIONARIES))
    g.add_argument("--marker", type=float, default=0.0, help="ChArUco marker size in mm (default 0.75 x square)")
    g.add_argument("--max-tilt", type=float, default=BoardSettings.max_tilt_deg,
                   help=f"reject views tilted more than this (degrees, default {BoardSettings.max_tilt_deg:g})")
    g.add_argument("--max-edge-width", type=float, default=BoardSettings.max_edge_width_px,
                   help=f"reject chessboards with edges wider than this (px, default {BoardSettings.max_edge_width_px:g})")


def add_fit_options(p) -> None:
    g = p.add_argument_group("fit")
    g.add_argument("--fix-k3", choices=("auto", "yes", "no"), default="auto",
                   help=f"hold k3 at 0 (auto: below {CameraSettings.k3_min_views} views)")
    g.add_argument("--fix-tangential", choices=("auto", "yes", "no"), default="auto",
                   help=f"hold p1, p2 at 0 (auto: below {CameraSettings.tangential_min_views} views)")
    g.add_argument("--min-views", type=int, default=CameraSettings.min_views,
                   help=f"fewest usable views (default {CameraSettings.min_views})")


def add_force_option(p) -> None:
    p.add_argument("--force", action="store_true",
                   help="write the result even where the calibration finds it cannot stand behind it (what it "
                        "cannot determine is printed as warnings); without it such a result is refused and "
                        "nothing is written")


def refuse_unless_forced(args, problems: list[str], out) -> None:
    """One line naming every problem and nothing written, unless --force (then warnings)."""
    if not problems:
        return
    if getattr(args, "force", False):
        for p in problems:
            print(f"warning: {p}")
        print("--force: writing it all the same")
        return
    raise CalibrationError(None, f"not writing {out}: {'; '.join(problems)} (--force writes it anyway)")


def print_duplicates(dups: list[str]) -> None:
    for d in dups:
        print(f"  {d}: the same board pose as the earlier view, left out")


def board_from_args(args) -> Board:
    cols, rows = parse_size(args.board, "--board")
    try:
        return Board(cols=cols, rows=rows, square=args.square, charuco=args.charuco, marker=args.marker)
    except ValueError as e:
        raise ValueError(f"--board/--square/--marker: {e}") from None


def board_settings_from_args(args) -> BoardSettings:
    if not 0 < args.max_edge_width <= 1000:
        raise ValueError(f"--max-edge-width: expected px from 0 to 1000, got {args.max_edge_width:g}")
    if not 0 < args.max_tilt <= 90:
        raise ValueError(f"--max-tilt: expected degrees from 0 to 90, got {args.max_tilt:g}")
    return BoardSettings(max_edge_width_px=args.max_edge_width, max_tilt_deg=args.max_tilt)


def camera_settings_from_args(args) -> CameraSettings:
    tri = {"auto": None, "yes": True, "no": False}
    model = getattr(args, "lens_model", "standard")  # procam has no --lens-model
    if model != "standard" and args.fix_k3 != "auto":
        raise UsageError(f"--fix-k3 applies to --lens-model standard only (the {model} model always fits k3)")
    return CameraSettings(min_views=args.min_views, fix_k3=tri[args.fix_k3], fix_tangential=tri[args.fix_tangential],
                          lens_model=model)


def print_views(views) -> None:
    for v in views:
        found = "found" + (" (ChArUco board of OpenCV's legacy layout, before 4.6.0)" if v.legacy else "")
        print(f"  {v.name}: {found if v.found else v.reason}")


def print_calibration(what: str, cal) -> None:
    print(f"{what}: RMS reprojection error {cal.rms:.3f} px over {len(cal.names)} views; "
          f"fx {cal.K[0, 0]:.1f} fy {cal.K[1, 1]:.1f} cx {cal.K[0, 2]:.1f} cy {cal.K[1, 2]:.1f}; "
          f"dist {', '.join(f'{x:.4g}' for x in cal.dist)}; fixed: {', '.join(cal.fixed) or 'none'}")
    for n, e in zip(cal.names, cal.per_view):
        flag = "  <- spoils the fit" if n in cal.outliers else ""
        print(f"  {n}: {e:.3f} px{flag}")


# ----------------------------------------------------------------------------- camera


def add_camera_parser(calsub) -> None:
    p = calsub.add_parser("camera", help="camera intrinsics from chessboard or ChArUco images",
                          description="Detect the board in every image (found, or why not: not found, blurred, too "
                                      "oblique), calibrate the camera (OpenCV), print the reprojection error overall "
                                      "and per image, and write the rig file's camera block.")
    p.add_argument("images", nargs="+", metavar="IMAGE", help="board images (8/16-bit PNG/TIFF/JPEG)")
    add_board_options(p)
    add_fit_options(p)
    p.add_argument("--lens-model", choices=tuple(LENS_MODELS), default="standard",
                   help="distortion model: standard (k1, k2, p1, p2, k3), rational (+ k4, k5, k6: wide-angle lenses; "
                        f"needs {CameraSettings.wide_min_views} views and the board in the image's corners) or "
                        "thin-prism (+ s1..s4 as well); --fix-k3 applies to standard only (default standard)")
    p.add_argument("--out", default=None, metavar="JSON",
                   help="write {'camera': block, 'report': ...} here (the camera block of a rig file)")
    p.add_argument("--rig", default=None, metavar="RIG",
                   help="update this rig file's camera intrinsics in place (its extrinsics are kept)")
    p.add_argument("--plot", default=None, metavar="PNG_OR_SVG",
                   help="also draw the reprojection residuals (per view, and every corner's across the image) "
                        "into this PNG or SVG file")
    add_force_option(p)
    p.set_defaults(_calibrate=run_camera)


def run_camera(args) -> int:
    if not args.out and not args.rig:
        raise UsageError("calibrate camera: give --out JSON or --rig RIG (where the camera block goes)")
    if args.plot:
        check_output_file(args.plot, extensions=PLOT_FORMATS, what="plot (--plot)")
    board = board_from_args(args)
    bs = board_settings_from_args(args)
    check_outputs({"--out": args.out, "--rig": args.rig, "--plot": args.plot}, args.images)
    cs = camera_settings_from_args(args)
    rig_size = None
    if args.rig:
        r = parse_rig(read_json(args.rig), source=args.rig)
        rig_size = (r.camera.width, r.camera.height)
    views, size = _detect_all(args.images, board, bs, None, args.no_progress)
    print(f"board {board.cols}x{board.rows} found in {sum(v.found for v in views)} of {len(views)} images:")
    print_views(views)
    with progress_step("fitting the camera", enabled=not args.no_progress):
        cal = calibrate_camera(views, board=board, size=size, settings=cs)
    print_calibration("camera", cal)
    if cal.lens_model != "standard":
        print(f"  lens model: {cal.lens_model} ({len(cal.dist)} coefficients)")
    print_duplicates(cal.duplicates)
    problems = list(cal.problems)
    if rig_size is not None and size != rig_size:
        problems.append(f"the images are {size[0]}x{size[1]}, the camera of {args.rig} is "
                        f"{rig_size[0]}x{rig_size[1]} (its pose and light were calibrated at that size)")
    refuse_unless_forced(args, problems, args.out or args.rig)
    block = camera_block(cal)
    if args.plot:
        fig = residuals_figure(dict(zip(cal.names, cal.per_view)), reprojection_residuals(views, board, cal),
                               image_size=size, outliers=cal.outliers,
                               title=f"camera: RMS reprojection error {cal.rms:.3f} px over {len(cal.names)} views")
        save_figure(fig, args.plot)
        print(f"wrote {args.plot}")
    if args.out:
        atomic_write_json(args.out, {"camera": block, "report": calibration_report(cal)})
        print(f"wrote {args.out}")
    if args.rig:
        d = read_json(args.rig)
        cam = d.get("camera") if isinstance(d, dict) else None
        if not isinstance(cam, dict):
            raise FormatError(args.rig, "camera: missing or not an object")
        cam.update(block)
        save_rig(args.rig, parse_rig(d, source=args.rig))
        print(f"updated the camera of {args.rig}")
    return 0


# ----------------------------------------------------------------------------- stereo


def add_stereo_parser(calsub) -> None:
    p = calsub.add_parser("stereo", help="two cameras' intrinsics and relative pose from board image pairs",
                          description="Calibrates each camera from its board images (as calibrate camera does), "
                                      "then the pair's pose from the pairs in which both cameras found the board "
                                      "(OpenCV's stereoCalibrate, intrinsics held). Writes the pair as OpenCV "
                                      "FileStorage in the layout of OpenCV's structured-light sample (what "
                                      "ringscan import --rig reads).")
    p.add_argument("--cam1", nargs="+", required=True, metavar="IMAGE",
                   help="camera 1's board images, in the order of the pairs")
    p.add_argument("--cam2", nargs="+", required=True, metavar="IMAGE",
                   help="camera 2's board images of the same board poses, in the same order")
    add_board_options(p)
    add_fit_options(p)
    p.add_argument("--out", required=True, metavar="YML",
                   help="the pair as OpenCV FileStorage (.yml/.yaml/.xml; cam1_intrinsics ... R, T)")
    p.add_argument("--report", default=None, metavar="JSON", help="also write the figures as JSON")
    add_force_option(p)
    p.set_defaults(_calibrate=run_stereo)


def _detect_all(paths, board, bs, what: str | None, no_progress: bool):
    """(detections, image size) of the board in every image (of one camera: ``what``, for messages)."""
    views, size = [], None
    for path in progress_bar(paths, desc="detecting the board" + (f" ({what})" if what else ""), unit="image",
                             disable=no_progress, leave=False):
        img = read_image(path)
        s = (img.shape[1], img.shape[0])
        if size is None:
            size = s
        elif s != size:
            first = f"{what}'s first image" if what else "the first image"
            raise FormatError(path, f"image is {s[0]}x{s[1]}, {first} is {size[0]}x{size[1]}")
        views.append(detect_board(img, board=board, name=view_name(path), settings=bs))
    return views, size


def run_stereo(args) -> int:
    if len(args.cam1) != len(args.cam2):
        raise UsageError(f"--cam1 has {len(args.cam1)} images, --cam2 {len(args.cam2)}: give them in pairs "
                         "(the same board pose, in the same order)")
    if Path(args.out).suffix.lower() not in (".yml", ".yaml", ".xml"):
        raise UsageError(f"--out {args.out}: OpenCV FileStorage needs .yml, .yaml or .xml")
    board = board_from_args(args)
    bs = board_settings_from_args(args)
    check_outputs({"--out": args.out, "--report": args.report}, [*args.cam1, *args.cam2])
    cs = camera_settings_from_args(args)
    v1, size1 = _detect_all(args.cam1, board, bs, "camera 1", args.no_progress)
    v2, size2 = _detect_all(args.cam2, board, bs, "camera 2", args.no_progress)
    for what, views in (("camera 1", v1), ("camera 2", v2)):
        print(f"{what}: board {board.cols}x{board.rows} found in {sum(v.found for v in views)} of {len(views)} "
              "images:")
        print_views(views)
    with progress_step("fitting the cameras and their pose", enabled=not args.no_progress):
        cal = calibrate_stereo_boards(v1, v2, board=board, size1=size1, size2=size2, settings=cs)
    print_calibration("camera 1", cal.camera1)
    print_calibration("camera 2", cal.camera2)
    rot = math.degrees(float(np.linalg.norm(cv2.Rodrigues(cal.R)[0])))
    print(f"pair: RMS reprojection error {cal.rms:.3f} px over {len(cal.pairs)} pairs; baseline {cal.baseline:.2f} "
          f"(board units: mm when --square is); cameras turned {rot:.2f} deg from each other")
    for n, e in zip(cal.pairs, cal.per_pair):
        print(f"  {n}: {e:.3f} px")
    refuse_unless_forced(args, cal.problems, args.out)
    write_opencv_stereo_cameras(args.out, *cal.cameras())
    print(f"wrote {args.out} (import with: ringscan import CAPTURE --rig {args.out} --projector WxH)")
    if args.report:
        atomic_write_json(args.report, cal.report())
        print(f"wrote {args.report}")
    return 0


# ----------------------------------------------------------------------------- procam


def add_procam_parser(calsub) -> None:
    p = calsub.add_parser("procam", help="camera + perspective projector from Gray-code captures of a board",
                          description="Each CAPTURE_DIR holds graycode_NN frames of the board under the projector's "
                                      "column/row Gray code (see --layout). The board's corners are found in the white "
                                      "frame, each corner's projector position comes from a local homography fitted "
                                      "to the decoded pixels around it (Moreno & Taubin 2012); the projector is "
                                      "calibrated like a camera, then the pair is stereo-calibrated. Writes a rig "
                                      "file with the perspective light and a working volume around the boards.")
    p.add_argument("captures", nargs="+", metavar="CAPTURE_DIR", help="capture folders (one board pose each)")
    add_board_options(p)
    add_fit_options(p)
    p.add_argument("--projector", required=True, metavar="WxH", help="projector size in pixels, e.g. 1024x768")
    p.add_argument("--layout", choices=LAYOUTS, default="opencv-graycode",
                   help="frame order: opencv-graycode = column pairs, row pairs, white, black (OpenCV's files); "
                        "opencv-graycode-wb-first = white, black, then the pairs")
    p.add_argument("--window", type=int, default=ProcamSettings.window_px,
                   help=f"local-homography half window in camera px (default {ProcamSettings.window_px})")
    p.add_argument("--out", required=True, metavar="RIG", help="the rig file to write")
    p.add_argument("--report", default=None, metavar="JSON", help="also write the figures as JSON")
    add_force_option(p)
    p.set_defaults(_calibrate=run_procam)


def run_procam(args) -> int:
    board = board_from_args(args)
    proj_size = parse_size(args.projector, "--projector")
    if not 1 <= args.window <= MAX_WINDOW_PX:
        raise ValueError(f"--window: expected camera px from 1 to {MAX_WINDOW_PX}, got {args.window}")
    check_outputs({"--out": args.out, "--report": args.report}, folder_files(args.captures))
    settings = ProcamSettings(window_px=args.window, camera=camera_settings_from_args(args),
                              board=board_settings_from_args(args))
    caps, size, done = [], None, {}
    for folder in progress_bar(args.captures, desc="decoding captures", unit="capture", disable=args.no_progress,
                               leave=False):
        key = os.path.realpath(folder)
        if key in done:  # a folder given again is not decoded again; calibrate_procam leaves the repeat out
            cc = dataclasses.replace(done[key])  # its own object: repeats are told apart by identity
        else:
            cap = read_capture(folder, projector=proj_size, layout=args.layout)
            s = (cap.white.shape[1], cap.white.shape[0])
            if size is None:
                size = s
            elif s != size:
                raise FormatError(folder, f"frames are {s[0]}x{s[1]}, {args.captures[0]} has {size[0]}x{size[1]}")
            cc = done[key] = capture_corners(cap, board=board, name=Path(folder).name, settings=settings)
            del cap
        print(f"  {cc.name}: " + ("board found" if cc.camera_view.found else cc.camera_view.reason)
              + ("" if not cc.camera_view.found else
                 (f", {len(cc.projector_view.ids)} corners in the projector" if cc.projector_view.found
                  else f", {cc.projector_view.reason}")))
        caps.append(cc)
    with progress_step("fitting the camera and projector", enabled=not args.no_progress):
        res = calibrate_procam(caps, board=board, camera_size=size, projector_size=proj_size, settings=settings)
    print_duplicates(res.duplicates)
    print_calibration("camera", res.camera)
    print_calibration("projector", res.projector)
    print(f"stereo: RMS reprojection error {res.stereo_rms:.3f} px; baseline {np.linalg.norm(res.T):.1f}; "
          f"T {', '.join(f'{x:.1f}' for x in res.T)}")
    for n, e in res.stereo_per_view.items():
        print(f"  {n}: {e:.3f} px")
    refuse_unless_forced(args, res.problems, args.out)
    if not principal_point_inside(res.projector.K, proj_size):
        print(f"note: the projector's principal point ({res.projector.K[0, 2]:.0f}, {res.projector.K[1, 2]:.0f}) "
              "lies outside its image: rings about it are arcs, and the cone model is ill-conditioned where "
              "the camera rays graze them (see docs/calibration.md)")
    near, far = depth_range(res.depths)
    rig = procam_rig(cam_K=res.camera.K, cam_dist=res.camera.dist, cam_size=size, proj_K=res.projector.K,
                     proj_dist=res.projector.dist, proj_size=proj_size, R=res.R, T=res.T, z_range=(near, far))
    save_rig(args.out, rig)
    print(f"wrote {args.out} (perspective light; working volume {near:.0f}..{far:.0f} along the projector axis)")
    if args.report:
        atomic_write_json(args.report, {"camera": calibration_report(res.camera),
                                        "projector": calibration_report(res.projector),
                                        "stereo": {"rms_px": res.stereo_rms, "views": res.stereo_per_view,
                                                   "R": res.R.tolist(), "T": res.T.tolist()},
                                        "duplicates": list(res.duplicates), "problems": list(res.problems)})
    return 0


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
    if args.frame_bits is not None:
        try:
            check_frame_bits(args.frame_bits, where="--frame-bits")
        except FormatError as e:
            raise UsageError(str(e)) from None
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
    d["camera"]["R"], d["camera"]["t"] = R.tolist(), t.tolist()
    if rig.light.model == "perspective":
        # A projector calibrated with the camera (calibrate procam) is fixed to it: it
        # moves with the camera into the board's frame, so the baseline is kept.
        Rrel = rig.light.R @ cam.R.T
        Trel = rig.light.t - Rrel @ cam.t
        d["light"]["R"], d["light"]["t"] = (Rrel @ R).tolist(), (Rrel @ t + Trel).tolist()
    new = parse_rig(d, source=args.rig)
    if rig.light.model == "perspective":
        before = float(np.linalg.norm(-rig.light.R.T @ rig.light.t + cam.R.T @ cam.t))
        after = float(np.linalg.norm(-new.light.R.T @ new.light.t + new.camera.R.T @ new.camera.t))
        if abs(after - before) > 1e-6 * max(before, 1.0):
            raise CalibrationError(args.rig, f"the camera-projector baseline would change from {before:.1f} to "
                                             f"{after:.1f}; not written")
        print(f"the projector moves with the camera (baseline {after:.1f} kept)")
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


# ----------------------------------------------------------------------------- refine, projector-from-scan

OPENCV_EXTENSIONS = (".yml", ".yaml", ".xml")
"""What ``--opencv`` may end in (OpenCV FileStorage picks the format from it)."""


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


def load_scan_with_rig(args):
    """The scan, with the rig of --rig in place of its own (same cameras' image sizes), and the views to use."""
    if args.rig and Path(args.rig).suffix.lower() in OPENCV_EXTENSIONS:
        raise FormatError(args.rig, "an OpenCV FileStorage file; --rig takes a ringscan rig (JSON): import the "
                                    "calibration first (docs/calibration.md)")
    scan = load_scan(args.scan)
    if args.rig:
        rig = load_rig(args.rig)
        own = scan.rig
        for what, a, b in (("camera", rig.camera, own.camera), ("camera2", rig.camera2, own.camera2)):
            if (a is None) != (b is None):
                has = "two cameras" if rig.camera2 is not None else "one camera"
                raise FormatError(args.rig, f"has {has}, the scan {args.scan} "
                                            f"{'two cameras' if own.camera2 is not None else 'one camera'}")
            if a is not None and (a.width, a.height) != (b.width, b.height):
                raise FormatError(args.rig, f"{what} is {a.width}x{a.height}, the scan's frames are "
                                            f"{b.width}x{b.height}")
        scan = dataclasses.replace(scan, rig=rig)
    views = list(scan.views)
    if args.view:
        names = {v.name: v for v in views}
        missing = [n for n in args.view if n not in names]
        if missing:
            raise FormatError(scan.path, f"no view {missing[0]!r} (views: {', '.join(sorted(names))})")
        views = [names[n] for n in dict.fromkeys(args.view)]
    return scan, views


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


def gather_matches(scan, views, args, *, need: str):
    """Matches of every view, subsampled to --max-matches: (uv1, uv2 or None, proj, sigmas or None).

    ``need``: "cameras" (a two-camera scan's matches) or "projector" (camera-projector pairs:
    a two-camera scan's, or an imported one-camera scan's decoded pixels)."""
    two = [v for v in views if v.camera2 is not None]
    if need == "cameras" and len(two) < len(views):
        one = next(v for v in views if v.camera2 is None)
        raise FormatError(scan.path, f"view {one.name} has one camera's frames; matching cameras needs both")
    per = max(1, args.max_matches // max(1, len(views)))
    u1s, u2s, ps, ss = [], [], [], []
    for v in progress_bar(views, desc="matching", unit="view", disable=args.no_progress, leave=False):
        if v.camera2 is not None:
            u1, u2, pr, sg = view_matches(scan, v, device=args.device,
                                          ring_curvature=getattr(args, "ring_curvature", "on") == "on")
        else:
            u1, pr = decoded_pairs(scan, v, max_pairs=per)
            u2 = sg = None
        if u1.shape[0] > per:
            pick = np.sort(np.random.default_rng(len(u1s)).choice(u1.shape[0], per, replace=False))
            u1, pr = u1[pick], pr[pick]
            u2 = None if u2 is None else u2[pick]
            sg = None if sg is None else sg[pick]
        print(f"  {v.name}: {u1.shape[0]} matches")
        u1s.append(u1)
        ps.append(pr)
        if u2 is not None:
            u2s.append(u2)
        if sg is not None:
            ss.append(sg)
    uv1, proj = np.concatenate(u1s), np.concatenate(ps)
    uv2 = np.concatenate(u2s) if len(u2s) == len(u1s) else None
    sig = np.concatenate(ss) if len(ss) == len(u1s) else None
    return uv1, uv2, proj, sig


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
    p.set_defaults(_calibrate=run_refine)


def run_refine(args) -> int:
    if args.baseline is not None and not (np.isfinite(args.baseline) and 0 < args.baseline <= 1e5):
        raise UsageError(f"--baseline: expected mm from 0 to 100000, got {args.baseline:g}")
    outs = match_outputs(args)
    scan, views = load_scan_with_rig(args)
    rig = scan.rig
    pair = args.pair if args.pair != "auto" else ("cameras" if rig.camera2 is not None else "projector")
    if pair == "cameras" and rig.camera2 is None:
        raise FormatError(args.rig or scan.path, "has one camera: --pair cameras needs a two-camera rig")
    if pair == "projector" and not isinstance(rig.light, PerspectiveLight):
        raise FormatError(args.rig or scan.path, f"its projector is not calibrated (model {rig.light.model!r}): "
                                                 "refining it needs a perspective projector (a two-camera rig's "
                                                 "projector: `ringscan calibrate projector-from-scan`)")
    uv1, uv2, proj, sig = gather_matches(scan, views, args, need=pair)
    with progress_step("refining", enabled=not args.no_progress):
        if pair == "cameras":
            use_light = isinstance(rig.light, PerspectiveLight) and not args.two_view
            new, ref = refine_stereo_rig(rig, uv1, uv2, baseline_mm=args.baseline,
                                         sigma1=None if sig is None else sig[:, 0],
                                         sigma2=None if sig is None else sig[:, 1],
                                         uv_light=proj if use_light else None,
                                         sigma_light=None if sig is None or not use_light else sig[:, 2])
        else:
            # a two-camera rig's camera 2 (pose held) joins as the third device where every view has its matches
            use_cam2 = rig.camera2 is not None and uv2 is not None and not args.two_view
            new, ref = refine_procam_rig(rig, uv1, proj, baseline_mm=args.baseline,
                                         uv_camera2=uv2 if use_cam2 else None,
                                         sigma_cam=None if sig is None or not use_cam2 else sig[:, 0],
                                         sigma_proj=None if sig is None or not use_cam2 else sig[:, 2],
                                         sigma_camera2=None if sig is None or not use_cam2 else sig[:, 1])
            if rig.camera2 is not None and uv2 is None and not args.two_view:
                ref.notes.append("camera 2 was left out of the adjustment: a view has one camera's frames")
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
    p.set_defaults(_calibrate=run_projector_from_scan)


PARALLEL_RMS_PX = 0.5
"""A projector whose pixels are an affine function of the points to within this (px RMS) is a parallel
(collimated) light: a pinhole's are not, unless the points lie in one plane."""


def no_pinhole_projector(X: np.ndarray, uv: np.ndarray) -> str:
    """Why no pinhole projector fits the points' projector pixels (OpenCV only says that the principal
    point left the image): an affine map fits them (a parallel light), or they fit no camera model."""
    A = np.c_[X, np.ones(len(X))]
    coef, *_ = np.linalg.lstsq(A, uv, rcond=None)
    rms = float(np.sqrt(np.mean(np.sum((A @ coef - uv) ** 2, axis=1))))
    thick = float(np.linalg.svd(X - X.mean(0), compute_uv=False)[-1] / np.sqrt(len(X)))
    if rms <= PARALLEL_RMS_PX and thick > 1.0:
        return (f"no pinhole projector fits the scan: its projector pixels are an affine function of the points "
                f"(RMS {rms:.2f} px), the mark of a parallel (collimated) light such as the virtual rig's default "
                "(`ringscan simulate --light parallel`); projector-from-scan fits a perspective projector; a "
                "parallel light is calibrated with `ringscan calibrate light` (docs/calibration.md)")
    return ("no pinhole projector fits the scan's projector pixels (the fit put the principal point outside the "
            f"projector image; an affine map leaves {rms:.1f} px RMS): check --projector WxH and that the scan's "
            "projector coordinates are the projector's pixels")


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
    scan, views = load_scan_with_rig(args)
    rig = scan.rig
    if rig.camera2 is None:
        raise FormatError(args.rig or scan.path, "has one camera: projector-from-scan needs a two-camera rig "
                                                 "(camera2) and a two-camera scan")
    if size is None:
        size = (getattr(rig.light, "width", 0), getattr(rig.light, "height", 0))
        if not min(size) > 0:
            raise UsageError("--projector: the rig does not give the projector's size; give --projector WxH")
    uv1, uv2, proj, sig = gather_matches(scan, views, args, need="cameras")
    c1, c2 = rig.camera, rig.camera2
    R, t = relative_pose(c1, c2)
    n1 = cv2.undistortPoints(uv1.reshape(-1, 1, 2), c1.K, c1.dist).reshape(-1, 2)
    n2 = cv2.undistortPoints(uv2.reshape(-1, 1, 2), c2.K, c2.dist).reshape(-1, 2)
    err, front = reprojection_errors(R, t, c1, c2, uv1, uv2, n1, n2)
    print(f"two-camera points: reprojection error median {np.median(err):.3f} px, p95 "
          f"{np.percentile(err, 95):.3f} px over {err.size} matches")
    problems = []
    if not np.median(err) <= 1.0:
        problems.append(f"the rig's cameras do not fit the matches (reprojection median {np.median(err):.2f} px > "
                        "1 px): run `ringscan calibrate refine` first")
    keep = front & (err <= 3.0)
    Xc = triangulate_pair(R, t, n1[keep], n2[keep])
    Xw = (Xc - c1.t) @ c1.R
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


# ----------------------------------------------------------------------------- dispatch


def add_parser(sub):
    p = sub.add_parser("calibrate", help="calibrate a real rig: camera, projector (procam), response",
                       description="Calibration of a real rig; see docs/calibration.md.",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    calsub = p.add_subparsers(dest="what", metavar="WHAT")
    for name, fn in list(globals().items()):
        if name.startswith("add_") and name.endswith("_parser") and name not in ("add_parser",) and callable(fn):
            fn(calsub)
    return p


def run(args) -> int:
    fn = getattr(args, "_calibrate", None)
    if fn is None:
        raise UsageError("calibrate: say what to calibrate (e.g. `ringscan calibrate camera --help`)")
    return int(fn(args) or 0)
