"""Two cameras: camera 1's samples matched to camera 2 by equal projector
coordinate (no extrinsics used), the epipolar check of the rig against those
matches, and the two- or three-ray points (docs/reconstruction.md "Two cameras").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import warp as wp

from ringscan.kernels import init_warp, resolve_device
from ringscan.kernels.compact import count_values, gather, percentiles
from ringscan.kernels.launch import cpu_threads
from ringscan.kernels.samples import Samples
from ringscan.kernels.geometry import make_camera
from ringscan.kernels.stereo_match import MATCH_STATUS_NAMES, match_by_projector, projector_coordinates
from ringscan.kernels.error_terms import widen_sigmas
from ringscan.kernels.stereo_support import epipolar_distances as kernel_epipolar_distances
from ringscan.kernels.stereo_support import epipolar_slopes
from ringscan.kernels.stereo_support import RefineSettings, polar_sigmas, refine_codes, uv_sigmas, window_sums
from ringscan.kernels.triangulation import compact_points
from ringscan.pipeline.codecs.registry import codec_for
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.rig import Rig
from ringscan.pipeline.formats.scan import Scan, View, as_camera2, read_view_frames
from ringscan.pipeline.reconstruct.error_scale import fit_match_model, sample_subset
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

log = logging.getLogger(__name__)

__all__ = ["StereoMatches", "DeviceMatches", "match_view", "match_samples", "match_on_device", "decode_view", "epipolar_distances",
           "match_error_model", "widen_matches",
           "refine_integer_codes", "EPIPOLAR_WARN_PX"]

EPIPOLAR_WARN_PX = 1.0
"""Median epipolar distance (px) of a view's matches above which the rig file does not fit its images."""
EPIPOLAR_CHECK_MATCHES = 1 << 17
"""Matches the calibration check reads at most: an even stride through a view's matches beyond that (a
real capture's million cost ~0.07 s; the median and p95 of 2^17 are a whole view's to a quantile's
standard error, ~0.3 %)."""
QUERY_WINDOW_PX = 2
"""Half width (camera px) of the window whose plane reads camera 1's integer codes (5 x 5 pixels)."""
QUERY_MIN_PIXELS = 9
"""Fewest decoded pixels in that window for a plane (3 parameters; the rest its scatter)."""
QUERY_FIT_CHI2 = 4.0
"""Largest scatter of a window's codes about their plane, in variances the codes' sigmas predict
(integer codes: 1/12 px^2 each); beyond it the window straddles a depth edge or a misread code."""
INTEGER_TOLERANCE_PX = 1.0 / 64.0
"""A decoded coordinate this close to an integer is an integer code (the decoded frames' step is 1/32 px)."""


@dataclass
class StereoMatches:
    """Camera 1's samples with a camera-2 match (NumPy, n matches)."""

    uv1: np.ndarray
    """(n, 2) float64 camera-1 pixels as observed (distorted)."""
    uv2: np.ndarray
    """(n, 2) float64 camera-2 pixels where camera 2's projector coordinate equals camera 1's."""
    proj: np.ndarray
    """(n, 2) float64 projector pixels (u_p, v_p) decoded by camera 1."""
    sigma1: np.ndarray
    """(n,) float64 predicted standard deviation of uv1 (px, per axis)."""
    sigma2: np.ndarray
    """(n,) float64 predicted standard deviation of uv2 (px, per axis)."""
    sigma_proj: np.ndarray
    """(n, 2) float64 standard deviations of proj along u_p and v_p (projector px)."""
    sigma_rho: np.ndarray
    """(n,) float64 of proj's radius about the pattern centre (projector px)."""
    sigma_tan: np.ndarray
    """(n,) float64 of proj across its radius (projector px)."""
    index: np.ndarray
    """(n,) int64 index of each match in camera 1's samples."""
    stats: dict = field(default_factory=dict)
    """samples of each camera, matches, and the unmatched by reason (``MATCH_STATUS_NAMES``)."""

    def __len__(self) -> int:
        return self.uv1.shape[0]


