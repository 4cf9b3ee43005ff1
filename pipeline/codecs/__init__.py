"""Pattern codecs (docs/design.md §7): one module per codec (:mod:`.gray_rings`,
:mod:`.phase_rings`, :mod:`.rings`, :mod:`.decoded`), each a :class:`.base.Codec`
(render, extract, explain), looked up by name in :mod:`.registry`; projector frames
through :mod:`.render`.

This package module itself loads nothing (no Warp, no kernels): the names every
layer above may ask for without loading a codec live here."""

__all__ = ["DEFAULT_CODEC", "NO_ANGLE_CODE"]

DEFAULT_CODEC = "gray-rings"
"""The codec of the default pattern set (``ringscan patterns``/``simulate`` without
``--codec``, the demo, the Python API's ``simulate``, a conditioning map of a rig
file): Gray-coded ring bands with sectors and the angle code (docs/dense.md, "How sharp")."""

NO_ANGLE_CODE = " (no angle code: patterns.angle_steps 0); record the angle code (--angle-steps > 0) or"
"""How a scan of a codec that can carry the angle code (``Codec.has_angle_code``) but
does not gets the full projector coordinate (the middle of an error message that
ends "use --rays camera-projector")."""
