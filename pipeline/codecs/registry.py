"""TODO docstring (ringscan.pipeline.codecs.registry, split from ringscan.pipeline.reconstruct.scan)."""

from __future__ import annotations

import logging

import warp as wp

from ringscan.pipeline.codecs.gray_rings import _extract_gray_rings
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.scan import Scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

log = logging.getLogger(__name__)


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
