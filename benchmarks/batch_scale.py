"""``ringscan batch`` at scale: 100 small simulated scans, 5 of them corrupted.

Prints:

1. faults: 95 results, 5 clear errors in the batch report, exit status 1;
2. throughput in one run: ``--workers 1``, ``--workers 2`` and the NumPy reference
   (tools/bench/numpy_twins.py: read, decode, sample, triangulate) over the same
   folder one scan after another, in views per second, and their ratios;
3. the per-view time split (read, decode, sample, triangulate, write) of the batch report;
4. killed part-way (SIGKILL of the parent; SIGKILL of one worker) and rerun: which
   scans the rerun processed against those that were unfinished, and whether every
   result is byte-identical to the uninterrupted run (PLYs byte for byte, reports
   without their clock times and resume records: ``pipeline.batch.report.read_results``).

Usage::

    python benchmarks/batch_scale.py [--work DIR] [--scans 100] [--views 2]

The scans (320x240 camera, gray-rings, ``--views`` turntable views each) are made
once into ``--work`` (default /tmp/ringscan_batch_scale) and kept for reruns.
``--full --formats --scans 6 --views 2`` measures part 2 per frame format (PNG as OpenCV writes it by
default, ringscan's PNG, uncompressed TIFF, the packed frame store) on copies of the same scans, and one
view's reading time on one thread against copying its frames in memory; ``--device cuda:0`` runs its
batches on a GPU.
``--full [--tiff] [--rounds 3] --scans 16 --views 3 --work DIR`` measures part 2 on full-size views (the default
rig's 1280x1024 camera, the core accuracy codec: 28 frames a view), where per-view fixed
costs matter less; part 2 also runs every worker on one thread, which shows how the
workers themselves scale.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np

from ringscan.kernels.process import one_blas_thread, retain_freed_memory
from ringscan.pipeline.batch import batch_reconstruct, plan_batch
from ringscan.pipeline.batch.report import read_results
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.formats.scan import load_scan, read_view_frames
from ringscan.tools.bench.numpy_twins import decode_numpy, sample_numpy, triangulate_numpy

SPEC = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0, "pitch": 16.0,
        "bits": 5, "sector_bits": 4}
FULL_SPEC = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0, "pitch": 4.0,
             "bits": 7, "sector_bits": 6}
"""``--full``: the core accuracy configuration (docs/accuracy.md) on the default rig's 1280x1024 camera, 28 frames."""
SCENES = ("sphere", "cube")
CORRUPT = {
    "s010": "a frame replaced by bytes that are not an image",
    "s030": "scan.json cut short",
    "s050": "a frame file missing",
    "s070": "every frame black (no light reached the camera)",
    "s090": "a frame of another size",
}


CAMERA = (320, 240)


def small_rig(size=None):
    w, h = size or CAMERA
    f = 650.0 * w / 320.0
    rig = default_rig()
    cam = dataclasses.replace(rig.camera, width=w, height=h,
                              K=np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]]))
    return dataclasses.replace(rig, camera=cam)


def _simulate(args):
    from ringscan.pipeline.simulate.scan import simulate_scan

    folder, i, views, size, spec = args
    if (Path(folder) / "scan.json").is_file():
        return
    rig = default_rig() if size is None else small_rig(size)
    simulate_scan(folder, scene=SCENES[i % 2], rig=rig, patterns=parse_patterns(spec),
                  turntable_deg=tuple(360.0 * k / views + 7.0 * i for k in range(views)), progress=False,
                  device="cpu")


