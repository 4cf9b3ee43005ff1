"""One view: frames -> codec samples -> triangulation -> filtered points (a
:class:`ViewCloud`), and its PLY.
"""

from __future__ import annotations

import importlib
import logging
import time
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np
import warp as wp

from ringscan.kernels import init_warp, resolve_device
from ringscan.kernels.calibration_floor import calibration_floor, residual_floor
from ringscan.kernels.compact import count_values, finite_flags, finite_indices, gather, median, set_at
from ringscan.kernels.error_terms import widen_for_slope, widen_sigmas
from ringscan.kernels.launch import cpu_threads
from ringscan.kernels.point_filter import mark_isolated_points
from ringscan.kernels.triangulation import (
    STATUS_GRAZING,
    STATUS_ISOLATED,
    STATUS_NAMES,
    STATUS_OK,
    STATUS_UNMATCHED,
    camera_side_sigmas,
    compact_points,
    triangulate_rings,
)
from ringscan.pipeline.codecs import NO_ANGLE_CODE
from ringscan.pipeline.codecs.registry import codec_for
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.ply import write_ply
from ringscan.pipeline.formats.rig import has_calibrated_light
from ringscan.pipeline.formats.scan import Scan, View, as_camera2, read_view_frames
from ringscan.pipeline.geometry import camera_model_for, light_model_for
from ringscan.pipeline.reconstruct.error_scale import (
    MAX_CHECK_SAMPLES,
    MIN_PAIRS,
    fit_error_model,
    group_scale,
    region_scale,
    sample_subset,
)
from ringscan.pipeline.reconstruct.neighbour_checks import (
    fit_neighbour_model,
    reach_scale,
    widen_depth_sigma,
    widen_for_indirect,
    widen_for_shading,
)
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

log = logging.getLogger(__name__)

__all__ = ["ViewCloud", "reconstruct_view", "write_view_ply", "explain_no_points", "view_rays", "check_rays"]

CALIBRATION_WARN_PX = 1.0
"""Median projector-pixel residual above which a view warns that the rig does not fit its images."""
FLOOR_CHI2 = 9 * 0.455
"""The floor is applied where the median chi-square of the residuals is above this
(residuals three times the decode's predicted errors): below it the miss is the
decode model's own (a virtual rig shows about 1.3), above it the rig's (a real
calibration shows 80-130)."""
PROJECTOR_FLOOR_CHI2 = 2 * 0.455
"""Two cameras and the projector: the projector's floor is applied where the median chi-square of its
misses from the cameras' points is above this (its sigmas already carry the codes' fitted errors)."""
FLOOR_OUTLIER = 5.0
"""With a calibration floor c, a point is inconsistent only beyond this many c (and ``max_residual_px``)."""
LOW_MODULATION_WARN = 0.05
"""Share of a view's lit pixels whose finest code barely modulates (the codec's
``low_modulation``) above which the view warns. gray-rings on ringscan's renderer:
Spot 0-0.6 % (sharp, defocused 1.5 px, noise 4), a far dark plane 1.4 %, a far faint
one (the finest bit at ~7 % of white) 10.6 %; phase-rings at pitch 4 under a 1.5 px
defocus: ~all."""
INDIRECT_PRIOR_PX = 0.67
"""Without an angle: projector px a band edge moves per unit of measured indirect-light share
(``Samples.indirect`` above the view's median), which its neighbours cannot see (the shift is smooth
along the ring). The value the angle's pairs fit on Mitsuba's V-groove with inter-reflection
(docs/accuracy.md); on ringscan's renderer the fits read 0.14-0.54 px on Spot and the corner."""
SHADING_PRIOR_PX = 0.85
"""Without an angle: projector px a band edge moves per unit of the light's gradient across the image
(``Samples.shading``, its relative gradient per camera px: the camera's blur weighs the edge by the
light around it), which its neighbours see only where the gradient changes along the ring. The median
of the values the angle's pairs fit on Mitsuba's renders (0.31-1.43 px, eleven views: docs/accuracy.md,
"Then: the light's gradient"); on ringscan's own renderer, which blurs the pattern but not the light,
0.12-0.19 px on Spot."""
SHARED_POSITION_PX = 0.04
"""Camera px that a ring edge's measured place errs by in common to both projector coordinates (the
ray itself moved; a dense code's samples sit at pixel centres and take no such term): along a
surface the view grazes it moves the point by that times the depth gradient across the image, and
the two coordinates' disagreement, which fits every other term, cancels it. Neither the pairs nor a
ring's neighbours can measure it: the value both renderers show on a sphere's limb
(ringscan's 0.030-0.042 px, Mitsuba's 0.039-0.045 px: docs/accuracy.md)."""



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
    sigma: np.ndarray
    """(n,) float32 predicted standard deviation of the point along its camera ray (mm)."""
    stats: dict
    """Counts and seconds per stage."""
    residual: np.ndarray | None = None
    """(n,) float32 each point's residual in px: two cameras, the RMS reprojection
    error of its rays; camera-projector with the angle, the projector-side residual
    across the epipolar line (``kernels.triangulation.Triangulation.residual``).
    NaN where the point has none (placed by the rings alone: ``sector_residual``).
    None: not recorded."""
    sector_residual: np.ndarray | None = None
    """(n,) float32 for a point placed by the rings alone, how far its root lies
    outside its decoded sector, in sector widths (0 inside); NaN for the others and
    where the scan has no sectors. None: not recorded."""


@dataclass
class _ViewRun:
    """What every stage of one view's reconstruction reads: the scan, the view, its
    settings, where it runs, its frames and samples, and the stage times it adds to."""

    scan: Scan
    view: View
    settings: ReconstructSettings
    device: object
    threads: int
    frames: np.ndarray
    """(F, H, W) the view's frames, host."""
    samples: object
    """The codec's :class:`~ringscan.kernels.samples.Samples` of camera 1."""
    codec_stats: dict
    times: dict
    """Stage -> seconds, added to as stages run."""


