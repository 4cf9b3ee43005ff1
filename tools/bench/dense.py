"""``ringscan bench --dense``: the phase-rings stages against their NumPy twins, as ratios in one run."""

from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from ringscan.kernels import init_warp
from ringscan.kernels.phase import compact_phase_points, decode_phase, smooth_phase
from ringscan.kernels.response import response_tables
from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.settings import PhaseSettings
from ringscan.kernels.triangulation import TriangulateSettings, triangulate_rings
from ringscan.pipeline.codecs import phase_rings
from ringscan.pipeline.codecs.phase_rings import residual_light_gamma
from ringscan.pipeline.formats.patterns import PatternSpec, parse_patterns
from ringscan.pipeline.formats.scan import load_scan, read_view_frames
from ringscan.pipeline.geometry import camera_model_for, light_model_for
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.tools.bench.core import best_of, default_bench_scene
from ringscan.tools.bench.numpy_twins import decode_numpy, phase_numpy, points_numpy, smooth_numpy, triangulate_numpy

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_BENCH_PATTERNS", "bench_dense"]


DEFAULT_BENCH_PATTERNS = {"codec": phase_rings.NAME, "width": 1024, "height": 768, "center": [511.5, 383.5],
                          "rho0": 8.0, "pitch": 8.0, "bits": 6, "sector_bits": 6, "steps": 4}


def bench_dense(*, scan_dir: str | os.PathLike | None = None, scene: str | None = None, repeats: int = 3,
                devices=None, out=print) -> dict:
    """Time the dense stages of one phase-rings view against their NumPy twins.

    Stages: ``decode`` (band + sector Gray codes), ``phase`` (linearise, weighted
    phase, unwrap), ``smooth`` (smoothing, sector fill, compaction into points),
    ``triangulate``. The NumPy side runs ``tools.numpy_twins`` decode and
    triangulation and the twins in this module, on the same frames, in the same
    run; ratios are NumPy time / Warp time. Prints a table with ``out`` and
    returns the figures.

    Args:
        scan_dir: a phase-rings scan folder (default: simulate Spot, or the
            sphere when ../shared/data is absent, with the default rig).
        scene: scene of the default scan.
        repeats: best of this many runs per stage.
        devices: Warp devices (default: cpu, and cuda:0 when present).
        out: print function.
    """

    init_warp()
    scan, tmp = _bench_scan(scan_dir, scene, out)
    try:
        spec: PatternSpec = scan.patterns
        if spec.codec != phase_rings.NAME:
            raise ValueError(f"bench_dense: the scan's codec is {spec.codec!r}; the dense stages need "
                             f"{phase_rings.NAME}")
        inp = _dense_inputs(scan)
        ref, n_np = _time_numpy(inp, repeats)
        if devices is None:
            devices = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
        cpus = os.cpu_count() or 1
        runs = [_time_warp(inp, dev, threads, repeats)
                for dev in devices for threads in ([cpus, 1] if dev == "cpu" and cpus > 1 else [cpus])]
        _print_table(out, inp.frames, ref, n_np, runs, repeats)
        return {"numpy": ref, "numpy_points": n_np, "warp": runs,
                "ratio_total": {f"{r['device']}x{r['threads']}": ref["total"] / r["times"]["total"] for r in runs}}
    finally:
        if tmp is not None:
            tmp.cleanup()


def _bench_scan(scan_dir, scene, out):
    """The scan to time: ``scan_dir`` loaded, or a default view simulated into a temporary folder (also returned)."""
    tmp = None
    if scan_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="ringscan-dense-bench-")
        if scene is None:
            scene = default_bench_scene()
        out(f"simulating a phase-rings view of {Path(scene).stem} (default rig, pitch 8, 4 steps, 6 sector bits) ...")
        scan = simulate_scan(Path(tmp.name) / "scan", scene=scene, patterns=parse_patterns(DEFAULT_BENCH_PATTERNS),
                             progress=False)
    else:
        scan = load_scan(scan_dir)
    return scan, tmp


@dataclass
class _DenseInputs:
    """The first view's frames and what both sides decode them with."""

    frames: np.ndarray
    spec: PatternSpec
    rig: object
    ps: PhaseSettings
    lut: np.ndarray
    wlut: np.ndarray
    g_light: float
    vol: tuple
    kw: dict


def _dense_inputs(scan) -> _DenseInputs:
    """Read the scan's first view and make its response tables, light gamma and volume."""
    spec: PatternSpec = scan.patterns
    frames = read_view_frames(scan, scan.views[0])
    rig = scan.rig
    ps = PhaseSettings()
    full = 255 if frames.dtype == np.uint8 else 65535
    lut, wlut = response_tables(full, camera_gamma=rig.camera.gamma, weighted=ps.weighted)
    g_light = residual_light_gamma(scan)
    vol = (rig.volume.z_min, rig.volume.z_max, rig.volume.r_max)
    kw = dict(bits=spec.bits, sector_bits=spec.sector_bits)
    return _DenseInputs(frames, spec, rig, ps, lut, wlut, g_light, vol, kw)


