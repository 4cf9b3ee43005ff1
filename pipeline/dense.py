"""Dense reconstruction with phase-rings: a ring through every pixel (DESIGN §5).

:func:`extract_phase_rings` is the ``phase-rings`` codec's decode + sampling stage
for :func:`ringscan.pipeline.reconstruct.reconstruct_scan`: it decodes the band
and sector Gray codes (``kernels.ring_labels``), the phase frames
(``kernels.phase``: linearisation, weighted N-step phase, unwrapping anchored at
band edges, smoothing) and hands one sample per valid camera pixel, in raster
order, to the triangulation (which meets each pixel's ray with the quadric of its
own continuous rho).

Response (gamma) handling, ``PhaseSettings.response``:

- ``rig`` (default): the rig file's ``camera.response.gamma`` linearises the
  recorded values and ``light.response.gamma`` is undone after normalising by the
  white and black frames;
- ``estimate``: the camera gamma is estimated from the view's own frames
  (:func:`estimate_camera_gamma`: the N phase samples of a clean fringe average
  to the middle of white and black only in linear units); the light gamma is
  still taken from the rig;
- ``linear``: no correction.

This module also holds the vectorised NumPy twins of the dense stages
(:func:`phase_numpy`, :func:`smooth_numpy`, :func:`points_numpy`) that the tests
cross-check the kernels against and that :func:`bench_dense` times the kernels
against.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

from ringscan.kernels.phase import (
    PHASE_STATUS_NAMES,
    PhaseSettings,
    compact_phase_points,
    decode_phase,
    response_tables,
    smooth_phase,
)
from ringscan.kernels.ring_labels import decode_gray_rings

from .patterns import PatternSpec, parse_patterns
from .scan import Scan

log = logging.getLogger(__name__)

GAMMA_RANGE = (0.3, 4.0)
"""Search interval of :func:`estimate_camera_gamma`."""

__all__ = [
    "extract_phase_rings",
    "phase_settings_of",
    "view_response",
    "estimate_camera_gamma",
    "truth_rho_at",
    "phase_numpy",
    "smooth_numpy",
    "points_numpy",
    "bench_dense",
    "PhaseSettings",
]


def phase_settings_of(settings) -> PhaseSettings:
    """The phase block of a ``ReconstructSettings`` (its ``phase`` field), or the defaults."""
    ps = getattr(settings, "phase", None)
    if ps is None:
        return PhaseSettings()
    if not isinstance(ps, PhaseSettings):
        raise ValueError(f"settings.phase: expected PhaseSettings, got {type(ps).__name__}")
    return ps


def view_response(frames: np.ndarray | wp.array, scan: Scan, settings: PhaseSettings) -> tuple[float, float]:
    """(camera gamma, light gamma) used to linearise one view (see the module docstring)."""
    rig = scan.rig
    light_gamma = float(getattr(rig.light, "gamma", 1.0))
    if settings.response == "linear":
        return 1.0, 1.0
    if settings.response == "rig":
        return float(rig.camera.gamma), light_gamma
    fr = frames.numpy() if isinstance(frames, wp.array) else np.asarray(frames)
    spec = scan.patterns
    return estimate_camera_gamma(fr, bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps,
                                 light_gamma=light_gamma), light_gamma


def estimate_camera_gamma(
    frames: np.ndarray,
    *,
    bits: int,
    sector_bits: int,
    steps: int,
    light_gamma: float = 1.0,
    min_contrast: float = 12.0,
    stride: int = 4,
) -> float:
    """Estimate the camera's gamma from a phase-rings view.

    For a clean fringe the linearised phase samples average to the middle of the
    linearised white and black, (1/N) sum_n v_n = 1/2 with
    v_n = ((L_n - L_b) / (L_w - L_b))^(1 / light_gamma) and L = (r / full)^g, and
    only for the right g (a wrong exponent bends the samples, and the bend does
    not average out). The estimate is the g in ``GAMMA_RANGE`` that minimises the
    mean squared departure over the pixels with contrast, unsaturated white and a
    strong fringe (every ``stride``-th row and column), by golden-section search.

    Args:
        frames: (n, H, W) uint8/uint16 frames of one view (``frame_names`` order).
        bits, sector_bits, steps: the pattern's parameters.
        light_gamma: the light's exponent (from the rig).
        min_contrast: least white - black (8-bit levels, x257 for 16-bit).
        stride: pixel subsampling.

    Raises:
        ValueError: too few usable pixels (fewer than 100).
    """
    fr = np.asarray(frames)
    if fr.ndim != 3 or fr.dtype not in (np.uint8, np.uint16):
        raise ValueError("estimate_camera_gamma: frames must be (n, H, W) uint8 or uint16")
    phase0 = 2 + 2 * bits + 2 * sector_bits
    if fr.shape[0] < phase0 + steps:
        raise ValueError(f"estimate_camera_gamma: expected {phase0 + steps} frames, got {fr.shape[0]}")
    full = 255.0 if fr.dtype == np.uint8 else 65535.0
    sub = fr[:, ::stride, ::stride].astype(np.float64) / full
    w, b, p = sub[0], sub[1], sub[phase0:phase0 + steps]
    ok = ((w - b) * full >= min_contrast * (full / 255.0)) & (w < 0.97) & (b > 0.5 / full)
    # a strong fringe: the phase samples spread over most of white - black
    ok &= (p.max(0) - p.min(0)) >= 0.5 * (w - b)
    if np.count_nonzero(ok) < 100:
        raise ValueError(f"estimate_camera_gamma: only {int(np.count_nonzero(ok))} usable pixels (need 100): "
                         "too little fringe contrast to estimate the response")
    w, b, p = w[ok], b[ok], p[:, ok]
    ig = 1.0 / float(light_gamma)

    def cost(g):
        lw, lb, lp = w ** g, b ** g, p ** g
        u = np.clip((lp - lb) / (lw - lb), 0.0, 1.0) ** ig
        return float(np.mean((u.mean(0) - 0.5) ** 2))

    lo, hi = GAMMA_RANGE
    grid = np.linspace(lo, hi, 38)
    costs = [cost(g) for g in grid]
    i = int(np.argmin(costs))
    a, c = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    r = (math.sqrt(5) - 1) / 2
    x1, x2 = c - r * (c - a), a + r * (c - a)
    f1, f2 = cost(x1), cost(x2)
    for _ in range(40):
        if f1 < f2:
            c, x2, f2 = x2, x1, f1
            x1 = c - r * (c - a)
            f1 = cost(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + r * (c - a)
            f2 = cost(x2)
    g = 0.5 * (a + c)
    log.info("estimated camera gamma %.3f from %d pixels", g, w.size)
    return float(g)


def extract_phase_rings(frames: wp.array, scan: Scan, settings, threads: int):
    """Decode + sampling stage of the ``phase-rings`` codec (see ``reconstruct.EXTRACTORS``).

    Args:
        frames: (n, H, W) uint8/uint16 Warp array of one view.
        scan: the scan (patterns, rig).
        settings: ``ReconstructSettings`` (its ``decode`` block, and its ``phase``
            block where it has one).
        threads: CPU threads.

    Returns:
        (Samples, stats) with stats ``pixels_decoded`` (pixels with a phase),
        ``samples`` (points handed on), ``phase_dropped`` (pixels per reason),
        ``camera_gamma``/``light_gamma`` used and ``times_s``.
    """
    from .reconstruct import Samples

    spec = scan.patterns
    if spec.codec != "phase-rings":
        raise ValueError(f"extract_phase_rings: the scan's codec is {spec.codec!r}, not phase-rings")
    ps = phase_settings_of(settings)
    dev = frames.device
    t0 = time.perf_counter()
    labels = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits, settings=settings.decode,
                               threads=threads)
    g_cam, g_light = view_response(frames, scan, ps)
    full = 255 if frames.dtype == wp.uint8 else 65535
    lut_np, wlut_np = response_tables(full, camera_gamma=g_cam, weighted=ps.weighted)
    lut = wp.array(lut_np, dtype=wp.float32, device=dev)
    wlut = wp.array(wlut_np, dtype=wp.float32, device=dev)
    phase = decode_phase(frames, labels, bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps, lut=lut,
                         wlut=wlut, light_gamma=g_light, settings=ps, threads=threads)
    wp.synchronize_device(dev)
    t1 = time.perf_counter()
    sm = smooth_phase(phase, labels.sector, settings=ps, threads=threads)
    pts = compact_phase_points(sm, rho0=spec.rho0, pitch=spec.pitch, threads=threads)
    wp.synchronize_device(dev)
    t2 = time.perf_counter()
    st = sm.status.numpy()
    counts = np.bincount(st.ravel(), minlength=len(PHASE_STATUS_NAMES))
    decoded = int(np.count_nonzero(phase.status.numpy() == 0))
    stats = {
        "pixels_decoded": decoded,
        "samples": len(pts),
        "phase_dropped": {name: int(counts[i]) for i, name in enumerate(PHASE_STATUS_NAMES) if i > 0},
        "camera_gamma": g_cam,
        "light_gamma": g_light,
        "times_s": {"decode": t1 - t0, "sample": t2 - t1},
    }
    return Samples(uv=pts.uv, rho=pts.rho, ring=None, sector=pts.sector, confidence=pts.confidence,
                   pixel=pts.pixel), stats


def truth_rho_at(scan: Scan, view_name: str, uv: np.ndarray, *, max_step_mm: float = 0.5) -> np.ndarray:
    """Ring radius (projector px) of the truth surface at sub-pixel camera positions.

    The truth world points of the four pixel centres around each position (from
    the virtual rig's depth map) are interpolated bilinearly and projected onto the
    pattern. NaN where a neighbour saw nothing or the four points are more than
    ``max_step_mm`` apart (a depth edge): there the truth is not smooth enough to
    judge a label. Used to count mislabelled ring samples (a sample of ring k whose
    truth radius is nearer another ring).
    """
    from .evaluate import _projector_polar, truth_points

    cam = scan.rig.camera
    w, h = cam.width, cam.height
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    X, pix = truth_points(scan, view_name)
    grid = np.full((h * w, 3), np.nan)
    grid[pix] = X
    x0 = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, h - 2)
    fx = (uv[:, 0] - x0)[:, None]
    fy = (uv[:, 1] - y0)[:, None]
    p00, p10 = grid[y0 * w + x0], grid[y0 * w + x0 + 1]
    p01, p11 = grid[(y0 + 1) * w + x0], grid[(y0 + 1) * w + x0 + 1]
    Xi = (1 - fy) * ((1 - fx) * p00 + fx * p10) + fy * ((1 - fx) * p01 + fx * p11)
    corners = np.stack([p00, p10, p01, p11], 1)
    spread = np.max(np.linalg.norm(corners - corners.mean(1, keepdims=True), axis=2), axis=1)
    ok = np.isfinite(spread) & (spread <= max_step_mm)
    rho = np.full(uv.shape[0], np.nan)
    if ok.any():
        rho[ok] = _projector_polar(scan.rig, Xi[ok], scan.patterns.center)
    return rho


# ----------------------------------------------------------------------------- NumPy twins


def _ctz(k: np.ndarray) -> np.ndarray:
    """Trailing zeros of k > 0 (vectorised); 0 where k <= 0."""
    k = np.asarray(k, np.int64)
    low = k & -k
    return np.where(k > 0, np.log2(np.maximum(low, 1)).astype(np.int64), 0)


def phase_numpy(frames: np.ndarray, dec: dict, *, bits: int, sector_bits: int, steps: int, lut: np.ndarray,
                wlut: np.ndarray, light_gamma: float = 1.0, settings: PhaseSettings = PhaseSettings()) -> dict:
    """NumPy twin of ``kernels.phase.decode_phase`` (same rules).

    ``dec`` is the band decode as ``tools.numpy_reference.decode_numpy`` returns it
    (``code``, ``weak``, ``contrast``). Returns ``t``, ``modulation``, ``status``.
    """
    s = settings
    scale = 257.0 if frames.dtype == np.uint16 else 1.0
    h, w = frames.shape[1:]
    phase0 = 2 + 2 * bits + 2 * sector_bits
    c = dec["contrast"].astype(np.float32)
    status = np.zeros((h, w), np.int32)
    t = np.zeros((h, w), np.float32)
    mod = np.zeros((h, w), np.float32)
    lw = lut[frames[0]]
    lb = lut[frames[1]]
    span = lw - lb
    dark = (c < s.min_contrast * scale) | (span <= 0)
    status[dark] = 1
    live = ~dark
    idx = np.nonzero(live)
    raw = frames[phase0:phase0 + steps][:, idx[0], idx[1]]
    val = lut[raw]
    wt = wlut[raw]
    lb_l, span_l = lb[idx], span[idx]
    normalise = light_gamma != 1.0
    if normalise:
        ig = np.float32(1.0 / light_gamma)
        u = np.clip((val - lb_l) / span_l, 1e-6, 1.0)
        val = u ** ig
        g = ig * u ** (ig - 1.0) / span_l
        wt = wt / (g * g)
    dl = 2.0 * np.pi * np.arange(steps) / steps
    cn = np.cos(dl).astype(np.float32)[:, None]
    sn = np.sin(dl).astype(np.float32)[:, None]
    s0, sc, ss = wt.sum(0), (wt * cn).sum(0), (wt * sn).sum(0)
    scc, scs, sss = (wt * cn * cn).sum(0), (wt * cn * sn).sum(0), (wt * sn * sn).sum(0)
    r0, rc, rs = (wt * val).sum(0), (wt * cn * val).sum(0), (wt * sn * val).sum(0)
    # Solve the symmetric 3x3 system by its adjugate (Cramer).
    a11, a12, a13, a22, a23, a33 = s0, sc, ss, scc, scs, sss
    c11 = a22 * a33 - a23 * a23
    c12 = a13 * a23 - a12 * a33
    c13 = a12 * a23 - a13 * a22
    c22 = a11 * a33 - a13 * a13
    c23 = a12 * a13 - a11 * a23
    c33 = a11 * a22 - a12 * a12
    det = a11 * c11 + a12 * c12 + a13 * c13
    good = det > 1e-9 * s0 * s0 * s0
    with np.errstate(divide="ignore", invalid="ignore"):
        bc = (c12 * r0 + c22 * rc + c23 * rs) / det
        bs = (c13 * r0 + c23 * rc + c33 * rs) / det
    amp = np.sqrt(bc * bc + bs * bs)
    q = 2.0 * amp if normalise else 2.0 * amp / span_l
    q = np.where(good, q, 0.0).astype(np.float32)
    f = np.arctan2(bs, bc) / (2.0 * np.pi)
    f = f - np.floor(f)
    st = np.zeros(q.shape, np.int32)
    st[~good] = 3
    st[good & (q < s.min_modulation)] = 3
    code = dec["code"][idx].astype(np.int64)
    wk = dec["weak"][idx].astype(np.int64)
    kk = code.copy()
    shift = 1
    while shift < bits:
        kk ^= kk >> shift
        shift <<= 1
    nb = 1 << bits
    has_lo = (kk >= 1) & (kk < nb)
    has_hi = (kk + 1 >= 1) & (kk + 1 < nb)
    m_lo = np.where(has_lo, 1 << _ctz(kk), 0)
    m_hi = np.where(has_hi, 1 << _ctz(kk + 1), 0)
    bad_code = (wk != 0) & (wk != m_lo) & (wk != m_hi)
    st[(st == 0) & bad_code] = 2
    d = frames[2:2 + 2 * bits:2][:, idx[0], idx[1]].astype(np.float32) - frames[3:3 + 2 * bits:2][:, idx[0], idx[1]]
    cl = c[idx]
    ar = np.arange(kk.size)
    b_lo = np.clip(bits - 1 - _ctz(kk), 0, bits - 1)
    b_hi = np.clip(bits - 1 - _ctz(kk + 1), 0, bits - 1)
    e_lo = np.where(has_lo, np.abs(d[b_lo, ar]) / cl, 2.0)
    e_hi = np.where(has_hi, np.abs(d[b_hi, ar]) / cl, 2.0)
    near = np.minimum(e_lo, e_hi) < s.edge_ratio
    edge = np.where(near, np.where(e_lo <= e_hi, kk, kk + 1), -1)
    tb = np.where(near, edge, kk + 0.5)
    # round half away from zero, as wp.round does
    x = tb - f
    tt = np.sign(x) * np.floor(np.abs(x) + 0.5) + f
    emask = np.where(edge == kk, m_lo, m_hi)
    strong = near & ((wk & emask) == 0)
    slip = strong & (((edge == kk) & (tt < edge - s.slip_tolerance)) | ((edge == kk + 1) & (tt > edge + s.slip_tolerance)))
    st[(st == 0) & slip] = 4
    status[idx] = st
    mod[idx] = np.where(good, q, 0.0)
    t[idx] = np.where(st == 0, tt, 0.0)
    return {"t": t, "modulation": mod, "status": status}


def smooth_numpy(ph: dict, sector: np.ndarray, *, settings: PhaseSettings = PhaseSettings()) -> dict:
    """NumPy twin of ``kernels.phase.smooth_phase``: ``t``, ``status``, ``sector``, ``modulation``."""
    s = settings
    t, status = ph["t"], ph["status"]
    h, w = t.shape
    r = int(s.smooth_radius)
    ok = status == 0
    P = max(r, 2)
    tp = np.pad(t, P)
    okp = np.pad(ok, P)
    acc = t.astype(np.float32).copy()
    cnt = np.ones((h, w), np.float32)
    pairs = np.zeros((h, w), np.int32)
    seen = np.zeros((h, w), np.int32)
    for dy in range(0, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx <= 0:
                continue
            sa = (slice(P + dy, P + dy + h), slice(P + dx, P + dx + w))
            sb = (slice(P - dy, P - dy + h), slice(P - dx, P - dx + w))
            oa, ob = okp[sa], okp[sb]
            seen += oa | ob
            ta, tb = tp[sa], tp[sb]
            agree = oa & ob & (np.abs(np.float32(0.5) * (ta + tb) - t) <= np.float32(s.smooth_tolerance))
            acc += np.where(agree, ta + tb, np.float32(0))
            cnt += 2 * agree
            pairs += agree
    out_status = status.copy()
    if r > 0:
        out_status[ok & (seen > 0) & (pairs < s.min_pairs)] = 5
    out_t = np.where(ok, acc / cnt, t).astype(np.float32)
    sec = sector.copy()
    fill = ok & (sector < 0)
    sp = np.pad(sector, P, constant_values=-1)
    offs = sorted(((dy * dy + dx * dx, dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)))
    todo = fill.copy()
    for _, dy, dx in offs:
        cand = sp[P + dy:P + dy + h, P + dx:P + dx + w]
        take = todo & (cand >= 0)
        sec[take] = cand[take]
        todo &= ~take
    return {"t": out_t, "status": out_status, "sector": sec, "modulation": ph["modulation"]}


def points_numpy(sm: dict, *, rho0: float, pitch: float) -> dict:
    """NumPy twin of ``kernels.phase.compact_phase_points`` (raster order)."""
    h, w = sm["t"].shape
    pix = np.flatnonzero(sm["status"].ravel() == 0).astype(np.int32)
    y, x = np.divmod(pix, w)
    return {"pixel": pix, "uv": np.stack([x, y], -1).astype(np.float32),
            "rho": (np.float32(rho0) + np.float32(pitch) * sm["t"].ravel()[pix]).astype(np.float32),
            "sector": sm["sector"].ravel()[pix].astype(np.int32),
            "confidence": np.clip(sm["modulation"].ravel()[pix], 0.0, 1.0).astype(np.float32)}


# ----------------------------------------------------------------------------- bench


def _best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


DEFAULT_BENCH_PATTERNS = {"codec": "phase-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                          "rho0": 8.0, "pitch": 8.0, "bits": 6, "sector_bits": 6, "steps": 4}


def bench_dense(*, scan_dir: str | os.PathLike | None = None, scene: str | None = None, repeats: int = 3,
                devices=None, out=print) -> dict:
    """Time the dense stages of one phase-rings view against their NumPy twins.

    Stages: ``decode`` (band + sector Gray codes), ``phase`` (linearise, weighted
    phase, unwrap), ``smooth`` (smoothing, sector fill, compaction into points),
    ``triangulate``. The NumPy side runs ``tools.numpy_reference`` decode and
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
    from ringscan.kernels import init_warp
    from ringscan.kernels.triangulation import TriangulateSettings, triangulate_rings
    from ringscan.tools.numpy_reference import decode_numpy, triangulate_numpy

    from .reconstruct import camera_model_for, light_model_for
    from .scan import load_scan, read_view_frames
    from .simulate import simulate_scan

    init_warp()
    tmp = None
    if scan_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="ringscan-dense-bench-")
        if scene is None:
            shared = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "models" / "odedstein_spot.obj"
            scene = str(shared) if shared.is_file() else "sphere"
        out(f"simulating a phase-rings view of {Path(scene).stem} (default rig, pitch 8, 4 steps, 6 sector bits) ...")
        scan = simulate_scan(Path(tmp.name) / "scan", scene=scene, patterns=parse_patterns(DEFAULT_BENCH_PATTERNS),
                             progress=False)
    else:
        scan = load_scan(scan_dir)
    try:
        spec: PatternSpec = scan.patterns
        if spec.codec != "phase-rings":
            raise ValueError(f"bench_dense: the scan's codec is {spec.codec!r}; the dense stages need phase-rings")
        frames = read_view_frames(scan, scan.views[0])
        nf, h, w = frames.shape
        rig = scan.rig
        ps = PhaseSettings()
        full = 255 if frames.dtype == np.uint8 else 65535
        lut, wlut = response_tables(full, camera_gamma=rig.camera.gamma, weighted=ps.weighted)
        g_light = float(getattr(rig.light, "gamma", 1.0))
        vol = (rig.volume.z_min, rig.volume.z_max, rig.volume.r_max)
        kw = dict(bits=spec.bits, sector_bits=spec.sector_bits)

        ref, state = {}, {}

        def np_decode():
            state["dec"] = decode_numpy(frames, **kw)

        def np_phase():
            state["ph"] = phase_numpy(frames, state["dec"], steps=spec.steps, lut=lut, wlut=wlut,
                                      light_gamma=g_light, settings=ps, **kw)

        def np_smooth():
            sm = smooth_numpy(state["ph"], state["dec"]["sector"], settings=ps)
            state["pts"] = points_numpy(sm, rho0=spec.rho0, pitch=spec.pitch)

        def np_tri():
            p = state["pts"]
            state["tri"] = triangulate_numpy(p["uv"], p["rho"], p["sector"], rig, center=spec.center,
                                             sector_bits=spec.sector_bits)

        for name, fn in (("decode", np_decode), ("phase", np_phase), ("smooth", np_smooth), ("triangulate", np_tri)):
            fn()
            ref[name] = _best(fn, repeats)
        ref["total"] = sum(ref.values())
        n_np = int(np.count_nonzero(state["tri"][1] == 0))

        if devices is None:
            devices = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
        cpus = os.cpu_count() or 1
        runs = []
        for dev in devices:
            for threads in ([cpus, 1] if dev == "cpu" and cpus > 1 else [cpus]):
                fr = wp.array(frames, device=dev)
                lut_w = wp.array(lut, dtype=wp.float32, device=dev)
                wlut_w = wp.array(wlut, dtype=wp.float32, device=dev)
                cam, light = camera_model_for(rig), light_model_for(rig)
                ws = {}

                def wdec():
                    ws["lab"] = decode_gray_rings(fr, threads=threads, **kw)
                    wp.synchronize_device(dev)

                def wphase():
                    ws["ph"] = decode_phase(fr, ws["lab"], steps=spec.steps, lut=lut_w, wlut=wlut_w,
                                            light_gamma=g_light, settings=ps, threads=threads, **kw)
                    wp.synchronize_device(dev)

                def wsmooth():
                    sm = smooth_phase(ws["ph"], ws["lab"].sector, settings=ps, threads=threads)
                    ws["pts"] = compact_phase_points(sm, rho0=spec.rho0, pitch=spec.pitch, threads=threads)
                    wp.synchronize_device(dev)

                def wtri():
                    p = ws["pts"]
                    ws["tri"] = triangulate_rings(p.uv, p.rho, p.sector, p.confidence, camera=cam, light=light,
                                                  volume=vol, center=spec.center, sector_bits=spec.sector_bits,
                                                  settings=TriangulateSettings(), threads=threads)
                    wp.synchronize_device(dev)

                stages = (("decode", wdec), ("phase", wphase), ("smooth", wsmooth), ("triangulate", wtri))
                for _, fn in stages:  # warm up: compile or load the kernels
                    fn()
                tm = {name: _best(fn, repeats) for name, fn in stages}
                tm["total"] = sum(tm.values())
                n_pts = int(np.count_nonzero(ws["tri"].status.numpy() == 0))
                runs.append({"device": dev, "threads": threads, "times": tm, "points": n_pts})

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
        return {"numpy": ref, "numpy_points": n_np, "warp": runs,
                "ratio_total": {f"{r['device']}x{r['threads']}": ref["total"] / r["times"]["total"] for r in runs}}
    finally:
        if tmp is not None:
            tmp.cleanup()
