"""The ``reconstruct`` hook of the single-shot ``rings`` codec: line detection
(kernels) + labelling (:mod:`.labeller`) -> samples for triangulation.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import warp as wp

from ringscan.kernels.ring_lines import detect_ring_lines
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
    samples = Samples(
        uv=wp.array(d["uv"][keep], dtype=wp.vec2, device=dev),
        rho=wp.array(rho, dtype=wp.float32, device=dev),
        ring=wp.array(ring, dtype=wp.int32, device=dev),
        sector=wp.array(sector, dtype=wp.int32, device=dev),
        confidence=wp.array(d["confidence"][keep], dtype=wp.float32, device=dev),
        pixel=wp.array(d["pixel"][keep], dtype=wp.int32, device=dev),
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