def decode_view(scan: Scan, view: View, *, settings: ReconstructSettings, device, frames: np.ndarray | None = None,
                threads: int | None = None) -> tuple[Samples, dict, np.ndarray]:
    """One camera's samples of a view with the scan's codec, as matching reads them
    (``Codec.extract_for_matching``): (samples, codec stats, frames)."""
    threads = threads or cpu_threads()
    if frames is None:
        frames = read_view_frames(scan, view, threads=threads)
    on_cpu = wp.get_device(device).is_cpu and frames.flags.c_contiguous
    frames_w = wp.array(frames, dtype=wp.uint8 if frames.dtype == np.uint8 else wp.uint16, device=device,
                        copy=not on_cpu)
    codec = codec_for(scan.patterns.codec, source=scan.path)
    samples, stats = codec.extract_for_matching(frames_w, scan, codec.settings_from(settings), threads=threads)
    return samples, stats, frames


def _coordinates(scan: Scan, samples: Samples, which: str):
    if samples.phi is None or samples.sigma_rho is None or samples.sigma_tan is None or samples.rho is None:
        raise FormatError(scan.path, f"{which}: the {scan.patterns.codec} codec decodes no polar angle in this "
                                     "scan, so the two cameras cannot be matched by projector coordinate "
                                     "(record the angle code: --angle-steps > 0; or --rays camera-projector)")
    return projector_coordinates(samples.rho, samples.phi, samples.sigma_rho, samples.sigma_tan,
                                 center=scan.patterns.center)


def _cpu(a: np.ndarray, dtype) -> wp.array:
    """A NumPy array as a Warp array on the CPU (float64; no copy where it is already one)."""
    return wp.array(np.ascontiguousarray(a, np.float64), dtype=dtype, device="cpu", copy=False)


def _polar_to_uv(proj: np.ndarray, sigma_rho: np.ndarray, sigma_tan: np.ndarray, center) -> np.ndarray:
    """(n, 2) standard deviations along u_p and v_p of projector points whose errors are radial and
    tangential about ``center`` (``kernels.stereo_support.uv_sigmas``)."""
    if len(proj) == 0:
        return np.zeros((0, 2))
    return uv_sigmas(_cpu(proj, wp.vec2d), _cpu(sigma_rho, wp.float64), _cpu(sigma_tan, wp.float64),
                     center=(float(center[0]), float(center[1]))).numpy()


def _uv_to_polar(proj: np.ndarray, sigma_uv: np.ndarray, center) -> tuple[np.ndarray, np.ndarray]:
    """The radial and tangential standard deviations of projector points with independent u_p, v_p errors
    (``kernels.stereo_support.polar_sigmas``)."""
    if len(proj) == 0:
        return np.zeros(0), np.zeros(0)
    sr, st = polar_sigmas(_cpu(proj, wp.vec2d), _cpu(sigma_uv, wp.vec2d), center=(float(center[0]), float(center[1])))
    return sr.numpy(), st.numpy()


def _refine_settings() -> RefineSettings:
    """The window and tests of :func:`refine_integer_codes` for ``kernels.stereo_support.refine_codes``."""
    st = RefineSettings()
    st.radius, st.min_pixels = QUERY_WINDOW_PX, QUERY_MIN_PIXELS
    st.max_chi2, st.tolerance = QUERY_FIT_CHI2, INTEGER_TOLERANCE_PX
    return st


