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
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.progress import progress_bar

__all__ = ["Board", "BoardSettings", "BoardView", "detect_board", "board_points", "ARUCO_DICTIONARIES",
           "charuco_dictionary", "corner_id_problem", "detect_board_images", "view_name"]

log = logging.getLogger(__name__)

ARUCO_DICTIONARIES = tuple(
    n for n in (*(f"DICT_{k}X{k}_{m}" for k in (4, 5, 6, 7) for m in (50, 100, 250, 1000)), "DICT_ARUCO_ORIGINAL",
                "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h10", "DICT_APRILTAG_36h11",
                "DICT_ARUCO_MIP_36h12")
    if isinstance(getattr(cv2.aruco, n, None), int))
"""ArUco dictionaries accepted for ChArUco boards: every predefined dictionary of OpenCV
(``cv::aruco::PredefinedDictionaryType``) this OpenCV has."""

ID_FIT_SQUARES = 0.3
"""A ChArUco corner whose detected position lies farther than this many squares from where its board
neighbours place it (a local affine map of their board positions) has an id that does not fit the board."""


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
    legacy: bool = False
    """A ChArUco board of OpenCV's layout before 4.6.0 (``CharucoBoard.setLegacyPattern``: with an even
    number of rows of squares the markers start in the other colour). :func:`detect_board` tries it by
    itself where the current layout finds too few corners."""

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
        if self.charuco is None and self.legacy:
            raise ValueError("board: the legacy layout is a ChArUco board's (give its dictionary)")

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
    legacy: bool = False
    """A ChArUco board found in OpenCV's legacy layout (before 4.6.0)."""


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


def charuco_dictionary(name: str) -> str:
    """The predefined ArUco dictionary of ``name``, whatever its case (``dict_5x5_1000``,
    ``DICT_APRILTAG_36H11``).

    Raises:
        ValueError: no such dictionary, listing them.
    """
    for n in ARUCO_DICTIONARIES:
        if n.upper() == str(name).strip().upper():
            return n
    raise ValueError(f"unknown ArUco dictionary {name!r} (OpenCV's predefined ones: {', '.join(ARUCO_DICTIONARIES)})")


def _charuco_detector(board: Board, legacy: bool):
    aruco = cv2.aruco
    d = aruco.getPredefinedDictionary(getattr(aruco, board.charuco))
    marker = board.marker or 0.75 * board.square
    b = aruco.CharucoBoard((board.cols + 1, board.rows + 1), board.square, marker, d)
    if legacy:
        b.setLegacyPattern(True)
    return aruco.CharucoDetector(b)


