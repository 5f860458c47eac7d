"""ChArUco boards: their chessboard (saddle) corners, found from the board's detected markers.
No file I/O, no printing.

A board is described by :class:`CharucoSpec` (hashable: it is part of the detect stage's
parameters). Its frame is agvviz's board frame (:mod:`agvviz.recording.sidefiles`): origin at
the printed bottom-left outer corner, x along the bottom edge, y up, z out of the face; a point
(x, y, z) of OpenCV's board frame (origin top-left, y down, z into the board) is (x, H − y, −z)
here, H = ``squares_y`` · ``square_length_m``. Chessboard corner ``c`` is OpenCV's ChArUco
corner id: row ``c // (squares_x − 1)`` from the top, column ``c % (squares_x − 1)``.

:func:`detect_chessboard` gives OpenCV's ``CharucoDetector.detectBoard`` the markers agvviz
already detected (in OpenCV's own corner order: AprilTag corners are turned back by
:func:`agvviz.markers.apriltag.opencv_quarter_turns`), refines the saddles with
``cornerSubPix`` and keeps them only when they agree with the board's layout: every marker
must lie on the homography (board plane → image) of the others (RANSAC, :data:`MISPLACED_PX`;
a wrong ``legacy_pattern``, ``ids`` or square count moves some markers by whole squares — the
result then names them in ``misplaced_ids`` and the solve refuses the frame), the markers must
fit it as a whole (:data:`LAYOUT_RMS_PX`), and every saddle must lie near where it puts it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from agvviz.markers.apriltag import is_apriltag_dictionary, opencv_quarter_turns
from agvviz.markers.dictionary import aruco_dictionary
from agvviz.markers.types import ArucoError

#: cornerSubPix half window (px) on the saddles, at most; smaller on boards whose squares are
#: under 6× this many pixels (the window must stay inside the square's white margin).
SUBPIX_HALF_WINDOW_PX = 3
#: The board's markers must fit one homography (board plane → undistorted image) to this many
#: pixels (RMS), else the layout is not the image's (wrong legacy_pattern, ids, squares).
LAYOUT_RMS_PX = 1.5
#: A marker whose corners lie further than this (RMS, px) from the homography of the board's
#: other markers (RANSAC) is not where the board places it: the board's description is wrong
#: (a wrong legacy_pattern moves some markers by a square, others not at all).
MISPLACED_PX = 3.0
#: A refined saddle further than this fraction of a square (in px) from where the markers'
#: homography puts it is dropped (cornerSubPix walked to another feature).
SADDLE_OFFSET_FRACTION = 0.15
#: Fewest saddles kept for a board's chessboard view to enter the solve.
MIN_SADDLES = 4


#: What ends the name of a board's chessboard corners (:func:`chessboard_id`).
CHESSBOARD_SUFFIX = ":chessboard"


def chessboard_id(board_index: int) -> str:
    """The name of board ``board_index``'s chessboard corners in a frame's record
    (``used_marker_ids``, ``excluded_marker_ids``, notes) and in the viewer's labels."""
    return f"board{board_index}{CHESSBOARD_SUFFIX}"


def is_chessboard_id(marker_id: str) -> bool:
    return isinstance(marker_id, str) and marker_id.endswith(CHESSBOARD_SUFFIX)


@dataclass(frozen=True)
class CharucoSpec:
    """One ChArUco board's layout (what detection needs; its pose is the map's business)."""

    dictionary: str
    squares_x: int
    squares_y: int
    square_length_m: float
    marker_length_m: float
    ids: tuple[int, ...]
    legacy_pattern: bool = False

    @property
    def n_chessboard_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)


@dataclass(frozen=True)
class ChessboardCorners:
    """A board's saddles found in one frame (undistorted image px).

    board_index : the board's place in the map's ``boards``.
    corner_ids : (N,) int chessboard corner ids; corners_px : (N, 2).
    note : why none (or fewer) were kept, when the board's markers were seen.
    misplaced_ids : markers of the board seen where the board does not place them (then no
        corners): the board is not what the map says, and no pose from it can be trusted.
    """

    board_index: int
    corner_ids: np.ndarray
    corners_px: np.ndarray
    note: str = ""
    misplaced_ids: tuple[int, ...] = ()


@functools.lru_cache(maxsize=16)
def opencv_board(spec: CharucoSpec) -> cv2.aruco.CharucoBoard:
    """OpenCV's board of ``spec`` (the one its generator draws)."""
    board = cv2.aruco.CharucoBoard(
        (spec.squares_x, spec.squares_y), float(spec.square_length_m), float(spec.marker_length_m),
        aruco_dictionary(spec.dictionary), np.asarray(spec.ids, dtype=np.int32),
    )
    if spec.legacy_pattern:
        board.setLegacyPattern(True)
    return board


@functools.lru_cache(maxsize=16)
def opencv_corner_order(dictionary: str) -> np.ndarray:
    """Index array ``order`` with ``opencv_corners = agvviz_corners[order]`` for one marker
    (identity for ArUco; AprilTag corners turned back by OpenCV's quarter turns)."""
    if not is_apriltag_dictionary(dictionary):
        return np.arange(4)
    return (np.arange(4) - opencv_quarter_turns(dictionary)) % 4


