"""ringscan.hardware."""
