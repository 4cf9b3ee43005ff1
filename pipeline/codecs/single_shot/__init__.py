"""The paper's single-shot ``rings`` codec: line detection (kernels), pieces
(:mod:`.pieces`), the nesting labeller (:mod:`.labeller`), the reconstruct hook
(:mod:`.extract`) and its settings (:mod:`.settings`).

This package module itself loads nothing: a run that reads the codec's settings (every
reconstruct's settings do) imports :mod:`.settings` alone, not the line kernels."""
