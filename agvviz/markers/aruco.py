"""ArUco marker detection with sub-pixel corner refinement (OpenCV). No file I/O, no printing.

Any OpenCV predefined dictionary works. The AprilTag families (``DICT_APRILTAG_16h5``,
``DICT_APRILTAG_25h9``, ``DICT_APRILTAG_36h11``) are detected, and their module grids drawn, by
the AprilTag library itself (:mod:`agvviz.markers.apriltag`: OpenCV's AprilTag dictionaries are
turned 180° from the printed tags on OpenCV 5.0); ``DICT_APRILTAG_36h10`` is refused. A tag's
side is that of its black border, as for ArUco markers (AprilTag's "tag size").

Input frames come from an ideal pinhole camera (the pipeline undistorts first). Corners are in
OpenCV pixel coordinates and ArUco order TL, TR, BR, BL as printed (:mod:`agvviz.conventions`);
they are the outer corners of the marker's black border, so a marker of side ``s`` in a map has
corners ``(∓s/2, ±s/2)``.

Refinement (``refine=``, :data:`ARUCO_REFINE_METHODS`; ``ecc``, ``subpix`` and ``none`` are
the names the QR pipeline uses too):

``"ecc"``       the marker's own bit pattern (black border included) from the dictionary, aligned
                to the image by :func:`agvviz.markers.ecc.align_symbol_ecc`, started from the
                ``"subpix"`` corners; falls back to them when ECC fails (``refine_note`` says why);
``"subpix"``    OpenCV's ``CORNER_REFINE_SUBPIX`` (``cornerSubPix`` at each corner);
``"contour"``   OpenCV's ``CORNER_REFINE_CONTOUR`` (lines fitted to the marker's contour points);
``"apriltag"``  the AprilTag library's edge refinement: for AprilTag families the library's own
                (:mod:`agvviz.markers.apriltag`), for ArUco dictionaries OpenCV's
                ``CORNER_REFINE_APRILTAG``;
``"none"``      the detector's contour corners.

docs/refinement.md has each one's accuracy on real photos (``bench/bench_refiners.py``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from agvviz.geometry import se3
from agvviz.geometry.plane import DegenerateGeometryError, marker_frame_from_corners
from agvviz.markers.apriltag import (
    APRILTAG_REFINE_METHODS,
    apriltag_modules,
    detect_apriltags,
    is_apriltag_dictionary,
)
from agvviz.markers.charuco import (
    CharucoSpec,
    charuco_marker_corners,
    check_board_frame,
    chessboard_corners_board_m,
)
from agvviz.markers.dictionary import aruco_dictionary
from agvviz.markers.ecc import align_symbol_ecc
from agvviz.markers.types import ArucoDetection, ArucoError


@functools.lru_cache(maxsize=64)
def aruco_modules(name: str, marker_id: int) -> np.ndarray:
    """Dark modules ((n + 2)², bool, row 0 the printed top) of marker ``marker_id`` including
    its one-module black border."""
    dictionary = aruco_dictionary(name)
    count = dictionary.bytesList.shape[0]
    if not 0 <= int(marker_id) < count:
        raise ArucoError(f"marker id {marker_id} is outside {name} (ids 0..{count - 1})")
    if is_apriltag_dictionary(name):
        return apriltag_modules(name, int(marker_id))
    n = dictionary.markerSize + 2
    image = cv2.aruco.generateImageMarker(dictionary, int(marker_id), n, borderBits=1)
    return image == 0


#: Corner refinements of ArUco/AprilTag markers (module docstring), most accurate first.
ARUCO_REFINE_METHODS = ("ecc", "subpix", "contour", "apriltag", "none")
#: OpenCV's corner refinement run by the detector for each ``refine`` (ECC starts from SUBPIX).
_OPENCV_REFINEMENT = {
    "ecc": cv2.aruco.CORNER_REFINE_SUBPIX,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
    "none": cv2.aruco.CORNER_REFINE_NONE,
}


#: Largest ECC template resolution for ArUco/AprilTag markers (px per module; QR codes keep
#: :data:`agvviz.markers.ecc.TEMPLATE_PX_PER_MODULE_RANGE`). ECC's cost grows with the template's
#: pixel count: on 85–127 px DICT_6X6 markers (bench/bench_dense_board.py) a cap of 8 instead of
#: 12 halves the time per marker (2.2 → 1.0 ms) at the same corner error (0.012 px median);
#: 6 costs accuracy (0.017 px). Markers below 8 px per module are not affected.
ECC_MAX_PX_PER_MODULE = 8


def _parameters(refine: str) -> cv2.aruco.DetectorParameters:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = _OPENCV_REFINEMENT[refine]
    return params


@functools.lru_cache(maxsize=16)
def _detector(name: str, refine: str) -> cv2.aruco.ArucoDetector:
    return cv2.aruco.ArucoDetector(aruco_dictionary(name), _parameters(refine))


def detect_aruco(gray: np.ndarray, dictionary_name: str, refine: str = "ecc") -> list[ArucoDetection]:
    """Every marker of ``dictionary_name`` found in the uint8 gray image, corners refined
    (``refine`` one of :data:`ARUCO_REFINE_METHODS`; AprilTag families by
    :func:`agvviz.markers.apriltag.detect_apriltags`)."""
    _check_refine(refine)
    if is_apriltag_dictionary(dictionary_name):
        aruco_dictionary(dictionary_name)  # refuses an unsupported family as ArucoError
        check_apriltag_refine(refine)
        return detect_apriltags(gray, dictionary_name, refine=refine)
    return _refined(gray, _detector(dictionary_name, refine), refine, functools.partial(aruco_modules, dictionary_name))


def detect_with_dictionary(gray: np.ndarray, dictionary: cv2.aruco.Dictionary, refine: str = "ecc") -> list[ArucoDetection]:
    """:func:`detect_aruco` for a dictionary that is not predefined (e.g. one read from a file)."""
    _check_refine(refine)
    n = dictionary.markerSize + 2

    def modules(marker_id: int) -> np.ndarray:
        return cv2.aruco.generateImageMarker(dictionary, int(marker_id), n, borderBits=1) == 0

    return _refined(gray, cv2.aruco.ArucoDetector(dictionary, _parameters(refine)), refine, modules)


def check_apriltag_refine(refine: str) -> None:
    """:class:`ArucoError` when ``refine`` is an OpenCV ArUco refinement the AprilTag library's
    detector does not have (``contour``)."""
    if refine not in APRILTAG_REFINE_METHODS:
        raise ArucoError(
            f"refine={refine} is OpenCV's ArUco corner refinement; AprilTag families take "
            f"refine={' or '.join(APRILTAG_REFINE_METHODS)}"
        )


def _check_refine(refine: str) -> None:
    if refine not in ARUCO_REFINE_METHODS:
        raise ValueError(f"unknown refine method {refine!r}; valid: {', '.join(ARUCO_REFINE_METHODS)}")


def _refined(gray: np.ndarray, detector: cv2.aruco.ArucoDetector, refine: str, modules) -> list[ArucoDetection]:
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None:
        return []
    opencv_method = "subpix" if refine == "ecc" else refine
    detections = []
    for marker_corners, marker_id in zip(corners, ids.ravel()):
        raw = marker_corners.reshape(4, 2).astype(float)
        detection = ArucoDetection(int(marker_id), raw.copy(), raw, opencv_method)
        if refine == "ecc":
            refined, note = align_symbol_ecc(gray, modules(int(marker_id)), raw, max_px_per_module=ECC_MAX_PX_PER_MODULE)
            if refined is None:
                detection.refine_ok = False
                detection.refine_note = f"ecc: {note}; kept subpix"
            else:
                detection.corners_px = refined
                detection.refine_method = "ecc"
        detections.append(detection)
    return detections


@dataclass(frozen=True)
class MapMarker:
    """One ArUco marker of a marker map.

    frame : "world" (fixed) or "agv" (mounted on the vehicle).
    corners_m : (4, 3) corners TL, TR, BR, BL in ``frame``.
    T_frame_marker : (4, 4) the marker frame in ``frame`` (:mod:`agvviz.conventions`).
    points_marker_m : (4, 3) the corners in the marker frame (z = 0).
    """

    frame: str
    corners_m: np.ndarray
    T_frame_marker: np.ndarray
    points_marker_m: np.ndarray


@dataclass(frozen=True)
class MapBoard:
    """One ChArUco board of a marker map (its markers are in :attr:`ArucoMap.markers`).

    spec : its layout (:class:`agvviz.markers.charuco.CharucoSpec`).
    frame : "world" or "agv"; T_frame_board : (4, 4) the board frame in ``frame``.
    points_board_m : (N, 3) chessboard corners by corner id in the board frame (z = 0);
    corners_m : (N, 3) the same in ``frame``.
    """

    spec: object
    frame: str
    T_frame_board: np.ndarray
    points_board_m: np.ndarray
    corners_m: np.ndarray


@dataclass(frozen=True)
class ArucoMap:
    """An ``agvviz.MarkerMap`` of ArUco markers: the dictionary, the markers by id and the
    ChArUco boards (optional ``boards`` key)."""

    dictionary: str
    markers: dict[int, MapMarker]
    boards: tuple[MapBoard, ...] = ()


def parse_aruco_map(marker_map: dict) -> ArucoMap | None:
    """The :class:`ArucoMap` of an ``agvviz.MarkerMap`` message, or None when the map is of
    QR codes (``dictionary`` "qr", whose codes carry their own coordinates).

    Raises :class:`ArucoError` — and nothing else, whatever the (untrusted, JSON-decoded)
    input — for a map that is not an object, an unknown dictionary, markers that are not a
    list of objects, a non-integer, out-of-range or repeated id, an unknown frame, or corners
    that are not 4 finite points x, y, z within :data:`MAX_ABS_CORNER_M` or do not form a
    square's plane.
    """
    if not isinstance(marker_map, dict):
        raise ArucoError(f"marker map must be a JSON object, got {type(marker_map).__name__}")
    dictionary = marker_map.get("dictionary")
    if isinstance(dictionary, str) and dictionary == "qr":
        return None
    if not isinstance(dictionary, str):
        raise ArucoError(f"marker map: dictionary must be a string ('qr' or e.g. DICT_5X5_50), got {type(dictionary).__name__}")
    aruco_dictionary(dictionary)  # raises for an unknown name
    count = aruco_dictionary(dictionary).bytesList.shape[0]
    entries = marker_map.get("markers", [])
    if not isinstance(entries, list):
        raise ArucoError(f"marker map: markers must be a list, got {type(entries).__name__}")
    markers: dict[int, MapMarker] = {}
    for position, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise ArucoError(f"marker map: marker {position} must be an object, got {type(entry).__name__}")
        raw_id = entry.get("id")
        # ASCII digits only: str.isdigit() is also true for "²" (int() refuses it) and "٣".
        if isinstance(raw_id, int) and not isinstance(raw_id, bool):
            marker_id = raw_id
        elif isinstance(raw_id, str) and raw_id.isascii() and raw_id.isdigit() and len(raw_id) <= 9:
            marker_id = int(raw_id)
        else:
            marker_id = None
        if marker_id is None or not 0 <= marker_id < count:
            shown = _shown(raw_id)
            raise ArucoError(f"marker map: id {shown} is not an id of {dictionary} (0..{count - 1})")
        if marker_id in markers:
            raise ArucoError(f"marker map: id {marker_id} appears more than once")
        frame = entry.get("frame", "world")
        if not (isinstance(frame, str) and frame in ("world", "agv")):
            raise ArucoError(f"marker map: marker {marker_id} has frame {_shown(frame)}; expected 'world' or 'agv'")
        corners = _corners(entry.get("corners_world_m"), marker_id)
        try:
            T_frame_marker, points_marker_m = marker_frame_from_corners(corners)
        except DegenerateGeometryError as exc:
            raise ArucoError(f"marker map: marker {marker_id}: {exc}") from None
        markers[marker_id] = MapMarker(frame, corners, T_frame_marker, points_marker_m[:4])
    boards_in = marker_map.get("boards", [])
    if boards_in is None:
        boards_in = []
    if not isinstance(boards_in, list):
        raise ArucoError(f"marker map: boards must be a list, got {type(boards_in).__name__}")
    boards = tuple(_map_board(entry, i, dictionary, count, markers) for i, entry in enumerate(boards_in))
    return ArucoMap(dictionary, markers, boards)


#: A board's stored chessboard corners and its markers' corners must agree with its layout and
#: pose to this (metres; JSON round trips are exact, a hand edit is not).
BOARD_TOLERANCE_M = 1e-6


def _map_board(entry: object, index: int, dictionary: str, count: int, markers: dict[int, MapMarker]) -> MapBoard:
    """A ``boards`` entry checked against its layout, its pose and the map's markers."""
    where = f"marker map: board {index}"
    if not isinstance(entry, dict):
        raise ArucoError(f"{where} must be an object, got {type(entry).__name__}")
    if entry.get("type", "charuco") != "charuco":
        raise ArucoError(f"{where}: type {_shown(entry.get('type'))} is not supported; only 'charuco'")
    if entry.get("dictionary", dictionary) != dictionary:
        raise ArucoError(f"{where}: dictionary {_shown(entry.get('dictionary'))} differs from the map's {dictionary!r}")
    values = {}
    for key in ("squares_x", "squares_y"):
        v = entry.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or not 2 <= v <= 200:
            raise ArucoError(f"{where}: {key} must be an integer in 2..200, got {_shown(v)}")
        values[key] = v
    for key in ("square_length_m", "marker_length_m"):
        v = entry.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
            raise ArucoError(f"{where}: {key} must be a positive number, got {_shown(v)}")
        values[key] = float(v)
    if values["marker_length_m"] >= values["square_length_m"]:
        raise ArucoError(f"{where}: marker_length_m must be below square_length_m")
    legacy = entry.get("legacy_pattern", False)
    if not isinstance(legacy, bool):
        raise ArucoError(f"{where}: legacy_pattern must be true or false")
    ids = entry.get("ids")
    n_markers = values["squares_x"] * values["squares_y"] // 2
    if (not isinstance(ids, list) or len(ids) != n_markers
            or any(isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < count for i in ids) or len(set(ids)) != len(ids)):
        raise ArucoError(f"{where}: ids must list {n_markers} distinct ids of {dictionary}")
    frame = entry.get("frame", "world")
    if not (isinstance(frame, str) and frame in ("world", "agv")):
        raise ArucoError(f"{where}: frame {_shown(frame)}; expected 'world' or 'agv'")
    pose = entry.get("pose")
    try:
        pose = np.asarray(pose, dtype=float)
    except (TypeError, ValueError):
        pose = None
    if pose is None or pose.shape != (7,) or not np.all(np.isfinite(pose)) or abs(np.linalg.norm(pose[3:]) - 1.0) > 1e-3:
        raise ArucoError(f"{where}: pose must be [x, y, z, qx, qy, qz, qw] with a unit quaternion")
    T_frame_board = se3.from_quaternion_xyzw(pose[3:] / np.linalg.norm(pose[3:]), pose[:3])
    spec = CharucoSpec(dictionary, values["squares_x"], values["squares_y"], values["square_length_m"],
                       values["marker_length_m"], tuple(ids), legacy)
    check_board_frame(spec)
    points_board_m = chessboard_corners_board_m(spec)
    corners_m = se3.transform_points(T_frame_board, points_board_m)
    if "chessboard_corners_m" in entry:
        try:
            stored = np.asarray(entry["chessboard_corners_m"], dtype=float)
        except (TypeError, ValueError):
            stored = None
        if stored is None or stored.shape != corners_m.shape or not np.all(np.abs(stored - corners_m) <= BOARD_TOLERANCE_M):
            raise ArucoError(f"{where}: chessboard_corners_m are not the {len(corners_m)} corners of its layout at its pose")
    expected = charuco_marker_corners(spec.squares_x, spec.squares_y, spec.square_length_m, spec.marker_length_m,
                                      dictionary, list(ids), legacy)
    for marker_id in ids:
        marker = markers.get(marker_id)
        if marker is None or marker.frame != frame:
            raise ArucoError(f"{where}: its marker {marker_id} is not among the map's markers (in frame {frame!r})")
        if not np.all(np.abs(se3.transform_points(T_frame_board, expected[marker_id]) - marker.corners_m) <= BOARD_TOLERANCE_M):
            raise ArucoError(f"{where}: marker {marker_id}'s corners are not where the board puts them")
    return MapBoard(spec, frame, T_frame_board, points_board_m, corners_m)


