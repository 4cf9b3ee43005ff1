"""ringscan.pipeline.simulate."""
