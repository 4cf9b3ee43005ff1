"""Codec registry: codec name -> its :class:`~ringscan.pipeline.codecs.base.Codec`.

A codec's module is imported the first time its name is asked for (:func:`codec_for`), by
its full path in :data:`CODEC_CLASSES`: a run loads its own codec's kernels only (Warp
parses every kernel of a module as the module is imported: an imported capture's
reconstruct loaded the phase, ring and line decoders' too, ~0.1 s of every command), and
an import error inside a codec's module surfaces as itself, never as "unknown codec".
Adding a codec = one module under ``pipeline/codecs/`` (a ``Codec`` subclass) and one
line in :data:`CODEC_CLASSES` (its data-level ``PatternLayout`` registered in
``formats.patterns``; see docs/architecture.md).
"""

from __future__ import annotations

import importlib

import warp as wp

from ringscan.kernels.samples import Samples
from ringscan.pipeline.codecs.base import Codec, StageSettings
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.scan import Scan

__all__ = ["CODEC_CLASSES", "REGISTRY", "all_codecs", "codec_for", "extract_samples"]

CODEC_CLASSES: dict[str, str] = {
    "rings": "ringscan.pipeline.codecs.rings:RingsCodec",
    "gray-rings": "ringscan.pipeline.codecs.gray_rings:GrayRingsCodec",
    "phase-rings": "ringscan.pipeline.codecs.phase_rings:PhaseRingsCodec",
    "decoded": "ringscan.pipeline.codecs.decoded:DecodedCodec",
}
"""codec name -> ``module:class`` of its codec."""

REGISTRY: dict[str, Codec] = {}
"""The codecs loaded so far, by name (:func:`codec_for` adds each as it is first asked for; a codec defined
outside the package, as a test's, may be added here by hand)."""


def codec_for(name: str, *, source=None) -> Codec:
    """The codec of ``name`` (its module imported the first time).

    Raises:
        FormatError: no codec of that name (naming ``source``).
    """
    codec = REGISTRY.get(name)
    if codec is None:
        where = CODEC_CLASSES.get(name)
        if where is None:
            raise FormatError(source, f"patterns.codec: no reconstruction for codec {name!r}")
        module, cls = where.split(":")
        codec = REGISTRY.setdefault(name, getattr(importlib.import_module(module), cls)())
    return codec


def all_codecs() -> dict[str, Codec]:
    """Every codec by name (each module imported), in :data:`CODEC_CLASSES`' order, then any added to
    :data:`REGISTRY` by hand."""
    for name in CODEC_CLASSES:
        codec_for(name)
    return {**{name: REGISTRY[name] for name in CODEC_CLASSES}, **REGISTRY}


def extract_samples(frames: wp.array, scan: Scan, settings: StageSettings, threads: int) -> tuple[Samples, dict]:
    """Run the scan's codec's decode and sampling stages on one view's frames, with
    the codec's settings picked from ``settings`` (a run's stage blocks)."""
    codec = codec_for(scan.patterns.codec, source=scan.path)
    return codec.extract(frames, scan, codec.settings_from(settings), threads=threads)
