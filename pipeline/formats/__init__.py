"""ringscan.pipeline.formats."""
