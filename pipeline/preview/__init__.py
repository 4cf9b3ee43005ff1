"""ringscan.pipeline.preview."""
