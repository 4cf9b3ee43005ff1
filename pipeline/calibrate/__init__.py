"""Calibration: from images of a real rig to a rig file (docs/calibration.md).

- ``board``: chessboard / ChArUco detection, and why a view was rejected;
- ``camera``: camera intrinsics from board views (OpenCV);
- ``graycode``: decoding column/row Gray-code captures to sub-pixel projector coordinates;
- ``procam``: projector calibration through local homographies (Moreno & Taubin) and stereo;
- ``response``: the projector's response curve from captured levels;
- ``rig_refine``: a rig's extrinsics refined from a scan's own matches;
- ``projector_fit``: a projector fitted to triangulated points and their projector pixels;
- ``opencv_files``: a rig written as OpenCV FileStorage;
- ``stereo_boards``: two cameras calibrated from board photos.
"""

from ringscan.pipeline.calibrate.errors import CalibrationError

__all__ = ["CalibrationError"]