@dataclass
class _Placed:
    """Each sample's placed point and what :func:`_finish` keeps of it (Warp arrays, (n,))."""

    points: object
    """vec3 world points."""
    status: object
    """int32 status (0: placed)."""
    confidence: object
    sigma: object
    """float32 predicted standard deviation along the camera ray (mm)."""
    residual: object
    """float32 residual (px where ``residual_px``, else sector widths; < 0 none)."""
    residual_px: wp.array
    """(n,) int32 1 where the residual is in px (on the device)."""
    extra: dict
    """Report entries of the placement (calibration, checks)."""


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
    frames_w = wp.array(frames, dtype=wp.uint8 if frames.dtype == np.uint8 else wp.uint16, device=device,
                        copy=not on_cpu)
    times["upload"] = time.perf_counter() - t

    codec = codec_for(scan.patterns.codec, source=scan.path)
    samples, codec_stats = codec.extract(frames_w, scan, codec.settings_from(settings), threads=threads)
    times.update(codec_stats.pop("times_s"))
    _warn_low_modulation(view, codec_stats)
    _warn_fine_angle(view, codec_stats, scan.patterns)
    # A codec may decide sectors of its own (the rings codec: line orientation
    # sectors); it says how many bits they carry.
    sector_bits = int(codec_stats.pop("sector_bits", scan.patterns.sector_bits))

    run = _ViewRun(scan=scan, view=view, settings=settings, device=device, threads=threads, frames=frames,
                   samples=samples, codec_stats=codec_stats, times=times)
    t = time.perf_counter()
    rays = view_rays(scan, view, settings)
    if rays in ("camera-camera", "all"):
        return _finish(run, _stereo_points(run, sector_bits), rays=rays)
    if samples.sigma_uv is not None and samples.sigma_rho is None:
        samples = run.samples = _camera_side(scan, samples, settings, sector_bits, threads)
    triangulated, calibration = _camera_projector(scan, view, settings, samples, sector_bits, threads)
    neighbours = {}
    if samples.phi is None:  # no angle to measure the ring's errors against: its neighbours do
        base = triangulated.sigma
        triangulated, neighbours = _neighbour_sigmas(scan, samples, triangulated, settings)
        if samples.bias_uv is not None and samples.sigma_uv is not None:
            triangulated = _with_line_bias(samples, triangulated, base)
    wp.synchronize_device(device)
    times["triangulate"] = time.perf_counter() - t
    check = {}
    if calibration:
        check = {"kind": "ray-ray", "samples": calibration["samples"], "median_px": calibration["residual_px_median"],
                 "p95_px": calibration["residual_px_p95"],
                 "fits": bool(calibration["residual_px_median"] <= CALIBRATION_WARN_PX)}
    return _finish(run, _Placed(points=triangulated.points, status=triangulated.status,
                                confidence=triangulated.confidence, sigma=triangulated.sigma,
                                residual=triangulated.residual, residual_px=_angle_used(samples, settings),
                                extra={**({"calibration": calibration} if calibration else {}),
                                       **({"error_model": neighbours} if neighbours else {}),
                                       **({"calibration_check": check} if check else {})}), rays=rays)


def _camera_projector(scan: Scan, view: View, settings: ReconstructSettings, samples, sector_bits: int,
                      threads: int):
    """Camera 1's samples triangulated against the calibrated projector, with the calibration
    floor where the rig misses by more than the decode's own errors: (Triangulation, the
    calibration dict of :func:`calibration_floor` with ``floor_px`` and ``floor_applied``, or {}).
    The one-camera path and the two-camera fallback (``auto``) both place points this way."""
    rig = scan.rig
    vol = rig.volume
    triangulate = partial(triangulate_rings, samples.uv, samples.rho, samples.sector, samples.confidence,
                          camera=camera_model_for(rig), light=light_model_for(rig),
                          volume=(vol.z_min, vol.z_max, vol.r_max), center=scan.patterns.center,
                          sector_bits=sector_bits, phi=samples.phi, threads=threads)
    sigma_rho, sigma_tan, fit = _honest_sigmas(scan, samples, settings, sector_bits, threads)
    if fit:
        # The view's own frames measured what the decode's model misses; the
        # calibration's share of it is the floor across the epipolar line.
        floor = fit["floor_px"]
        ts = replace(settings.triangulate,
                     max_residual_px=max(settings.triangulate.max_residual_px, FLOOR_OUTLIER * floor))
        triangulated = triangulate(sigma_rho=sigma_rho, sigma_tan=sigma_tan, settings=ts, floor=floor)
        _, calibration = calibration_floor(triangulated)
        if calibration:
            calibration.update(floor_px=floor, floor_applied=bool(floor > 0), error_model=fit)
    else:
        triangulated = triangulate(sigma_rho=sigma_rho, sigma_tan=sigma_tan, settings=settings.triangulate)
        floor, calibration = calibration_floor(triangulated)
        if calibration:
            calibration["floor_px"] = floor
            calibration["floor_applied"] = bool(calibration["chi2_median"] > FLOOR_CHI2)
        if floor > 0 and calibration["floor_applied"]:
            # The rig's calibration misses by more than the decode's own errors:
            # discount that direction (across the epipolar line) by the miss
            # (docs/reconstruction.md, "Calibration floor").
            ts = replace(settings.triangulate,
                         max_residual_px=max(settings.triangulate.max_residual_px, FLOOR_OUTLIER * floor))
            triangulated = triangulate(sigma_rho=sigma_rho, sigma_tan=sigma_tan, settings=ts, floor=floor)
    if fit and samples.ring is not None:
        # the pairs' fit cannot see what both coordinates share (their disagreement cancels it): a ring
        # edge's place in the camera is measured; a dense code's samples sit at pixel centres
        triangulated = _with_shared_slope(scan, samples, triangulated, threads)
    if calibration and calibration["residual_px_median"] > CALIBRATION_WARN_PX:
        log.warning("%s: the rig does not fit these images: the two projector coordinates miss each other's "
                    "point by %.2f px (median; p95 %.2f px): check the calibration (docs/calibration.md)",
                    view.name, calibration["residual_px_median"], calibration["residual_px_p95"])
    return triangulated, calibration


