"""Accuracy against the virtual rig's truth (:mod:`.metrics`) and the ring-count
sweep (:mod:`.sweep`)."""

from ringscan.pipeline.evaluate.metrics import evaluate_recon, evaluate_view
from ringscan.pipeline.evaluate.sweep import SweepSettings, run_sweep

__all__ = ["evaluate_recon", "evaluate_view", "SweepSettings", "run_sweep"]
