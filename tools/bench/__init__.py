"""ringscan.tools.bench."""
