"""``ringscan import CAPTURE... --rig RIG --projector WxH --out SCAN``.

Real column/row Gray-code captures become a scan folder of the ``decoded`` codec
(docs/formats.md, docs/calibration.md): every camera pixel's sub-pixel projector
position, which ``ringscan reconstruct`` triangulates through the cone model. A
capture of two cameras (OpenCV's structured-light sample: pattern_camN_imK frames or
an image list) with a camera-camera calibration becomes a two-camera scan.
"""

from __future__ import annotations

from pathlib import Path

from ringscan.pipeline.calibrate.capture_files import CAPTURE_INPUTS
from ringscan.pipeline.calibrate.graycode import LAYOUTS, GrayCodeSettings
from ringscan.pipeline.calibrate.importer import ImportSettings, import_captures, parse_units
from ringscan.pipeline.calibrate.opencv_files import (
    opencv_calibration_kind,
    read_opencv_calibration,
    read_stereo_calibration,
)
from ringscan.pipeline.formats.patterns import decoded_scale
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.formats.rig import has_calibrated_light, load_rig
from ringscan.tools.calibrate_options import parse_size
from ringscan.tools.cli import UsageError, basic_options, check_frame_bits_option

OPENCV_SUFFIXES = (".xml", ".yml", ".yaml")


def add_parser(sub):
    p = sub.add_parser("import", help="real Gray-code captures -> a scan folder (decoded projector positions)",
                       description="Decode each CAPTURE (one view each) to sub-pixel projector positions and write a "
                                   "scan folder that `ringscan reconstruct` triangulates. A CAPTURE is "
                                   + "; or ".join(CAPTURE_INPUTS) + ". Two cameras' frames with a two-camera rig "
                                   "(an OpenCV stereo calibration file) give a two-camera scan.")
    p.add_argument("captures", nargs="+", metavar="CAPTURE",
                   help="capture folders or image lists (FileStorage YAML/XML/JSON, or plain text: one path a line)")
    p.add_argument("--layout", choices=LAYOUTS, default="opencv-graycode",
                   help="frame order of every capture (the names may be graycode_NN from 00, pattern_camN_imK from 1 "
                        "as OpenCV's sample writes them, or an image list's order): opencv-graycode = column "
                        "pattern/inverse pairs (MSB first), row pairs, white, black (OpenCV's files; default); "
                        "opencv-graycode-wb-first = white, black, then the pairs. Frames: PNG, TIFF, JPEG or BMP")
    p.add_argument("--rig", required=True,
                   help="a ringscan rig (JSON: one camera and a perspective light, or two cameras), or an OpenCV "
                        "calibration file (cv::FileStorage XML/YAML/JSON): camera-projector (cam_int, cam_dist, proj_int, proj_dist, "
                        "rotation, translation) or camera-camera as OpenCV's structured-light sample has it "
                        "(cam1_intrinsics, cam1_distorsion, cam1_size, cam2_..., R, T)")
    p.add_argument("--projector-rig", default=None, metavar="PROCAM",
                   help="with a camera-camera --rig: the projector's calibration against camera 1 (an OpenCV "
                        "camera-projector file or a ringscan rig), for a two-camera rig with a calibrated projector "
                        "(default: the projector stays uncalibrated)")
    p.add_argument("--camera", type=int, choices=(1, 2), default=None,
                   help="import only this camera's frames of two-camera captures: a one-camera scan (the rig must "
                        "calibrate the projector)")
    p.add_argument("--projector", required=True, metavar="WxH", help="projector size, e.g. 1024x768")
    p.add_argument("--depth", type=float, nargs=2, default=None, metavar=("NEAR", "FAR"),
                   help="working depths for an OpenCV file: along the projector axis (camera-projector) or camera "
                        "1's axis (camera-camera); default: from a plain triangulation of the captures")
    p.add_argument("--units", default=None, metavar="UNIT",
                   help="the units of an OpenCV calibration file's translations (and of --depth), which the file "
                        "does not state: mm, cm, m, in, or the millimetres of one unit (a board square's size when "
                        "the calibration counted in squares); the scan is in mm. Default: millimetres, assumed "
                        "and said. A ringscan rig states its own (mm)")
    p.add_argument("--sector-bits", type=int, default=ImportSettings.sector_bits,
                   help=f"polar-angle sector bits for the root choice (default {ImportSettings.sector_bits})")
    p.add_argument("--min-contrast", type=float, default=GrayCodeSettings.min_contrast, metavar="LEVELS",
                   help="least white - black of a pixel decoded on contrast alone, 8-bit grey levels (default "
                        f"{GrayCodeSettings.min_contrast:g}; dimmer pixels down to {GrayCodeSettings.dim_contrast:g} "
                        "only where the patterns visibly modulate them; docs/calibration.md)")
    p.add_argument("--frame-bits", type=int, default=None, metavar="N",
                   help="bits the captures' 16-bit frames hold (10, 12: a 10- or 12-bit camera's values "
                        "0..1023, 0..4095), scaled to 16 bits as they are read, so that --min-contrast keeps its "
                        "meaning (default: the frames' own bits)")
    p.add_argument("--integer", action="store_true", help="write integer codes only (no sub-pixel positions)")
    p.add_argument("--out", required=True, metavar="SCAN", help="the scan folder to write")
    basic_options(p, "--layout", "--camera", "--min-contrast", "--frame-bits")
    return p


