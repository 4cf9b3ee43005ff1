"""The error calibration raises for input it cannot use."""

from __future__ import annotations

from ringscan.pipeline.formats.errors import RingscanError

__all__ = ["CalibrationError"]


class CalibrationError(RingscanError, ValueError):
    """Calibration input that gives no trustworthy result (no board, too few views,
    a capture of the wrong layout). The message names the files and the problem."""
