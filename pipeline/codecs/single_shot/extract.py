"""The ``reconstruct`` hook of the single-shot ``rings`` codec: line detection
(kernels) + labelling (:mod:`.labeller`) -> samples for triangulation.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import warp as wp

from ringscan.kernels.ring_lines import centre_sigmas, detect_ring_lines
from ringscan.kernels.samples import Samples
from ringscan.pipeline.codecs.single_shot.labeller import label_ring_lines
from ringscan.pipeline.codecs.single_shot.settings import SECTOR_BITS, SingleShotSettings
from ringscan.pipeline.formats.scan import Scan

log = logging.getLogger(__name__)

__all__ = ["extract_rings"]


def extract_rings(frames: wp.array, scan: Scan, settings: SingleShotSettings,
                  threads: int) -> tuple[Samples, dict]:
    """Decode + sampling of one view of a ``rings`` scan (``codecs.rings.RingsCodec``).

    Args:
        frames: (1, H, W) uint8/uint16 Warp stack (the ``rings`` frame).
        scan: the :class:`~ringscan.pipeline.formats.scan.Scan`.
        settings: line detection and labelling settings.
        threads: CPU threads for the row-run kernels.

    Returns:
        (:class:`~ringscan.kernels.samples.Samples` of the labelled samples in raster
        order, stats with pixels_decoded, samples, the labelling counts and times_s
        {"decode": line detection, which reads the frame, "sample": labelling,
        which makes the samples, as in the other codecs}). ``sector`` holds the
        sector (``SECTOR_BITS`` bits) of the root that the orientation rule
        chose, -1 where it does not decide; stats["sector_bits"] says so.
    """

    spec = scan.patterns
    if spec.codec != "rings":
        raise ValueError(f"extract_rings: codec {spec.codec!r} is not 'rings'")
    if not isinstance(frames, wp.array) or frames.ndim != 3 or frames.shape[0] < 1:
        raise ValueError("extract_rings: frames must be a (1, H, W) Warp array")
    if not isinstance(settings, SingleShotSettings):
        raise ValueError(f"extract_rings: settings must be SingleShotSettings, got {type(settings).__name__}")
    ss = settings
    dev = frames.device
    t0 = time.perf_counter()
    lines = detect_ring_lines(frames, frame=0, settings=ss.lines, threads=threads)
    d = lines.numpy()
    t1 = time.perf_counter()
    lab = label_ring_lines(d["uv"], d["normal"], d["pixel"], lines.smoothed, contrast=d["contrast"], rig=scan.rig,
                           patterns=spec, settings=ss)
    keep = np.nonzero(lab.ring >= 0)[0]
    ring = lab.ring[keep]
    n_sec = 2 ** SECTOR_BITS
    phi = lab.phi[keep].astype(np.float64)
    sector = np.where(np.isfinite(phi), np.floor((np.nan_to_num(phi) + np.pi) / (2 * np.pi) * n_sec), -1)
    sector = np.clip(sector, -1, n_sec - 1).astype(np.int32)
    rho = (spec.rho0 + spec.pitch * ring).astype(np.float32)
    # each centre's error lies across its line, in the camera: triangulation states it in projector px;
    # along the normal the labeller linked the next lines by (their depths give the surface's slope)
    normal = lab.normal if lab.normal is not None else d["normal"]
    sigma_uv = normal[keep] * centre_sigmas(d["curvature"][keep], sigma=ss.lines.sigma)[:, None]
    kept_at = np.full(len(d["uv"]) + 1, -1, np.int64)
    kept_at[keep] = np.arange(keep.size)
    if lab.across is not None:
        across = kept_at[np.where(lab.across[keep] >= 0, lab.across[keep], len(d["uv"]))]
        across_px = np.where(across >= 0, lab.gap[keep], 0.0)
    else:
        across, across_px = np.full((keep.size, 2), -1), np.zeros((keep.size, 2))
    samples = Samples(
        uv=wp.array(d["uv"][keep], dtype=wp.vec2, device=dev),
        rho=wp.array(rho, dtype=wp.float32, device=dev),
        ring=wp.array(ring, dtype=wp.int32, device=dev),
        sector=wp.array(sector, dtype=wp.int32, device=dev),
        confidence=wp.array(d["confidence"][keep], dtype=wp.float32, device=dev),
        pixel=wp.array(d["pixel"][keep], dtype=wp.int32, device=dev),
        sigma_uv=wp.array(sigma_uv.astype(np.float32), dtype=wp.vec2, device=dev),
        across=wp.array(across.astype(np.int32), dtype=wp.vec2i, device=dev),
        across_px=wp.array(across_px.astype(np.float32), dtype=wp.vec2, device=dev),
        bias_uv=wp.array(_line_bias(d, lab.gap)[keep], dtype=wp.float32, device=dev),
    )
    wp.synchronize_device(dev)
    t2 = time.perf_counter()
    stats = {"pixels_decoded": int(keep.size), "samples": int(keep.size), "line_samples": len(lines),
             "sector_bits": SECTOR_BITS, **lab.stats, "times_s": {"decode": t1 - t0, "sample": t2 - t1}}
    log.info("rings: %d line centres, %d pieces, %d labelled (%d dropped), %d samples", len(lines),
             lab.stats["pieces"], lab.stats["pieces_labelled"], lab.stats["pieces_dropped"], keep.size)
    if "object_unlabelled" in lab.stats:
        log.warning("rings (%s): %s", scan.folder, lab.stats["object_unlabelled"])
    return samples, stats


def _line_bias(d: dict, gap) -> np.ndarray:
    """(n,) float32 camera px: how far each centre may sit off its line by what its neighbours along
    the line share: the light's gradient (``RingLines.shading``) and the image's scale changing across
    the line (a surface turning away: the lines on either side at unequal gaps, d ln(gap) / dn, times
    the profile's variance, its height over its curvature), in quadrature."""
    b = d["shading"].astype(np.float64)
    if gap is None:
        return b.astype(np.float32)
    g0, g1 = gap[:, 0].astype(np.float64), gap[:, 1].astype(np.float64)
    both = (g0 > 0) & (g1 > 0)
    grad = np.zeros_like(b)
    grad[both] = np.abs(np.log(g0[both] / g1[both])) / (0.5 * (g0[both] + g1[both]))
    var = d["contrast"].astype(np.float64) / np.maximum(d["curvature"].astype(np.float64), 1e-6)
    return np.sqrt(b * b + (grad * var) ** 2).astype(np.float32)
