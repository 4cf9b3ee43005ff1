"""Calibration boards: chessboard and ChArUco detection, and why a view was rejected.

A view is one image of the board. :func:`detect_board` finds the inner corners to
sub-pixel precision and says why it refused a view:

- ``not found``: OpenCV found no (complete) board;
- ``blurred``: the board's edges are wider than ``BoardSettings.max_edge_width_px``
  (``cv2.estimateChessboardSharpness``; chessboards only);
- ``too oblique``: the board plane is tilted more than ``max_tilt_deg`` from the
  view direction (estimated with a nominal focal length of max(W, H) px: a board
  seen that obliquely pins the focal length badly and its corners are elongated).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Board", "BoardSettings", "BoardView", "detect_board", "board_points", "ARUCO_DICTIONARIES"]

log = logging.getLogger(__name__)

ARUCO_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_5X5_50", "DICT_5X5_100", "DICT_5X5_250",
                      "DICT_6X6_50", "DICT_6X6_250", "DICT_7X7_50", "DICT_ARUCO_ORIGINAL")
"""ArUco dictionaries accepted for ChArUco boards."""


MIN_SQUARE_MM = 0.01
"""Smallest board square accepted (mm): a typo guard, like the largest."""
MAX_SQUARE_MM = 10000.0
"""Largest board square accepted (mm): 10 m (1e308 made OpenCV fail deep inside)."""

MAX_EDGE_WIDTH_MEASURED = 9999.0
"""What ``cv2.estimateChessboardSharpness`` returns when it cannot measure an edge."""


@dataclass(frozen=True)
class Board:
    """A planar calibration board."""

    cols: int
    """Inner corners per row (a 9x7 chessboard has 10 x 8 squares)."""
    rows: int
    """Inner corners per column."""
    square: float
    """Square size in the rig's units (mm)."""
    charuco: str | None = None
    """ArUco dictionary name of a ChArUco board (None: a plain chessboard)."""
    marker: float = 0.0
    """ChArUco marker size (same units; 0: 0.75 * square)."""

    def __post_init__(self):
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"board: need at least 2x2 inner corners, got {self.cols}x{self.rows}")
        if not (MIN_SQUARE_MM <= self.square <= MAX_SQUARE_MM):  # NaN fails too
            raise ValueError(f"board: square size must be a number of mm from {MIN_SQUARE_MM:g} to {MAX_SQUARE_MM:g}, "
                             f"got {self.square:g}")
        if not (0 <= self.marker < self.square):
            raise ValueError(f"board: marker size must be from 0 (0.75 x square) to below the square size "
                             f"{self.square:g}, got {self.marker:g}")
        if self.charuco is not None and self.charuco not in ARUCO_DICTIONARIES:
            raise ValueError(f"board: unknown ArUco dictionary {self.charuco!r} (known: {', '.join(ARUCO_DICTIONARIES)})")

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows


@dataclass(frozen=True)
class BoardSettings:
    """Detection settings."""

    max_edge_width_px: float = 6.0
    """A chessboard whose average edge (10 %..90 % rise) is wider than this is blurred."""
    max_tilt_deg: float = 70.0
    """A board tilted more than this from the view direction is too oblique."""
    min_charuco_corners: int = 12
    """Fewest ChArUco corners a view must show."""


@dataclass
class BoardView:
    """The outcome of detecting a board in one image."""

    name: str
    """The image's name (file name)."""
    found: bool
    """True when the view is usable."""
    reason: str
    """Why the view was rejected ('' when found)."""
    corners: np.ndarray | None
    """(n, 2) float32 sub-pixel corner positions (None when not found)."""
    ids: np.ndarray | None
    """(n,) int32 corner indices into :func:`board_points` (row-major)."""
    sharpness: float = float("nan")
    """Average edge width in px (chessboards), NaN where not measured."""
    tilt_deg: float = float("nan")
    """Estimated board tilt from the view direction (degrees)."""


