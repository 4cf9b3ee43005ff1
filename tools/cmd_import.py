"""``ringscan import CAPTURE_DIR... --layout opencv-graycode --rig RIG --projector WxH --out SCAN``.

Real column/row Gray-code captures become a scan folder of the ``decoded`` codec
(docs/formats.md, docs/calibration.md): every camera pixel's sub-pixel projector
position, which ``ringscan reconstruct`` triangulates through the cone model.
"""

from __future__ import annotations

from pathlib import Path

from ringscan.pipeline.calibrate.graycode import LAYOUTS, GrayCodeSettings
from ringscan.pipeline.calibrate.importer import ImportSettings, import_captures, read_opencv_calibration
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.formats.rig import load_rig
from ringscan.tools.cli import UsageError
from ringscan.tools.cmd_calibrate import parse_size


def add_parser(sub):
    p = sub.add_parser("import", help="real Gray-code captures -> a scan folder (decoded projector positions)",
                       description="Decode each CAPTURE_DIR (graycode_NN frames, one view each) to sub-pixel "
                                   "projector positions and write a scan folder that `ringscan reconstruct` "
                                   "triangulates through the cone (perspective light) model.")
    p.add_argument("captures", nargs="+", metavar="CAPTURE_DIR", help="capture folders")
    p.add_argument("--layout", choices=LAYOUTS, default="opencv-graycode",
                   help="frame order: opencv-graycode = column pairs, row pairs, white, black (OpenCV's files); "
                        "opencv-graycode-wb-first = white, black, then the pairs")
    p.add_argument("--rig", required=True,
                   help="a ringscan rig (JSON) with a perspective light, or an OpenCV calibration file (XML/YAML: "
                        "cam_int, cam_dist, proj_int, proj_dist, rotation, translation)")
    p.add_argument("--projector", required=True, metavar="WxH", help="projector size, e.g. 1024x768")
    p.add_argument("--depth", type=float, nargs=2, default=None, metavar=("NEAR", "FAR"),
                   help="working depths along the projector axis for an OpenCV file (default: from the captures)")
    p.add_argument("--sector-bits", type=int, default=ImportSettings.sector_bits,
                   help=f"polar-angle sector bits for the root choice (default {ImportSettings.sector_bits})")
    p.add_argument("--min-contrast", type=float, default=GrayCodeSettings.min_contrast, metavar="LEVELS",
                   help="least white - black of a pixel decoded on contrast alone, 8-bit grey levels (default "
                        f"{GrayCodeSettings.min_contrast:g}; dimmer pixels down to {GrayCodeSettings.dim_contrast:g} "
                        "only where the patterns visibly modulate them; docs/calibration.md)")
    p.add_argument("--integer", action="store_true", help="write integer codes only (no sub-pixel positions)")
    p.add_argument("--out", required=True, metavar="SCAN", help="the scan folder to write")
    return p


def run(args) -> int:
    proj = parse_size(args.projector, "--projector")
    rig_path = Path(args.rig)
    kw = {}
    if rig_path.suffix.lower() in (".xml", ".yml", ".yaml"):
        kw["opencv"] = read_opencv_calibration(rig_path)
    else:
        kw["rig"] = load_rig(rig_path)
    if not (args.min_contrast >= 0 and args.min_contrast < 255):
        raise UsageError(f"--min-contrast {args.min_contrast:g}: expected grey levels from 0 to below 255")
    settings = ImportSettings(sector_bits=args.sector_bits, integer_only=args.integer,
                              graycode=GrayCodeSettings(min_contrast=args.min_contrast))
    with progress_step(f"decoding {len(args.captures)} capture(s)", enabled=not args.no_progress):
        scan, stats = import_captures(args.captures, out=args.out, projector=proj, layout=args.layout,
                                      depth=tuple(args.depth) if args.depth else None, settings=settings, **kw)
    for name, st in stats.items():
        print(f"  {name}: {st['decoded']} pixels decoded, {100 * st['subpixel_share']:.0f} % with sub-pixel "
              "projector positions")
    li = scan.rig.light
    print(f"wrote {args.out}: {len(scan.views)} view(s), codec decoded, centre = the projector's principal point "
          f"({li.K[0, 2]:.1f}, {li.K[1, 2]:.1f})")
    return 0
