"""``ringscan simulate``: render a scan folder with ground truth on the virtual rig."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from ringscan.pipeline.formats.atomic import check_no_overwrite, check_output_folder
from ringscan.pipeline.formats.frame_store import STORE_NAME
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.rig import default_rig, has_calibrated_light, load_rig
from ringscan.pipeline.simulate.opencv_graycode import (
    IMAGE_LIST,
    STEREO_FILE,
    graycode_outputs,
    render_graycode_captures,
)
from ringscan.pipeline.simulate.scan import CAMERA2_DIR, add_camera2, simulate_scan
from ringscan.pipeline.simulate.scenes import SCENES, parse_point
from ringscan.pipeline.simulate.virtual_rig import RenderSettings
from ringscan.tools.cli import UsageError, add_device_option, basic_options
from ringscan.tools.cmd_patterns import add_pattern_options, pattern_spec_from_args


def add_parser(sub):
    p = sub.add_parser("simulate", help="render a scan of a virtual object (with ground truth)",
                       description="Ray-trace a scene on the virtual rig under every frame of a pattern codec "
                                   "and write a scan folder (scan.json, <view>/<frame>.png) plus truth/ "
                                   "(object.ply, <view>_depth.tiff, <view>_lit.png).")
    p.add_argument("--scene", default="sphere",
                   help=f"{'|'.join(SCENES)}, plate:H (a flat plate at height H mm) or the path of an "
                        f"OBJ/PLY/STL mesh (default sphere)")
    p.add_argument("--size-mm", type=float, default=80.0, help="longest side of the object in mm (default 80)")
    p.add_argument("--up", choices=("auto", "y", "z"), default="auto",
                   help="up axis of a mesh file (default auto: z for STL, y otherwise)")
    p.add_argument("--pose", default=None, metavar="POSE",
                   help="resting pose for flip-and-rescan: upright (default), upside-down, side-x, side-y, "
                        "tetra-1, tetra-2, tetra-3 (with upright: the 4 poses that light every normal), or "
                        "AXIS:DEG[,AXIS:DEG...] (e.g. x:-90 or x:135,z:20); the object is turned about its "
                        "bounding-box centre, then set down on z = 0")
    p.add_argument("--place", default=None, metavar="X,Y,Z",
                   help="put the centre of the object's bounding box at this world point (mm) instead of "
                        "standing it on z = 0 at the origin (a rig looking at a wall: see docs/virtual_rig.md); "
                        "write --place=-50,436,1000 when X is negative")
    p.add_argument("--wall", type=float, default=None, metavar="Z",
                   help="add an opaque wall, the plane z = Z (mm), behind the object, part of the ground truth")
    p.add_argument("--captures", choices=("scan", "opencv-graycode"), default="scan",
                   help="scan (default): a ringscan scan folder of --codec; opencv-graycode: OpenCV's column/row "
                        "Gray code for the rig's projector, as capture_0/graycode_NN.png plus rig.json and truth/, "
                        "for `ringscan import` (the pattern options do not apply)")
    p.add_argument("--out", required=True, help="scan folder to write")
    p.add_argument("--rig", default=None, help="rig file (default: the built-in virtual rig)")
    p.add_argument("--light", choices=("parallel", "perspective"), default=None,
                   help="light model of the built-in rig (default parallel)")
    p.add_argument("--camera2", action="store_true",
                   help="add a second camera: camera 1 turned 180 degrees about the light axis (world z), so the two "
                        "stand symmetric about it; both cameras' frames and truth are written (camera 2's in "
                        "<view>/cam2/, truth/<view>_cam2_*); a rig file with camera2 renders both without it")
    p.add_argument("--gamma", type=float, default=None,
                   help="camera response gamma (default 2.2 for the built-in rig, the rig file's otherwise)")
    p.add_argument("--views", type=int, default=1, help="turntable views at k * 360 / N degrees (default 1)")
    add_pattern_options(p, size=False)
    p.add_argument("--center", type=float, nargs=2, default=None, metavar=("CU", "CV"),
                   help="pattern (ring) centre in projector px (default the image centre, (W-1)/2, (H-1)/2; "
                        "a projector's principal point makes the rings' cones right circular)")
    s = p.add_argument_group("rendering")
    d = RenderSettings()
    s.add_argument("--noise", type=float, default=d.noise,
                   help=f"camera noise sigma, 8-bit grey levels (default {d.noise})")
    s.add_argument("--supersample", type=int, default=d.supersample,
                   help=f"sub-samples per pixel side (default {d.supersample})")
    s.add_argument("--ambient", type=float, default=d.ambient,
                   help=f"ambient light, fraction of white (default {d.ambient})")
    s.add_argument("--albedo", type=float, default=d.albedo, help=f"surface albedo (default {d.albedo})")
    s.add_argument("--defocus", type=float, default=d.defocus_px,
                   help=f"projector blur sigma in px (default {d.defocus_px})")
    s.add_argument("--exposure", type=float, default=d.exposure,
                   help=f"recorded level of full white (default {d.exposure})")
    s.add_argument("--bit-depth", type=int, choices=(8, 16), default=d.bit_depth, help="frame bit depth (default 8)")
    s.add_argument("--seed", type=int, default=d.seed, help="noise seed (default 0)")
    s.add_argument("--image-format", "--format", dest="format", choices=("png", "tiff", "packed"),
                   default="png", help="frame files (default png; tiff: uncompressed, 2.3x the space, ~4x faster to "
                                       "read; packed: one frame store per view, about the PNGs' size, 6-11x faster)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    m = p.add_argument_group("renderer")
    m.add_argument("--renderer", choices=("warp", "mitsuba"), default="warp",
                   help="warp (default): ringscan's own ray tracer, which shares the reconstruction's camera and "
                        "light geometry; mitsuba: Mitsuba 3's path tracer, an independent renderer that only reads "
                        "the rig (inverse-square fall-off, inter-reflections; needs pip install 'ringscan[mitsuba]'; "
                        "--device does not apply; docs/virtual_rig.md)")
    add_device_option(p)
    basic_options(p, "--scene", "--codec", "--views", "--rig", "--light", "--camera2", "--captures", "--size-mm")
    return p


def build_rig(args):
    """The rig of the command line: --rig, or the built-in one with --light/--gamma; --camera2 adds camera 2."""
    if args.rig:
        if args.light:
            raise UsageError("--light applies to the built-in rig only (the rig file sets its light)")
        rig = load_rig(args.rig)
        if args.gamma is not None:
            g = _gamma(args.gamma)
            rig = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, gamma=g),
                                      camera2=None if rig.camera2 is None else
                                      dataclasses.replace(rig.camera2, gamma=g))
    else:
        rig = default_rig(gamma=_gamma(2.2 if args.gamma is None else args.gamma),
                          light_model=args.light or "parallel")
    if getattr(args, "camera2", False):
        if rig.camera2 is not None:
            raise UsageError(f"--camera2: the rig file {args.rig} has a second camera already (drop --camera2)")
        rig = add_camera2(rig)
    if not has_calibrated_light(rig):
        raise UsageError(f"--rig {args.rig}: its projector is uncalibrated ('uncalibrated' light): the virtual rig "
                         "needs the projector's geometry to render")
    return rig


def _outputs(out: Path, spec, views: int, fmt: str, cameras: int = 1) -> list[Path]:
    """The files ``simulate`` writes (simulate_scan's layout)."""
    files = [out / "scan.json", out / "truth" / "object.ply"]
    for k in range(max(int(views), 0)):
        for c in range(1, cameras + 1):
            sub = out / f"view_{k:03d}" / (CAMERA2_DIR if c == 2 else "")
            pre = f"view_{k:03d}_{'cam2_' if c == 2 else ''}"
            if fmt == "packed":
                files.append(sub / STORE_NAME / "zarr.json")
            else:
                files += [sub / f"{n}.{fmt}" for n in frame_names(spec)]
            files += [out / "truth" / f"{pre}depth.tiff", out / "truth" / f"{pre}lit.png"]
    return files


def _settings(args) -> RenderSettings:
    return RenderSettings(supersample=args.supersample, ambient=args.ambient, albedo=args.albedo,
                          defocus_px=args.defocus, noise=args.noise, bit_depth=args.bit_depth,
                          exposure=args.exposure, seed=args.seed)


def _run_graycode(args, out: Path, rig, place) -> int:
    """``--captures opencv-graycode``: OpenCV's Gray code for the rig's projector, one capture."""
    li = rig.light
    if not (getattr(li, "width", 0) and getattr(li, "height", 0)):
        raise ValueError("--captures opencv-graycode: the rig's light does not state its size (a projector's "
                         "width and height)")
    if args.views != 1:
        raise ValueError(f"--captures opencv-graycode renders one capture; got --views {args.views}")
    if args.format != "png":
        raise ValueError("--captures opencv-graycode writes PNG frames (OpenCV's files); drop --image-format")
    inputs = [p for p in (args.rig, args.scene) if p and Path(p).is_file()]
    two = rig.camera2 is not None
    check_no_overwrite(graycode_outputs(out, (li.width, li.height), cameras=2 if two else 1), inputs)
    t0 = time.perf_counter()
    doc = render_graycode_captures(out, rig=rig, scene=args.scene, settings=_settings(args), device=args.device,
                                   progress=not args.no_progress, size_mm=args.size_mm, up=args.up, pose=args.pose,
                                   place=place, wall_z=args.wall)
    cap = next(iter(doc["captures"]))
    if two:
        print(f"{doc['captures'][cap]['frames']} opencv-graycode frames x 2 cameras of {args.scene} for a "
              f"{li.width}x{li.height} projector ({rig.camera.width}x{rig.camera.height}, {args.bit_depth}-bit) in "
              f"{time.perf_counter() - t0:.1f} s -> {out / cap} (pattern_camN_imK; image list {out / IMAGE_LIST}, "
              f"stereo calibration {out / STEREO_FILE}, truth in {out / 'truth'}); import: ringscan import "
              f"{out / IMAGE_LIST} --rig {out / STEREO_FILE} --projector {li.width}x{li.height} --out SCAN")
        return 0
    print(f"{doc['captures'][cap]['frames']} opencv-graycode frames of {args.scene} for a {li.width}x{li.height} "
          f"projector ({rig.camera.width}x{rig.camera.height}, {args.bit_depth}-bit) in "
          f"{time.perf_counter() - t0:.1f} s -> {out / cap} (rig {out / 'rig.json'}, truth in {out / 'truth'}); "
          f"import: ringscan import {out / cap} --rig {out / 'rig.json'} --projector {li.width}x{li.height} "
          "--out SCAN")
    return 0


def _gamma(g: float) -> float:
    if not g > 0:
        raise UsageError(f"--gamma: must be > 0, got {g}")
    return float(g)


def _mitsuba_settings(args):
    """MitsubaSettings (its defaults: 4 samples a texel, one bounce; MitsubaSettings in Python for others) for
    --renderer mitsuba, None for warp."""
    if args.renderer != "mitsuba":
        return None
    if args.captures != "scan":
        raise UsageError("--renderer mitsuba renders scan folders only (--captures scan); OpenCV Gray-code "
                         "captures are rendered by ringscan's own renderer")
    from ringscan.pipeline.simulate.mitsuba_render import MitsubaMissing, MitsubaSettings, mitsuba_available

    if not mitsuba_available():
        raise MitsubaMissing()
    return MitsubaSettings()


def run(args) -> int:
    out = check_output_folder(args.out, what="scan folder (--out)")
    rig = build_rig(args)
    place = parse_point(args.place, what="--place") if args.place is not None else None
    mitsuba = _mitsuba_settings(args)
    if args.captures == "opencv-graycode":
        return _run_graycode(args, out, rig, place)
    li = rig.light
    width, height = (li.width, li.height) if getattr(li, "width", 0) else (1024, 768)
    spec = pattern_spec_from_args(args, width, height, args.center)
    inputs = [p for p in (args.rig, args.scene) if p and Path(p).is_file()]
    check_no_overwrite(_outputs(out, spec, args.views, args.format, 2 if rig.camera2 is not None else 1), inputs)
    settings = _settings(args)
    t0 = time.perf_counter()
    scan = simulate_scan(args.out, scene=args.scene, rig=rig, patterns=spec, views=args.views, settings=settings,
                         device=args.device, progress=not args.no_progress, size_mm=args.size_mm, up=args.up,
                         image_format=args.format, pose=args.pose, place=place, wall_z=args.wall,
                         renderer=args.renderer, mitsuba=mitsuba)
    n_frames = len(scan.views[0].frames) if scan.views else 0
    by = f" (Mitsuba {scan.extra['truth']['renderer']['variant']})" if mitsuba else ""
    print(f"{len(scan.views)} view(s) x {n_frames} {spec.codec} frame(s){' x 2 cameras' if rig.camera2 else ''} "
          f"of {args.scene}{by} "
          f"({rig.camera.width}x{rig.camera.height}, {args.bit_depth}-bit) in {time.perf_counter() - t0:.1f} s "
          f"-> {scan.folder} (truth in {scan.folder / 'truth'})")
    return 0
