"""From a scan folder to one point cloud per view (``ringscan reconstruct``).

Per view: read the frames, upload them to the device, decode (per pixel), sample
the rings to sub-pixel precision, triangulate every sample against its ring's
quadric (DESIGN §3, §4), keep the valid points in sample order and write

- ``<out>/<view>.ply``: binary PLY in the world frame (mm): x, y, z, ring (band
  boundary or ring index), rho (projector px), view, confidence, u, v (camera px);
- ``<out>/report.json``: counts (pixels decoded, samples, points, roots dropped by
  reason), seconds per stage, the rig, the patterns and the resolved settings;
- ``<out>/settings.json``: the resolved settings.

The report is rewritten (atomically) after every view, so ``resume=True`` skips
views that are already done after an interrupted run.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from ringscan.kernels import init_warp, resolve_device
from ringscan.kernels.geometry import make_camera, make_parallel_light, make_perspective_light
from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.ring_sampling import ring_radii, sample_gray_rings
from ringscan.kernels.point_filter import mark_isolated_points
from ringscan.kernels.triangulation import STATUS_ISOLATED, STATUS_NAMES, compact_points, triangulate_rings

from .errors import FormatError
from .io import atomic_write_json, read_json, write_ply
from .rig import ParallelLight, Rig, rig_to_dict
from .scan import Scan, View, load_scan, read_view_frames
from .settings import ReconstructSettings, settings_to_dict

log = logging.getLogger(__name__)

REPORT_FORMAT = "ringscan.report/1"

__all__ = ["REPORT_FORMAT", "ViewCloud", "LiveReconstructor", "reconstruct_scan", "reconstruct_view", "light_model_for",
           "camera_model_for", "extract_samples", "EXTRACTORS", "Samples"]


@dataclass
class ViewCloud:
    """The points of one view (NumPy, world frame)."""

    points: np.ndarray
    """(n, 3) float32 world points (mm)."""
    ring: np.ndarray
    """(n,) int32 ring / band-boundary index (-1 for dense codecs)."""
    rho: np.ndarray
    """(n,) float32 ring radius in projector pixels."""
    confidence: np.ndarray
    """(n,) float32 in [0, 1]."""
    uv: np.ndarray
    """(n, 2) float32 camera pixel of each point."""
    stats: dict
    """Counts and seconds per stage."""


def camera_model_for(rig: Rig):
    c = rig.camera
    return make_camera(c.K, c.dist, c.R, c.t)


def light_model_for(rig: Rig):
    li = rig.light
    if isinstance(li, ParallelLight):
        return make_parallel_light(li.R, li.t, li.pixel_pitch_mm, li.axis_px)
    return make_perspective_light(li.K, li.dist, li.R, li.t)


def _extract_gray_rings(frames: wp.array, scan: Scan, settings: ReconstructSettings, threads: int):
    spec = scan.patterns
    t0 = time.perf_counter()
    labels = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits, settings=settings.decode,
                               threads=threads)
    wp.synchronize_device(frames.device)
    t1 = time.perf_counter()
    samples = sample_gray_rings(frames, labels, bits=spec.bits, settings=settings.sample, threads=threads)
    rho = ring_radii(samples.ring, rho0=spec.rho0, pitch=spec.pitch)
    wp.synchronize_device(frames.device)
    t2 = time.perf_counter()
    band = labels.band.numpy()
    stats = {"pixels_decoded": int(np.count_nonzero(band >= 0)), "samples": len(samples),
             "times_s": {"decode": t1 - t0, "sample": t2 - t1}}
    return Samples(uv=samples.uv, rho=rho, ring=samples.ring, sector=samples.sector, confidence=samples.confidence,
                   pixel=samples.pixel), stats


@dataclass
class Samples:
    """What a codec's decode + sampling stages hand to triangulation (Warp arrays, length n)."""

    uv: wp.array
    """vec2 camera pixel coordinates."""
    rho: wp.array
    """float32 ring radius (projector px)."""
    ring: wp.array | None
    """int32 ring / band-boundary index, or None for dense codecs."""
    sector: wp.array
    """int32 decoded sector (-1 unknown)."""
    confidence: wp.array
    """float32 sample confidence."""
    pixel: wp.array
    """int32 linear camera pixel index of each sample."""


