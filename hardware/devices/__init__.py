"""ringscan.hardware.devices."""
