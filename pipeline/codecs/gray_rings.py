"""TODO docstring (ringscan.pipeline.codecs.gray_rings, split from ringscan.pipeline.reconstruct.scan)."""

from __future__ import annotations

import logging
import time

import numpy as np
import warp as wp

from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.ring_sampling import ring_radii, sample_gray_rings
from ringscan.pipeline.codecs.samples import Samples
from ringscan.pipeline.formats.scan import Scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

log = logging.getLogger(__name__)


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