def _is_opencv(path: Path) -> bool:
    """An OpenCV FileStorage calibration: XML/YAML, or JSON with OpenCV's keys and no ringscan ``format``."""
    if path.suffix.lower() in OPENCV_SUFFIXES:
        return True
    if path.suffix.lower() != ".json" or not path.is_file():
        return False
    from ringscan.pipeline.formats.atomic import read_json

    try:
        d = read_json(path)
    except Exception:  # load_rig names what is wrong with it
        return False
    return isinstance(d, dict) and "format" not in d and any(k in d for k in ("cam_int", "cam1_intrinsics"))


BASELINE_HINT = (1.0, 5000.0)
"""Baselines (mm) outside which an assumed millimetre is doubted aloud: a rig of cameras and a projector
under 1 mm apart is one counted in metres, over 5 m one counted in smaller units."""


def _hint_units(kw: dict) -> None:
    """Say so when the calibration's baseline is no rig's in millimetres (a file in metres, say)."""
    import logging

    import numpy as np

    for key in ("opencv", "stereo", "projector_rig"):
        cal = kw.get(key)
        if isinstance(cal, dict):
            b = float(np.linalg.norm(cal["T"]))
            if not (BASELINE_HINT[0] <= b <= BASELINE_HINT[1]):
                logging.getLogger(__name__).warning(
                    "the calibration's baseline is %g units: %s? give --units (docs/calibration.md)", b,
                    "metres" if b < BASELINE_HINT[0] else "not millimetres")
                return


def run(args) -> int:
    proj = parse_size(args.projector, "--projector")
    try:
        decoded_scale(*proj)  # (the scan's 16-bit maps hold a side of at most 65534 px)
    except ValueError as e:
        raise UsageError(f"--projector {args.projector}: {e}") from None
    if args.depth is not None and not (0 < args.depth[0] < args.depth[1]):
        raise UsageError(f"--depth: expected 0 < NEAR < FAR, got {args.depth[0]:g} {args.depth[1]:g}")
    rig_path = Path(args.rig)
    mm_per_unit = None
    if args.units is not None:
        try:
            mm_per_unit = parse_units(args.units)
        except ValueError as e:
            raise UsageError(f"--units: {e}") from None
    kw, opencv_paths = _calibrations(args, rig_path, mm_per_unit)
    if not (args.min_contrast >= 0 and args.min_contrast < 255):
        raise UsageError(f"--min-contrast {args.min_contrast:g}: expected grey levels from 0 to below 255")
    check_frame_bits_option(args.frame_bits)
    settings = ImportSettings(sector_bits=args.sector_bits, integer_only=args.integer,
                              graycode=GrayCodeSettings(min_contrast=args.min_contrast), frame_bits=args.frame_bits)
    with progress_step(f"decoding {len(args.captures)} capture(s)", enabled=not args.no_progress):
        scan, stats = import_captures(args.captures, out=args.out, projector=proj, layout=args.layout,
                                      depth=tuple(args.depth) if args.depth else None, settings=settings,
                                      camera=args.camera,
                                      sources={"rig": rig_path, "projector_rig": args.projector_rig},
                                      mm_per_unit=mm_per_unit, **kw)
    two = scan.rig.camera2 is not None
    _print_decoded(stats, two)
    names = ", ".join(str(p.name) for p in opencv_paths)
    if not opencv_paths:
        print(f"  units: mm ({rig_path.name} states them)")
    elif mm_per_unit is None:
        print(f"  units: {names} states none: assuming millimetres (give --units: m, cm, in, or the millimetres "
              "of one unit, e.g. a board square's)")
        _hint_units(kw)
    else:
        print(f"  units: {args.units} ({mm_per_unit:g} mm, --units): {names} converted to mm")
    li = scan.rig.light
    if not has_calibrated_light(scan.rig):
        v = scan.rig.volume
        print(f"wrote {args.out}: {len(scan.views)} view(s), two cameras, codec decoded, projector {li.width}x"
              f"{li.height} uncalibrated (world = camera 1's frame, working depth {v.z_min:.0f}..{v.z_max:.0f} mm); "
              "reconstruct camera to camera (--rays camera-camera)")
    else:
        print(f"wrote {args.out}: {len(scan.views)} view(s), {'two cameras, ' if two else ''}codec decoded, "
              f"centre = the projector's principal point ({li.K[0, 2]:.1f}, {li.K[1, 2]:.1f})")
    return 0


