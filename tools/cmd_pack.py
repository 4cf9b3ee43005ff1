"""``ringscan pack SCAN_OR_ROOT``: image frames to packed frame stores (lossless, checked, resumable)."""

from __future__ import annotations

import sys
from functools import partial
from pathlib import Path

from ringscan.pipeline.batch.discover import iter_scans
from ringscan.pipeline.formats.errors import FormatError, RingscanError
from ringscan.pipeline.formats.packing import pack_scan
from ringscan.tools.cli import basic_options


def add_parser(sub):
    p = sub.add_parser("pack", help="pack scans' image frames into one frame store per view (lossless)",
                       description="Pack the PNG/TIFF frames of a scan folder, or of every scan folder below "
                                   "ROOT, into one frame store per view (<view>/frames.zarr, a Zarr v3 array: "
                                   "about the PNGs' size, 6-11x faster to read than PNG; docs/formats.md). Each view's "
                                   "store is read back and compared frame by frame before scan.json names it "
                                   "and the image files are removed. Rerunning resumes a killed run. Exit "
                                   "status 1 when a scan failed (named in one line each).")
    p.add_argument("root", metavar="SCAN_OR_ROOT",
                   help="a scan folder, or a folder whose scans (found as `ringscan batch` finds them) are packed")
    p.add_argument("--keep", action="store_true", help="leave the image files in place")
    add_workers_option(p)
    basic_options(p, "--keep", "--workers")
    return p


def add_workers_option(p) -> None:
    p.add_argument("--workers", type=int, default=1, metavar="N",
                   help="scans converted at a time, on N processes (default 1)")


def _attempt(convert, folder: Path):
    """``convert(folder)``, or the error's one line (errors cross the process boundary as text): a scan's
    failure, whatever it is, is that scan's, and the others go on."""
    try:
        return convert(folder), None
    except RingscanError as e:
        return None, str(e)
    except OSError as e:  # the disk: full, read-only, no permission
        return None, f"{e.filename + ': ' if e.filename else ''}{e.strerror or e}"
    except Exception as e:  # noqa: BLE001 - a library's exception, named as the batch names it
        return None, f"{type(e).__name__}: {' '.join(str(e).split())}"


def run_each(root: str, convert, verb: str, *, workers: int = 1) -> int:
    """Run ``convert(folder)`` on every scan below ``root`` (``workers`` scans at a time,
    on processes); one line per scan, in the order they finish."""
    if not Path(root).is_dir():
        raise FormatError(root, "not a folder")
    if workers < 1:
        raise ValueError(f"--workers: expected 1 or more, got {workers}")
    failed = total = 0
    skipped: list = []

    def report(folder, r, err):
        nonlocal failed
        if err is not None:
            failed += 1
            print(f"{folder}: failed: {err}", file=sys.stderr)
            return
        size = (f", {r.bytes_before / 1e6:.1f} -> {r.bytes_after / 1e6:.1f} MB" if r.converted else "")
        print(f"{folder}: {len(r.converted)} view(s) {verb}, {len(r.already)} already{size}"
              + (f", {r.removed} old file(s) removed" if r.removed else ""), flush=True)

    if workers == 1:
        for folder in iter_scans(root, skipped=skipped):
            total += 1
            report(folder, *_attempt(convert, folder))
    else:
        import os
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
        from multiprocessing import get_context

        from ringscan.pipeline.batch.local import children_without_ctrl_c, end_pool
        from ringscan.pipeline.batch.worker import init_child

        # the workers leave Ctrl-C to this process and exit when it is gone (even SIGKILLed); Ctrl-C ends them
        ex = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=init_child,
                                 initargs=(os.getpid(),))
        finished = False
        try:
            running = {}
            scans = iter_scans(root, skipped=skipped)
            while True:
                for folder in scans:  # a bounded window: a root of a million scans is never listed whole
                    total += 1
                    with children_without_ctrl_c():
                        running[ex.submit(_attempt, convert, folder)] = folder
                    if len(running) >= 2 * workers:
                        break
                if not running:
                    break
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for f in done:
                    report(running.pop(f), *f.result())
            finished = True
        finally:
            if not finished:
                end_pool(ex)
            ex.shutdown(wait=True, cancel_futures=True)
    for path, why in skipped:  # a scan nested in a scan's folder, a link loop: said, as batch says it
        print(f"not searched: {path}: {why}")
    if total == 0:
        raise FormatError(root, "no scan folder (with a scan.json) found")
    return 1 if failed else 0


def run(args) -> int:
    return run_each(args.root, partial(pack_scan, keep=args.keep), "packed", workers=args.workers)