# codec -> function(frames, scan, settings, threads) -> (Samples, stats), or the
# "module:function" name of one (imported when first used).
EXTRACTORS = {
    "gray-rings": _extract_gray_rings,
    "phase-rings": "ringscan.pipeline.dense:extract_phase_rings",
    "rings": "ringscan.pipeline.single_shot:extract_rings",
}


def extract_samples(frames: wp.array, scan: Scan, settings: ReconstructSettings, threads: int):
    """Run the codec's decode and sampling stages on a view's frames."""
    fn = EXTRACTORS.get(scan.patterns.codec)
    if isinstance(fn, str):
        import importlib

        mod, name = fn.split(":")
        try:
            fn = EXTRACTORS[scan.patterns.codec] = getattr(importlib.import_module(mod), name)
        except (ImportError, AttributeError):
            fn = None
    if fn is None:
        raise FormatError(scan.path, f"patterns.codec: no reconstruction for codec {scan.patterns.codec!r} in this build")
    return fn(frames, scan, settings, threads)


def reconstruct_view(
    scan: Scan,
    view: View,
    *,
    settings: ReconstructSettings = ReconstructSettings(),
    device: str | None = None,
    frames: np.ndarray | None = None,
) -> ViewCloud:
    """Reconstruct one view of a scan into world points.

    Args:
        scan: a loaded scan.
        view: one of ``scan.views``.
        settings: stage settings.
        device: Warp device ("cpu", "cuda:0", None = best available).
        frames: the view's frames if already in memory ((n, H, W) in
            ``frame_names`` order); read from disk otherwise.
    """
    init_warp()
    device = resolve_device(device)
    threads = settings.threads or os.cpu_count() or 1
    times = {}
    t = time.perf_counter()
    if frames is None:
        frames = read_view_frames(scan, view)
    times["read"] = time.perf_counter() - t
    t = time.perf_counter()
    fr = wp.array(frames, dtype=wp.uint8 if frames.dtype == np.uint8 else wp.uint16, device=device)
    times["upload"] = time.perf_counter() - t

    smp, st = extract_samples(fr, scan, settings, threads)
    times.update(st.pop("times_s"))
    # An extractor may decide sectors of its own (single-shot: line orientation
    # sectors); it says how many bits they carry.
    sector_bits = int(st.pop("sector_bits", scan.patterns.sector_bits))

    t = time.perf_counter()
    rig = scan.rig
    vol = rig.volume
    cam = camera_model_for(rig)
    tri = triangulate_rings(smp.uv, smp.rho, smp.sector, smp.confidence, camera=cam, light=light_model_for(rig),
                            volume=(vol.z_min, vol.z_max, vol.r_max), center=scan.patterns.center,
                            sector_bits=sector_bits, settings=settings.triangulate, threads=threads)
    wp.synchronize_device(device)
    times["triangulate"] = time.perf_counter() - t
    t = time.perf_counter()
    status_w = mark_isolated_points(tri.points, smp.pixel, tri.status, camera=cam, width=rig.camera.width,
                                    height=rig.camera.height, isolated_status=STATUS_ISOLATED, settings=settings.filter,
                                    threads=threads)
    idx = compact_points(status_w)
    wp.synchronize_device(device)
    times["filter"] = time.perf_counter() - t

    t = time.perf_counter()
    idx_np = idx.numpy()
    status = status_w.numpy()
    counts = np.bincount(status, minlength=len(STATUS_NAMES)) if status.size else np.zeros(len(STATUS_NAMES), int)
    cloud = ViewCloud(
        points=tri.points.numpy()[idx_np],
        ring=smp.ring.numpy()[idx_np] if smp.ring is not None else np.full(idx_np.size, -1, np.int32),
        rho=smp.rho.numpy()[idx_np],
        confidence=tri.confidence.numpy()[idx_np],
        uv=smp.uv.numpy()[idx_np],
        stats={},
    )
    if settings.min_confidence > 0:
        keep = cloud.confidence >= settings.min_confidence
        cloud = ViewCloud(cloud.points[keep], cloud.ring[keep], cloud.rho[keep], cloud.confidence[keep], cloud.uv[keep], {})
    times["download"] = time.perf_counter() - t
    cloud.stats = {
        "pixels": int(frames.shape[1] * frames.shape[2]),
        **st,
        "points": int(cloud.points.shape[0]),
        "dropped": {name: int(counts[i]) for i, name in enumerate(STATUS_NAMES) if i > 0},
        "times_s": times,
    }
    return cloud


