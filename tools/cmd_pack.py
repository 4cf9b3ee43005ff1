"""``ringscan pack SCAN_OR_ROOT``: image frames to packed frame stores (lossless, checked, resumable)."""

from __future__ import annotations

import sys
from pathlib import Path

from ringscan.pipeline.batch.discover import iter_scans
from ringscan.pipeline.formats.errors import FormatError, RingscanError
from ringscan.pipeline.formats.packing import pack_scan


def add_parser(sub):
    p = sub.add_parser("pack", help="pack scans' image frames into one frame store per view (lossless)",
                       description="Pack the PNG/TIFF frames of a scan folder, or of every scan folder below "
                                   "ROOT, into one frame store per view (<view>/frames.zarr, a Zarr v3 array: "
                                   "about the PNGs' size, ~10x faster to read; docs/formats.md). Each view's "
                                   "store is read back and compared frame by frame before scan.json names it "
                                   "and the image files are removed. Rerunning resumes a killed run. Exit "
                                   "status 1 when a scan failed (named in one line each).")
    p.add_argument("root", metavar="SCAN_OR_ROOT")
    p.add_argument("--keep", action="store_true", help="leave the image files in place")
    return p


def run_each(root: str, convert, verb: str) -> int:
    """Run ``convert(folder)`` on every scan below ``root``; one line per scan."""
    if not Path(root).is_dir():
        raise FormatError(root, "not a folder")
    failed = total = 0
    for folder in iter_scans(root):
        total += 1
        try:
            r = convert(folder)
        except RingscanError as e:
            failed += 1
            print(f"{folder}: failed: {e}", file=sys.stderr)
            continue
        size = (f", {r.bytes_before / 1e6:.1f} -> {r.bytes_after / 1e6:.1f} MB" if r.converted else "")
        print(f"{folder}: {len(r.converted)} view(s) {verb}, {len(r.already)} already{size}"
              + (f", {r.removed} old file(s) removed" if r.removed else ""))
    if total == 0:
        raise FormatError(root, "no scan folder (with a scan.json) found")
    return 1 if failed else 0


def run(args) -> int:
    return run_each(args.root, lambda f: pack_scan(f, keep=args.keep), "packed")
