"""ringscan.hardware.emulators."""