def _camera_side(scan: Scan, samples, settings: ReconstructSettings, sector_bits: int, threads: int):
    """The samples with ``sigma_rho`` from their camera-side error (``sigma_uv``: a line centre's
    across its line): the rings place each point once, and the change of rho per camera px there
    turns the one into the other (:func:`~ringscan.kernels.triangulation.camera_side_sigmas`), times
    what the error does along the ray over that (:func:`_surface_slope`)."""
    rig = scan.rig
    vol = rig.volume
    camera, light = camera_model_for(rig), light_model_for(rig)
    first = triangulate_rings(samples.uv, samples.rho, samples.sector, samples.confidence, camera=camera, light=light,
                              volume=(vol.z_min, vol.z_max, vol.r_max), center=scan.patterns.center,
                              sector_bits=sector_bits, threads=threads,
                              settings=replace(settings.triangulate, constraint="rings"))
    sigma_rho = camera_side_sigmas(samples.uv, samples.sigma_uv, first.points, first.status, camera=camera,
                                   light=light, center=scan.patterns.center, threads=threads)
    if samples.across is not None and len(samples):
        # along its ray a point errs by the surface's slope too (_surface_slope); the neighbours along the
        # line then fit their factor to the sigma as it stands along the ray (they see the ring's share:
        # their factor takes the view's average of this one, each sample keeps its own ratio)
        def placed(uv):  # the samples' rays through uv, on their rings
            return triangulate_rings(uv, samples.rho, samples.sector, samples.confidence, camera=camera, light=light,
                                     volume=(vol.z_min, vol.z_max, vol.r_max), center=scan.patterns.center,
                                     sector_bits=sector_bits, threads=threads,
                                     settings=replace(settings.triangulate, constraint="rings"))
        along_ray = _surface_slope(samples, first, placed, np.asarray(rig.camera.center, np.float64))
        sigma_rho = wp.array((sigma_rho.numpy() * along_ray).astype(np.float32), dtype=wp.float32,
                             device=sigma_rho.device)
    return replace(samples, sigma_rho=sigma_rho)


