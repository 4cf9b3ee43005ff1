"""Pattern codecs (DESIGN §5): projector frames (:mod:`.render`), the samples type
(:mod:`.samples`), and each codec's decode + sampling stage (:mod:`.gray_rings`,
:mod:`.phase_rings`, :mod:`.single_shot`), looked up in :mod:`.registry`."""
