"""ringscan.pipeline.codecs."""
