"""Codec registry: codec name -> its :class:`~ringscan.pipeline.codecs.base.Codec`.

Every codec module is imported here directly, so an import error inside one
surfaces as itself, never as "unknown codec". Adding a codec = one module under
``pipeline/codecs/`` (a ``Codec`` subclass) and one line in :data:`REGISTRY`
(its data-level ``PatternLayout`` registered in ``formats.patterns``; see
docs/architecture.md).
"""

from __future__ import annotations

import warp as wp

from ringscan.kernels.samples import Samples
from ringscan.pipeline.codecs.base import Codec, StageSettings
from ringscan.pipeline.codecs.decoded import DecodedCodec
from ringscan.pipeline.codecs.gray_rings import GrayRingsCodec
from ringscan.pipeline.codecs.phase_rings import PhaseRingsCodec
from ringscan.pipeline.codecs.rings import RingsCodec
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.scan import Scan

__all__ = ["REGISTRY", "codec_for", "extract_samples"]

REGISTRY: dict[str, Codec] = {codec.name: codec for codec in (RingsCodec(), GrayRingsCodec(), PhaseRingsCodec(),
                                                              DecodedCodec())}
"""codec name -> its codec."""


def codec_for(name: str, *, source=None) -> Codec:
    """The codec of ``name``.

    Raises:
        FormatError: no codec of that name (naming ``source``).
    """
    codec = REGISTRY.get(name)
    if codec is None:
        raise FormatError(source, f"patterns.codec: no reconstruction for codec {name!r}")
    return codec


def extract_samples(frames: wp.array, scan: Scan, settings: StageSettings, threads: int) -> tuple[Samples, dict]:
    """Run the scan's codec's decode and sampling stages on one view's frames, with
    the codec's settings picked from ``settings`` (a run's stage blocks)."""
    codec = codec_for(scan.patterns.codec, source=scan.path)
    return codec.extract(frames, scan, codec.settings_from(settings), threads=threads)
