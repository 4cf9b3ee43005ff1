"""Two cameras: camera 1's samples matched to camera 2 by equal projector
coordinate (no extrinsics used), the epipolar check of the rig against those
matches, and the two- or three-ray points (docs/reconstruction.md "Two cameras").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ringscan.kernels import init_warp, resolve_device
from ringscan.kernels.launch import cpu_threads
from ringscan.kernels.samples import Samples
from ringscan.kernels.stereo import (
    MATCH_STATUS_NAMES,
    match_by_projector,
    projector_coordinates,
)
from ringscan.pipeline.codecs.registry import codec_for
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.rig import Rig
from ringscan.pipeline.formats.scan import Scan, View, as_camera2, read_view_frames
from ringscan.pipeline.geometry import undistort_normalized
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

log = logging.getLogger(__name__)

__all__ = ["StereoMatches", "match_view", "match_samples", "decode_view", "epipolar_distances",
           "EPIPOLAR_WARN_PX"]

EPIPOLAR_WARN_PX = 1.0
"""Median epipolar distance (px) of a view's matches above which the rig file does not fit its images."""


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
    """One camera's samples of a view with the scan's codec: (samples, codec stats, frames)."""
    threads = threads or cpu_threads()
    if frames is None:
        frames = read_view_frames(scan, view, threads=threads)
    on_cpu = wp.get_device(device).is_cpu and frames.flags.c_contiguous
    frames_w = wp.array(frames, dtype=wp.uint8 if frames.dtype == np.uint8 else wp.uint16, device=device,
                        copy=not on_cpu)
    codec = codec_for(scan.patterns.codec, source=scan.path)
    samples, stats = codec.extract(frames_w, scan, codec.settings_from(settings), threads=threads)
    return samples, stats, frames


def _coordinates(scan: Scan, samples: Samples, which: str):
    if samples.phi is None or samples.sigma_rho is None or samples.sigma_tan is None or samples.rho is None:
        raise FormatError(scan.path, f"{which}: the {scan.patterns.codec} codec decodes no polar angle in this "
                                     "scan, so the two cameras cannot be matched by projector coordinate "
                                     "(record the angle code: --angle-steps > 0; or --rays camera-projector)")
    return projector_coordinates(samples.rho, samples.phi, samples.sigma_rho, samples.sigma_tan,
                                 center=scan.patterns.center)


def match_samples(scan: Scan, samples1: Samples, samples2: Samples, *,
                  settings: ReconstructSettings = ReconstructSettings(), threads: int | None = None) -> StereoMatches:
    """Match camera 1's samples to camera 2's by equal projector coordinate
    (``kernels.stereo.match_by_projector``); the rig's extrinsics are not used."""
    p1, s1 = _coordinates(scan, samples1, "camera 1")
    p2, s2 = _coordinates(scan, samples2, "camera 2")
    light = scan.rig.light
    M = match_by_projector(p1, s1, p2, samples2.uv, s2, projector_size=(light.width, light.height),
                           settings=settings.stereo.match, threads=threads)
    status = M.status.numpy()
    ok = np.flatnonzero(status == 0)
    proj = p1.numpy()[ok].astype(np.float64)
    sr = samples1.sigma_rho.numpy()[ok].astype(np.float64)
    st = samples1.sigma_tan.numpy()[ok].astype(np.float64)
    off = proj - np.asarray(scan.patterns.center, float)
    r = np.maximum(np.hypot(off[:, 0], off[:, 1]), 1e-12)
    c, s = off[:, 0] / r, off[:, 1] / r
    sigma_proj = np.stack([np.sqrt(sr ** 2 * c ** 2 + st ** 2 * s ** 2),
                           np.sqrt(sr ** 2 * s ** 2 + st ** 2 * c ** 2)], 1)
    counts = np.bincount(status, minlength=len(MATCH_STATUS_NAMES))
    stats = {"samples_camera1": int(len(samples1)), "samples_camera2": int(len(samples2)), "matches": int(ok.size),
             "unmatched": {name: int(counts[i]) for i, name in enumerate(MATCH_STATUS_NAMES) if i > 0}}
    return StereoMatches(uv1=samples1.uv.numpy()[ok].astype(np.float64), uv2=M.uv2.numpy()[ok].astype(np.float64),
                         proj=proj, sigma1=M.sigma1.numpy()[ok].astype(np.float64),
                         sigma2=M.sigma2.numpy()[ok].astype(np.float64), sigma_proj=sigma_proj, sigma_rho=sr,
                         sigma_tan=st, index=ok.astype(np.int64), stats=stats)


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


def epipolar_distances(rig: Rig, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """(n,) distance (camera-2 px) of each uv2 from the epipolar line of its uv1
    under the rig's two cameras (lens distortion undone; NaN where a pixel has no
    undistorted point): what a rig that fits its images keeps near the matches' noise."""
    c1, c2 = rig.camera, rig.camera2
    if c2 is None:
        raise ValueError("epipolar_distances: the rig has one camera")
    uv1 = np.asarray(uv1, np.float64).reshape(-1, 2)
    uv2 = np.asarray(uv2, np.float64).reshape(-1, 2)
    if uv1.shape[0] == 0:
        return np.zeros(0)
    x1 = np.stack([*undistort_normalized(c1, uv1[:, 0], uv1[:, 1]), np.ones(len(uv1))], 1)
    x2 = np.stack([*undistort_normalized(c2, uv2[:, 0], uv2[:, 1]), np.ones(len(uv2))], 1)
    R = c2.R @ c1.R.T
    t = c2.t - R @ c1.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    line = x1 @ (tx @ R).T  # E x1, in camera 2's normalised plane
    d = np.abs(np.sum(line * x2, axis=1)) / np.hypot(line[:, 0], line[:, 1])
    return d * np.sqrt(c2.K[0, 0] * c2.K[1, 1])


def epipolar_check(rig: Rig, matches: StereoMatches) -> dict:
    """The calibration check of a two-camera view: the epipolar distance of its
    matches (px), median and p95, and whether it warns (median above ``EPIPOLAR_WARN_PX``)."""
    d = epipolar_distances(rig, matches.uv1, matches.uv2)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {}
    med = float(np.median(d))
    return {"kind": "epipolar", "matches": int(d.size), "epipolar_px_median": med,
            "epipolar_px_p95": float(np.percentile(d, 95)), "fits": bool(med <= EPIPOLAR_WARN_PX)}