def _shown(value: object) -> str:
    """A short, never-failing description of an untrusted value for an error message."""
    if isinstance(value, str) and len(value) <= 40:
        return repr(value)
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() <= 64:
        return str(value)
    return f"of type {type(value).__name__}"


#: Largest accepted |corner coordinate| of a marker map (metres): far beyond any site, small
#: enough that the frame construction cannot overflow (1000 km; float spacing there 1e-10 m).
MAX_ABS_CORNER_M = 1e6


def _corners(value: object, marker_id: int) -> np.ndarray:
    """(4, 3) finite real corners within ±MAX_ABS_CORNER_M, else ArucoError."""
    expected = f"marker map: marker {marker_id}: corners_world_m must be 4 points [x, y, z] in metres"
    if isinstance(value, (str, bytes, dict)) or value is None:
        raise ArucoError(expected)
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError, OverflowError):  # ragged, or not array-like
        raise ArucoError(expected) from None
    if raw.shape != (4, 3) or raw.dtype.kind not in "iuf":  # no bools, strings, objects
        raise ArucoError(expected)
    corners = raw.astype(float)
    if not np.all(np.isfinite(corners)) or np.max(np.abs(corners)) > MAX_ABS_CORNER_M:
        raise ArucoError(f"{expected}, finite and within ±{MAX_ABS_CORNER_M:g} m")
    return corners