def charuco_marker_corners(
    squares_x: int, squares_y: int, square_length_m: float, marker_length_m: float,
    dictionary: str, ids: list[int] | None = None, legacy_pattern: bool = False,
) -> dict[int, np.ndarray]:
    """Corners (4, 3) TL, TR, BR, BL of every ArUco marker of a ChArUco board, by id, in the
    board frame of :mod:`agvviz.recording.sidefiles` (origin bottom-left, y up, z out of the face).

    The board is the one OpenCV's generator draws. Its AprilTags are OpenCV's bits, turned from
    the printed tags on OpenCV 5.0 (:func:`agvviz.markers.apriltag.opencv_quarter_turns`): their
    corners are re-ordered so that corner 0 is the drawn tag's own top-left, the corner the
    AprilTag detector reports first."""
    args = ((squares_x, squares_y), float(square_length_m), float(marker_length_m), aruco_dictionary(dictionary))
    board = cv2.aruco.CharucoBoard(*args, np.asarray(ids, dtype=np.int32)) if ids is not None else cv2.aruco.CharucoBoard(*args)
    if legacy_pattern:
        board.setLegacyPattern(True)
    square, half = float(square_length_m), float(marker_length_m) / 2.0
    height_m = squares_y * square
    corners = {}
    for marker_id, points in zip(np.asarray(board.getIds()).ravel(), board.getObjPoints()):
        # OpenCV's points are float32: take the layout (which square, which corner is which)
        # from them and compute the coordinates in float64.
        p = np.asarray(points, dtype=float).reshape(4, 2 if np.size(points) == 8 else 3)[:, :2]
        centre = p.mean(axis=0)
        cell = np.floor(centre / square)
        exact = (cell + 0.5) * square + np.sign(p - centre) * half
        corners[int(marker_id)] = np.column_stack([exact[:, 0], height_m - exact[:, 1], np.zeros(4)])
    if is_apriltag_dictionary(dictionary):
        order = (np.arange(4) + opencv_quarter_turns(dictionary)) % 4
        corners = {marker_id: points[order] for marker_id, points in corners.items()}
    return corners