def _time_numpy(inp: _DenseInputs, repeats: int) -> tuple[dict, int]:
    """Best times of the NumPy twins per stage (and their total), and the points they keep."""
    frames, spec, rig, ps, kw = inp.frames, inp.spec, inp.rig, inp.ps, inp.kw
    ref, state = {}, {}

    def np_decode():
        state["dec"] = decode_numpy(frames, **kw)

    def np_phase():
        state["ph"] = phase_numpy(frames, state["dec"], steps=spec.steps, lut=inp.lut, wlut=inp.wlut,
                                  light_gamma=inp.g_light, settings=ps, **kw)

    def np_smooth():
        sm = smooth_numpy(state["ph"], state["dec"]["sector"], settings=ps)
        state["pts"] = points_numpy(sm, rho0=spec.rho0, pitch=spec.pitch)

    def np_tri():
        p = state["pts"]
        state["tri"] = triangulate_numpy(p["uv"], p["rho"], p["sector"], rig, center=spec.center,
                                         sector_bits=spec.sector_bits)

    for name, fn in (("decode", np_decode), ("phase", np_phase), ("smooth", np_smooth), ("triangulate", np_tri)):
        fn()
        ref[name] = best_of(fn, repeats)
    ref["total"] = sum(ref.values())
    return ref, int(np.count_nonzero(state["tri"][1] == 0))


def _time_warp(inp: _DenseInputs, dev: str, threads: int, repeats: int) -> dict:
    """Best times of the Warp stages on one device and thread count (after a warm-up run), and the points kept."""
    spec, ps, kw = inp.spec, inp.ps, inp.kw
    fr = wp.array(inp.frames, device=dev)
    lut_w = wp.array(inp.lut, dtype=wp.float32, device=dev)
    wlut_w = wp.array(inp.wlut, dtype=wp.float32, device=dev)
    cam, light = camera_model_for(inp.rig), light_model_for(inp.rig)
    ws = {}

    def wdec():
        ws["lab"] = decode_gray_rings(fr, threads=threads, **kw)
        wp.synchronize_device(dev)

    def wphase():
        ws["ph"] = decode_phase(fr, ws["lab"], steps=spec.steps, lut=lut_w, wlut=wlut_w,
                                light_gamma=inp.g_light, settings=ps, threads=threads, **kw)
        wp.synchronize_device(dev)

    def wsmooth():
        sm = smooth_phase(ws["ph"], ws["lab"].sector, settings=ps, threads=threads)
        ws["pts"] = compact_phase_points(sm, rho0=spec.rho0, pitch=spec.pitch, threads=threads)
        wp.synchronize_device(dev)

    def wtri():
        p = ws["pts"]
        ws["tri"] = triangulate_rings(p.uv, p.rho, p.sector, p.confidence, camera=cam, light=light,
                                      volume=inp.vol, center=spec.center, sector_bits=spec.sector_bits,
                                      settings=TriangulateSettings(), threads=threads)
        wp.synchronize_device(dev)

    stages = (("decode", wdec), ("phase", wphase), ("smooth", wsmooth), ("triangulate", wtri))
    for _, fn in stages:  # warm up: compile or load the kernels
        fn()
    tm = {name: best_of(fn, repeats) for name, fn in stages}
    tm["total"] = sum(tm.values())
    n_pts = int(np.count_nonzero(ws["tri"].status.numpy() == 0))
    return {"device": dev, "threads": threads, "times": tm, "points": n_pts}


def _print_table(out, frames: np.ndarray, ref: dict, n_np: int, runs: list, repeats: int) -> None:
    """Print the per-stage times and ratios, and the points per second, with ``out``."""
    nf, h, w = frames.shape
    out(f"dense path, one view: {nf} frames of {w}x{h} ({frames.dtype}); points: {n_np} (NumPy), "
        f"{runs[0]['points']} (Warp); best of {repeats}")
    header = f"{'stage':<12}{'numpy ms':>10}" + "".join(
        f"{r['device'] + (' x' + str(r['threads']) if r['device'] == 'cpu' else ''):>14}{'ratio':>8}" for r in runs)
    out(header)
    for stage in ("decode", "phase", "smooth", "triangulate", "total"):
        line = f"{stage:<12}{ref[stage] * 1e3:>10.1f}"
        for r in runs:
            line += f"{r['times'][stage] * 1e3:>12.1f}ms{ref[stage] / r['times'][stage]:>7.1f}x"
        out(line)
    pps = f"points/s: numpy {n_np / ref['total']:.3g}" + "".join(
        f", {r['device']}{' x' + str(r['threads']) if r['device'] == 'cpu' else ''} "
        f"{r['points'] / r['times']['total']:.3g}" for r in runs)
    out(pps)
