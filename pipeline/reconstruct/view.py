"""One view: frames -> codec samples -> triangulation -> filtered points (a
:class:`ViewCloud`), and its PLY.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from ringscan.kernels import init_warp, resolve_device
from ringscan.kernels.launch import cpu_threads
from ringscan.kernels.point_filter import mark_isolated_points
from ringscan.kernels.triangulation import STATUS_ISOLATED, STATUS_NAMES, compact_points, triangulate_rings
from ringscan.pipeline.codecs.registry import extract_samples
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.ply import write_ply
from ringscan.pipeline.formats.scan import Scan, View, read_view_frames
from ringscan.pipeline.geometry import camera_model_for, light_model_for
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

log = logging.getLogger(__name__)

__all__ = ["ViewCloud", "reconstruct_view", "write_view_ply", "explain_no_points"]


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
    threads = settings.threads or cpu_threads()
    times = {}
    t = time.perf_counter()
    if frames is None:
        frames = read_view_frames(scan, view, threads=threads)
    times["read"] = time.perf_counter() - t
    t = time.perf_counter()
    # On the CPU the Warp array is a view of the frames (kernels only read them): no copy.
    on_cpu = wp.get_device(device).is_cpu and frames.flags.c_contiguous
    fr = wp.array(frames, dtype=wp.uint8 if frames.dtype == np.uint8 else wp.uint16, device=device, copy=not on_cpu)
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
    low_confidence = 0
    if settings.min_confidence > 0:
        keep = cloud.confidence >= settings.min_confidence
        low_confidence = int(keep.size - np.count_nonzero(keep))
        cloud = ViewCloud(cloud.points[keep], cloud.ring[keep], cloud.rho[keep], cloud.confidence[keep], cloud.uv[keep], {})
    times["download"] = time.perf_counter() - t
    cloud.stats = {
        "pixels": int(frames.shape[1] * frames.shape[2]),
        **st,
        "points": int(cloud.points.shape[0]),
        # every sample not written, by reason: the kernels' statuses, then min_confidence
        "dropped": {**{name: int(counts[i]) for i, name in enumerate(STATUS_NAMES) if i > 0},
                    "low_confidence": low_confidence},
        "times_s": times,
    }
    if cloud.stats["points"] == 0:
        cloud.stats["no_points"] = explain_no_points(frames, scan, cloud.stats, settings)
    return cloud


def explain_no_points(frames: np.ndarray, scan: Scan, stats: dict,
                      settings: ReconstructSettings = ReconstructSettings()) -> str:
    """Why a view gave no point, in one sentence for the user.

    Args:
        frames: the view's (n, H, W) frames in the codec's frame order.
        scan: the scan.
        stats: the view's counts (``pixels_decoded``, ``samples``, ``dropped``, ...).
        settings: the settings the view was reconstructed with.
    """
    frames = np.asarray(frames)
    names = frame_names(scan.patterns)
    full = 65535.0 if frames.dtype == np.uint16 else 255.0
    scale = full / 255.0

    def lighting(lo_mean: float, hi_mean: float) -> str:
        if hi_mean < 0.05 * full:
            return "everything is dark: the projector's light did not reach the camera (projector off, lens cap, " \
                   "exposure too short)"
        if lo_mean > 0.95 * full:
            return "everything is saturated: the exposure is too long or the ambient light too strong"
        return "the projector's light does not change the image (projector off or aimed elsewhere, or the " \
               "frames are all alike)"

    if "white" in names and "black" in names:
        white = frames[names.index("white")].astype(np.float32)
        black = frames[names.index("black")].astype(np.float32)
        thr = settings.decode.min_contrast * scale
        lit = int(np.count_nonzero(white - black >= thr))
        if lit == 0:
            return (f"no ring found: no contrast between the white and black frames (white - black is below "
                    f"{thr:g} grey levels at every pixel; white {white.mean():.0f}, black {black.mean():.0f} on "
                    f"average): {lighting(float(black.mean()), float(white.mean()))}")
        if stats.get("pixels_decoded", 0) == 0:
            return (f"no ring found: {lit} pixels have contrast, but none decodes to a ring band (every bit too "
                    f"weak: check the frame order and the exposure)")
    elif "rings" in names:
        f = frames[names.index("rings")].astype(np.float32)
        lo, hi = (float(x) for x in np.percentile(f, [1.0, 99.0]))
        if hi - lo < settings.single_shot.lines.min_contrast * scale:
            return (f"no ring found: the rings frame has no contrast (grey levels {lo:.0f} to {hi:.0f} between the "
                    f"1st and 99th percentile): {lighting(lo, hi)}")
        if stats.get("samples", 0) == 0:
            return (f"no ring found: {stats.get('line_samples', 0)} line centres in {stats.get('pieces', 0)} "
                    f"pieces, none labelled with a ring (see the labelling counts in the report)")
    if stats.get("samples", 0) == 0:
        return f"no ring found: {stats.get('pixels_decoded', 0)} pixels decoded, but no ring edge was sampled"
    dropped = ", ".join(f"{k} {v}" for k, v in stats.get("dropped", {}).items() if v)
    return (f"every one of the {stats['samples']} ring samples was dropped ({dropped or 'below min_confidence'}): "
            f"check the rig's calibration and working volume")


def write_view_ply(path: Path, cloud: ViewCloud, view_index: int) -> None:
    n = cloud.points.shape[0]
    write_ply(path, {
        "x": cloud.points[:, 0].astype(np.float32), "y": cloud.points[:, 1].astype(np.float32),
        "z": cloud.points[:, 2].astype(np.float32),
        "ring": cloud.ring.astype(np.int32), "rho": cloud.rho.astype(np.float32),
        "view": np.full(n, view_index, np.int32), "confidence": cloud.confidence.astype(np.float32),
        "u": cloud.uv[:, 0].astype(np.float32), "v": cloud.uv[:, 1].astype(np.float32),
    }, comments=["ringscan point cloud, world frame, mm"])
