"""``ringscan calibrate camera | stereo | procam``: the calibrations from board images (docs/calibration.md).

- ``camera IMAGES...``: camera intrinsics from chessboard or ChArUco images;
- ``stereo --cam1 IMAGES... --cam2 IMAGES...``: two cameras and their pose from board image pairs;
- ``procam CAPTURE_DIR...``: camera + perspective projector from Gray-code captures.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.board import detect_board_images
from ringscan.pipeline.calibrate.camera import (
    LENS_MODELS,
    CameraSettings,
    calibrate_camera,
    calibration_report,
    camera_block,
    reprojection_residuals,
)
from ringscan.pipeline.calibrate.graycode import LAYOUTS
from ringscan.pipeline.calibrate.opencv_files import write_opencv_stereo_cameras
from ringscan.pipeline.calibrate.procam import (
    ProcamSettings,
    calibrate_procam,
    capture_corners_of_folders,
    depth_range,
    principal_point_inside,
    procam_rig,
)
from ringscan.pipeline.calibrate.stereo_boards import calibrate_stereo_boards
from ringscan.pipeline.formats.atomic import atomic_write_json, check_output_file, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.formats.rig import parse_rig, save_rig
from ringscan.pipeline.preview.plots import PLOT_FORMATS, residuals_figure, save_figure
from ringscan.tools.calibrate_options import (
    add_board_options,
    add_fit_options,
    add_force_option,
    board_from_args,
    board_settings_from_args,
    camera_settings_from_args,
    check_outputs,
    folder_files,
    parse_size,
    print_calibration,
    print_duplicates,
    print_views,
    refuse_unless_forced,
)
from ringscan.tools.cli import UsageError, basic_options

MAX_WINDOW_PX = 200
"""Largest ``calibrate procam --window`` (camera px): a homography is fitted to the (2w+1)^2 pixels around each
corner, so the time grows with its square (100000 ran for minutes)."""


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
    basic_options(p, "--lens-model", "--rig", "--plot", "--board", "--charuco")
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
    views, size = detect_board_images(args.images, board=board, settings=bs, progress=not args.no_progress)
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
    basic_options(p, "--board", "--charuco", "--report")
    p.set_defaults(_calibrate=run_stereo)


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
    v1, size1 = detect_board_images(args.cam1, board=board, settings=bs, what="camera 1", progress=not args.no_progress)
    v2, size2 = detect_board_images(args.cam2, board=board, settings=bs, what="camera 2", progress=not args.no_progress)
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
    basic_options(p, "--layout", "--board", "--charuco", "--report")
    p.set_defaults(_calibrate=run_procam)


def run_procam(args) -> int:
    board = board_from_args(args)
    proj_size = parse_size(args.projector, "--projector")
    if not 1 <= args.window <= MAX_WINDOW_PX:
        raise ValueError(f"--window: expected camera px from 1 to {MAX_WINDOW_PX}, got {args.window}")
    check_outputs({"--out": args.out, "--report": args.report}, folder_files(args.captures))
    settings = ProcamSettings(window_px=args.window, camera=camera_settings_from_args(args),
                              board=board_settings_from_args(args))

    def print_capture(cc) -> None:
        print(f"  {cc.name}: " + ("board found" if cc.camera_view.found else cc.camera_view.reason)
              + ("" if not cc.camera_view.found else
                 (f", {len(cc.projector_view.ids)} corners in the projector" if cc.projector_view.found
                  else f", {cc.projector_view.reason}")))

    caps, size = capture_corners_of_folders(args.captures, board=board, projector=proj_size, layout=args.layout,
                                            settings=settings, progress=not args.no_progress,
                                            on_capture=print_capture)
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

