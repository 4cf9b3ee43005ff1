"""Each Warp kernel of a full-size view on its own: its launches replayed, one thread.

Reconstructs the views of the first ``--scans`` scans below ROOT once on Warp's CPU
backend (one thread), keeping a copy of every named kernel's inputs at each launch,
then replays each kernel's launches ``--reps`` times over (every view in turn, so a
view's inputs are out of the caches again when its turn comes) and prints the
milliseconds a view of each kernel (the least and the median over the reps) and a
digest of its outputs. A kernel compared with another version of itself on the same
inputs, without the rest of the view around it: the least of several reps is steadier
than a whole view's time on a shared machine (``kernel_stages.py``), and the digest
says whether its outputs are the same bytes.

Usage::

    python benchmarks/kernel_replay.py ROOT [--scans 4] [--reps 7] [KERNEL ...]

ROOT: scans such as ``benchmarks/batch_scale.py --full --formats`` makes
(``WORK/scans_packed``). KERNEL: Warp kernel names (default: the gray-rings view's
largest: ``decode_gray_rings_swar_kernel``, ``count_edges_kernel``,
``camera_rays_kernel``, ``triangulate_kernel``, ``count_neighbours_sorted_kernel``).
Outputs a kernel writes only in part (the sampler's packed slots) have digests that
differ between runs; compare the others.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

from ringscan.kernels import init_warp
from ringscan.kernels.launch import set_cpu_threads
from ringscan.kernels.process import one_blas_thread, retain_freed_memory
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.view import reconstruct_view

DEFAULT_KERNELS = ("decode_gray_rings_swar_kernel", "count_edges_kernel", "camera_rays_kernel", "triangulate_kernel",
                   "count_neighbours_sorted_kernel")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("kernels", nargs="*", default=list(DEFAULT_KERNELS))
    ap.add_argument("--scans", type=int, default=4, help="scans reconstructed (default 4)")
    ap.add_argument("--reps", type=int, default=7, help="replays of each kernel's launches (default 7)")
    a = ap.parse_args()
    scans = [load_scan(p.parent) for p in sorted(a.root.glob("*/scan.json"))][: a.scans]
    if not scans:
        print(f"{a.root}: no scan.json in its subfolders", file=sys.stderr)
        return 1
    retain_freed_memory()
    one_blas_thread()  # as ringscan's own processes
    set_cpu_threads(1)
    init_warp()
    launches = collections.defaultdict(list)
    launch = wp.launch

    def keep(kernel, *args, **kwargs):
        if kernel.key in a.kernels:
            # inputs copied now (a view's buffers are reused later), outputs fresh
            kw = dict(kwargs)
            kw["inputs"] = [wp.clone(x) if isinstance(x, wp.array) else x for x in kwargs.get("inputs", [])]
            kw["outputs"] = [wp.empty(shape=x.shape, dtype=x.dtype, device=x.device) if isinstance(x, wp.array)
                             else x for x in kwargs.get("outputs", [])]
            launches[kernel.key].append((kernel, args, kw))
        return launch(kernel, *args, **kwargs)

    wp.launch = keep
    try:
        for scan in scans:
            for view in scan.views:
                reconstruct_view(scan, view, device="cpu")
    finally:
        wp.launch = launch
    n_views = sum(len(s.views) for s in scans)
    print(f"{n_views} views, one CPU thread, {a.reps} reps (ms a view)")
    for name in a.kernels:
        runs = launches.get(name)
        if not runs:
            print(f"   {name:34s} not launched")
            continue
        ms = []
        for _ in range(a.reps):
            t = time.perf_counter()
            for kernel, args, kw in runs:
                launch(kernel, *args, **kw)
            ms.append(1000 * (time.perf_counter() - t) / n_views)
        digest = hashlib.sha1()
        for _, _, kw in runs:
            for o in kw["outputs"]:
                if isinstance(o, wp.array):
                    digest.update(o.numpy().tobytes())
        print(f"   {name:34s} least {min(ms):6.2f}  median {np.median(ms):6.2f}  outputs {digest.hexdigest()[:12]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
