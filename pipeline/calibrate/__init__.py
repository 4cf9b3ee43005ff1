"""Calibration: from images of a real rig to a rig file (docs/calibration.md).

- ``board``: chessboard / ChArUco detection, and why a view was rejected;
- ``camera``: camera intrinsics from board views (OpenCV);
- ``graycode``: decoding column/row Gray-code captures to sub-pixel projector coordinates;
- ``procam``: projector calibration through local homographies (Moreno & Taubin) and stereo;
- ``response``: the projector's response curve from captured levels.
"""

from ringscan.pipeline.calibrate.errors import CalibrationError

__all__ = ["CalibrationError"]
