"""``ringscan unpack SCAN_OR_ROOT``: packed frame stores back to image files (lossless, checked, resumable)."""

from __future__ import annotations

from functools import partial

from ringscan.pipeline.formats.packing import unpack_scan
from ringscan.tools.cli import basic_options
from ringscan.tools.cmd_pack import add_workers_option, run_each


def add_parser(sub):
    p = sub.add_parser("unpack", help="write packed frame stores back as PNG or TIFF frames",
                       description="Write the frames of every packed view of a scan folder, or of every scan "
                                   "folder below ROOT, back as <view>/<frame>.png (or .tiff), checked frame by "
                                   "frame before scan.json names them and the store is removed. Rerunning "
                                   "resumes a killed run. Exit status 1 when a scan failed.")
    p.add_argument("root", metavar="SCAN_OR_ROOT", help="a scan folder, or a folder whose packed scans are unpacked")
    p.add_argument("--image-format", choices=("png", "tiff"), default="png",
                   help="frame files to write (default png; tiff: uncompressed)")
    p.add_argument("--keep", action="store_true", help="leave the frame stores in place")
    add_workers_option(p)
    basic_options(p, "--image-format", "--keep", "--workers")
    return p


def run(args) -> int:
    return run_each(args.root, partial(unpack_scan, image_format=args.image_format, keep=args.keep), "unpacked",
                    workers=args.workers)
