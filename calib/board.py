"""Calibration boards (checkerboard, ChArUco): their geometry, their printed image, and finding them in images.

A board is given as text (``BOARD`` on the command line):

- ``checkerboard:COLSxROWS:SQUARE_M``: ``COLS x ROWS`` *inner* corners, as ``cv2.findChessboardCorners``
  counts them (a board of 5 x 8 squares has 4 x 7 inner corners), squares ``SQUARE_M`` metres wide;
- ``charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT``: ``COLS x ROWS`` *squares*, as ``cv2.aruco.CharucoBoard``
  counts them, squares ``SQUARE_M`` and ArUco markers ``MARKER_M`` metres wide, markers from OpenCV's
  predefined dictionary ``DICT`` (``DICT_4X4_50``, ``DICT_5X5_100``, ...).

Board frame: x along a row of corners, y along a column, z = x × y pointing into the board, away from a
camera that sees its printed side; corners lie at z = 0, in metres. A detection lists the board corners
found (their ids, which index :attr:`Board.object_points`) and their pixels (pixel centres at integers).

A checkerboard's corners could be listed from any of its four corners. :func:`detect` always lists them
the same way, so that every camera agrees which corner is which: the listing goes counter-clockwise in the
image as the board's x and y axes do (a board seen from its printed side), and starts at the end of the board
where the first square, between corners 0, 1, COLS and COLS + 1, is dark. The second rule tells the two
ends apart only when COLS + ROWS is odd (a board of 4 x 7 corners, not 6 x 8): a board with COLS + ROWS
even looks the same turned by 180 degrees, which is no harm for one camera's intrinsics but leaves two
cameras of a rig disagreeing; :attr:`Board.symmetric` says so. ChArUco corners carry ids of their own.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

import cv2
import numpy as np

from calib.errors import InputError

KINDS = ("checkerboard", "charuco")

# Detection of a checkerboard, in the order tried: the sector-based detector (NORMALIZE evens out the exposure,
# ACCURACY refines each corner on an upsampled patch), then the classic quad detector with adaptive thresholds,
# which finds some boards the former misses (strong perspective, uneven light). On a 780 x 580 image without a
# board they take about 0.35 and 0.15 s. (The sector detector's EXHAUSTIVE search, 0.4 s more, found no board
# in rendered studio views that these two missed.)
DETECTORS = (
    ("sector", cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY),
    ("classic", cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FILTER_QUADS),
)
# The detectors cost time growing with the image area; larger images are searched at this longest side and
# the corners found are refined on the full image.
SEARCH_SIZE_PX = 1280
# cornerSubPix stops after 50 iterations or once a corner moves less than 1e-3 px.
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
# cornerSubPix's half window as a fraction of the smallest distance between neighbouring corners: large
# enough to hold the corner's four edges, small enough to keep the neighbouring corners out of it (at 0.6 the
# refinement of a foreshortened board jumps to the wrong corner; on rendered boards 0.4 halves the sector
# detector's error, 0.1 px to 0.05 px).
SUBPIX_WINDOW_FRACTION = 0.4
SUBPIX_WINDOW_PX = (2, 11)
# A refined corner that moved by more than this fraction of the corner spacing went astray.
SUBPIX_MAX_SHIFT = 0.2
# Fewest ChArUco corners accepted in one view: a homography needs four, a pose six to be trusted.
MIN_CHARUCO_CORNERS = 6

_SIZE = re.compile(r"(\d+)[xX](\d+)")


@dataclass(frozen=True)
class Board:
    """A planar calibration board.

    Parameters
    ----------
    kind : {"checkerboard", "charuco"}
    columns, rows : int
        checkerboard: inner corners per row and per column; charuco: squares per row and per column.
    square_m : float
        Side of a square, metres.
    marker_m : float
        charuco: side of an ArUco marker, metres (0 for a checkerboard).
    dictionary : str
        charuco: OpenCV's predefined dictionary name, e.g. ``"DICT_4X4_50"`` ("" for a checkerboard).
    """

    kind: str
    columns: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = ""

    @property
    def corner_grid(self) -> tuple[int, int]:
        """(columns, rows) of inner corners."""
        if self.kind == "checkerboard":
            return self.columns, self.rows
        return self.columns - 1, self.rows - 1

    @property
    def n_corners(self) -> int:
        columns, rows = self.corner_grid
        return columns * rows

    @property
    def object_points(self) -> np.ndarray:
        """(N, 3) corner positions in the board frame, metres, in id order (row by row)."""
        if self.kind == "charuco":
            return np.asarray(_charuco_board(self).getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        columns, rows = self.corner_grid
        x, y = np.meshgrid(np.arange(columns), np.arange(rows))
        return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]) * self.square_m

    @property
    def symmetric(self) -> bool:
        """Whether the board looks the same turned by 180 degrees, so that cameras may disagree on its corners."""
        return self.kind == "checkerboard" and (self.columns + self.rows) % 2 == 0

    @property
    def extent_m(self) -> tuple[float, float]:
        """(width, height) of the printed pattern, metres (a checkerboard's outer squares included)."""
        if self.kind == "checkerboard":
            return (self.columns + 1) * self.square_m, (self.rows + 1) * self.square_m
        return self.columns * self.square_m, self.rows * self.square_m

    @property
    def pattern_origin_m(self) -> np.ndarray:
        """(2,) position of the printed pattern's top-left corner in the board frame, metres."""
        if self.kind == "checkerboard":
            return np.array([-self.square_m, -self.square_m])
        return np.zeros(2)

    def describe(self) -> str:
        """The board as ``BOARD`` text (what :func:`parse_board` reads)."""
        if self.kind == "checkerboard":
            return f"checkerboard:{self.columns}x{self.rows}:{self.square_m:g}"
        return f"charuco:{self.columns}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"


def parse_board(text: str) -> Board:
    """The board described by ``text`` (see the module docstring); InputError naming the part that is wrong."""
    parts = text.split(":")
    kind = parts[0].lower()
    if kind not in KINDS:
        raise InputError(f"--board {text!r}: unknown board kind {parts[0]!r}, expected checkerboard:COLSxROWS:SQUARE_M "
                         "or charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT")
    expected = 3 if kind == "checkerboard" else 5
    usage = "checkerboard:COLSxROWS:SQUARE_M" if kind == "checkerboard" else "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT"
    if len(parts) != expected:
        raise InputError(f"--board {text!r}: {len(parts)} fields, expected {expected} ({usage})")
    size = _SIZE.fullmatch(parts[1])
    if not size:
        raise InputError(f"--board {text!r}: size {parts[1]!r} is not COLSxROWS (two whole numbers, e.g. 7x5)")
    columns, rows = int(size[1]), int(size[2])
    smallest = 2 if kind == "checkerboard" else 3
    if min(columns, rows) < smallest:
        counted = "inner corners" if kind == "checkerboard" else "squares"
        raise InputError(f"--board {text!r}: {columns}x{rows} {counted}, expected at least {smallest} each way")
    square = _length(parts[2], "square size", text)
    if kind == "checkerboard":
        return Board(kind, columns, rows, square)
    marker = _length(parts[3], "marker size", text)
    if marker >= square:
        raise InputError(f"--board {text!r}: marker {marker:g} m is not smaller than the square {square:g} m")
    name = parts[4].upper()
    if not name.startswith("DICT_") or not isinstance(getattr(cv2.aruco, name, None), int):
        raise InputError(f"--board {text!r}: {parts[4]!r} is not one of OpenCV's ArUco dictionaries "
                         "(expected a name like DICT_4X4_50, DICT_5X5_100, DICT_6X6_250)")
    board = Board(kind, columns, rows, square, marker, name)
    markers = (columns * rows) // 2
    available = _dictionary(name).bytesList.shape[0]
    if markers > available:
        raise InputError(f"--board {text!r}: {columns}x{rows} squares hold {markers} markers but {name} has only "
                         f"{available}; expected a larger dictionary")
    return board


def _length(word: str, what: str, text: str) -> float:
    try:
        value = float(word)
    except ValueError:
        raise InputError(f"--board {text!r}: {what} {word!r} is not a number (metres)") from None
    if not 0 < value < 10:
        raise InputError(f"--board {text!r}: {what} {value:g} m, expected metres (e.g. 0.1 for 10 cm)")
    return value


@functools.lru_cache(maxsize=8)
def _dictionary(name: str) -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@functools.lru_cache(maxsize=8)
def _charuco_board(board: Board) -> cv2.aruco.CharucoBoard:
    return cv2.aruco.CharucoBoard((board.columns, board.rows), board.square_m, board.marker_m,
                                  _dictionary(board.dictionary))


@functools.lru_cache(maxsize=8)
def _charuco_detector(board: Board) -> cv2.aruco.CharucoDetector:
    detector_parameters = cv2.aruco.DetectorParameters()
    # Boards far from a camera have small markers: accept markers down to 1 % of the image's longer side in
    # perimeter (about 2 px a side in a 780-px image; the default 3 % drops 6-px markers), and refine their corners.
    detector_parameters.minMarkerPerimeterRate = 0.01
    detector_parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    charuco_parameters = cv2.aruco.CharucoParameters()
    charuco_parameters.tryRefineMarkers = True
    return cv2.aruco.CharucoDetector(_charuco_board(board), charuco_parameters, detector_parameters)


def board_image(board: Board, pixels_per_square: int, *, margin_squares: float = 0.5) -> np.ndarray:
    """(H, W) uint8 picture of the board to print (or to texture a rendering with): black on white.

    The pattern (:attr:`Board.extent_m`) is drawn at ``pixels_per_square`` pixels per square, inside a white
    margin of ``margin_squares`` squares; pixel (0, 0) of the pattern is at board-frame position
    :attr:`Board.pattern_origin_m`.
    """
    margin = int(round(margin_squares * pixels_per_square))
    if board.kind == "checkerboard":
        black = np.add.outer(np.arange(board.rows + 1), np.arange(board.columns + 1)) % 2 == 0
        pattern = _squares(black, pixels_per_square)
    else:
        # Drawn here rather than by CharucoBoard.generateImage, which fails for some sizes (an ROI assertion when
        # the marker's pixel size does not divide evenly): squares exact, markers to the nearest pixel. The
        # markers sit in the white squares; every other square is black.
        charuco = _charuco_board(board)
        scale = pixels_per_square / board.square_m
        marker_corners = [np.asarray(corners).reshape(4, 3)[0, :2] for corners in charuco.getObjPoints()]
        black = np.ones((board.rows, board.columns), dtype=bool)
        for corner in marker_corners:
            column, row = np.floor(corner / board.square_m).astype(int)
            black[row, column] = False
        pattern = _squares(black, pixels_per_square)
        side = int(round(board.marker_m * scale))
        for marker_id, corner in zip(charuco.getIds().ravel(), marker_corners, strict=True):
            left, top = np.rint(corner * scale).astype(int)
            pattern[top : top + side, left : left + side] = cv2.aruco.generateImageMarker(
                _dictionary(board.dictionary), int(marker_id), side, borderBits=1)
    return cv2.copyMakeBorder(pattern, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)


def _squares(black: np.ndarray, pixels_per_square: int) -> np.ndarray:
    """(rows p, columns p) uint8: the squares of ``black`` (rows, columns) bool, black 0 and white 255."""
    return np.kron(np.where(black, 0, 255).astype(np.uint8), np.ones((pixels_per_square,) * 2, dtype=np.uint8))


@dataclass(frozen=True, eq=False)
class Detection:
    """The board corners found in one image.

    Attributes
    ----------
    ids : (n,) int
        Indices into :attr:`Board.object_points`.
    corners : (n, 2) float
        Their pixels, pixel centres at integers.
    """

    ids: np.ndarray
    corners: np.ndarray


def detect(board: Board, image: np.ndarray) -> Detection | None:
    """The board's corners in ``image`` ((H, W) grey or (H, W, 3) BGR uint8), or None when it is not found.

    A checkerboard is found whole or not at all; a ChArUco board may be partly seen (at least
    :data:`MIN_CHARUCO_CORNERS` corners, not all on one line).
    """
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if board.kind == "charuco":
        return _detect_charuco(board, grey)
    corners = _find_checkerboard(grey, board.corner_grid)
    if corners is None:
        return None
    return Detection(np.arange(board.n_corners), _canonical_order(grey, corners, board.corner_grid))


def _find_checkerboard(grey: np.ndarray, grid: tuple[int, int]) -> np.ndarray | None:
    """(N, 2) inner corners in OpenCV's order, sub-pixel refined on the full image, or None."""
    scale = min(1.0, SEARCH_SIZE_PX / max(grey.shape))
    small = grey if scale == 1.0 else cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    for method, flags in DETECTORS:
        finder = cv2.findChessboardCornersSB if method == "sector" else cv2.findChessboardCorners
        found, corners = finder(small, grid, flags=flags)
        if found:
            break
    else:
        return None
    corners = corners.reshape(-1, 2).astype(np.float64)
    if scale != 1.0:  # pixel centres at integers: x_full + 0.5 = (x_small + 0.5) / scale
        corners = (corners + 0.5) / scale - 0.5
    return _refine(grey, corners, grid)


def _refine(grey: np.ndarray, corners: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """``corners`` (N, 2) moved to the saddle point of the image within a window sized to the board's squares.

    A corner that the refinement moves by more than :data:`SUBPIX_MAX_SHIFT` of a square has slid towards a
    neighbouring edge or corner (a strongly foreshortened board): it keeps the detector's position.
    """
    columns, rows = grid
    lattice = corners.reshape(rows, columns, 2)
    step = min(np.linalg.norm(np.diff(lattice, axis=axis), axis=2).min() for axis in (0, 1))
    half = int(np.clip(round(SUBPIX_WINDOW_FRACTION * step), *SUBPIX_WINDOW_PX))
    refined = cv2.cornerSubPix(grey, corners.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1),
                               SUBPIX_CRITERIA).reshape(-1, 2).astype(np.float64)
    slid = np.linalg.norm(refined - corners, axis=1) > SUBPIX_MAX_SHIFT * step
    refined[slid] = corners[slid]
    return refined


def _canonical_order(grey: np.ndarray, corners: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """``corners`` (N, 2) relisted by the rules of the module docstring (handedness, then the dark first square)."""
    columns, rows = grid
    lattice = corners.reshape(rows, columns, 2)
    along_x, along_y = lattice[0, -1] - lattice[0, 0], lattice[-1, 0] - lattice[0, 0]
    if along_x[0] * along_y[1] - along_x[1] * along_y[0] < 0:  # the listing runs clockwise: mirror it
        lattice = lattice[:, ::-1]
    # Square centres between the corners, as the mean of each square's four corners (exact for a homography's
    # image of the centre up to second order; ample to tell black from white).
    centres = (lattice[:-1, :-1] + lattice[:-1, 1:] + lattice[1:, :-1] + lattice[1:, 1:]) / 4.0
    levels = cv2.remap(grey, centres[..., 0].astype(np.float32), centres[..., 1].astype(np.float32),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    parity = np.add.outer(np.arange(rows - 1), np.arange(columns - 1)) % 2
    if levels[parity == 0].mean() > levels[parity == 1].mean():  # the first square is light: start at the far end
        lattice = lattice[::-1, ::-1]
    return np.ascontiguousarray(lattice.reshape(-1, 2))


def _detect_charuco(board: Board, grey: np.ndarray) -> Detection | None:
    corners, ids, _, _ = _charuco_detector(board).detectBoard(grey)
    if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    ids = ids.reshape(-1).astype(np.int64)
    if _charuco_board(board).checkCharucoCornersCollinear(ids.astype(np.int32).reshape(-1, 1)):
        return None
    order = np.argsort(ids)
    return Detection(ids[order], corners.reshape(-1, 2).astype(np.float64)[order])