def chessboard_corners_board_m(spec: CharucoSpec) -> np.ndarray:
    """(N, 3) chessboard corners by corner id, in agvviz's board frame (module docstring)."""
    nx = spec.squares_x - 1
    c = np.arange(spec.n_chessboard_corners)
    square = float(spec.square_length_m)
    x = (c % nx + 1) * square
    y = spec.squares_y * square - (c // nx + 1) * square
    return np.column_stack([x, y, np.zeros(len(c))])


@functools.lru_cache(maxsize=16)
def check_board_frame(spec: CharucoSpec) -> np.ndarray:
    """``T_agvviz_opencv`` (4, 4): the rigid transform from OpenCV's board frame to agvviz's,
    fitted to OpenCV's marker object points (in OpenCV's corner order) against agvviz's
    expansion (:func:`charuco_marker_corners`) of the same board;
    it must also take OpenCV's chessboard corners onto :func:`chessboard_corners_board_m`.
    Raises :class:`ArucoError` when either does not fit (the two disagree on the board)."""
    board = opencv_board(spec)
    ours = charuco_marker_corners(spec.squares_x, spec.squares_y, spec.square_length_m, spec.marker_length_m,
                                  spec.dictionary, list(spec.ids), spec.legacy_pattern)
    order = opencv_corner_order(spec.dictionary)
    ocv_ids = np.asarray(board.getIds()).ravel()
    ocv = np.vstack([np.asarray(p, dtype=float).reshape(4, 3) for p in board.getObjPoints()])
    mine = np.vstack([ours[int(i)][order] for i in ocv_ids])
    U, _, Vt = np.linalg.svd((ocv - ocv.mean(0)).T @ (mine - mine.mean(0)))
    R = (U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt).T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, mine.mean(0) - R @ ocv.mean(0)
    tolerance_m = 1e-6 * max(1.0, spec.squares_x * spec.square_length_m, spec.squares_y * spec.square_length_m)
    worst = float(np.max(np.abs(ocv @ R.T + T[:3, 3] - mine)))
    chess_ocv = np.asarray(board.getChessboardCorners(), dtype=float).reshape(-1, 3)
    worst_chess = float(np.max(np.abs(chess_ocv @ R.T + T[:3, 3] - chessboard_corners_board_m(spec))))
    if worst > tolerance_m or worst_chess > tolerance_m:
        raise ArucoError(
            f"ChArUco board {spec.squares_x}x{spec.squares_y} {spec.dictionary}: OpenCV's board and agvviz's "
            f"expansion differ by {max(worst, worst_chess) * 1000:.3g} mm (not one rigid transform)"
        )
    return T


def detect_chessboard(
    gray: np.ndarray, spec: CharucoSpec, board_index: int, markers: dict[int, np.ndarray]
) -> ChessboardCorners | None:
    """The board's saddles in the (undistorted) uint8 ``gray`` image from its detected
    ``markers`` ({id: (4, 2) corners TL, TR, BR, BL as printed}); None when fewer than two of
    its markers are in view. A result without corners carries the ``note`` saying why."""
    seen = [i for i in spec.ids if i in markers]
    if len(seen) < 2:
        return None
    empty = np.zeros(0, dtype=int), np.zeros((0, 2))
    where = chessboard_id(board_index)
    check_board_frame(spec)
    ours = charuco_marker_corners(spec.squares_x, spec.squares_y, spec.square_length_m, spec.marker_length_m,
                                  spec.dictionary, list(spec.ids), spec.legacy_pattern)
    plane = np.vstack([ours[i][:, :2] for i in seen])
    pixels = np.vstack([np.asarray(markers[i], dtype=float).reshape(4, 2) for i in seen])
    # RANSAC (OpenCV's, seeded the same on every call) then least squares on the markers it keeps: a marker that
    # is not where the board places it shows up as one far from the others' homography.
    H, _ = cv2.findHomography(plane, pixels, cv2.RANSAC, MISPLACED_PX) if len(seen) >= 3 else (None, None)
    if H is None:
        H, _ = cv2.findHomography(plane, pixels, 0)
    if H is None:
        return ChessboardCorners(board_index, *empty, f"{where}: its markers fit no homography")
    fitted = cv2.perspectiveTransform(plane.reshape(1, -1, 2), H).reshape(-1, 2)
    per_marker_px = np.sqrt(np.mean(np.sum((fitted - pixels) ** 2, axis=1).reshape(-1, 4), axis=1))
    misplaced = tuple(int(i) for i, d in zip(seen, per_marker_px) if d > MISPLACED_PX)
    if misplaced:
        shown = ", ".join(map(str, misplaced[:6])) + (", …" if len(misplaced) > 6 else "")
        return ChessboardCorners(
            board_index, *empty,
            f"{where} not used: its markers {shown} ({len(misplaced)} of {len(seen)} seen) do not lie where the board "
            f"places them (up to {per_marker_px.max():.0f} px from the others' homography; check squares_x/y, ids, "
            "legacy_pattern)",
            misplaced,
        )
    H, _ = cv2.findHomography(plane, pixels, 0)
    if H is None:
        return ChessboardCorners(board_index, *empty, f"{where}: its markers fit no homography")
    fitted = cv2.perspectiveTransform(plane.reshape(1, -1, 2), H).reshape(-1, 2)
    layout_rms = float(np.sqrt(np.mean(np.sum((fitted - pixels) ** 2, axis=1))))
    if layout_rms > LAYOUT_RMS_PX:
        return ChessboardCorners(
            board_index, *empty,
            f"{where} not used: its {len(seen)} markers do not lie where the board places them "
            f"(RMS {layout_rms:.1f} px from one plane's homography; check squares_x/y, ids, legacy_pattern)",
        )
    board = opencv_board(spec)
    order = opencv_corner_order(spec.dictionary)
    marker_corners = tuple(np.asarray(markers[i], dtype=np.float32).reshape(4, 2)[order].reshape(1, 4, 2) for i in seen)
    marker_ids = np.asarray(seen, dtype=np.int32).reshape(-1, 1)
    try:
        corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(
            gray, markerCorners=marker_corners, markerIds=marker_ids
        )
    except cv2.error as exc:
        return ChessboardCorners(board_index, *empty, f"{where}: OpenCV: {str(exc).strip().splitlines()[-1]}")
    if ids is None or len(ids) == 0:
        return ChessboardCorners(board_index, *empty, f"{where}: no saddle between its markers")
    ids = np.asarray(ids, dtype=int).ravel()
    corners = np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2)
    board_m = chessboard_corners_board_m(spec)
    predicted = cv2.perspectiveTransform(board_m[ids, :2].reshape(1, -1, 2), H).reshape(-1, 2)
    # Square size in px around each corner, from the homography: the subpix window and the gate.
    step = cv2.perspectiveTransform((board_m[ids, :2] + [spec.square_length_m, 0.0]).reshape(1, -1, 2), H).reshape(-1, 2)
    square_px = np.linalg.norm(step - predicted, axis=1)
    half = int(max(1, min(SUBPIX_HALF_WINDOW_PX, np.floor(np.min(square_px) / 6.0))))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    refined = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), criteria).reshape(-1, 2).astype(float)
    keep = np.linalg.norm(refined - predicted, axis=1) <= SADDLE_OFFSET_FRACTION * square_px
    note = ""
    if not np.all(keep):
        note = f"{where}: {int((~keep).sum())} of {len(ids)} saddles dropped (away from where the markers put them)"
    if keep.sum() < MIN_SADDLES or 2 * keep.sum() < len(ids):
        return ChessboardCorners(board_index, *empty, (note or where) + "; too few left, not used")
    return ChessboardCorners(board_index, ids[keep], refined[keep], note)

