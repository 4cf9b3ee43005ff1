"""Stage timings of one view: Warp (CPU, and CUDA where present) against the
plain NumPy implementation of the same stages, measured in the same run, plus the
floor set by reading every frame once at this machine's memory bandwidth.

Speeds are printed as ratios (NumPy time / Warp time): single timings on shared
machines are noisy, ratios taken in one run are not.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from ringscan.kernels import init_warp
from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.ring_sampling import ring_radii, sample_gray_rings
from ringscan.kernels.settings import DecodeSettings, SampleSettings
from ringscan.kernels.triangulation import TriangulateSettings, triangulate_rings
from ringscan.pipeline.codecs import gray_rings, phase_rings
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.scan import load_scan, read_view_frames
from ringscan.pipeline.geometry import camera_model_for, light_model_for
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.tools.bench.numpy_twins import decode_numpy, sample_numpy, triangulate_numpy

log = logging.getLogger(__name__)

__all__ = ["best_of", "floor_note", "memory_bandwidth", "run_bench"]


def best_of(fn, repeats: int) -> float:
    """The shortest of ``repeats`` wall times of ``fn()`` (seconds): the least
    disturbed run on a noisy machine."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def memory_bandwidth(nbytes: int = 256 << 20, repeats: int = 5) -> float:
    """Copy bandwidth in bytes/s (read + write counted), best of ``repeats``."""
    src = np.ones(nbytes, np.uint8)
    dst = np.empty_like(src)
    t = best_of(lambda: np.copyto(dst, src), repeats)
    return 2 * nbytes / t


def default_bench_scene() -> str:
    """The bench's default scene: Spot from ../shared/data/models (``RINGSCAN_SHARED_DATA``
    names another data folder), else the procedural sphere."""
    data = os.environ.get("RINGSCAN_SHARED_DATA") or Path(__file__).resolve().parents[2].parent / "shared" / "data"
    spot = Path(data) / "models" / "odedstein_spot.obj"
    return str(spot) if spot.is_file() else "sphere"


def floor_note(runs: list[dict], floor: float) -> str:
    """The Warp total against the memory floor (``floor`` seconds): of the first run on
    the CPU (every core), or, where no CPU run was asked for (``--device cuda:0``), of
    the first run, named by its device."""
    r = next((r for r in runs if r["device"] == "cpu"), runs[0])
    name = "CPU" if r["device"] == "cpu" else r["device"]
    return f"Warp {name} total is {r['times']['total'] / floor:.1f}x that floor"