def make_scans(root: Path, n: int, views: int, size, spec: dict = SPEC, corrupt: bool = True) -> None:
    todo = [(str(root / f"s{i:03d}"), i, views, size, spec) for i in range(n)
            if not (root / f"s{i:03d}" / "scan.json").is_file()]
    if todo:
        t = time.perf_counter()
        with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as ex:
            list(ex.map(_simulate, todo))
        print(f"simulated {len(todo)} scans in {time.perf_counter() - t:.0f} s")
    marker = root / ".corrupted"
    if marker.exists() or not corrupt:
        return
    for name, what in CORRUPT.items():
        s = root / name
        if not s.is_dir():
            continue
        v = s / "view_000"
        if name == "s010":
            (v / "white.png").write_bytes(b"not an image at all")
        elif name == "s030":
            (s / "scan.json").write_text((s / "scan.json").read_text()[:200])
        elif name == "s050":
            (v / "black.png").unlink()
        elif name == "s070":
            for vv in s.glob("view_*"):
                for p in vv.glob("*.png"):
                    im = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                    cv2.imwrite(str(p), np.zeros_like(im))
        elif name == "s090":
            im = cv2.imread(str(v / "white.png"), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(v / "white.png"), cv2.resize(im, (160, 120)))
    marker.write_text(json.dumps(CORRUPT))