def _calibrations(args, rig_path: Path, mm_per_unit: float | None) -> tuple[dict, list[Path]]:
    """The calibration keywords of ``import_captures`` (``rig``, ``opencv`` or ``stereo``, and
    ``projector_rig``) read from ``--rig`` and ``--projector-rig``, and the OpenCV files among them."""
    kw = {}
    opencv_paths = [p for p in (rig_path, Path(args.projector_rig) if args.projector_rig else None)
                    if p is not None and _is_opencv(p)]
    if mm_per_unit is not None and not opencv_paths:
        raise UsageError(f"--units: {rig_path} is a ringscan rig, which states its units (mm); --units is for an "
                         "OpenCV calibration file, which states none")
    if _is_opencv(rig_path):
        if opencv_calibration_kind(rig_path) == "stereo":
            kw["stereo"] = read_stereo_calibration(rig_path)
        else:
            kw["opencv"] = read_opencv_calibration(rig_path)
    else:
        kw["rig"] = load_rig(rig_path)
    if args.projector_rig is not None:
        if "stereo" not in kw:
            raise UsageError("--projector-rig goes with a camera-camera (stereo) --rig: the projector's calibration "
                             "to add to it")
        pr = Path(args.projector_rig)
        kw["projector_rig"] = read_opencv_calibration(pr) if _is_opencv(pr) else load_rig(pr)
    return kw, opencv_paths


def _print_decoded(stats: dict, two: bool) -> None:
    """One line per view (and camera) of what was decoded, and the frame order where it was guessed."""

    def coarse(st):
        parts = []
        if st.get("unresolved_share", 0.0) >= 0.01:  # (a sliver at 1.0 projector px a camera px is no news)
            parts.append(f"{100 * st['unresolved_share']:.0f} % from coarser bits where a camera pixel spans more "
                         "than one projector pixel")
        if st["coarse_share"] or st["low_modulation"]:
            parts.append(f"{100 * st['coarse_share']:.0f} % from coarser bits where the finest barely modulate; "
                         f"{st['low_modulation']} left out: low_modulation")
        return f" ({'; '.join(parts)})" if parts else ""

    for name, st in stats.items():
        if "frames_in_name_order" in st:
            first, last = st["frames_in_name_order"]
            print(f"  {name}: frames taken in name order, {first} (first) .. {last} (last); if that is not the "
                  "capture order, give an image list (one path a line, docs/calibration.md)")
        print(f"  {name}: {'camera 1: ' if two else ''}{st['decoded']} pixels decoded, "
              f"{100 * st['subpixel_share']:.0f} % with sub-pixel projector positions{coarse(st)}")
        if "camera2" in st:
            c2 = st["camera2"]
            print(f"  {name}: camera 2: {c2['decoded']} pixels decoded, {100 * c2['subpixel_share']:.0f} % with "
                  f"sub-pixel projector positions{coarse(c2)}")
