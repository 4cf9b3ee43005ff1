"""Pattern codecs (docs/design.md §7): one module per codec (:mod:`.gray_rings`,
:mod:`.phase_rings`, :mod:`.rings`, :mod:`.decoded`), each a :class:`.base.Codec`
(render, extract, explain), looked up by name in :mod:`.registry`; projector frames
through :mod:`.render`."""