def to_tiff(root: Path) -> None:
    """Rewrite every scan's frames as uncompressed TIFF (docs/design.md §11 allows PNG or TIFF): PNG decoding is
    the largest part of a view's time; an uncompressed frame is read at the speed of the page cache."""
    n = 0
    for sj in sorted(root.glob("*/scan.json")):
        d = json.loads(sj.read_text())
        for v in d["views"]:
            for name, rel in v["frames"].items():
                if not rel.endswith(".png"):
                    continue
                src = sj.parent / rel
                img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
                dst = src.with_suffix(".tif")
                cv2.imwrite(str(dst), img, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
                src.unlink()
                v["frames"][name] = rel[:-4] + ".tif"
                n += 1
        sj.write_text(json.dumps(d, indent=2))
    if n:
        print(f"rewrote {n} frames as uncompressed TIFF")


def numpy_reference(root: Path, spec: dict = SPEC) -> tuple[int, float, float, float]:
    """Every view of every scan, one after another, with the NumPy twins (read, decode, sample, triangulate).

    Returns (views, seconds, of which reading the frames, CPU seconds of this process)."""
    spec = parse_patterns(spec)
    n, t, t_read, cpu = 0, time.perf_counter(), 0.0, time.process_time()
    for i in range(1000):
        folder = root / f"s{i:03d}"
        if not folder.is_dir():
            break
        try:
            scan = load_scan(folder)
            for v in scan.views:
                t0 = time.perf_counter()
                frames = read_view_frames(scan, v, threads=1)
                t_read += time.perf_counter() - t0
                dec = decode_numpy(frames, bits=spec.bits, sector_bits=spec.sector_bits)
                smp = sample_numpy(frames, dec, bits=spec.bits)
                rho = (spec.rho0 + smp["ring"] * spec.pitch).astype(np.float32)
                triangulate_numpy(smp["uv"], rho, smp["sector"], scan.rig, center=spec.center,
                                  sector_bits=spec.sector_bits)
                n += 1
        except Exception:  # noqa: BLE001 - the corrupted scans fail here too
            continue
    return n, time.perf_counter() - t, t_read, time.process_time() - cpu


def _read_views(args) -> tuple[int, float]:
    """Read every ``k``-th view's frames (from view ``i`` on), one thread: (views, seconds)."""
    root, i, k = args
    retain_freed_memory()  # as in a batch worker
    views = []
    for sj in sorted(Path(root).glob("s*/scan.json")):
        try:
            scan = load_scan(sj.parent)
        except Exception:  # noqa: BLE001 - a corrupted scan
            continue
        views += [(scan, v) for v in scan.views]
    n, t = 0, time.perf_counter()
    for scan, v in views[i::k]:
        try:
            read_view_frames(scan, v, threads=1)
            n += 1
        except Exception:  # noqa: BLE001 - a corrupted view
            pass
    return n, time.perf_counter() - t


def read_ceiling(root: Path, procs: int) -> float:
    """Views per second of reading the frames alone in ``procs`` processes, one thread each,
    the views shared out (timed inside the processes: their start-up is not counted).
    No implementation that has to read these frames on ``procs`` cores can go faster."""
    with ProcessPoolExecutor(procs, mp_context=get_context("spawn")) as ex:
        res = list(ex.map(_read_views, [(str(root), i, procs) for i in range(procs)]))
    return sum(n for n, _ in res) / max(1e-9, max(t for _, t in res))


def cli(root: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "ringscan.tools.cli", "batch", str(root), "--out", str(out),
                             "--no-progress", "--device", "cpu", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_entries(out: Path, n: int, proc: subprocess.Popen) -> None:
    while proc.poll() is None:
        try:
            if len(json.loads((out / "batch_report.json").read_text())["scans"]) >= n:
                return
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    raise SystemExit(f"the batch ended before {n} scans were done: {proc.stderr.read()[-2000:]}")


def children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def rerun_check(root: Path, out: Path, ref: dict, label: str) -> None:
    unfinished = {p.scan for p in plan_batch(root, out) if p.action == "run"} - set(CORRUPT)
    proc = cli(root, out, "--workers", "2")
    proc.communicate()
    rep = json.loads((out / "batch_report.json").read_text())
    computed = {s["scan"] for s in rep["scans"] if s.get("computed_views", 0) > 0} - set(CORRUPT)
    failed = sorted(s["scan"] for s in rep["scans"] if s["status"] == "failed")
    same = read_results(out) == ref
    print(f"{label}: {len(unfinished)} good scans unfinished, the rerun computed {len(computed)}; same set: "
          f"{computed == unfinished}; failed again: {failed}; rerun exit status {proc.returncode}; "
          f"results byte-identical to the uninterrupted run: {same}")


def throughput(root: Path, work: Path, views: int, ref: dict | None, spec: dict = SPEC, rounds: int = 1) -> dict:
    """Part 2: 1 worker, 2 workers (default threads, then one thread each), the NumPy reference and the
    reading ceiling over the same folder, ``rounds`` times in turn (this machine is shared and noisy:
    the medians are the figures)."""
    cores = os.cpu_count() or 1
    configs = (("w1", 1, None), ("w2", 2, None), ("s1", 1, 1), ("s2", 2, 1), ("p1", 1, 1))
    # p1: s1 with the allocator policy off in the worker (RINGSCAN_KEEP_FREED_MB=0, kernels.process)

    def steady(r):  # views/s between the first scan back (workers started, Warp and its kernel cache loaded) and
        # the last (closing the pool and the final report write after it are not a rate)
        return (r["computed_views"] - views) / max(1e-9, r["last_result_s"] - r["first_result_s"])

    runs: dict = {k: [] for k in ("w1", "w2", "s1", "s2", "p1", "numpy", "ceiling", "np_read", "np_n",
                                  "k_s1", "k_p1")}
    last: dict = {}
    for i in range(rounds):
        for key, workers, threads in configs:
            out = work / f"out_{key}"
            shutil.rmtree(out, ignore_errors=True)
            if key == "p1":
                os.environ["RINGSCAN_KEEP_FREED_MB"] = "0"  # inherited by the spawned worker
            try:
                last[key] = batch_reconstruct(root, out, workers=workers, cpu_threads=threads, device="cpu",
                                              progress=False)["totals"]
            finally:
                os.environ.pop("RINGSCAN_KEEP_FREED_MB", None)
            runs[key].append(steady(last[key]))
            if key in ("s1", "p1"):
                pv = last[key]["per_view_s"]
                runs[f"k_{key}"].append(sum(pv[k] for k in ("decode", "sample", "triangulate", "other")))
        n_np, s_np, read_np, _ = numpy_reference(root, spec)
        runs["numpy"].append(n_np / s_np)
        runs["np_read"].append(read_np / max(1, n_np))
        runs["np_n"].append((s_np - read_np) / max(1, n_np))
        runs["ceiling"].append(read_ceiling(root, cores))
        if rounds > 1:
            print(f"   round {i + 1}: views/s after the first scan: 1 worker {runs['w1'][-1]:.2f}, 2 workers "
                  f"{runs['w2'][-1]:.2f}, one thread each {runs['s1'][-1]:.2f} / {runs['s2'][-1]:.2f}; NumPy "
                  f"{runs['numpy'][-1]:.2f}; reading ceiling {runs['ceiling'][-1]:.2f}", flush=True)
    med = {k: float(np.median(v)) for k, v in runs.items()}
    ratio = {k: float(np.median([a / b for a, b in zip(runs[x], runs[y])]))
             for k, (x, y) in {"w": ("w2", "w1"), "s": ("s2", "s1"), "np": ("w2", "numpy"),
                               "ceil": ("ceiling", "numpy"), "of_ceil": ("w2", "ceiling")}.items()}
    tag = f"median of {rounds} rounds" if rounds > 1 else "one round"
    print(f"\n2. throughput ({last['w2']['computed_views']} views; views/s from the first scan back to the last, "
          f"{tag}):")
    print(f"   ringscan batch --workers 1: {med['w1']:.2f} views/s; --workers 2: {med['w2']:.2f}")
    print(f"   ringscan batch --workers 1 --cpu-threads 1: {med['s1']:.2f} views/s; --workers 2 --cpu-threads 1: "
          f"{med['s2']:.2f}")
    print(f"   scaling, one thread per worker: 2 workers / 1 worker {ratio['s']:.2f}x (target >= 1.7x)")
    print(f"   allocator policy, one worker with one thread: {med['s1']:.2f} views/s keeping freed memory, "
          f"{med['p1']:.2f} with RINGSCAN_KEEP_FREED_MB=0; kernel stages (decode, sample, triangulate, filter, "
          f"up/download) {1000 * med['k_s1']:.0f} ms a view against {1000 * med['k_p1']:.0f} ms")
    pv = last["s1"]["per_view_s"]
    print("   per view in that worker: " + ", ".join(f"{k} {1000 * v:.1f} ms" for k, v in pv.items()))
    starts = [last[k]["worker_start_s"]["median"] for k in ("w1", "w2", "s1", "s2") if "worker_start_s" in last[k]]
    if starts:
        print(f"   worker start-up (spawn to ready, once per worker; the last round's runs): median "
              f"{np.median(starts):.2f} s; first scan back after {last['w2']['first_result_s']:.2f} s (2 workers)")
    print(f"   NumPy reference, one scan after another: {med['numpy']:.2f} views/s (per view {1000 * med['np_read']:.0f} "
          f"ms reading frames + {1000 * med['np_n']:.0f} ms computing)")
    print(f"   reading the frames alone, {cores} processes (one per core): {med['ceiling']:.2f} views/s = "
          f"{ratio['ceil']:.2f}x the NumPy reference: the ceiling for any implementation that reads these "
          f"frames on this machine")
    print(f"   2 workers / 1 worker: {ratio['w']:.2f}x (target >= 1.7x); batch (2 workers) / NumPy: {ratio['np']:.2f}x "
          f"(target >= 6x; {ratio['of_ceil']:.0%} of the reading ceiling)")
    if ref is not None:
        print(f"   same bytes with 1 and 2 workers as the reference run: "
              f"{read_results(work / 'out_w1') == ref and read_results(work / 'out_w2') == ref}")
    try:
        print(f"   load average after: {os.getloadavg()[0]:.2f}")
    except OSError:
        pass
    return last["w2"]


FORMATS = ("png-opencv", "png", "tiff", "packed")
"""``--formats``: PNG as another program writes it (OpenCV's default parameters), ringscan's PNG
(pipeline.formats.images.png_params), uncompressed TIFF, and the packed frame store."""


def make_format_copies(work: Path, base: Path) -> dict[str, Path]:
    """Copies of the ringscan-PNG scans below ``base`` in every format of :data:`FORMATS` (made once)."""
    from ringscan.pipeline.formats.packing import pack_scan

    roots = {"png": base}
    for fmt in FORMATS[:1] + FORMATS[2:]:
        root = work / f"scans_{fmt}"
        roots[fmt] = root
        if (root / ".done").exists():
            continue
        shutil.rmtree(root, ignore_errors=True)
        shutil.copytree(base, root)
        if fmt == "png-opencv":
            for p in root.glob("*/view_*/*.png"):
                cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED))  # OpenCV's defaults
        elif fmt == "tiff":
            to_tiff(root)
        else:
            for sj in sorted(root.glob("*/scan.json")):
                pack_scan(sj.parent)
        (root / ".done").write_text("")
    return roots


