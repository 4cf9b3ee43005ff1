"""Pattern codecs (docs/design.md §7): one module per codec (:mod:`.gray_rings`,
:mod:`.phase_rings`, :mod:`.rings`, :mod:`.decoded`), each a :class:`.base.Codec`
(render, extract, explain), looked up by name in :mod:`.registry`; projector frames
through :mod:`.render`.

This package module itself loads nothing (no Warp, no kernels): the names every
layer above may ask for without loading a codec live here."""

__all__ = ["DEFAULT_CODEC"]

DEFAULT_CODEC = "gray-rings"
"""The codec of the default pattern set (``ringscan patterns``/``simulate`` without
``--codec``, the demo, the Python API's ``simulate``, a conditioning map of a rig
file): Gray-coded ring bands with sectors and the angle code (docs/dense.md, "How sharp")."""