def corner_id_problem(board: Board, corners: np.ndarray, ids: np.ndarray) -> str | None:
    """Why detected corner ids do not fit the board's geometry, or None where they do.

    Each corner's image position is predicted from its detected neighbours within two squares on the
    board (the affine map of their board positions to their image positions: perspective and lens
    distortion are smooth over that span); a corner farther than ``ID_FIT_SQUARES`` squares from its
    prediction carries an id that is not its place on the board (an id shifted by one lands a whole
    square off). Ids outside the board, or twice, do not fit either.
    """
    ids = np.asarray(ids, np.int64).ravel()
    x = np.asarray(corners, np.float64).reshape(-1, 2)
    if ids.size and (ids.min() < 0 or ids.max() >= board.n_corners):
        bad = int(ids[(ids < 0) | (ids >= board.n_corners)][0])
        return f"corner id {bad} is not on a {board.cols}x{board.rows} board"
    u, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        return f"corner id {int(u[counts > 1][0])} found twice"
    g = np.c_[ids % board.cols, ids // board.cols].astype(np.float64)  # board position in squares
    worst, at = 0.0, -1
    for i in range(len(ids)):
        d = np.abs(g - g[i]).max(axis=1)
        nb = np.flatnonzero((d > 0) & (d <= 2))
        if nb.size < 4:
            continue
        G = np.c_[g[nb] - g[i], np.ones(nb.size)]
        if np.linalg.matrix_rank(G[:, :2]) < 2:
            continue
        coef, *_ = np.linalg.lstsq(G, x[nb], rcond=None)  # x = A (g - g_i) + x_i's prediction
        scale = np.sqrt(abs(np.linalg.det(coef[:2])))  # px per square
        if not scale > 0:
            continue
        r = float(np.linalg.norm(x[i] - coef[2]) / scale)
        if r > worst:
            worst, at = r, i
    if worst > ID_FIT_SQUARES:
        return (f"corner {int(ids[at])} lies {worst:.1f} squares from where its neighbours on the board place it: "
                "its id is not its place on the board")
    return None


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
        legacy = board.legacy
        ch_corners, ch_ids, _, _ = _charuco_detector(board, legacy).detectBoard(img)
        n = 0 if ch_ids is None else len(ch_ids)
        if n < settings.min_charuco_corners and (board.rows + 1) % 2 == 0:
            # with an even number of rows of squares OpenCV's layout before 4.6.0 (setLegacyPattern) puts the
            # markers in the other squares: the board finds (almost) no corner in the other layout
            c2, i2, _, _ = _charuco_detector(board, not legacy).detectBoard(img)
            n2 = 0 if i2 is None else len(i2)
            if n2 > n:
                ch_corners, ch_ids, n, legacy = c2, i2, n2, not legacy
                log.info("%s: a ChArUco board of OpenCV's %s layout", name, "legacy (before 4.6.0)" if legacy
                         else "current")
        if n < settings.min_charuco_corners:
            return BoardView(name, False, f"not found ({n} ChArUco corners < {settings.min_charuco_corners})",
                             None, None)
        corners = ch_corners.reshape(-1, 2).astype(np.float32)
        ids = ch_ids.ravel().astype(np.int32)
        why = corner_id_problem(board, corners, ids)
        if why:
            return BoardView(name, False, f"ChArUco corner ids do not fit the board ({why}): a board of another size "
                                          f"or numbering than --board {board.cols}x{board.rows} --charuco "
                                          f"{board.charuco}?", None, None)
    tilt = _tilt_deg(board, corners, ids, size)
    if math.isfinite(tilt) and tilt > settings.max_tilt_deg:
        return BoardView(name, False, f"too oblique (tilted {tilt:.0f} deg > {settings.max_tilt_deg:g})", None, None,
                         sharp, tilt)
    log.debug("%s: board found (%d corners, edge width %.2f px, tilt %.0f deg)", name, len(ids), sharp, tilt)
    return BoardView(name, True, "", corners, ids, sharp, tilt, legacy=board.charuco is not None and legacy)


def view_name(path) -> str:
    """An image's name in messages: its folder and file name (captures share file names)."""
    return "/".join(Path(path).parts[-2:])


def detect_board_images(paths, *, board: Board, settings: BoardSettings = BoardSettings(), what: str | None = None,
                        progress: bool = True) -> tuple[list[BoardView], tuple[int, int] | None]:
    """The board detected in every image of ``paths`` (of one camera: ``what``, for messages), each view named by
    :func:`view_name`, and the images' size (width, height).

    Raises:
        FormatError: naming the image: unreadable, or of another size than the first image.
    """
    views, size = [], None
    for path in progress_bar(paths, desc="detecting the board" + (f" ({what})" if what else ""), unit="image",
                             disable=not progress, leave=False):
        img = read_image(path)
        s = (img.shape[1], img.shape[0])
        if size is None:
            size = s
        elif s != size:
            first = f"{what}'s first image" if what else "the first image"
            raise FormatError(path, f"image is {s[0]}x{s[1]}, {first} is {size[0]}x{size[1]}")
        views.append(detect_board(img, board=board, name=view_name(path), settings=settings))
    return views, size