def _default_scan(out: Path, scene: str | None, device: str | None):
    spec = parse_patterns({"codec": gray_rings.NAME, "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 6})
    return simulate_scan(out, scene=scene or default_bench_scene(), patterns=spec, device=device, progress=False)


def run_bench(*, scan_dir: str | None = None, scene: str | None = None, repeats: int = 5, devices=None,
              out=print) -> dict:
    """Time decode, sampling and triangulation of one view; print a table with ``out``."""
    import warp as wp

    init_warp()
    tmp = None
    if scan_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="ringscan-bench-")
        out(f"simulating a view of {Path(scene or default_bench_scene()).stem} (virtual rig, gray-rings 7 bits + 6 "
            f"sector bits) ...")
        scan = _default_scan(Path(tmp.name) / "scan", scene, None)
    else:
        scan = load_scan(scan_dir)
    spec = scan.patterns
    if spec.codec not in (gray_rings.NAME, phase_rings.NAME):  # the codecs of the binary frames
        raise ValueError(f"bench: the scan's codec is {spec.codec!r}; the binary stages need {gray_rings.NAME} "
                         "frames")
    view = scan.views[0]
    frames = read_view_frames(scan, view)
    nf, h, w = frames.shape
    ref, n_numpy = _time_numpy(frames, spec, scan.rig, repeats)
    if devices is None:
        devices = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
    cpus = os.cpu_count() or 1
    runs = [_time_warp(frames, spec, scan.rig, dev, threads, repeats)
            for dev in devices for threads in ([cpus, 1] if dev == "cpu" and cpus > 1 else [cpus])]

    bw = memory_bandwidth()
    floor = frames.nbytes / (bw / 2)
    out(f"one view: {nf} frames of {w}x{h} ({frames.dtype}), {n_numpy} samples (NumPy) / "
        f"{runs[0]['samples']} (Warp); best of {repeats}")
    header = f"{'stage':<12}{'numpy ms':>10}" + "".join(
        f"{r['device'] + (' x' + str(r['threads']) if r['device'] == 'cpu' else ''):>14}{'ratio':>8}" for r in runs)
    out(header)
    for stage in ("decode", "sample", "triangulate", "total"):
        line = f"{stage:<12}{ref[stage] * 1e3:>10.1f}"
        for r in runs:
            line += f"{r['times'][stage] * 1e3:>12.1f}ms{ref[stage] / r['times'][stage]:>7.1f}x"
        out(line)
    out(f"memory floor: reading {frames.nbytes / 1e6:.1f} MB of frames once at {bw / 2 / 1e9:.1f} GB/s "
        f"(half of the measured copy bandwidth) = {floor * 1e3:.1f} ms; {floor_note(runs, floor)}")
    if tmp is not None:
        tmp.cleanup()
    return {"numpy": ref, "warp": runs, "bandwidth_Bps": bw, "floor_s": floor}


def _time_numpy(frames: np.ndarray, spec, rig, repeats: int) -> tuple[dict, int]:
    """The NumPy reference's best times of the three stages (same frames, same rules) and its sample count."""
    ref = {}
    dec_np = decode_numpy(frames, bits=spec.bits, sector_bits=spec.sector_bits)
    ref["decode"] = best_of(lambda: decode_numpy(frames, bits=spec.bits, sector_bits=spec.sector_bits), repeats)
    smp_np = sample_numpy(frames, dec_np, bits=spec.bits)
    ref["sample"] = best_of(lambda: sample_numpy(frames, dec_np, bits=spec.bits), repeats)
    rho_np = (spec.rho0 + smp_np["ring"] * spec.pitch).astype(np.float32)
    ref["triangulate"] = best_of(lambda: triangulate_numpy(smp_np["uv"], rho_np, smp_np["sector"], rig,
                                                         center=spec.center, sector_bits=spec.sector_bits), repeats)
    ref["total"] = sum(ref.values())
    return ref, len(smp_np["uv"])


def _time_warp(frames: np.ndarray, spec, rig, dev: str, threads: int, repeats: int) -> dict:
    """The Warp kernels' best times of the three stages on one device (and CPU thread count), after a warm-up."""
    import warp as wp

    ds, ss, ts = DecodeSettings(), SampleSettings(), TriangulateSettings()
    vol = (rig.volume.z_min, rig.volume.z_max, rig.volume.r_max)
    fr = wp.array(frames, device=dev)
    cam, light = camera_model_for(rig), light_model_for(rig)
    state = {}

    def dec():
        state["lab"] = decode_gray_rings(fr, bits=spec.bits, sector_bits=spec.sector_bits, settings=ds,
                                         threads=threads)
        wp.synchronize_device(dev)

    def smp():
        s = sample_gray_rings(fr, state["lab"], bits=spec.bits, settings=ss, threads=threads)
        state["s"] = s
        state["rho"] = ring_radii(s.ring, rho0=spec.rho0, pitch=spec.pitch)
        wp.synchronize_device(dev)

    def tri():
        s = state["s"]
        state["t"] = triangulate_rings(s.uv, state["rho"], s.sector, s.confidence, camera=cam, light=light,
                                       volume=vol, center=spec.center, sector_bits=spec.sector_bits,
                                       settings=ts, threads=threads)
        wp.synchronize_device(dev)

    dec(), smp(), tri()  # warm up: compile or load kernels
    t = {"decode": best_of(dec, repeats), "sample": best_of(smp, repeats), "triangulate": best_of(tri, repeats)}
    t["total"] = sum(t.values())
    return {"device": dev, "threads": threads, "times": t, "samples": len(state["s"])}
