"""Where a full-size view's CPU goes: each stage and each Warp kernel, one thread.

Reconstructs every view of the scans below ROOT (``reconstruct_view``, frames read
from their files or store inside it, as a batch worker's read-ahead does), after one
warm-up view, ``--rounds`` times over, on Warp's CPU backend with one thread, and
prints the process's CPU milliseconds a view, the stage times
(``ViewCloud.stats["times_s"]``) and each kernel's milliseconds a view (every
``wp.launch`` timed: on one CPU thread a launch returns when its work is done; on
``--device cuda:N`` each launch is followed by a synchronisation, which the
kernels' own times then include).

Usage::

    python benchmarks/kernel_stages.py ROOT [--rounds 2] [--device cuda:0]

ROOT: scans such as ``benchmarks/batch_scale.py --full`` makes (``WORK/scans``; its
``--formats`` copies: ``WORK/scans_packed``, ...). To compare two versions of the
code, run it from each checkout in turn, alternately, several times: on a shared
machine one run can be 15 % off, and only the medians of interleaved runs say which
is faster.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import warp as wp

from ringscan.kernels import init_warp
from ringscan.kernels.launch import set_cpu_threads
from ringscan.kernels.process import one_blas_thread, retain_freed_memory
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.view import reconstruct_view


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--top", type=int, default=12, help="kernels listed (default 12)")
    ap.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    a = ap.parse_args()
    scans = [load_scan(p.parent) for p in sorted(a.root.glob("*/scan.json"))]
    if not scans:
        print(f"{a.root}: no scan.json in its subfolders", file=sys.stderr)
        return 1
    retain_freed_memory()  # as ringscan's own processes
    one_blas_thread()
    set_cpu_threads(1)
    init_warp()

    per_kernel: dict = collections.defaultdict(float)
    launches: collections.Counter = collections.Counter()
    launch = wp.launch

    def timed(kernel, *args, **kwargs):
        t = time.perf_counter()
        try:
            out = launch(kernel, *args, **kwargs)
            wp.synchronize_device(kwargs.get("device"))
            return out
        finally:
            per_kernel[kernel.key] += time.perf_counter() - t
            launches[kernel.key] += 1

    wp.launch = timed  # the launch helpers call wp.launch through the module, so every launch is seen
    reconstruct_view(scans[0], scans[0].views[0], device=a.device)  # loads the kernels (not counted)
    per_kernel.clear()
    launches.clear()
    stages: dict = collections.defaultdict(float)
    n = 0
    cpu, wall = time.process_time(), time.perf_counter()
    for _ in range(a.rounds):
        for scan in scans:
            for view in scan.views:
                cloud = reconstruct_view(scan, view, device=a.device)
                for k, s in cloud.stats["times_s"].items():
                    stages[k] += s
                n += 1
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    print(f"{n} views ({len(scans)} scans x {a.rounds} rounds) on {a.device}, one CPU thread: "
          f"CPU {1000 * cpu / n:.1f} ms a view, wall {1000 * wall / n:.1f} ms")
    print("stages (ms a view): " + ", ".join(f"{k} {1000 * s / n:.1f}" for k, s in
                                             sorted(stages.items(), key=lambda kv: -kv[1])))
    print(f"Warp kernels, {1000 * sum(per_kernel.values()) / n:.1f} ms a view in all:")
    for k, s in sorted(per_kernel.items(), key=lambda kv: -kv[1])[:a.top]:
        print(f"   {k:42s} {1000 * s / n:7.2f} ms  ({launches[k] / n:.0f} launch(es) a view)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