def board_points(board: Board) -> np.ndarray:
    """(cols*rows, 3) float32 board-frame corner positions (z = 0), row-major."""
    g = np.mgrid[0:board.cols, 0:board.rows].T.reshape(-1, 2).astype(np.float32)
    return np.concatenate([g * board.square, np.zeros((g.shape[0], 1), np.float32)], 1)


def _tilt_deg(board: Board, corners: np.ndarray, ids: np.ndarray, size: tuple[int, int]) -> float:
    w, h = size
    f = float(max(w, h))
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    obj = board_points(board)[ids]
    ok, rvec, tvec = cv2.solvePnP(obj, corners.reshape(-1, 1, 2).astype(np.float64), K, None)
    if not ok:
        return float("nan")
    R, _ = cv2.Rodrigues(rvec)
    n = R[:, 2]
    centre = R @ obj.mean(0) + tvec.ravel()
    cosang = abs(float(n @ centre)) / float(np.linalg.norm(centre))
    return math.degrees(math.acos(min(1.0, cosang)))


def _charuco_detector(board: Board):
    aruco = cv2.aruco
    d = aruco.getPredefinedDictionary(getattr(aruco, board.charuco))
    marker = board.marker or 0.75 * board.square
    b = aruco.CharucoBoard((board.cols + 1, board.rows + 1), board.square, marker, d)
    return aruco.CharucoDetector(b)


def detect_board(
    image: np.ndarray,
    *,
    board: Board,
    name: str = "",
    settings: BoardSettings = BoardSettings(),
) -> BoardView:
    """Find the board's inner corners in one grey image.

    Args:
        image: (H, W) uint8 or uint16 grey image.
        board: the board.
        name: the image's name, for messages.
        settings: detection thresholds.

    Returns:
        A :class:`BoardView`; ``found`` is False with a ``reason`` for a rejected view.
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"detect_board: image must be (H, W) uint8 or uint16, got {img.shape} {img.dtype}")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    size = (img.shape[1], img.shape[0])
    sharp = float("nan")
    if board.charuco is None:
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        ok, corners = cv2.findChessboardCornersSB(img, (board.cols, board.rows), flags=flags)
        if not ok:
            ok, corners = cv2.findChessboardCorners(img, (board.cols, board.rows),
                                                    flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
            if ok:
                corners = cv2.cornerSubPix(img, corners, (5, 5), (-1, -1),
                                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3))
        if not ok:
            return BoardView(name, False, "not found", None, None)
        corners = corners.reshape(-1, 2).astype(np.float32)
        ids = np.arange(board.n_corners, dtype=np.int32)
        try:
            sharp = float(cv2.estimateChessboardSharpness(img, (board.cols, board.rows), corners.reshape(-1, 1, 2))[0][0])
        except cv2.error:
            sharp = float("nan")
        if math.isfinite(sharp) and sharp >= MAX_EDGE_WIDTH_MEASURED:
            return BoardView(name, False, "blurred (OpenCV could not measure the width of the board's edges: no "
                                          "sharp edge along its squares)", None, None, float("nan"))
        if math.isfinite(sharp) and sharp > settings.max_edge_width_px:
            return BoardView(name, False, f"blurred (edges {sharp:.1f} px wide > {settings.max_edge_width_px:g})",
                             None, None, sharp)
    else:
        ch_corners, ch_ids, _, _ = _charuco_detector(board).detectBoard(img)
        n = 0 if ch_ids is None else len(ch_ids)
        if n < settings.min_charuco_corners:
            return BoardView(name, False, f"not found ({n} ChArUco corners < {settings.min_charuco_corners})",
                             None, None)
        corners = ch_corners.reshape(-1, 2).astype(np.float32)
        ids = ch_ids.ravel().astype(np.int32)
    tilt = _tilt_deg(board, corners, ids, size)
    if math.isfinite(tilt) and tilt > settings.max_tilt_deg:
        return BoardView(name, False, f"too oblique (tilted {tilt:.0f} deg > {settings.max_tilt_deg:g})", None, None,
                         sharp, tilt)
    log.debug("%s: board found (%d corners, edge width %.2f px, tilt %.0f deg)", name, len(ids), sharp, tilt)
    return BoardView(name, True, "", corners, ids, sharp, tilt)