def refine_integer_codes(pixel: np.ndarray, proj: np.ndarray, sigma_uv: np.ndarray, *, width: int, height: int,
                         radius: int = QUERY_WINDOW_PX) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer projector codes of a dense per-pixel map read to a fraction of a projector pixel from
    their camera neighbourhood: each integer coordinate (u_p or v_p apart) is replaced by the value
    at its pixel of the plane fitted (weighted least squares, weights 1 / sigma^2) to the decoded
    coordinates of the (2 radius + 1)^2 pixels around it. A window whose scatter about its plane is
    beyond ``QUERY_FIT_CHI2`` times what the codes' sigmas allow (a depth edge, a misread code) keeps
    the code as it is.

    Integer codes are uniform over a projector pixel (sigma 1 / sqrt 12): at about one camera pixel
    per projector pixel the code of camera 1's pixel is as far off as camera 2's fitted position
    averages away, and the match is no better than the plain decode's; the plane through 25 of
    them is a few times better.

    Args:
        pixel: (n,) linear pixel index y * width + x of each sample (one sample per pixel).
        proj: (n, 2) projector coordinates (u_p, v_p).
        sigma_uv: (n, 2) their standard deviations (projector px).
        width, height: the camera's size.
        radius: the window's half width (px).

    Returns:
        (proj, sigma_uv, refined): the coordinates and sigmas with the integer ones refined (the
        sigma of the plane at the pixel, scaled by the window's scatter where that is larger), and
        (n, 2) bool: which coordinates were.
    """
    proj = np.asarray(proj, np.float64)
    sigma_uv = np.asarray(sigma_uv, np.float64)
    out_p, out_s = proj.copy(), sigma_uv.copy()
    refined = np.zeros(proj.shape, bool)
    n = proj.shape[0]
    if n == 0:
        return out_p, out_s, refined
    pixel = np.asarray(pixel, np.int64)
    r = int(radius)
    for axis in (0, 1):
        val = proj[:, axis]
        integer = np.abs(val - np.round(val)) < INTEGER_TOLERANCE_PX
        if not integer.any():
            continue
        weight = 1.0 / np.maximum(sigma_uv[:, axis], 1e-3) ** 2
        sel = np.flatnonzero(integer)
        # weighted moments of each window about its centre pixel, the coordinate as an offset from the
        # centre's own code p0 (sums of w (p - p0), w dx (p - p0), ...)
        (S, Sx, Sy, Sxx, Sxy, Syy, wP, wPx, wPy, wPP, cnt), p0, at = _window_moments(pixel, val, weight, sel, width,
                                                                                      height, r)
        Sp, Sxp, Syp = wP - p0 * S, wPx - p0 * Sx, wPy - p0 * Sy
        Spp = wPP - 2 * p0 * wP + p0 * p0 * S
        # the 3x3 normal equations [S Sx Sy; Sx Sxx Sxy; Sy Sxy Syy] beta = (Sp, Sxp, Syp), by cofactors
        c00, c01, c02 = Sxx * Syy - Sxy * Sxy, Sxy * Sy - Sx * Syy, Sx * Sxy - Sxx * Sy
        c11, c12, c22 = S * Syy - Sy * Sy, Sx * Sy - S * Sxy, S * Sxx - Sx * Sx
        det = S * c00 + Sx * c01 + Sy * c02
        good = (cnt >= QUERY_MIN_PIXELS) & (det > 1e-9 * np.maximum(S, 1e-30) * np.maximum(c00, 1e-30))
        inv_det = np.where(good, 1.0 / np.where(good, det, 1.0), 0.0)
        b0 = (c00 * Sp + c01 * Sxp + c02 * Syp) * inv_det  # the plane at the centre (offset from p0)
        b1 = (c01 * Sp + c11 * Sxp + c12 * Syp) * inv_det
        b2 = (c02 * Sp + c12 * Sxp + c22 * Syp) * inv_det
        chi2 = np.maximum(Spp - (b0 * Sp + b1 * Sxp + b2 * Syp), 0.0)
        dof = np.maximum(cnt - 3, 1)
        good &= chi2 <= QUERY_FIT_CHI2 * dof
        keep = good[at]
        g, at = sel[keep], at[keep]
        out_p[g, axis] = val[g] + b0[at]
        out_s[g, axis] = np.sqrt(c00[at] * inv_det[at] * np.maximum(1.0, chi2[at] / dof[at]))
        refined[g, axis] = True
    return out_p, out_s, refined


def _window_moments(pixel: np.ndarray, val: np.ndarray, weight: np.ndarray, sel: np.ndarray, width: int,
                    height: int, r: int) -> tuple[tuple, np.ndarray, np.ndarray]:
    """The 11 window sums of :func:`refine_integer_codes` for the samples ``sel`` (their centres' codes p0,
    and each one's index into the sums): at their own pixels where they are few (a kernel reads each
    window's samples through the pixels' sample index), else at every pixel by the image's filters."""
    at = pixel[sel]
    if at.size * (2 * r + 1) ** 2 < height * width:
        sample_of = np.full(height * width, -1, np.int32)
        sample_of[pixel] = np.arange(pixel.size, dtype=np.int32)
        sums = window_sums(wp.array(at.astype(np.int32), dtype=wp.int32, device="cpu"),
                           wp.array(sample_of, dtype=wp.int32, device="cpu", copy=False), _cpu(val, wp.float64),
                           _cpu(weight, wp.float64), width=width, height=height, radius=r).numpy()
        return tuple(sums), val[sel], np.arange(at.size)
    w = np.zeros((height, width))
    w.flat[pixel] = weight
    p0 = np.zeros(height * width)
    p0[pixel] = val
    return _windows_all(w, p0, width, height, r), p0, at


def _windows_all(w: np.ndarray, p: np.ndarray, width: int, height: int, r: int) -> tuple:
    """The window sums of :func:`refine_integer_codes` at every pixel, as ``kernels.stereo_support.window_sums`` gives
    them at a few: (S, Sx, Sy, Sxx, Sxy, Syy, sum w p, sum w p dx, sum w p dy, sum w p^2, count of pixels
    with w > 0), each (height * width,), separable filters over the (height, width) weights ``w`` and
    the raveled coordinates ``p``."""
    import cv2

    off = np.arange(-r, r + 1, dtype=np.float64)  # a window pixel's offset from its centre, along x or y
    one = np.ones_like(off)
    kernels = {"1": (one, one), "x": (off, one), "y": (one, off), "xx": (off * off, one), "xy": (off, off),
               "yy": (one, off * off)}

    def window(a, k):  # each pixel's window sum of a times the offsets' powers (separable), raveled
        kx, ky = kernels[k]
        return cv2.sepFilter2D(a, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT).ravel()

    wp_ = w * p.reshape(height, width)
    S, Sx, Sy = (window(w, k) for k in ("1", "x", "y"))
    Sxx, Sxy, Syy = (window(w, k) for k in ("xx", "xy", "yy"))
    wP, wPx, wPy = (window(wp_, k) for k in ("1", "x", "y"))
    wPP = window(wp_ * p.reshape(height, width), "1")
    cnt = window((w > 0).astype(np.float64), "1")
    return S, Sx, Sy, Sxx, Sxy, Syy, wP, wPx, wPy, wPP, cnt


@dataclass
class DeviceMatches:
    """Camera 1's samples with a camera-2 match, as Warp arrays (n matches) on the samples' device:
    what :func:`match_on_device` hands the two-camera triangulation without a host round trip."""

    index: wp.array
    """(n,) int32 each match's sample in camera 1."""
    uv1: wp.array
    """(n,) vec2 camera-1 pixels as observed (distorted)."""
    uv2: wp.array
    """(n,) vec2 camera-2 pixels where camera 2's projector coordinate equals camera 1's."""
    sigma1: wp.array
    """(n,) float32 predicted standard deviation of uv1 (px, per axis)."""
    sigma2: wp.array
    """(n,) float32 predicted standard deviation of uv2 (px, per axis)."""
    proj: wp.array
    """(n,) vec2 projector pixels (u_p, v_p) decoded by camera 1."""
    sigma_rho: wp.array
    """(n,) float32 proj's standard deviation along its radius about the pattern centre (projector px)."""
    sigma_tan: wp.array
    """(n,) float32 proj's across its radius (projector px)."""
    proj_map: wp.array | None = None
    """(n,) vec4 how uv2 moves with proj (the matcher's local map, row-major 2x2, camera-2 px per projector
    px: ``kernels.stereo_match.Matches.proj_map``): uv2 carries proj's error through it."""
    query_model: wp.array | None = None
    """(n,) float32 sigma1's second term alone (camera-2 px): what proj carries beyond sigma_rho and sigma_tan,
    isotropic (the query's share of its neighbourhood's scatter about the map, ``Matches.query_model``)."""
    gain: wp.array | None = None
    """(n,) float32 the map's camera-2 px per projector px (``Matches.gain``)."""
    stats: dict = field(default_factory=dict)
    """As :class:`StereoMatches`' ``stats``."""

    def __len__(self) -> int:
        return self.index.shape[0]


def match_on_device(scan: Scan, samples1: Samples, samples2: Samples, *,
                    settings: ReconstructSettings = ReconstructSettings(), maps: bool = True,
                    threads: int | None = None) -> tuple[DeviceMatches, tuple | None]:
    """Match camera 1's samples to camera 2's by equal projector coordinate
    (``kernels.stereo_match.match_by_projector``; the rig's extrinsics are not used), the matches
    compacted and gathered on the samples' device (the statuses counted there). Camera 1's integer
    codes of a dense map (an imported Gray code that kept them) are first read from their
    neighbourhood (:func:`refine_integer_codes`, on the host).

    ``maps``: gather what three rays read (``proj_map``, ``query_model``, ``gain``; None without).

    Returns:
        (matches, refined): ``refined`` None, or where the refinement changed camera 1's codes
        (proj1 (n1,) vec2d, sigma_rho (n1,), sigma_tan (n1,) float64 Warp arrays on the device), as
        refined (the matches hold them in float32).
    """
    p1, s1 = _coordinates(scan, samples1, "camera 1")
    p2, s2 = _coordinates(scan, samples2, "camera 2")
    light = scan.rig.light
    center = scan.patterns.center
    threads = threads or cpu_threads()
    host = None
    sr_dev, st_dev = samples1.sigma_rho, samples1.sigma_tan
    n_refined = 0
    if samples1.ring is None and len(samples1):  # one sample per pixel: a dense map
        cam = scan.rig.camera
        ref = refine_codes(p1, samples1.sigma_rho, samples1.sigma_tan, samples1.pixel, center=center, width=cam.width,
                           height=cam.height, settings=_refine_settings(), threads=threads)
        if ref is not None:
            n_refined = ref["count"]
            host = (ref["proj64"], ref["sigma_rho64"], ref["sigma_tan64"])
            p1, s1, sr_dev, st_dev = ref["proj"], ref["sigma"], ref["sigma_rho"], ref["sigma_tan"]
    M = match_by_projector(p1, s1, p2, samples2.uv, s2, projector_size=(light.width, light.height),
                           settings=settings.stereo.match, maps=maps, threads=threads)
    ok = compact_points(M.status)  # the matched samples (status 0), in order
    counts = count_values(M.status, len(MATCH_STATUS_NAMES), threads=threads)
    stats = {"samples_camera1": int(len(samples1)), "samples_camera2": int(len(samples2)), "matches": int(len(ok)),
             "unmatched": {name: int(counts[i]) for i, name in enumerate(MATCH_STATUS_NAMES) if i > 0}}
    if n_refined:
        stats["integer_codes_refined"] = n_refined
    g = partial(gather, index=ok, threads=threads)
    three = {"proj_map": g(M.proj_map), "query_model": g(M.query_model), "gain": g(M.gain)} if maps else {}
    return (DeviceMatches(index=ok, uv1=g(samples1.uv), uv2=g(M.uv2), sigma1=g(M.sigma1), sigma2=g(M.sigma2),
                          proj=g(p1), sigma_rho=g(sr_dev), sigma_tan=g(st_dev), stats=stats, **three), host)


def match_samples(scan: Scan, samples1: Samples, samples2: Samples, *,
                  settings: ReconstructSettings = ReconstructSettings(), threads: int | None = None) -> StereoMatches:
    """Match camera 1's samples to camera 2's by equal projector coordinate
    (:func:`match_on_device`), read to the host as :class:`StereoMatches`."""
    m, refined = match_on_device(scan, samples1, samples2, settings=settings, threads=threads)
    ok = m.index.numpy().astype(np.int64)
    center = scan.patterns.center
    if refined is not None:  # refined integer codes: their float64 coordinates and sigmas, as refined
        proj, sr, st = (a.numpy()[ok] for a in refined)
    else:
        proj = m.proj.numpy().astype(np.float64)
        sr, st = m.sigma_rho.numpy().astype(np.float64), m.sigma_tan.numpy().astype(np.float64)
    return StereoMatches(uv1=m.uv1.numpy().astype(np.float64), uv2=m.uv2.numpy().astype(np.float64), proj=proj,
                         sigma1=m.sigma1.numpy().astype(np.float64), sigma2=m.sigma2.numpy().astype(np.float64),
                         sigma_proj=_polar_to_uv(proj, sr, st, center), sigma_rho=sr, sigma_tan=st, index=ok,
                         stats=m.stats)


def match_view(scan: Scan, view: View, *, settings: ReconstructSettings = ReconstructSettings(),
               device: str | None = None) -> StereoMatches:
    """Decode both cameras of a two-camera view with the scan's codec and match
    camera 1's samples to camera 2 by equal projector coordinate.

    Args:
        scan: a loaded scan whose rig has ``camera2``.
        view: one of ``scan.views`` with ``camera2`` frames.
        settings: the decode stages' settings and ``stereo.match``.
        device: Warp device (None: the best available).

    Raises:
        FormatError: a one-camera view or rig, or a codec without the polar angle.
    """
    if scan.rig.camera2 is None or view.camera2 is None:
        raise FormatError(scan.path, f"view {view.name}: not a two-camera view (the rig needs camera2 and the "
                                     "view camera 2's frames)")
    init_warp()
    device = resolve_device(device)
    threads = settings.threads or cpu_threads()
    samples1, _, _ = decode_view(scan, view, settings=settings, device=device, threads=threads)
    s2 = as_camera2(scan)
    samples2, _, _ = decode_view(s2, view.camera2, settings=settings, device=device, threads=threads)
    return match_samples(scan, samples1, samples2, settings=settings, threads=threads)


def _epipolar_geometry(rig: Rig) -> dict:
    """The two cameras' models, the essential matrix (unit baseline) and camera 2's px per normalised unit:
    the keywords of ``kernels.stereo_support``'s epipolar kernels."""
    c1, c2 = rig.camera, rig.camera2
    if c2 is None:
        raise ValueError("epipolar_distances: the rig has one camera")
    R = c2.R @ c1.R.T
    t = c2.t - R @ c1.t
    t = t / max(np.linalg.norm(t), 1e-300)  # the line's scale cancels: a unit baseline keeps float32 in range
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return dict(camera1=make_camera(c1.K, c1.dist, c1.R, c1.t), camera2=make_camera(c2.K, c2.dist, c2.R, c2.t),
                E=tx @ R, scale=float(np.sqrt(c2.K[0, 0] * c2.K[1, 1])))


def _epipolar_device(rig: Rig, w1: wp.array, w2: wp.array, threads: int | None) -> wp.array:
    """(n,) float32 on w1's device: :func:`epipolar_distances` of (n,) vec2 Warp arrays."""
    return kernel_epipolar_distances(w1, w2, **_epipolar_geometry(rig), threads=threads)


def match_error_model(rig: Rig, matches: DeviceMatches, *, floor: bool = True, max_distance_px: float = np.inf,
                      threads: int | None = None) -> dict:
    """What the matches' predicted sigmas miss, measured by their own distances from their epipolar lines
    (``error_scale.fit_match_model``, on at most ``error_scale.MAX_CHECK_SAMPLES`` matches spread over the
    view: their distances and slopes computed on the device, read once): {} with too few matches, else
    the fit ({k, floor_px, miss_px, pairs, z_median, beyond_3, z_median_fitted, beyond_3_fitted, regions}),
    whose k, floor_px and regions :func:`widen_matches` applies (``floor`` False: k alone; ``max_distance_px``:
    matches farther from their lines left out, as ``fit_match_model`` takes them)."""
    n = len(matches)
    if n == 0 or rig.camera2 is None:
        return {}
    dev = matches.uv1.device
    pick = wp.array(sample_subset(n).astype(np.int32), dtype=wp.int32, device=dev)
    g = partial(gather, index=pick, threads=threads)
    uv1, uv2 = g(matches.uv1), g(matches.uv2)
    dist, slope2 = epipolar_slopes(uv1, uv2, **_epipolar_geometry(rig), threads=threads)
    return fit_match_model(dist.numpy(), slope2.numpy(), g(matches.sigma1).numpy(), g(matches.sigma2).numpy(),
                           uv1.numpy(), floor=floor, max_distance_px=max_distance_px)


def widen_matches(matches: DeviceMatches, model: dict, *, projector: bool = False,
                  threads: int | None = None) -> DeviceMatches:
    """The matches with both cameras' sigmas sqrt(k^2 s^2 + floor^2) (:func:`match_error_model`'s fit; times the
    square root of its region's factor where camera 1's pixel lies in a tile the fit widened), and with
    ``projector`` the query's projector point's alike (the third ray's: ``sigma_rho`` and ``sigma_tan`` k times
    theirs, ``query_model`` as the cameras', the floor in camera px, which the third ray reads over the gain); the
    same matches where the fit is empty or changes nothing; on their device."""
    regions = model.get("regions") if model else None
    if not model or (model["k"] <= 1.0 and model["floor_px"] <= 0.0 and not (regions and regions.get("scales"))):
        return matches
    tiles = dict(uv=matches.uv1, regions=regions) if regions and regions.get("scales") else {}
    widen = partial(widen_sigmas, k=model["k"], floor=model["floor_px"], threads=threads, **tiles)
    out = replace(matches, sigma1=widen(matches.sigma1), sigma2=widen(matches.sigma2))
    if projector:
        scale = partial(widen_sigmas, k=model["k"], floor=0.0, threads=threads, **tiles)
        out = replace(out, sigma_rho=scale(matches.sigma_rho), sigma_tan=scale(matches.sigma_tan),
                      query_model=None if matches.query_model is None else widen(matches.query_model))
    return out


def epipolar_distances(rig: Rig, uv1: np.ndarray, uv2: np.ndarray, *, threads: int | None = None) -> np.ndarray:
    """(n,) distance (camera-2 px) of each uv2 from the epipolar line of its uv1
    under the rig's two cameras (lens distortion undone; NaN where a pixel has no
    undistorted point): what a rig that fits its images keeps near the matches' noise.
    One Warp kernel (``kernels.stereo_support.epipolar_distances``, float32: within 1e-3 px of
    the float64 arithmetic); ``uv1``, ``uv2`` NumPy (n, 2) or (n,) vec2 Warp arrays."""
    if rig.camera2 is None:
        raise ValueError("epipolar_distances: the rig has one camera")
    init_warp()
    w1, w2 = (a if isinstance(a, wp.array) else
              wp.array(np.ascontiguousarray(np.asarray(a, np.float64).reshape(-1, 2), np.float32), dtype=wp.vec2,
                       device="cpu") for a in (uv1, uv2))
    if w1.shape[0] == 0:
        return np.zeros(0)
    return _epipolar_device(rig, w1, w2, threads).numpy().astype(np.float64)


def epipolar_check(rig: Rig, matches, *, uv: tuple[wp.array, wp.array] | None = None) -> dict:
    """The calibration check of a two-camera view: the epipolar distance of its
    matches (px), median and p95, and whether it warns (median above ``EPIPOLAR_WARN_PX``); on the
    device, of at most ``EPIPOLAR_CHECK_MATCHES`` of them (an even stride).
    ``uv``: the matches' uv1, uv2 as (n,) vec2 Warp arrays where the caller has them: the distances
    and their percentiles are then taken on their device (four values read)."""
    if uv is not None:
        n = uv[0].shape[0]
        if n == 0:
            return {}
        u1, u2 = uv
        if n > EPIPOLAR_CHECK_MATCHES:
            every = -(-n // EPIPOLAR_CHECK_MATCHES)
            idx = wp.array(np.arange(0, n, every, dtype=np.int32), device=u1.device)
            u1, u2 = gather(u1, idx), gather(u2, idx)
        (med, p95), count = percentiles(_epipolar_device(rig, u1, u2, None), [50, 95])
    else:
        d = epipolar_distances(rig, matches.uv1, matches.uv2)
        d = d[np.isfinite(d)]
        count = int(d.size)
        if count:
            med, p95 = (float(x) for x in np.percentile(d, [50, 95]))  # one partition for both
    if count == 0:
        return {}
    return {"kind": "epipolar", "matches": int(count), "epipolar_px_median": med,
            "epipolar_px_p95": p95, "fits": bool(med <= EPIPOLAR_WARN_PX)}
