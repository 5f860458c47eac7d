"""Side files: what a robot's own log lacks — the marker map, a camera calibration, a camera
extrinsic (``agvviz run LOG --markers FILE --calibration CAM=FILE --extrinsic CAM=x,y,z,qx,qy,qz,qw``).

Each loader returns the value the recording reader yields for the same role, so the replay
cannot tell a side file from a recorded message:

* :func:`load_marker_map` → the ``agvviz.MarkerMap`` dict of ``/markers/map``;
* :func:`load_calibration` → :class:`~agvviz.model.messages.CalibrationMsg`;
* :func:`parse_extrinsic` → :class:`~agvviz.model.messages.FrameTransformMsg`.

Longer than 600 lines because the three loaders share their parsing helpers and
their error style (numbers, poses, YAML/JSON reading, :class:`SideFileError`); split apart, the
calibration and extrinsic loaders would import the marker-map loader's private helpers.

Every problem raises :class:`SideFileError` (an :class:`~agvviz.errors.InputError`, exit code 2)
whose message is one line naming the file (or the option) and what is wrong.

Marker maps (YAML or JSON; docs/robot-logs.md "Side files")
-----------------------------------------------------------
The in-recording ``agvviz.MarkerMap`` JSON is accepted as is (a map lifted out of one recording
works for another). On top of it a side file may

* give a marker by its ``pose`` (``[x, y, z, qx, qy, qz, qw]``, the marker frame of
  :mod:`agvviz.conventions` in ``frame``) and ``side_m`` instead of its four corners;
* give an integer ``id`` (ArUco / AprilTag ids are integers);
* list a QR code by its ``payload`` alone: the strict parser (:func:`agvviz.markers.parse_payload`)
  gives its id and world corners;
* list ChArUco ``boards`` by their parameters and pose; each expands to its ArUco markers'
  corners. Board frame: origin at the board's bottom-left outer corner as printed, x along the
  bottom edge, y up the left edge, z out of the printed face (the marker frame's axes).
  OpenCV (≥ 4.6) puts the origin at the top-left with y down and z into the board: a point
  (x, y, z) of OpenCV's board frame is (x, H − y, −z) here, H = ``squares_y`` ·
  ``square_length_m``.

The result is checked as strictly as a recorded map (its JSON schema, then what the replay
checks: a known dictionary, ids inside it, corners that span a plane) and more: unknown keys,
duplicate ids, corners that are not a convex quadrilateral in TL, TR, BR, BL order, a
``side_m`` that disagrees with the corners, QR corners that disagree with the payload.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.errors import InputError
from agvviz.geometry import PinholeCamera, se3
from agvviz.model.messages import CalibrationMsg, FrameTransformMsg
from agvviz.recording.values import image_size_problem
from agvviz.recording.schemas import MARKER_MAP, validate

#: The dictionary name of QR-code maps.
QR_DICTIONARY = "qr"
#: Marker frames a map may place markers in.
MAP_FRAMES = (WORLD_FRAME, AGV_FRAME)
#: A marker's edges may differ from its ``side_m`` by this much (relative) plus
#: :data:`SIDE_TOLERANCE_M`; four corners typed by hand to the millimetre pass.
SIDE_TOLERANCE_REL = 0.01
SIDE_TOLERANCE_M = 1e-3
#: A quaternion whose norm is further than this from 1 is refused (not silently normalised).
QUATERNION_NORM_TOLERANCE = 1e-3
#: Largest ChArUco board side in squares.
MAX_BOARD_SQUARES = 200
#: Accepted AprilTag dictionaries (OpenCV's names; DICT_APRILTAG_36h10 is refused, see
#: agvviz.markers.apriltag); any OpenCV ArUco dictionary works too.
APRILTAG_DICTIONARIES = ("DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h11")

_MAP_KEYS = {"dictionary", "markers", "boards"}
_MARKER_KEYS = {"id", "side_m", "corners_world_m", "pose", "payload", "frame"}
_BOARD_KEYS = {
    "type", "squares_x", "squares_y", "square_length_m", "marker_length_m", "dictionary",
    "pose", "frame", "first_id", "ids", "legacy_pattern",
}


class SideFileError(InputError):
    """A side file (or side-file option) that cannot be used; the message names it and why."""


# -- shared helpers ----------------------------------------------------------------------------
def _number(value, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{what} must be a finite number, got {value!r}")
    return float(value)


def _pose_matrix(values, what: str) -> np.ndarray:
    """4×4 from ``[x, y, z, qx, qy, qz, qw]`` (metres, unit quaternion)."""
    if isinstance(values, str):
        values = [v.strip() for v in values.split(",")]
        try:
            values = [float(v) for v in values]
        except ValueError:
            raise ValueError(f"{what} must be 7 numbers x,y,z,qx,qy,qz,qw") from None
    if not isinstance(values, (list, tuple)) or len(values) != 7:
        raise ValueError(f"{what} must be 7 numbers [x, y, z, qx, qy, qz, qw], got {values!r}")
    numbers = [_number(v, what) for v in values]
    q = np.array(numbers[3:])
    with np.errstate(over="ignore"):  # a huge component gives norm inf, refused below
        norm = float(np.linalg.norm(q))
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        raise ValueError(
            f"{what}: quaternion (qx, qy, qz, qw) = {numbers[3:]} has norm {norm:.6g}, not 1 "
            f"(within {QUATERNION_NORM_TOLERANCE:g})"
        )
    return se3.from_quaternion_xyzw(q / norm, np.array(numbers[:3]))


def _read_structured(path: Path) -> object:
    """A YAML or JSON document (JSON by the ``.json`` suffix, YAML otherwise)."""
    import yaml

    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SideFileError(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise SideFileError(f"{path}: not a UTF-8 text file") from None
    except OSError as exc:
        raise SideFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    try:
        if path.suffix.lower() == ".json":
            return json.loads(text)
        return yaml.safe_load(text)
    except json.JSONDecodeError as exc:
        raise SideFileError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise SideFileError(f"{path}: not valid YAML{where}: {problem}") from None


# -- marker maps -------------------------------------------------------------------------------
def load_marker_map(path) -> dict:
    """The ``agvviz.MarkerMap`` dict of a YAML or JSON marker-map side file.

    Parameters
    ----------
    path : str or Path
        ``.json`` is read as JSON, anything else as YAML (which also reads JSON).

    Returns
    -------
    dict
        ``{"dictionary": str, "markers": [{"id": str, "side_m": float, "corners_world_m":
        [[x, y, z]] * 4, "payload"?: str, "frame"?: "agv"}], "boards"?: [...]}`` — exactly what
        the reader yields for ``/markers/map``; boards are expanded into their markers and kept
        under ``boards`` (layout, pose, chessboard corners in their frame).

    Raises
    ------
    SideFileError
        One line: the file and the first problem found (module docstring).
    """
    path = Path(path)
    document = _read_structured(path)
    try:
        return marker_map_from_document(document)
    except ValueError as exc:
        raise SideFileError(f"marker map {path}: {exc}") from None


def marker_map_from_document(document: object) -> dict:
    """:func:`load_marker_map` on an already parsed document; raises ``ValueError``."""
    from agvviz.markers.aruco import parse_aruco_map
    from agvviz.markers.dictionary import aruco_dictionary
    from agvviz.markers.types import ArucoError

    if not isinstance(document, dict):
        raise ValueError(f"expected a mapping with 'dictionary' and 'markers', got {type(document).__name__}")
    unknown = sorted(set(map(str, document)) - _MAP_KEYS)
    if unknown:
        raise ValueError(f"unknown key(s) {unknown}; expected {sorted(_MAP_KEYS)}")
    dictionary = document.get("dictionary")
    if not isinstance(dictionary, str) or not dictionary:
        raise ValueError("'dictionary' must name an OpenCV ArUco/AprilTag dictionary (e.g. DICT_6X6_250) or 'qr'")
    is_qr = dictionary == QR_DICTIONARY
    if not is_qr:
        try:
            count = aruco_dictionary(dictionary).bytesList.shape[0]
        except ArucoError as exc:
            raise ValueError(str(exc)) from None
    markers_in = document.get("markers", [])
    boards_in = document.get("boards", [])
    if markers_in is None:
        markers_in = []
    if boards_in is None:
        boards_in = []
    if not isinstance(markers_in, list) or not isinstance(boards_in, list):
        raise ValueError("'markers' and 'boards' must be lists")
    if not markers_in and not boards_in:
        raise ValueError("the map lists no markers and no boards")
    if boards_in and is_qr:
        raise ValueError("boards are ChArUco boards of ArUco markers; a 'qr' map cannot hold them")

    markers: list[dict] = []
    for i, entry in enumerate(markers_in):
        where = f"markers[{i}]"
        marker = _qr_marker(entry, where) if is_qr else _aruco_marker(entry, where, dictionary, count)
        markers.append(marker)
    boards: list[dict] = []
    for i, board in enumerate(boards_in):
        if isinstance(board, dict) and "chessboard_corners_m" in board:
            # A board of an agvviz.MarkerMap (a map lifted out of a recording): its markers are
            # listed already; parse_aruco_map below checks it against them.
            boards.append(board)
            continue
        board_markers, board_entry = _charuco_markers(board, f"boards[{i}]", dictionary)
        markers.extend(board_markers)
        boards.append(board_entry)

    seen: dict[str, int] = {}  # the replay looks markers up by id alone, whatever their frame
    for i, marker in enumerate(markers):
        key = marker["id"]
        if key in seen:
            raise ValueError(f"marker id {marker['id']!r} appears twice (entries {seen[key]} and {i} after expanding boards)")
        seen[key] = i

    result = {"dictionary": dictionary, "markers": markers}
    if boards:
        result["boards"] = boards
    problems = validate(MARKER_MAP, result)
    if problems:
        raise ValueError("; ".join(problems[:3]))
    if not is_qr:
        try:
            parse_aruco_map(result)  # what the replay checks on a recorded map
        except (ArucoError, ValueError) as exc:
            raise ValueError(str(exc).removeprefix("marker map: ")) from None
    return result


def _check_keys(entry: object, allowed: set[str], where: str) -> dict:
    if not isinstance(entry, dict):
        raise ValueError(f"{where} must be a mapping, got {type(entry).__name__}")
    unknown = sorted(set(map(str, entry)) - allowed)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(allowed)}")
    return entry


def _frame(entry: dict, where: str) -> str:
    frame = entry.get("frame", WORLD_FRAME)
    if frame not in MAP_FRAMES:
        raise ValueError(f"{where}: frame {frame!r} must be one of {list(MAP_FRAMES)}")
    return frame


def _corners(value, where: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != 4:
        raise ValueError(f"{where}: corners_world_m must be 4 points [x, y, z] (TL, TR, BR, BL)")
    rows = []
    for j, point in enumerate(value):
        if not isinstance(point, list) or len(point) != 3:
            raise ValueError(f"{where}: corners_world_m[{j}] must be [x, y, z] in metres, got {point!r}")
        rows.append([_number(v, f"{where}: corners_world_m[{j}]") for v in point])
    return np.array(rows)


def _check_square(corners: np.ndarray, side_m: float | None, where: str) -> float:
    """Mean edge length of ``corners`` after checking they are a convex quadrilateral in TL,
    TR, BR, BL order whose edges match ``side_m``."""
    from agvviz.geometry.plane import DegenerateGeometryError, marker_frame_from_corners

    edges = np.roll(corners, -1, axis=0) - corners
    lengths = np.linalg.norm(edges, axis=1)
    if np.min(lengths) < 1e-9:
        raise ValueError(f"{where}: marker corners coincide")
    # Newell's normal of the polygon; every turn must agree with it (a bow-tie — two corners
    # swapped — has a near-zero normal or turns of both signs).
    normal = np.cross(corners, np.roll(corners, -1, axis=0)).sum(axis=0)
    turns = np.cross(edges, np.roll(edges, -1, axis=0)) @ normal
    if np.linalg.norm(normal) < 1e-9 * np.max(lengths) ** 2 or not np.all(turns > 0):
        raise ValueError(f"{where}: corners are not a convex quadrilateral in TL, TR, BR, BL order (as printed)")
    try:
        marker_frame_from_corners(corners)  # planarity, as the replay checks it
    except DegenerateGeometryError as exc:
        raise ValueError(f"{where}: {exc}") from None
    mean = float(lengths.mean())
    reference = mean if side_m is None else side_m
    worst = float(np.max(np.abs(lengths - reference)))
    if worst > SIDE_TOLERANCE_REL * reference + SIDE_TOLERANCE_M:
        raise ValueError(
            f"{where}: corner edges {np.round(lengths, 4).tolist()} m do not match a square of side "
            f"{reference:g} m (tolerance {SIDE_TOLERANCE_REL:.0%} + {SIDE_TOLERANCE_M * 1000:g} mm)"
        )
    return mean


def _square_from_pose(T_frame_marker: np.ndarray, side_m: float) -> np.ndarray:
    from agvviz.geometry.plane import square_points_marker

    return se3.transform_points(T_frame_marker, square_points_marker(side_m))


def _side(entry: dict, where: str, required: bool) -> float | None:
    if "side_m" not in entry:
        if required:
            raise ValueError(f"{where}: side_m is required with a pose")
        return None
    side = _number(entry["side_m"], f"{where}: side_m")
    if side <= 0:
        raise ValueError(f"{where}: side_m must be > 0, got {side:g}")
    return side


def _aruco_marker(entry: object, where: str, dictionary: str, count: int) -> dict:
    entry = _check_keys(entry, _MARKER_KEYS - {"payload"}, where)
    marker_id = entry.get("id")
    if isinstance(marker_id, bool) or not (
        isinstance(marker_id, int) or (isinstance(marker_id, str) and marker_id.isascii() and marker_id.isdigit())
    ):
        raise ValueError(f"{where}: id must be a non-negative integer id of {dictionary}, got {marker_id!r}")
    marker_id = int(marker_id)
    if not 0 <= marker_id < count:
        raise ValueError(f"{where}: id {marker_id} is not an id of {dictionary} (0..{count - 1})")
    where = f"{where} (id {marker_id})"
    empty = [key for key in ("side_m", "pose", "corners_world_m") if key in entry and entry[key] is None]
    if empty:
        raise ValueError(f"{where}: {' and '.join(empty)} empty — fill in the marker's size and position, or "
                         "remove the entry (docs/starting-without-a-map.md)")
    frame = _frame(entry, where)
    has_corners, has_pose = "corners_world_m" in entry, "pose" in entry
    if has_corners == has_pose:
        raise ValueError(f"{where}: give either corners_world_m or pose (with side_m), not {'both' if has_pose else 'neither'}")
    side = _side(entry, where, required=has_pose)
    if has_pose:
        corners = _square_from_pose(_pose_matrix(entry["pose"], f"{where}: pose"), side)
    else:
        corners = _corners(entry["corners_world_m"], where)
    mean_side = _check_square(corners, side, where)
    marker = {"id": str(marker_id), "side_m": side if side is not None else mean_side, "corners_world_m": corners.tolist()}
    if frame != WORLD_FRAME:
        marker["frame"] = frame
    return marker


def _qr_marker(entry: object, where: str) -> dict:
    from agvviz.markers.payload import PayloadError, parse_payload
    from agvviz.recording.checks import PAYLOAD_MAP_TOLERANCE_M

    entry = _check_keys(entry, _MARKER_KEYS, where)
    frame = _frame(entry, where)
    payload_text = entry.get("payload")
    corners = None
    if payload_text is not None:
        if not isinstance(payload_text, str):
            raise ValueError(f"{where}: payload must be the code's text, got {type(payload_text).__name__}")
        try:
            payload = parse_payload(payload_text)
        except PayloadError as exc:
            raise ValueError(f"{where}: payload refused: {exc}") from None
        marker_id = payload.marker_id
        if "id" in entry and str(entry["id"]) != marker_id:
            raise ValueError(f"{where}: id {entry['id']!r} differs from the payload's id {marker_id!r}")
        payload_corners = np.asarray(payload.points_world_m, dtype=float)[:4]
        corners = payload_corners
    else:
        marker_id = entry.get("id")
        if isinstance(marker_id, bool) or not isinstance(marker_id, (str, int)) or str(marker_id) == "":
            raise ValueError(f"{where}: a QR code needs its payload or an id, got id {marker_id!r}")
        marker_id = str(marker_id)
    where = f"{where} (id {marker_id})"
    side = _side(entry, where, required="pose" in entry)
    if "pose" in entry and "corners_world_m" in entry:
        raise ValueError(f"{where}: give either corners_world_m or pose (with side_m), not both")
    given = None
    if "pose" in entry:
        given = _square_from_pose(_pose_matrix(entry["pose"], f"{where}: pose"), side)
    elif "corners_world_m" in entry:
        given = _corners(entry["corners_world_m"], where)
    if given is not None and corners is not None:
        error = float(np.max(np.linalg.norm(given - corners, axis=1)))
        if error > PAYLOAD_MAP_TOLERANCE_M:
            raise ValueError(
                f"{where}: corners are up to {error * 1000:.1f} mm from the payload's vertices "
                f"(tolerance {PAYLOAD_MAP_TOLERANCE_M * 1000:g} mm)"
            )
    if given is not None:
        corners = given  # as given (they agree with the payload): a recorded map stays as it is
    elif corners is None:
        raise ValueError(f"{where}: a QR code without a payload needs corners_world_m or a pose")
    mean_side = _check_square(corners, side, where)
    marker = {"id": marker_id, "side_m": side if side is not None else mean_side, "corners_world_m": corners.tolist()}
    if payload_text is not None:
        marker["payload"] = payload_text
    if frame != WORLD_FRAME:
        marker["frame"] = frame
    return marker


def _positive_int(board: dict, key: str, where: str, low: int, high: int) -> int:
    value = board.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"{where}: {key} must be an integer in {low}..{high}, got {value!r}")
    return value


def _charuco_markers(board: object, where: str, dictionary: str) -> tuple[list[dict], dict]:
    """The board's markers (map entries) and the board's own map entry (its layout, pose and
    chessboard corners in its frame: the ``boards`` of ``agvviz.MarkerMap``)."""
    from agvviz.markers.dictionary import aruco_dictionary
    from agvviz.markers.charuco import CharucoSpec, charuco_marker_corners, chessboard_corners_board_m

    board = _check_keys(board, _BOARD_KEYS, where)
    if board.get("type", "charuco") != "charuco":
        raise ValueError(f"{where}: type {board.get('type')!r} is not supported; only 'charuco' boards")
    if board.get("dictionary", dictionary) != dictionary:
        raise ValueError(
            f"{where}: dictionary {board.get('dictionary')!r} differs from the map's {dictionary!r} "
            "(a map holds one dictionary)"
        )
    squares_x = _positive_int(board, "squares_x", where, 2, MAX_BOARD_SQUARES)
    squares_y = _positive_int(board, "squares_y", where, 2, MAX_BOARD_SQUARES)
    square = _number(board.get("square_length_m"), f"{where}: square_length_m")
    marker = _number(board.get("marker_length_m"), f"{where}: marker_length_m")
    if not 0 < marker < square:
        raise ValueError(f"{where}: need 0 < marker_length_m ({marker:g}) < square_length_m ({square:g})")
    if "pose" not in board:
        raise ValueError(f"{where}: pose [x, y, z, qx, qy, qz, qw] of the board frame is required")
    T_frame_board = _pose_matrix(board["pose"], f"{where}: pose")
    frame = _frame(board, where)
    legacy = board.get("legacy_pattern", False)
    if not isinstance(legacy, bool):
        raise ValueError(f"{where}: legacy_pattern must be true or false")
    n_markers = (squares_x * squares_y) // 2
    count = aruco_dictionary(dictionary).bytesList.shape[0]
    if "ids" in board and "first_id" in board:
        raise ValueError(f"{where}: give ids or first_id, not both")
    if "ids" in board:
        ids = board["ids"]
        if not isinstance(ids, list) or any(isinstance(i, bool) or not isinstance(i, int) for i in ids):
            raise ValueError(f"{where}: ids must be a list of integers")
        if len(ids) != n_markers:
            raise ValueError(f"{where}: ids lists {len(ids)} ids; a {squares_x}x{squares_y} board has {n_markers} markers")
    else:
        first = board.get("first_id", 0)
        if isinstance(first, bool) or not isinstance(first, int) or first < 0:
            raise ValueError(f"{where}: first_id must be a non-negative integer, got {first!r}")
        ids = list(range(first, first + n_markers))
    bad = [i for i in ids if not 0 <= i < count]
    if bad:
        raise ValueError(f"{where}: marker ids {bad[:5]} are outside {dictionary} (0..{count - 1})")
    if len(set(ids)) != len(ids):
        raise ValueError(f"{where}: ids repeat")
    corners = charuco_marker_corners(squares_x, squares_y, square, marker, dictionary, ids, legacy)
    out = []
    for marker_id in ids:
        world = se3.transform_points(T_frame_board, corners[marker_id])
        entry = {"id": str(marker_id), "side_m": marker, "corners_world_m": world.tolist()}
        if frame != WORLD_FRAME:
            entry["frame"] = frame
        out.append(entry)
    spec = CharucoSpec(dictionary, squares_x, squares_y, square, marker, tuple(ids), legacy)
    board_entry = {
        "type": "charuco", "squares_x": squares_x, "squares_y": squares_y, "square_length_m": square,
        "marker_length_m": marker, "dictionary": dictionary, "legacy_pattern": legacy, "ids": list(ids),
        "pose": [float(v) for v in T_frame_board[:3, 3]] + [float(v) for v in se3.to_quaternion_xyzw(T_frame_board)],
        "chessboard_corners_m": se3.transform_points(T_frame_board, chessboard_corners_board_m(spec)).tolist(),
    }
    if frame != WORLD_FRAME:
        board_entry["frame"] = frame
    return out, board_entry


# -- calibration -------------------------------------------------------------------------------
_K_KEYS = ("camera_matrix", "cameraMatrix", "K")
_D_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
_WIDTH_KEYS = ("image_width", "width")
_HEIGHT_KEYS = ("image_height", "height")


def load_calibration(cam_name: str, path) -> CalibrationMsg:
    """The calibration of camera ``cam_name`` from a YAML file.

    Accepted: a ROS ``camera_info`` YAML (``camera_calibration`` / ``camera_info_manager``:
    ``image_width``, ``image_height``, ``camera_matrix: {rows, cols, data}``,
    ``distortion_model``, ``distortion_coefficients``), a ``sensor_msgs/CameraInfo`` message
    dumped as YAML (``width``, ``height``, ``k``, ``d``, ``distortion_model``), or an OpenCV
    FileStorage YAML or XML (``%YAML:1.0``, ``!!opencv-matrix`` or ``<?xml``; read with
    ``cv2.FileStorage``: ``camera_matrix`` or
    ``cameraMatrix``, ``distortion_coefficients`` or ``distCoeffs``, ``image_width``,
    ``image_height``). Distortion: plumb_bob (up to 5 coefficients k1, k2, p1, p2, k3) or
    rational_polynomial (8); OpenCV's longer models only when their extra coefficients are 0.

    Raises :class:`SideFileError` naming the file and the problem.
    """
    path = Path(path)
    try:
        head = path.read_bytes()[:64]
    except FileNotFoundError:
        raise SideFileError(f"calibration {path}: no such file") from None
    except OSError as exc:
        raise SideFileError(f"calibration {path}: cannot be read ({exc.strerror or exc})") from None
    try:
        if (
            head.lstrip().startswith((b"%YAML:", b"<?xml"))
            or b"!!opencv-matrix" in path.read_bytes()[:65536]
        ):
            K, D, width, height, model = _opencv_filestorage(path)
        else:
            K, D, width, height, model = _ros_camera_info(_read_structured(path))
        problem = image_size_problem(width, height)
        if problem:
            raise ValueError(problem)
        D = _usable_distortion(D, model)
        camera = PinholeCamera(K, D, width, height)
    except SideFileError as exc:
        raise SideFileError(f"calibration {exc}") from None
    except ValueError as exc:
        raise SideFileError(f"calibration {path}: {exc}") from None
    model_name = "" if not np.any(D) else ("rational_polynomial" if len(D) == 8 else "plumb_bob")
    return CalibrationMsg(cam_name, camera_frame(cam_name), camera, model_name)


def _matrix(value, what: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    if isinstance(value, dict) and "data" in value:
        data = value["data"]
        rows, cols = value.get("rows"), value.get("cols")
    else:
        data, rows, cols = value, None, None
    if not isinstance(data, list) or not data:
        raise ValueError(f"{what} must be a list of numbers (or {{rows, cols, data}}), got {value!r}")
    flat = [_number(v, what) for v in (np.asarray(data, dtype=object).ravel().tolist())]
    for key, count in (("rows", rows), ("cols", cols)):
        if count is not None and (isinstance(count, bool) or not isinstance(count, int)):
            raise ValueError(f"{what}: {key} must be an integer, got {count!r}")
    if rows is not None and cols is not None and rows * cols != len(flat):
        raise ValueError(f"{what}: rows × cols = {rows}×{cols} but data has {len(flat)} numbers")
    array = np.array(flat, dtype=float)
    if shape is not None:
        if array.size != int(np.prod(shape)):
            raise ValueError(f"{what} must have {int(np.prod(shape))} numbers, got {array.size}")
        array = array.reshape(shape)
    return array


def _first(document: dict, keys: tuple[str, ...]):
    for key in keys:
        if key in document:
            return document[key]
    return None


def _integer(value, what: str) -> int:
    if (
        isinstance(value, bool) or not isinstance(value, (int, float))
        or not math.isfinite(value) or value != int(value)
    ):
        raise ValueError(f"{what} must be an integer number of pixels, got {value!r}")
    return int(value)


def _ros_camera_info(document: object):
    if not isinstance(document, dict):
        raise ValueError("expected a ROS camera_info YAML (image_width, image_height, camera_matrix, ...)")
    K_value = _first(document, _K_KEYS + ("k",))
    if K_value is None:
        raise ValueError(
            "no camera matrix: expected a ROS camera_info YAML (camera_matrix: {rows, cols, data}), "
            "a CameraInfo message (k: [...]) or an OpenCV FileStorage YAML starting with %YAML:1.0"
        )
    width = _first(document, _WIDTH_KEYS)
    height = _first(document, _HEIGHT_KEYS)
    if width is None or height is None:
        raise ValueError("image size missing: expected image_width and image_height (or width and height)")
    D_value = _first(document, _D_KEYS + ("d",))
    D = np.zeros(0) if D_value in (None, []) else _matrix(D_value, "distortion_coefficients").ravel()
    model = document.get("distortion_model", "plumb_bob" if D.size else "")
    if not isinstance(model, str):
        raise ValueError(f"distortion_model must be a name, got {model!r}")
    return (
        _matrix(K_value, "camera_matrix", (3, 3)), D,
        _integer(width, "image_width"), _integer(height, "image_height"), model,
    )


def _opencv_filestorage(path: Path):
    import cv2

    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise ValueError(f"not a readable OpenCV FileStorage file ({str(exc).strip().splitlines()[-1][:120]})") from None
    try:
        if not storage.isOpened():
            raise ValueError("not a readable OpenCV FileStorage file")

        def node(keys):
            for key in keys:
                n = storage.getNode(key)
                if not n.empty():
                    return n
            return None

        K_node = node(_K_KEYS)
        if K_node is None:
            raise ValueError(f"no camera matrix (expected one of {list(_K_KEYS)})")
        K = K_node.mat()
        if K is None:
            raise ValueError("camera_matrix is not an opencv-matrix")
        D_node = node(_D_KEYS)
        D = np.zeros(0) if D_node is None or D_node.mat() is None else D_node.mat().astype(float).ravel()
        w_node, h_node = node(_WIDTH_KEYS), node(_HEIGHT_KEYS)
        if w_node is None or h_node is None or not w_node.isInt() or not h_node.isInt():
            raise ValueError("image size missing: expected integer image_width and image_height")
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise ValueError(f"camera_matrix must be 3x3, got {K.shape[0]}x{K.shape[1] if K.ndim > 1 else 1}")
        if not np.all(np.isfinite(K)) or not np.all(np.isfinite(D)):
            raise ValueError("camera_matrix or distortion_coefficients contain NaN/inf")
        return K, D, int(w_node.real()), int(h_node.real()), "plumb_bob" if D.size else ""
    finally:
        storage.release()


def _usable_distortion(D: np.ndarray, model: str) -> np.ndarray:
    """Coefficients for :class:`PinholeCamera`: up to 5 (plumb_bob) or 8 (rational_polynomial)."""
    if model not in ("", "plumb_bob", "rational_polynomial"):
        raise ValueError(
            f"distortion_model {model!r} is not supported; expected plumb_bob or rational_polynomial"
        )
    if D.size <= 5:
        return D
    if D.size == 8 or np.all(D[8:] == 0):
        D8 = D[:8]
        return D8 if np.any(D8[5:] != 0) else D8[:5]
    raise ValueError(
        f"{D.size} distortion coefficients with non-zero thin-prism/tilt terms are not supported "
        "(plumb_bob: up to 5, rational_polynomial: 8)"
    )


# -- extrinsic ---------------------------------------------------------------------------------
def parse_extrinsic(cam_name: str, text: str, body_frame: str) -> FrameTransformMsg:
    """``T_body_cam`` of camera ``cam_name`` from ``x,y,z,qx,qy,qz,qw``.

    The camera's pose in ``body_frame``: position in metres and a unit quaternion (x, y, z, w,
    norm within :data:`QUATERNION_NORM_TOLERANCE` of 1, then normalised); the camera frame is
    OpenCV's optical frame (x right, y down, z along the optical axis), ``cam_<name>``.
    Example: a camera 0.3 m forward of ``base_link`` (x forward, z up, REP 103) looking
    forward: ``0.3,0,0.2,-0.5,0.5,-0.5,0.5``.

    Raises :class:`SideFileError` naming the option and the problem.
    """
    try:
        if not isinstance(text, str):
            raise ValueError(f"expected text x,y,z,qx,qy,qz,qw, got {type(text).__name__}")
        parts = [p.strip() for p in text.strip().split(",")]
        if len(parts) != 7:
            raise ValueError(f"expected 7 comma-separated numbers x,y,z,qx,qy,qz,qw, got {len(parts)}")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"expected numbers x,y,z,qx,qy,qz,qw, got {text.strip()!r}") from None
        T = _pose_matrix(values, "extrinsic")
    except ValueError as exc:
        raise SideFileError(f"--extrinsic {cam_name}={text}: {exc}") from None
    if not isinstance(body_frame, str) or not body_frame:
        raise SideFileError(f"--extrinsic {cam_name}: the body frame must be named")
    return FrameTransformMsg(body_frame, camera_frame(cam_name), T)
