"""The ``gray-rings`` codec (DESIGN §5): decode the band Gray code per pixel, then
sample every band boundary to sub-pixel precision where the frame that flips there
crosses its inverse (``kernels.ring_labels``, ``kernels.ring_sampling``)."""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.ring_sampling import ring_radii, sample_gray_rings
from ringscan.pipeline.codecs.samples import Samples
from ringscan.pipeline.formats.scan import Scan

__all__ = ["extract_gray_rings"]


def extract_gray_rings(frames: wp.array, scan: Scan, settings, threads: int) -> tuple[Samples, dict]:
    """Decode + sampling of one view of a ``gray-rings`` scan.

    Args:
        frames: (F, H, W) uint8/uint16 Warp stack in the order of the scan's frame names (read).
        scan: the scan (its patterns give bits, sector bits, rho0 and pitch).
        settings: the reconstruction settings; their ``decode`` and ``sample`` blocks are used.
        threads: CPU threads for the row-run kernels.

    Returns:
        (samples, stats) with stats ``pixels_decoded``, ``samples`` and ``times_s``.
    """
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
