"""The error calibration raises for input it cannot use."""

from __future__ import annotations

from ringscan.pipeline.formats.errors import FormatError

__all__ = ["CalibrationError"]


class CalibrationError(FormatError):
    """Calibration input that gives no trustworthy result (no board, too few views,
    a capture of the wrong layout). ``CalibrationError(path_or_None, message)``: the
    message names the files and the problem."""
