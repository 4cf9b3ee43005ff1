"""A batch worker's CPU a view, in this process: ``batch_reconstruct(ROOT, --workers 0)`` on one thread.

Runs the batch over the scans below ROOT ``--rounds`` times after one warm-up batch
(Warp and its kernel cache loaded, the frames in the page cache), each into a fresh
output folder, with ringscan's allocator policy (as a worker process has it), and
prints the process's CPU milliseconds and wall milliseconds a computed view for each
round: everything a worker does for a scan (freshness checks, reading the frames on
the read-ahead thread, the kernels, PLYs and reports on the writer thread), without
the pool's processes.

Usage::

    python benchmarks/batch_inline.py ROOT [--rounds 3]

To compare two versions of the code, run it from each checkout in turn, alternately,
several times (``ROOT``: e.g. ``benchmarks/batch_scale.py --full --formats``'s
``WORK/scans_packed``); on a shared machine only the medians of interleaved runs say
which is faster.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ringscan.kernels import retain_freed_memory
from ringscan.kernels.process import one_blas_thread
from ringscan.pipeline.batch import batch_reconstruct


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    retain_freed_memory()
    one_blas_thread()  # as a batch worker
    tmp = Path(tempfile.mkdtemp(prefix="ringscan_batch_inline_"))
    try:
        cpu, wall = [], []
        for i in range(a.rounds + 1):
            out = tmp / "out"
            shutil.rmtree(out, ignore_errors=True)
            c, w = time.process_time(), time.perf_counter()
            rep = batch_reconstruct(a.root, out, workers=0, cpu_threads=1, device="cpu", progress=False)
            n = max(1, rep["totals"]["computed_views"])
            if i:  # the first batch loads the kernels
                cpu.append(1000 * (time.process_time() - c) / n)
                wall.append(1000 * (time.perf_counter() - w) / n)
        print(f"{n} views a round, {a.rounds} rounds, one thread: CPU {np.median(cpu):.1f} ms a view "
              f"(rounds {', '.join(f'{x:.0f}' for x in cpu)}), wall {np.median(wall):.1f} ms a view")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
