"""Codec registry: the decode + sampling stage of each pattern codec.

``EXTRACTORS[codec](frames, scan, settings, threads) -> (Samples, stats)``. Every
codec module is imported here directly, so an import error inside one surfaces as
itself, never as "unknown codec".
"""

from __future__ import annotations

from collections.abc import Callable

import warp as wp

from ringscan.pipeline.codecs.decoded import extract_decoded
from ringscan.pipeline.codecs.gray_rings import extract_gray_rings
from ringscan.pipeline.codecs.phase_rings import extract_phase_rings
from ringscan.pipeline.codecs.samples import Samples
from ringscan.pipeline.codecs.single_shot.extract import extract_rings
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.scan import Scan

__all__ = ["EXTRACTORS", "extract_samples"]

EXTRACTORS: dict[str, Callable[..., tuple[Samples, dict]]] = {
    "gray-rings": extract_gray_rings,
    "phase-rings": extract_phase_rings,
    "rings": extract_rings,
    "decoded": extract_decoded,
}
"""codec name -> its decode + sampling function."""


def extract_samples(frames: wp.array, scan: Scan, settings, threads: int) -> tuple[Samples, dict]:
    """Run the scan's codec's decode and sampling stages on one view's frames."""
    fn = EXTRACTORS.get(scan.patterns.codec)
    if fn is None:
        raise FormatError(scan.path, f"patterns.codec: no reconstruction for codec {scan.patterns.codec!r}")
    return fn(frames, scan, settings, threads)