def _surface_slope(samples, first, triangulate, center: np.ndarray) -> np.ndarray:
    """(n,) float64 what camera-side samples' errors do along their rays over what their rings' share
    is: a centre off by du across its line puts the point on its ring's surface at the wrong ray, so
    along the ray it is off by (dt_ring/du - dt_surface/du) du, where ``camera_side_sigmas`` (and the
    neighbours along the line, which see the placed depths) count the ring's term alone. The surface's
    is read from the depths of the next lines across (``Samples.across``), the ring's from the ray
    moved +-0.5 px and placed on the same ring; 1 where either is missing, never below 1. Where the view
    grazes the surface (a silhouette) the second term rules. Host NumPy over the view's samples (this codec's few)."""
    s_uv = samples.sigma_uv.numpy().astype(np.float64)
    length = np.linalg.norm(s_uv, axis=1)
    n = s_uv / np.maximum(length, 1e-12)[:, None]
    uv = samples.uv.numpy().astype(np.float64)

    def depths(t):
        P = t.points.numpy().astype(np.float64)
        ok = (t.status.numpy() == STATUS_OK) | (t.status.numpy() == STATUS_GRAZING)
        return np.where(ok, np.linalg.norm(P - center, axis=1), np.nan)

    t0 = depths(first)
    moved = [depths(triangulate(wp.array((uv + sgn * 0.5 * n).astype(np.float32), dtype=wp.vec2,
                                         device=samples.uv.device))) for sgn in (1.0, -1.0)]
    ring_slope = moved[0] - moved[1]  # along the ray, per camera px along n, on the same ring
    across, gap = samples.across.numpy(), samples.across_px.numpy().astype(np.float64)
    ta = np.where(across >= 0, t0[np.maximum(across, 0)], np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        one = np.stack([(ta[:, 0] - t0) / gap[:, 0], (t0 - ta[:, 1]) / gap[:, 1]], 1)
        surface = np.where(np.isfinite(one).all(axis=1), (ta[:, 0] - ta[:, 1]) / (gap[:, 0] + gap[:, 1]),
                           np.where(np.isfinite(one[:, 0]), one[:, 0], one[:, 1]))
        factor = np.abs(ring_slope - surface) / np.abs(ring_slope)
    # never below 1: where the two slopes nearly cancel, the surface's (read over the ~40 px to the next
    # lines) is not known well enough to shrink a sigma by it (on the sphere such samples erred 5x theirs)
    return np.where(np.isfinite(factor), np.maximum(factor, 1.0), 1.0)


def _with_shared_slope(scan: Scan, samples, triangulated, threads: int):
    """``triangulated`` with each point's sigma grown by the error its two coordinates share on a
    steep surface: ``SHARED_POSITION_PX`` times its depth gradient across the image, read from the
    points around it (:func:`~ringscan.kernels.error_terms.widen_for_slope`)."""
    cam = scan.rig.camera
    sigma, _ = widen_for_slope(triangulated.points, triangulated.status, triangulated.sigma, samples.uv,
                               samples.pixel, center=np.asarray(cam.center, np.float64), width=cam.width,
                               height=cam.height, position_px=SHARED_POSITION_PX, threads=threads)
    return replace(triangulated, sigma=sigma)


def _with_line_bias(samples, triangulated, base: wp.array):
    """``triangulated`` with each depth sigma grown by its sample's ``bias_uv`` (camera px, what the
    neighbours along its line share and cannot check), in depth as the sample's camera-side sigma
    ``sigma_uv`` is: ``base`` (the depth sigma before the neighbours' terms) per its length."""
    s_uv = np.linalg.norm(samples.sigma_uv.numpy().astype(np.float64), axis=1)
    b = np.asarray(base.numpy(), np.float64) * samples.bias_uv.numpy() / np.maximum(s_uv, 1e-12)
    sigma = np.asarray(triangulated.sigma.numpy(), np.float64)
    out = np.sqrt(sigma * sigma + b * b).astype(np.float32)
    return replace(triangulated, sigma=wp.array(out, dtype=wp.float32, device=triangulated.sigma.device))


def _warn_low_modulation(view: View, stats: dict) -> None:
    """One warning line where more than ``LOW_MODULATION_WARN`` of a view's lit pixels
    have a finest code that barely modulates (the codec's ``low_modulation`` of its
    ``pixels_lit``): what is lost there is lost silently otherwise."""
    low, lit = stats.get("low_modulation", 0), stats.get("pixels_lit", 0)
    if lit and low > LOW_MODULATION_WARN * lit:
        log.warning("%s: the finest pattern barely modulates on %.0f %% of the lit pixels (%d, low_modulation): "
                    "no point comes from them; a far, dark or grazing surface or a defocused projector (a "
                    "coarser pattern or more light helps)", view.name, 100.0 * low / lit, low)


def _warn_fine_angle(view: View, stats: dict, spec) -> None:
    """One warning line where the angle code's least period spans fewer than ``MIN_PERIOD_CAMERA_PX`` camera px
    in the middle of the rig's volume (the codec's ``angle_period_camera_px``): the camera is too coarse for the
    patterns, and the way out is a pattern, not a setting (docs/dense.md)."""
    least = stats.get("angle_period_camera_px")
    if least is None:
        return
    from ringscan.pipeline.codecs.angle_code import MIN_PERIOD_CAMERA_PX

    # a third over the least period that spans MIN_PERIOD_CAMERA_PX, to a multiple of 4 px (the sphere at a
    # quarter of the default camera's resolution: 12 px still 4.0 % beyond 3 sigma on ringscan's render, 16 1.7 %)
    need = float(spec.angle_period) * MIN_PERIOD_CAMERA_PX / least
    advice = int(4 * np.ceil(1.3 * need / 4))
    log.warning("%s: the angle code's least period spans %.1f camera px here (under %.1f: its fringes fade or alias "
                "in this camera); record the patterns with --angle-period %d (docs/dense.md)", view.name, least,
                MIN_PERIOD_CAMERA_PX, advice)


def _row_bands(rows: np.ndarray) -> np.ndarray:
    """Indices of the samples in every R-th band of three camera rows (R chosen so that
    at most ``MAX_CHECK_SAMPLES`` are kept): evenly spread over the view, each with the
    rows above and below it, where a dense code's neighbouring pixels check rho."""
    period = max(3, int(np.ceil(3 * rows.size / MAX_CHECK_SAMPLES)))
    return np.flatnonzero(rows % period <= 2)


def _honest_sigmas(scan: Scan, samples, settings: ReconstructSettings, sector_bits: int, threads: int):
    """(sigma_rho, sigma_tan, the :class:`ErrorModel` or {}): the samples' predicted
    standard deviations with the error terms the view's own frames show the decode's
    model to miss (:mod:`ringscan.pipeline.reconstruct.error_scale`): a subset of the
    samples with an angle is placed by the ring alone, by the angle alone and by both,
    and the two depths' disagreement measures the terms."""
    if samples.phi is None or samples.sigma_tan is None or len(samples) < MIN_PAIRS:
        return samples.sigma_rho, samples.sigma_tan, {}
    rig = scan.rig
    vol = rig.volume
    dev = samples.uv.device
    codec = codec_for(scan.patterns.codec, source=scan.path)
    window = codec.pixel_window(codec.settings_from(settings)) if samples.ring is None else None
    dense = window is not None  # one sample a pixel that its neighbours can check (below)
    # the samples with an angle, and of them an evenly spread subset, found and gathered on the device:
    # the fit reads the subset (at most MAX_CHECK_SAMPLES), not the view
    with_angle = finite_indices(samples.phi, threads=threads)
    if dense:
        rows = gather(samples.pixel, with_angle, threads=threads).numpy() // scan.rig.camera.width
        chosen = _row_bands(rows)
    else:
        chosen = sample_subset(len(with_angle))
    if chosen.size < MIN_PAIRS:
        return samples.sigma_rho, samples.sigma_tan, {}
    pick = gather(with_angle, wp.array(chosen.astype(np.int32), dtype=wp.int32, device=dev), threads=threads)
    sub = {k: gather(getattr(samples, k), pick, threads=threads)
           for k in ("uv", "rho", "sector", "confidence", "phi", "sigma_rho", "sigma_tan")}
    host = {k: sub[k].numpy() for k in ("uv", "sigma_rho", "sigma_tan")}
    pixel = gather(samples.pixel, pick, threads=threads).numpy() if dense else None
    tri = partial(triangulate_rings, sub["uv"], sub["rho"], sub["sector"], sub["confidence"],
                  camera=camera_model_for(rig), light=light_model_for(rig),
                  volume=(vol.z_min, vol.z_max, vol.r_max), center=scan.patterns.center, sector_bits=sector_bits,
                  phi=sub["phi"], sigma_rho=sub["sigma_rho"], sigma_tan=sub["sigma_tan"], widen_angle=False,
                  threads=threads)
    cam = rig.camera
    center = -np.asarray(cam.R, np.float64).T @ np.asarray(cam.t, np.float64)
    def depth(t):
        d = np.linalg.norm(t.points.numpy().astype(np.float64) - center, axis=1)
        return np.where(t.status.numpy() == 0, d, np.nan), t.sigma.numpy()
    dr, sr = depth(tri(settings=replace(settings.triangulate, constraint="rings")))
    dt, st = depth(tri(settings=replace(settings.triangulate, constraint="angle")))
    both = tri(settings=replace(settings.triangulate, constraint="both"))
    rv = np.where(both.status.numpy() == 0, both.residual_var.numpy(), 0.0)
    rho_terms = None
    if dense:
        # a dense code's two predicted errors both scale with the pixel's contrast, so the
        # pairs cannot tell whose error they disagree by (phase-rings in linear light put
        # it all on rho: k_rho 11, and the default read 3.4x worse than rings alone); the
        # ring's neighbouring pixels measure rho's own
        nb = fit_neighbour_model(dr, sr, host["sigma_rho"], pixel, None, host["uv"],
                                 width=scan.rig.camera.width, window=window)
        if nb["measured_by"] is not None:
            rho_terms = (nb["k_rho"], nb["floor_rho_px"])
    # indirect light above the view's own typical floor (the blur that mixes every fine
    # pattern's edges is the view's; light bounced into a corner is a region's)
    indirect, middle = None, 0.0
    if samples.indirect is not None:
        middle = median(samples.indirect)
        indirect = np.maximum(gather(samples.indirect, pick, threads=threads).numpy().astype(np.float64) - middle, 0.0)
    shading = gather(samples.shading, pick, threads=threads).numpy() if samples.shading is not None else None
    fit = fit_error_model(dr, sr, dt, st, host["sigma_rho"], host["sigma_tan"], rv, host["uv"],
                          indirect=indirect, rho_terms=rho_terms, shading=shading)

    # every sample widened on the device (error_scale.apply_error_model and region_scale state it in NumPy);
    # parts of the view whose pairs disagree more than the view's model says (an object's facets beside a
    # plane) widen both coordinates alike: the weighting stays, sigma grows
    def widened(a, c):
        k, f, b, g = fit[f"k_{c}"], fit[f"floor_{c}_px"], fit[f"indirect_{c}_px"], fit[f"shading_{c}_px"]
        if k == 1.0 and f == 0.0 and not fit["regions"] and b == 0.0 and g == 0.0:
            return a
        return widen_sigmas(a, k=k, floor=f, indirect=samples.indirect, indirect_px=b, indirect_median=middle,
                            shading=samples.shading, shading_px=g, uv=samples.uv, regions=fit["regions"],
                            threads=threads)
    return widened(samples.sigma_rho, "rho"), widened(samples.sigma_tan, "tan"), dict(fit)


def _neighbour_sigmas(scan: Scan, samples, triangulated, settings: ReconstructSettings):
    """(triangulated with its sigma widened, the :class:`ErrorModel` or {}): where no
    angle checks the ring coordinate, its missed error terms measured from each point's
    disagreement with its neighbours on the same ring
    (:func:`~ringscan.pipeline.reconstruct.neighbour_checks.fit_neighbour_model`). The points
    stay where they are (one coordinate places them; its sigma weighs nothing), so the
    depth sigmas are widened after the one triangulation. A dense code (one sample a
    pixel: phase-rings) averages each pixel over a window (``Codec.pixel_window``); the
    errors its pixels share are taken into account."""
    if samples.sigma_rho is None or len(samples) < MIN_PAIRS:
        return triangulated, {}
    window, group = 1, None
    codec = codec_for(scan.patterns.codec, source=scan.path)
    if samples.ring is None:
        window = codec.pixel_window(codec.settings_from(settings))
        if window is None:  # a dense code whose neighbouring pixels cannot check it
            return triangulated, {}
    else:
        group = codec.error_groups(scan.patterns, samples.ring.numpy())
    cam = scan.rig.camera
    center = -np.asarray(cam.R, np.float64).T @ np.asarray(cam.t, np.float64)
    ok = triangulated.status.numpy() == 0
    depth = np.where(ok, np.linalg.norm(triangulated.points.numpy().astype(np.float64) - center, axis=1), np.nan)
    sigma = triangulated.sigma.numpy()
    sigma_px = samples.sigma_rho.numpy()
    ring = samples.ring.numpy() if samples.ring is not None else None
    uv = samples.uv.numpy()
    # how far along its ring each sample can be checked (kernels.ring_checks; neighbour_checks.check_reach in NumPy;
    # imported here: a view with an angle code or two cameras never loads the neighbour model's kernels)
    from ringscan.kernels.ring_checks import sample_reach

    reach = (sample_reach(samples.uv, samples.ring, samples.pixel, np.isfinite(depth), width=cam.width)
             if ring is not None else None)
    fit = fit_neighbour_model(depth, sigma, sigma_px, samples.pixel.numpy(), ring, uv,
                              width=cam.width, window=window, group=group, reach=reach,
                              device=triangulated.points.device)
    if fit["measured_by"] is None:
        return triangulated, {}
    widened = widen_depth_sigma(sigma, sigma_px, fit)
    if fit.get("groups"):  # the codec's groups of samples that err differently (Codec.error_groups)
        widened = (widened * np.sqrt(group_scale(fit["groups"], group))).astype(np.float32)
    if fit["regions"]:
        # parts of the view whose neighbours disagree more than the view's model says
        widened = (widened * np.sqrt(region_scale(fit["regions"], uv))).astype(np.float32)
    if fit.get("reach"):  # samples no check along their ring reached (fragments, edges): checked across rings
        widened = (widened * np.sqrt(reach_scale(fit["reach"], reach))).astype(np.float32)
    if samples.indirect is not None and samples.ring is not None:
        # bounced light shifts a ring's edges smoothly along it, which no neighbour sees: its measured
        # share widens sigma by the shift per unit share the angle's pairs fit (INDIRECT_PRIOR_PX; a
        # dense code's phase moves far less: phase-rings' sigma came out 2-4x too wide with it)
        widened = widen_for_indirect(widened, sigma, sigma_px, samples.indirect.numpy(), INDIRECT_PRIOR_PX)
        fit["indirect_rho_px"] = INDIRECT_PRIOR_PX
    if samples.shading is not None and samples.ring is not None:
        # the camera's blur moves an edge where the light changes fast across the image (error_scale), by as
        # much on its neighbours where the light changes alike along the ring (no check sees it there): the
        # shift per unit gradient the angle's pairs fit (SHADING_PRIOR_PX)
        widened = widen_for_shading(widened, sigma, sigma_px, samples.shading.numpy(), SHADING_PRIOR_PX)
        fit["shading_rho_px"] = SHADING_PRIOR_PX
    widened = wp.array(widened, dtype=wp.float32, device=triangulated.sigma.device)
    return replace(triangulated, sigma=widened), dict(fit)


def view_rays(scan: Scan, view: View, settings: ReconstructSettings) -> str:
    """The rays that place the view's points (``stereo.rays`` resolved):
    ``camera-projector``, ``camera-camera`` or ``all``.

    Raises:
        FormatError: two-camera rays asked of a one-camera view.
    """
    rays = settings.stereo.rays
    two = view.camera2 is not None and scan.rig.camera2 is not None
    if not two:
        if rays in ("camera-camera", "all"):
            raise FormatError(scan.path, f"view {view.name}: --rays {rays} needs a two-camera view (a rig with "
                                         "camera2 and the view's camera-2 frames); this one has one camera")
        return "camera-projector"
    if rays == "auto":
        if not has_calibrated_light(scan.rig):
            return "camera-camera"
        # a codec whose samples cannot be matched between the cameras: camera 1 and the projector
        return "all" if codec_for(scan.patterns.codec, source=scan.path).full_coordinate(scan.patterns) \
            else "camera-projector"
    return rays


def check_rays(scan: Scan, views, settings: ReconstructSettings) -> None:
    """Every view's rays can be had: two-camera rays need two-camera views and a
    codec whose samples carry the full projector coordinate (the cameras are
    matched by it), the projector's ray a calibrated projector (checked before
    anything is written).

    Raises:
        FormatError: naming the view and what is missing.
    """
    codec = codec_for(scan.patterns.codec, source=scan.path)
    for view in views:
        rays = view_rays(scan, view, settings)
        if rays in ("camera-camera", "all") and not codec.full_coordinate(scan.patterns):
            raise FormatError(scan.path, f"view {view.name}: --rays {settings.stereo.rays} matches the two cameras "
                                         f"by projector coordinate, but the {codec.name} codec's samples of this "
                                         "scan carry the ring radius only"
                                         + (NO_ANGLE_CODE if codec.has_angle_code else ";")
                                         + " use --rays camera-projector"
                                         + ("" if has_calibrated_light(scan.rig) else
                                            " (that needs a calibrated projector: ringscan calibrate "
                                            "projector-from-scan, docs/calibration.md)"))
        if rays != "camera-camera" and not has_calibrated_light(scan.rig):
            light_model_for(scan.rig)  # raises: the projector is not calibrated (its own message)


def load_view_modules(scan: Scan) -> None:
    """Import the modules a view of ``scan`` runs: its codec's, and with two cameras the matcher's and the
    rays'. Warp parses a module's kernels as it is imported (~0.1 s of Python for a two-camera view); called
    while the first view's frames are read (the image decoders release the interpreter), it costs no time."""
    codec_for(scan.patterns.codec, source=scan.path)
    if scan.rig.camera2 is not None:
        for name in ("ringscan.kernels.stereo_rays", "ringscan.pipeline.reconstruct.stereo"):
            importlib.import_module(name)


def _stereo_points(run: _ViewRun, sector_bits: int) -> _Placed:
    """Camera 1's samples matched in camera 2 and triangulated from two or three
    rays; with ``auto`` on a calibrated rig, the samples camera 2 does not match
    fall back to camera-projector."""
    # (the matcher's and the rays' modules and kernels load here: a one-camera run needs none, ~75 ms of imports)
    from ringscan.kernels.stereo_rays import (place_matches, polar_information, projector_misses, through_map,
                                              triangulate_rays, widen_along_rays, widen_by_chi)
    from ringscan.pipeline.reconstruct.stereo import (decode_view, epipolar_check, match_error_model,
                                                      match_on_device, widen_matches)

    scan, view, settings, device, threads, samples, times = (run.scan, run.view, run.settings, run.device,
                                                             run.threads, run.samples, run.times)
    rig = scan.rig
    vol = rig.volume
    t = time.perf_counter()
    samples2, _, _ = decode_view(as_camera2(scan), view.camera2, settings=settings, device=device, threads=threads)
    times["decode_camera2"] = time.perf_counter() - t
    t = time.perf_counter()
    st = settings.stereo
    use_light = st.rays == "all" or (st.rays == "auto" and has_calibrated_light(rig))
    # matched camera to camera, camera 1's code error goes through the map too (as three rays do) where its
    # radial and angular parts differ by far (ring edges, phase-rings): a stand-in on camera 1 cannot say which
    # part runs along the epipolar lines. An imported u, v map errs alike both ways: it keeps the stand-in
    # (exact for it; the statue-size path reads no map)
    cc_map = not use_light and not codec_for(scan.patterns.codec, source=scan.path).isotropic_code_error
    matches, _ = match_on_device(scan, samples, samples2, settings=settings, maps=use_light or cc_map,
                                 threads=threads)
    times["match"] = time.perf_counter() - t
    t = time.perf_counter()
    light = light_model_for(rig) if use_light else None  # raises for an uncalibrated projector
    n = len(samples)
    uv1, uv2 = matches.uv1, matches.uv2
    check = epipolar_check(rig, matches, uv=(uv1, uv2))
    max_res = st.max_residual_px
    if check and not check["fits"]:
        # a rig that misses: its points miss by the miss; the cloud is still made
        # (and the view warns), an outlier is a point beyond 5 times the miss
        max_res = max(max_res, FLOOR_OUTLIER * check["epipolar_px_median"])
    # What the matches' sigmas miss, measured across their epipolar lines (the calibration's smooth miss
    # left out; matches too far off to become points, two rays' residual over max_res, left out too), widens
    # both codes' errors alike: the same errors act along the lines, in depth. With the projector's ray the
    # query's code is the projector point, widened as camera 1's would be.
    error_model = match_error_model(rig, matches, max_distance_px=2.0 * max_res, threads=threads)
    matches = widen_matches(matches, error_model, projector=use_light or cc_map, threads=threads)
    camera1, camera2 = camera_model_for(rig), camera_model_for(as_camera2(scan).rig)
    rays = partial(triangulate_rays, camera1=camera1, camera2=camera2, volume=(vol.z_min, vol.z_max, vol.r_max),
                   min_sin=st.min_ray_sin, threads=threads)
    kw = {}
    sigma1 = matches.sigma1
    projector_check = {}
    if use_light or cc_map:
        # uv2 is where camera 2 reads camera 1's projector point: that point's error moves uv2 through the
        # matcher's map, and camera 1's pixel carries none of it (a ring edge: its radial part); counted once,
        # in the projector's ray, or without it in camera 2's covariance (docs/design.md §19)
        sigma1, query_extra, sigma_rho = through_map(matches.sigma1, matches.query_model, matches.proj_map,
                                                     matches.sigma_rho, matches.gain,
                                                     ring_edges=samples.ring is not None, threads=threads)
        kw = dict(proj_map=matches.proj_map,
                  proj_info=polar_information(matches.proj, sigma_rho, matches.sigma_tan,
                                              center=scan.patterns.center, extra=query_extra, gain=matches.gain,
                                              threads=threads))
    if use_light:
        kw.update(light=light, proj=matches.proj)
        # The two cameras fix each point without the projector: where the projector's calibration misses
        # their points by more than its sigmas allow (along camera 1's ray through it, where a miss moves the
        # point and no camera-projector check sees it), its ray is discounted by that miss (measured on at
        # most MAX_CHECK_SAMPLES matches spread over the view: a view's median)
        pick = wp.array(sample_subset(len(matches)).astype(np.int32), dtype=wp.int32, device=device)
        g = partial(gather, index=pick, threads=threads)
        two = rays(g(uv1), g(uv2), g(matches.sigma1), g(matches.sigma2), max_residual_px=max_res)
        floor_p, projector_check = residual_floor(*projector_misses(two, g(matches.proj), g(kw["proj_info"]),
                                                                    camera1=camera1, light=light, threads=threads),
                                                  threads=threads)
        if projector_check:
            applied = bool(floor_p > 0 and projector_check["chi2_median"] > PROJECTOR_FLOOR_CHI2)
            projector_check.update(floor_px=floor_p, floor_applied=applied)
            if applied:
                # (and, as a one-camera view's calibration floor, a point is inconsistent only beyond 5 times it)
                kw["projector_floor_px"] = floor_p
                kw["max_residual_px"] = max(max_res, FLOOR_OUTLIER * floor_p)
            if projector_check["residual_px_median"] > CALIBRATION_WARN_PX:
                log.warning("%s: the projector's calibration does not fit the two cameras': it misses their points "
                            "by %.2f px (median; p95 %.2f px), and its ray is discounted by that (or the cameras' "
                            "vergence is off, which their epipolar check cannot see): check the calibrations "
                            "(docs/calibration.md)",
                            view.name, projector_check["residual_px_median"], projector_check["residual_px_p95"])
    tri = rays(uv1, uv2, sigma1, matches.sigma2, **{"max_residual_px": max_res, **kw})
    # a point whose rays disagree beyond their sigmas is less sure than they say: its sigma grows by its chi
    # (three rays: 6 numbers for 3, two: 4), as a one-camera point of both coordinates does
    tri = widen_by_chi(tri, dof=3 if use_light else 1, threads=threads)
    extra = {}
    if st.rays == "auto" and use_light:
        # camera 1's samples without a match in camera 2 (hidden from it): camera-projector, exactly as
        # a one-camera view places them (the calibration floor included)
        tp, calibration = _camera_projector(scan, view, settings, samples, sector_bits, threads)
        points, status, confidence, sigma, residual = tp.points, tp.status, tp.confidence, tp.sigma, tp.residual
        if projector_check.get("floor_applied"):
            # the projector's miss the cameras found runs along camera 1's rays, unseen by these points' checks
            sigma = widen_along_rays(tp, projector_check["floor_px"], camera1=camera1, light=light, threads=threads)
        extra["fallback_camera_projector"] = int(n - len(matches))
        if calibration:
            extra["calibration"] = calibration
    else:
        points = wp.zeros(n, dtype=wp.vec3, device=device)
        confidence = wp.zeros(n, dtype=wp.float32, device=device)
        sigma = wp.zeros(n, dtype=wp.float32, device=device)
        status = wp.full(n, STATUS_UNMATCHED, dtype=wp.int32, device=device)
        residual = wp.full(n, -1.0, dtype=wp.float32, device=device)
    # each match's point written at its sample on the device (kernels.stereo_rays.place_matches)
    place_matches(matches.index, tri, samples.confidence, points=points, status=status, sigma=sigma,
                  residual=residual, placed_confidence=confidence, threads=threads)
    residual_px = (_angle_used(samples, settings) if st.rays == "auto" and use_light
                   else wp.zeros(n, dtype=wp.int32, device=device))
    set_at(residual_px, matches.index, 1, threads=threads)  # the rays' RMS reprojection error
    _stereo_report(view, matches, tri, check, use_light, extra)
    if error_model:
        extra["stereo"]["error_model"] = error_model
    if projector_check:
        extra["stereo"]["projector_check"] = projector_check
    wp.synchronize_device(device)
    times["triangulate"] = time.perf_counter() - t
    return _Placed(points=points, status=status, confidence=confidence, sigma=sigma, residual=residual,
                   residual_px=residual_px, extra=extra)


def _stereo_report(view: View, matches, tri, check: dict, use_light: bool, extra: dict) -> None:
    """Add a two-camera view's report entries to ``extra``: ``stereo`` (the matcher's counts,
    three rays or two, the rays' median residual, the camera-projector fallback) and
    ``calibration_check`` (the epipolar check, which warns where the rig misses)."""
    if check:
        check = {"kind": check.pop("kind"), "samples": check.pop("matches"),
                 "median_px": check.pop("epipolar_px_median"), "p95_px": check.pop("epipolar_px_p95"), **check}
        if not check["fits"]:
            from ringscan.pipeline.reconstruct.stereo import EPIPOLAR_WARN_PX  # (loaded: a two-camera view)

            log.warning("%s: the rig file does not fit the images: camera 2's matches lie %.2f px from their "
                        "epipolar lines (median; p95 %.2f px; above %.1f px): check the cameras' calibration "
                        "(ringscan calibrate refine, docs/calibration.md)", view.name, check["median_px"],
                        check["p95_px"], EPIPOLAR_WARN_PX)
    placed = compact_points(tri.status)  # the rays' residuals' median, on the device (two values read)
    extra["stereo"] = {**matches.stats, "three_rays": bool(use_light),
                       "residual_px_median": median(gather(tri.residual, placed), dtype=np.float32)
                       if len(placed) else None}
    if "fallback_camera_projector" in extra:
        extra["stereo"]["fallback_camera_projector"] = extra.pop("fallback_camera_projector")
    if check:
        extra["calibration_check"] = check


def _angle_used(samples, settings: ReconstructSettings) -> wp.array:
    """(n,) int32 on the device, 1 for the samples the camera-projector triangulation places with the
    angle (their residual is in projector px; the others' in sector widths): as
    ``kernels.triangulation``'s kernel decides, a finite angle and a constraint other than the rings
    (every codec gives an angle's ``sigma_tan`` > 0)."""
    if samples.phi is None or settings.triangulate.constraint == "rings":
        return wp.zeros(len(samples), dtype=wp.int32, device=samples.uv.device)
    return finite_flags(samples.phi)


def _finish(run: _ViewRun, placed: _Placed, *, rays: str) -> ViewCloud:
    """Filter, compact and count a view's per-sample results into its cloud."""
    scan, settings, device, threads, frames, samples, codec_stats, times = (
        run.scan, run.settings, run.device, run.threads, run.frames, run.samples, run.codec_stats, run.times)
    points, status, confidence, sigma, residual = (placed.points, placed.status, placed.confidence, placed.sigma,
                                                   placed.residual)
    residual_px, extra = placed.residual_px, placed.extra
    rig = scan.rig
    cam = camera_model_for(rig)
    t = time.perf_counter()
    status_dev = mark_isolated_points(points, samples.pixel, status, camera=cam, width=rig.camera.width,
                                      height=rig.camera.height, isolated_status=STATUS_ISOLATED,
                                      settings=settings.filter, threads=threads)
    idx = compact_points(status_dev)
    wp.synchronize_device(device)
    times["filter"] = time.perf_counter() - t

    t = time.perf_counter()
    # the kept points' fields gathered on the device, then read: the one download of a view (and its counts)
    counts = count_values(status_dev, len(STATUS_NAMES), threads=threads)
    def kept(a):
        return gather(a, idx, threads=threads).numpy()

    cloud = ViewCloud(
        points=kept(points),
        ring=kept(samples.ring) if samples.ring is not None else np.full(len(idx), -1, np.int32),
        rho=kept(samples.rho),
        confidence=kept(confidence),
        uv=kept(samples.uv),
        sigma=kept(sigma),
        stats={},
    )
    # one unit a property: px where the angle or a second camera placed the point, sector widths
    # (the rings alone) apart, NaN where the point has none
    res, in_px = kept(residual), kept(residual_px) != 0
    cloud.residual = np.where(in_px, res, np.float32(np.nan))
    cloud.sector_residual = np.where(~in_px & (res >= 0), res, np.float32(np.nan))
    low_confidence = 0
    if settings.min_confidence > 0:
        keep = cloud.confidence >= settings.min_confidence
        low_confidence = int(keep.size - np.count_nonzero(keep))
        cloud = ViewCloud(cloud.points[keep], cloud.ring[keep], cloud.rho[keep], cloud.confidence[keep],
                          cloud.uv[keep], cloud.sigma[keep], {}, cloud.residual[keep], cloud.sector_residual[keep])
    times["download"] = time.perf_counter() - t
    with_angle = samples.phi is not None and settings.triangulate.constraint != "rings"
    two = rays != "camera-projector"
    cloud.stats = {
        "pixels": int(frames.shape[1] * frames.shape[2]),
        **codec_stats,
        "constraint": ("both" if settings.triangulate.constraint == "auto" else settings.triangulate.constraint)
        if with_angle else "rings",
        "rays": rays,
        "points": int(cloud.points.shape[0]),
        "median_sigma_mm": float(np.median(cloud.sigma)) if cloud.sigma.size else None,
        "median_residual": float(np.nanmedian(cloud.residual)) if np.isfinite(cloud.residual).any() else None,
        **extra,
        # every sample not written, by reason: the kernels' statuses, then min_confidence
        "dropped": {**{name: int(counts[i]) for i, name in enumerate(STATUS_NAMES)
                       if i > 0 and (two or i != STATUS_UNMATCHED)},
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
        frames: the view's (n, H, W) frames in the codec's frame order (the codec
            reads them: ``Codec.explain_no_points``).
        scan: the scan.
        stats: the view's counts (``pixels_decoded``, ``samples``, ``dropped``, ...).
        settings: the settings the view was reconstructed with.
    """
    codec = codec_for(scan.patterns.codec, source=scan.path)
    why = codec.explain_no_points(np.asarray(frames), scan, stats, codec.settings_from(settings))
    if why is not None:
        return why
    if stats.get("samples", 0) == 0:
        return f"no ring found: {stats.get('pixels_decoded', 0)} pixels decoded, but no ring edge was sampled"
    dropped = ", ".join(f"{k} {v}" for k, v in stats.get("dropped", {}).items() if v)
    return (f"every one of the {stats['samples']} ring samples was dropped ({dropped or 'below min_confidence'}): "
            f"check the rig's calibration and working volume")


def write_view_ply(path: Path, cloud: ViewCloud, view_index: int) -> None:
    n = cloud.points.shape[0]
    f32 = lambda a: a.astype(np.float32, copy=False)  # noqa: E731  (float32 already: not copied before write_ply's own copy)
    write_ply(path, {
        "x": f32(cloud.points[:, 0]), "y": f32(cloud.points[:, 1]), "z": f32(cloud.points[:, 2]),
        "ring": cloud.ring.astype(np.int32, copy=False), "rho": f32(cloud.rho),
        "view": np.full(n, view_index, np.int32), "confidence": f32(cloud.confidence),
        "u": f32(cloud.uv[:, 0]), "v": f32(cloud.uv[:, 1]), "sigma": f32(cloud.sigma),
        **({"residual": f32(cloud.residual)} if cloud.residual is not None else {}),
        **({"sector_residual": f32(cloud.sector_residual)} if cloud.sector_residual is not None else {}),
    }, comments=["ringscan point cloud, world frame, mm"])
