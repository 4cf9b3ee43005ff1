"""ringscan.hardware.capture."""
