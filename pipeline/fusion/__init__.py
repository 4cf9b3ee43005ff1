"""ringscan.pipeline.fusion."""
