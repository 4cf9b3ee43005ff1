"""ringscan.tools."""