def write_view_ply(path: Path, cloud: ViewCloud, view_index: int) -> None:
    n = cloud.points.shape[0]
    write_ply(path, {
        "x": cloud.points[:, 0].astype(np.float32), "y": cloud.points[:, 1].astype(np.float32),
        "z": cloud.points[:, 2].astype(np.float32),
        "ring": cloud.ring.astype(np.int32), "rho": cloud.rho.astype(np.float32),
        "view": np.full(n, view_index, np.int32), "confidence": cloud.confidence.astype(np.float32),
        "u": cloud.uv[:, 0].astype(np.float32), "v": cloud.uv[:, 1].astype(np.float32),
    }, comments=["ringscan point cloud, world frame, mm"])


def reconstruct_scan(
    scan: Scan | str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    settings: ReconstructSettings = ReconstructSettings(),
    device: str | None = None,
    views: list[str] | None = None,
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """Reconstruct every view of a scan; write PLYs, report.json and settings.json.

    Args:
        scan: a loaded :class:`Scan` or its folder.
        out_dir: output folder (created).
        settings: stage settings.
        device: Warp device (None: CUDA when present, else CPU).
        views: names of the views to do (default: all).
        resume: keep views already finished in an earlier run of the same output.
        progress: show a progress bar.

    Returns:
        The report (also written to ``out_dir/report.json``).
    """
    if not isinstance(scan, Scan):
        scan = load_scan(scan)
    device = resolve_device(device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    chosen = list(scan.views) if views is None else [v for v in scan.views if v.name in set(views)]
    if views is not None and len(chosen) != len(set(views)):
        unknown = sorted(set(views) - {v.name for v in scan.views})
        raise ValueError(f"unknown view(s) {', '.join(unknown)} in {scan.path}")
    report_path = out / "report.json"
    done = {}
    if resume and report_path.is_file():
        try:
            old = read_json(report_path)
            if old.get("format") == REPORT_FORMAT and Path(old.get("scan", "")) == scan.folder.resolve():
                done = {v["name"]: v for v in old.get("views", []) if (out / v.get("ply", "")).is_file()}
        except FormatError as e:
            log.warning("cannot resume from %s (%s): starting again", report_path, e)
    report = {
        "format": REPORT_FORMAT,
        "scan": str(scan.folder.resolve()),
        "codec": scan.patterns.codec,
        "device": device,
        "patterns": scan.patterns.to_dict(),
        "rig": rig_to_dict(scan.rig),
        "settings": settings_to_dict(settings),
        "views": [],
    }
    atomic_write_json(out / "settings.json", report["settings"])
    t_all = time.perf_counter()
    from tqdm import tqdm

    todo = [v for v in chosen if v.name not in done]
    # Read the next view's frames while this one is reconstructed (image decoding
    # and Warp launches both release the GIL).
    from concurrent.futures import ThreadPoolExecutor

    reader = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ringscan-read")
    pending = {}

    def prefetch(k):
        if k < len(todo) and todo[k].name not in pending:
            pending[todo[k].name] = reader.submit(_timed_read, scan, todo[k])

    bar = tqdm(chosen, desc=f"reconstruct {scan.folder.name}", unit="view", disable=not progress, leave=False)
    try:
        for view in bar:
            index = scan.views.index(view)
            if view.name in done:
                report["views"].append(done[view.name])
                continue
            k = todo.index(view)
            prefetch(k)
            frames, read_s = pending.pop(view.name).result()
            prefetch(k + 1)
            _reconstruct_one(scan, view, index, frames, read_s, out, report, report_path, settings, device)
    finally:
        for f in pending.values():
            f.cancel()
        reader.shutdown(wait=True)
    report["totals"] = _totals(report["views"])
    report["time_s"] = time.perf_counter() - t_all
    atomic_write_json(report_path, report)
    return report


def _timed_read(scan: Scan, view: View) -> tuple[np.ndarray, float]:
    t = time.perf_counter()
    frames = read_view_frames(scan, view)
    return frames, time.perf_counter() - t


def _reconstruct_one(scan, view, index, frames, read_s, out, report, report_path, settings, device) -> None:
    """Reconstruct one view from its frames; write its PLY and the updated report."""
    cloud = reconstruct_view(scan, view, settings=settings, device=device, frames=frames)
    cloud.stats["times_s"]["read"] = read_s  # read ahead, while the previous view was reconstructed
    ply = f"{view.name}.ply"
    write_view_ply(out / ply, cloud, index)
    entry = {"name": view.name, "index": index, "turntable_deg": view.turntable_deg, "ply": ply,
             "camera_center": scan.rig.camera.center.tolist(), **cloud.stats}
    report["views"].append(entry)
    log.info("%s: %d samples -> %d points (%s)", view.name, cloud.stats.get("samples", 0), cloud.stats["points"],
             ", ".join(f"{k} {v}" for k, v in cloud.stats["dropped"].items()))
    atomic_write_json(report_path, report)


def _totals(views: list[dict]) -> dict:
    tot: dict = {"points": 0, "samples": 0, "pixels_decoded": 0, "dropped": {}}
    for v in views:
        for k in ("points", "samples", "pixels_decoded"):
            tot[k] += int(v.get(k, 0))
        for k, n in v.get("dropped", {}).items():
            tot["dropped"][k] = tot["dropped"].get(k, 0) + int(n)
    return tot


class LiveReconstructor:
    """Reconstruct each view of a scan while the next one is being captured.

    Pass the instance as ``on_view`` to :func:`ringscan.hardware.capture.capture_scan`:
    each finished view is queued to one background thread, which brings
    ``out_dir`` up to date with :func:`reconstruct_scan` (``resume=True``, so views
    already there are kept and each view is reconstructed once). Warp launches and
    image decoding release the GIL, so the capture goes on meanwhile. A failed
    reconstruction is logged and kept; the capture is never stopped by it.

    Call :meth:`finish` with the final scan when the capture ends (also after it
    stopped on a fault): it waits for the queue, brings the folder up to date with
    every complete view, and returns the report (None when a reconstruction failed;
    :attr:`error` says why).
    """

    def __init__(self, out_dir: str | os.PathLike, *, settings: ReconstructSettings = ReconstructSettings(),
                 device: str | None = None):
        from concurrent.futures import ThreadPoolExecutor

        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise ValueError(f"{self.out_dir}: exists and is not a folder (the reconstruction's output folder)")
        self.settings = settings
        self.device = resolve_device(device)
        self.error: str | None = None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ringscan-live")
        self._futures: list = []

    def _update(self, scan: Scan, names: list[str]) -> dict | None:
        if self.error is not None:
            return None
        try:
            report = reconstruct_scan(scan, self.out_dir, settings=self.settings, device=self.device, views=names,
                                      resume=True, progress=False)
        except Exception as e:  # noqa: BLE001 - the capture must go on; reported by finish()
            self.error = f"reconstructing {names[-1]} of {scan.folder} into {self.out_dir} failed: {e}"
            log.error("%s", self.error)
            return None
        log.info("live reconstruction: %s done (%d points)", names[-1], report["views"][-1]["points"])
        return report

    def __call__(self, scan: Scan, view: View) -> None:
        """Queue ``view`` (and any complete view before it) of ``scan``."""
        names = [v.name for v in scan.views[: scan.views.index(view) + 1]]
        self._futures.append(self._pool.submit(self._update, scan, names))

    def finish(self, scan: Scan | None = None) -> dict | None:
        """Wait for the queued views; then, given the scan, reconstruct its complete views not yet done."""
        for f in self._futures:
            f.result()
        self._futures.clear()
        report = None
        if scan is not None:
            from .patterns import frame_names

            need = set(frame_names(scan.patterns))
            names = [v.name for v in scan.views if need.issubset(v.frames)]
            if names:
                report = self._pool.submit(self._update, scan, names).result()
        self._pool.shutdown(wait=True)
        return report
