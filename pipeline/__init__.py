"""ringscan.pipeline."""
