"""ringscan.pipeline.reconstruct."""
