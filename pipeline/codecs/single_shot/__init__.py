"""ringscan.pipeline.codecs.single_shot."""
