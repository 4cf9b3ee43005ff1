"""ringscan.pipeline.evaluate."""
