"""Calibration: from images of a real rig to a rig file (docs/calibration.md).

- ``board``: chessboard / ChArUco detection, and why a view was rejected;
- ``camera``: camera intrinsics from board views (OpenCV);
- ``graycode``: decoding column/row Gray-code captures to sub-pixel projector coordinates;
- ``capture_files``: which files make a Gray-code capture (folders of frames, image lists);
- ``capture_reader``: a capture's frames read and sorted into white, black and pattern pairs;
- ``procam``: projector calibration through local homographies (Moreno & Taubin) and stereo;
- ``response``: the projector's response curve from captured levels;
- ``rig_refine``: a rig's extrinsics refined from a scan's own matches;
- ``scan_matches``: a scan's own matches gathered (with another rig), the extrinsics they refine;
- ``projector_fit``: a projector fitted to triangulated points and their projector pixels;
- ``opencv_files``: a rig written as OpenCV FileStorage;
- ``stereo_boards``: two cameras calibrated from board photos.
"""

from ringscan.pipeline.calibrate.errors import CalibrationError

__all__ = ["CalibrationError"]