def _frames_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file() and "truth" not in p.parts
               and p.name != "scan.json" and not p.name.startswith("."))


def _one_view_read(root: Path, reps: int = 5) -> tuple[float, float, float]:
    """Best-of-``reps`` seconds to read the first view's frames on one thread, and two memory floors: copying
    them into a preallocated stack whose pages are already mapped (``np.copyto``), and into a fresh one
    (``np.empty`` + copy: what the reader does, its output being a new array each view; a stack of 28
    full-size frames is above glibc's largest mmap threshold, so its pages are mapped anew every time)."""
    import numcodecs.blosc

    numcodecs.blosc.use_threads = False  # Blosc on this thread alone
    scan = load_scan(sorted(root.glob("*/scan.json"))[0].parent)
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        a = read_view_frames(scan, scan.views[0], threads=1)
        ts.append(time.perf_counter() - t)
    b = np.zeros_like(a)
    hot, fresh = [], []
    for _ in range(reps):
        t = time.perf_counter()
        np.copyto(b, a)
        hot.append(time.perf_counter() - t)
        t = time.perf_counter()
        np.copyto(np.empty_like(a), a)
        fresh.append(time.perf_counter() - t)
    numcodecs.blosc.use_threads = None
    return min(ts), min(hot), min(fresh)


def _plys(out: Path) -> dict:
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*.ply"))}


def _load() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def formats_compare(work: Path, base: Path, views: int, spec: dict, rounds: int = 1, device: str = "cpu") -> None:
    """Part 2 per frame format (:data:`FORMATS`); in each round every format in turn, the order rotated from
    round to round (a change of the machine's load does not always fall on the same format); medians of
    the rounds and of the per-round ratios printed, then the issue's targets and the bounds the machine sets on them."""
    cores = os.cpu_count() or 1
    roots = make_format_copies(work, base)

    def steady(r):  # as in throughput(): between the first scan's result and the last
        return (r["computed_views"] - views) / max(1e-9, r["last_result_s"] - r["first_result_s"])

    def steady_cpu(scans, workers):  # the workers' CPU a view, each worker's first scan (the scans are handed
        # out in folder order, normally one to each worker first), which loads the kernels it launches, left out
        rest = scans[workers:]
        return sum(e["cpu_s"] for e in rest) / max(1, sum(e["computed_views"] for e in rest))

    keys = ("w1", "w2", "ceiling", "numpy", "kernels", "read1", "floor", "floor_fresh", "cpu1", "cpu2", "np_cpu",
            "load")
    runs = {f: {k: [] for k in keys} for f in FORMATS}
    same = {}
    for i in range(rounds):
        order = FORMATS[i % len(FORMATS):] + FORMATS[:i % len(FORMATS)]
        for fmt in order:
            r = runs[fmt]
            r["load"].append(_load())
            for key, workers in (("w1", 1), ("w2", 2)):
                out = work / f"out_{fmt}_{key}"
                shutil.rmtree(out, ignore_errors=True)
                rep = batch_reconstruct(roots[fmt], out, workers=workers, device=device, progress=False)
                tot = rep["totals"]
                r[key].append(steady(tot))
                r["cpu" + key[1]].append(steady_cpu(rep["scans"], workers))
                if key == "w1":
                    pv = tot["per_view_s"]
                    r["kernels"].append(1.0 / sum(pv[k] for k in ("decode", "sample", "triangulate", "other")))
            n_np, s_np, _, cpu_np = numpy_reference(roots[fmt], spec)
            r["numpy"].append(n_np / s_np)
            r["np_cpu"].append(cpu_np / max(1, n_np))
            r["ceiling"].append(read_ceiling(roots[fmt], cores))
            t1, th, tf = _one_view_read(roots[fmt])
            r["read1"].append(t1)
            r["floor"].append(th)
            r["floor_fresh"].append(tf)
            print(f"   round {i + 1} {fmt} (load average {r['load'][-1]:.1f}): 1 worker {r['w1'][-1]:.2f}, 2 workers "
                  f"{r['w2'][-1]:.2f} views/s (worker CPU {1000 * r['cpu1'][-1]:.0f} / {1000 * r['cpu2'][-1]:.0f} ms "
                  f"a view); NumPy {r['numpy'][-1]:.2f} ({1000 * r['np_cpu'][-1]:.0f} ms CPU a view); ceiling "
                  f"{r['ceiling'][-1]:.2f}; one view read on one thread {1000 * t1:.1f} ms (copy {1000 * th:.1f} ms "
                  f"into a mapped stack, {1000 * tf:.1f} ms into a fresh one)", flush=True)
        for fmt in FORMATS:
            same[fmt] = same.get(fmt, True) and _plys(work / f"out_{fmt}_w2") == _plys(work / f"out_{FORMATS[0]}_w2")
    med = {f: {k: float(np.median(v)) for k, v in runs[f].items()} for f in FORMATS}
    ref = runs["png-opencv"]

    def rel(f, k, kr=None):  # median over rounds of the per-round ratio to PNG as another program writes it
        return float(np.median([a / b for a, b in zip(runs[f][k], ref[kr or k])]))

    def rel_to(f, k, kr):  # median over rounds of the per-round ratio of two figures of one format
        return float(np.median([a / b for a, b in zip(runs[f][k], runs[f][kr])]))

    def cpu_gain(k):  # median over rounds of PNG (OpenCV)'s worker CPU a view over the packed store's
        return float(np.median([b / a for a, b in zip(runs["packed"][k], ref[k])]))

    size0 = _frames_bytes(roots["png-opencv"])
    sizes = {f: _frames_bytes(roots[f]) for f in FORMATS}
    tag = f"median of {rounds} rounds" if rounds > 1 else "one round"
    loads = [x for f in FORMATS for x in runs[f]["load"]]
    print(f"\n2. per frame format ({views} views x {len(list(base.glob('*/scan.json')))} scans, full size, 28 frames a "
          f"view; views/s from the first scan back to the last; {tag}; {cores} cores; load average at the starts "
          f"{min(loads):.1f}-{max(loads):.1f}):")
    print("   | format | frames on disk | 1 view read, 1 thread | batch 1 worker | batch 2 workers | reading "
          "ceiling | NumPy reference | kernels only (1 worker) | worker CPU a view, steady (1 / 2 workers) | 2 workers / "
          "NumPy | 2 workers vs PNG (OpenCV) | same PLYs |")
    print("   |---|---|---|---|---|---|---|---|---|---|---|---|")
    for f in FORMATS:
        m = med[f]
        print(f"   | {f} | {sizes[f] / 1e6:.1f} MB ({sizes[f] / size0:.2f}x) | {1000 * m['read1']:.0f} ms "
              f"({rel_to(f, 'read1', 'floor'):.1f}x / {rel_to(f, 'read1', 'floor_fresh'):.1f}x the copies) | "
              f"{m['w1']:.2f} | {m['w2']:.2f} | {m['ceiling']:.2f} | {m['numpy']:.2f} | {m['kernels']:.2f} | "
              f"{1000 * m['cpu1']:.0f} / {1000 * m['cpu2']:.0f} ms | {rel_to(f, 'w2', 'numpy'):.2f}x | "
              f"{rel(f, 'w2'):.2f}x | {same.get(f)} |")
    p = "packed"
    print("\n   the issue's targets, packed frame store (medians of the per-round ratios, same run):")
    print(f"   (a) one view read on one thread: {1000 * med[p]['read1']:.1f} ms = {rel_to(p, 'read1', 'floor'):.1f}x "
          f"copying its frames into a mapped stack ({1000 * med[p]['floor']:.1f} ms), "
          f"{rel_to(p, 'read1', 'floor_fresh'):.1f}x copying them into a fresh one ({1000 * med[p]['floor_fresh']:.1f} "
          "ms; the reader's output is a fresh array) (target <= 4x)")
    print(f"   (b) batch views/s, packed / PNG as OpenCV writes it: 1 worker {rel(p, 'w1'):.2f}x, 2 workers "
          f"{rel(p, 'w2'):.2f}x (target >= 3x); worker CPU a view, PNG / packed: 1 worker "
          f"{cpu_gain('cpu1'):.2f}x, 2 workers {cpu_gain('cpu2'):.2f}x (what the clock "
          "ratio tends to where the workers' cores are theirs alone)")
    np_png = float(np.median([a / b for a, b in zip(runs[p]['w2'], ref['numpy'])]))
    print(f"   (c) packed batch (2 workers) / NumPy reference views/s: {rel_to(p, 'w2', 'numpy'):.2f}x with NumPy "
          f"reading the same store, {np_png:.2f}x against NumPy on the PNG (OpenCV) frames (target >= 6x); "
          f"CPU a view, NumPy reference / packed batch worker (2 workers; they use two cores, NumPy one): "
          f"{float(np.median([a / b for a, b in zip(runs[p]['np_cpu'], runs[p]['cpu2'])])):.2f}x")
    print(f"   (d) size on disk, packed / PNG as OpenCV writes it: {sizes[p] / size0:.2f}x (target <= 1.2x)")
    o = "png-opencv"
    print(f"   (e) PNG as OpenCV writes it, batch (2 workers) / its reading ceiling: {rel_to(o, 'w2', 'ceiling'):.0%} "
          f"(target >= 85 %); where reading and computing share the cores a batch reaches at most the reading's CPU "
          f"over a worker's CPU a view, ({cores} / ceiling) / (CPU a view, 2 workers): "
          f"{float(np.median([cores / (c * w) for c, w in zip(ref['ceiling'], ref['cpu2'])])):.0%}")
    # (b) against the compute alone: a batch cannot run faster than its own compute stages (decode, sample,
    # triangulate, the rest of a view: 1 worker, its kernels on every core), whatever the frames are read from
    print(f"   bound on (b): the packed batch's compute stages alone run at {med[p]['kernels']:.2f} views/s here; "
          f"3x PNG (OpenCV)'s batch is {3 * med[o]['w1']:.2f} (1 worker) and {3 * med[o]['w2']:.2f} (2 workers) "
          f"views/s = {float(np.median([3 * a / k for a, k in zip(ref['w1'], runs[p]['kernels'])])):.0%} and "
          f"{float(np.median([3 * a / k for a, k in zip(ref['w2'], runs[p]['kernels'])])):.0%} of that rate "
          "(>= 100 %: out of reach on this machine without faster compute stages, e.g. a GPU)")
    print(f"   load average after: {_load():.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/ringscan_batch_scale")
    ap.add_argument("--scans", type=int, default=100)
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--camera", default="320x240", metavar="WxH", help="camera size (default 320x240)")
    ap.add_argument("--throughput-only", action="store_true", help="only part 2 (throughput)")
    ap.add_argument("--full", action="store_true",
                    help="throughput only, on full-size views: the default rig's 1280x1024 camera, gray-rings 7 bits "
                         "pitch 4 + 6 sector bits (28 frames), no corrupted scans")
    ap.add_argument("--tiff", action="store_true", help="with --full: frames as uncompressed TIFF instead of PNG")
    ap.add_argument("--formats", action="store_true",
                    help="with --full: part 2 per frame format (PNG as OpenCV writes it by default, ringscan's PNG, "
                         "uncompressed TIFF, packed), on copies of the scans")
    ap.add_argument("--device", default="cpu",
                    help="with --formats: Warp device of the batches (default cpu; cuda:0 on a GPU machine, where the "
                         "compute stages leave the CPU and targets (b) and (e) are decided)")
    ap.add_argument("--rounds", type=int, default=1,
                    help="measure part 2 this many times in turn and print the medians (default 1)")
    a = ap.parse_args()
    # the NumPy reference runs in this process: the same allocator and BLAS policy as the batch workers (fair
    # to both)
    retain_freed_memory()
    one_blas_thread()
    size = None if a.full else tuple(int(x) for x in a.camera.split("x"))
    spec = FULL_SPEC if a.full else SPEC
    work = Path(a.work)
    root = work / "scans"
    root.mkdir(parents=True, exist_ok=True)
    make_scans(root, a.scans, a.views, size, spec, corrupt=not a.full)
    if a.full and a.tiff:
        to_tiff(root)
    for p in work.glob("out_*"):
        shutil.rmtree(p)
    try:
        load = os.getloadavg()
        print(f"load average before the runs (1/5/15 min): {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} "
              f"on {os.cpu_count()} cores")
    except OSError:
        pass

    if a.full and a.formats:
        formats_compare(work, root, a.views, spec, rounds=a.rounds, device=a.device)
        return 0
    if a.throughput_only or a.full:
        throughput(root, work, a.views, None, spec, rounds=a.rounds)
        return 0
    # 1. faults, through the CLI (exit status)
    proc = cli(root, work / "out_ref", "--workers", "2")
    stdout, _ = proc.communicate()
    rep = json.loads((work / "out_ref" / "batch_report.json").read_text())
    failed = [s for s in rep["scans"] if s["status"] == "failed"]
    print(f"\n1. {len(rep['scans'])} scans: {len(rep['scans']) - len(failed)} results, {len(failed)} errors, "
          f"exit status {proc.returncode}")
    for s in failed:
        print(f"   {s['scan']} ({CORRUPT.get(s['scan'], 'NOT CORRUPTED')}): {s['error']}")
    ref = read_results(work / "out_ref")

    r2 = throughput(root, work, a.views, ref, rounds=a.rounds)

    # 3. the per-view time split
    pv = r2["per_view_s"]
    print("\n3. per view (seconds in a worker): " + ", ".join(f"{k} {v * 1000:.1f} ms" for k, v in pv.items()))

    # 4. killed part-way, then rerun
    out = work / "out_kill_parent"
    proc = cli(root, out, "--workers", "2")
    wait_for_entries(out, 35, proc)
    kids = children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    time.sleep(2.0)
    alive = [k for k in kids if Path(f"/proc/{k}").exists() and Path(f"/proc/{k}/status").read_text().find(
        "State:\tZ") < 0]
    print(f"\n4. parent killed (SIGKILL) after >= 35 scans; of its {len(kids)} child processes (workers, "
          f"resource tracker), still running 2 s later: {len(alive)}")
    rerun_check(root, out, ref, "   after the parent was killed")

    out = work / "out_kill_worker"
    proc = cli(root, out, "--workers", "2")
    wait_for_entries(out, 35, proc)
    workers = [k for k in children(proc.pid)
               if "resource_tracker" not in Path(f"/proc/{k}/cmdline").read_text(errors="replace")]
    os.kill(workers[0], signal.SIGKILL)
    stdout, stderr = proc.communicate()
    rep = json.loads((out / "batch_report.json").read_text())
    failed = [s["scan"] for s in rep["scans"] if s["status"] == "failed"]
    print(f"   one worker killed (SIGKILL, pid {workers[0]}) after >= 35 scans: the run went on, exit status "
          f"{proc.returncode}, failed: {failed}; worker died and was replaced: "
          f"{'a batch worker died' in stderr}")
    print(f"   results byte-identical to the uninterrupted run: {read_results(out) == ref}")
    rerun_check(root, out, ref, "   rerun after the worker kill")
    return 0


if __name__ == "__main__":
    sys.exit(main())
