"""ChArUco chessboard (saddle) corners: the board agvviz builds in OpenCV has the geometry of
agvviz's own expansion, the saddles are found where they are, and a board whose layout is
wrong gives no saddles (a note), not wrong ones.

Boards are drawn by OpenCV's own generator (``CharucoBoard.generateImage``: OpenCV is the
reference for ChArUco) and warped by a known homography; the truth of every saddle is that
homography applied to OpenCV's chessboard corner, so nothing here comes from agvviz's geometry.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agvviz.markers.aruco import detect_aruco
from agvviz.markers.charuco import (
    CharucoSpec,
    check_board_frame,
    chessboard_corners_board_m,
    chessboard_id,
    detect_chessboard,
    is_chessboard_id,
    opencv_board,
)
from agvviz.markers.charuco import charuco_marker_corners

SQUARE_PX = 60
SADDLE_TOLERANCE_PX = 0.25
MARGIN_PX = 30
#: The warp: a mild perspective view (the saddles' truth is this map of OpenCV's corners).
H_WARP = np.array([[0.9, 0.12, 40.0], [-0.05, 0.85, 30.0], [2e-4, 1e-4, 1.0]])


def spec_of(dictionary: str, squares: tuple[int, int], legacy: bool) -> CharucoSpec:
    n = squares[0] * squares[1] // 2
    return CharucoSpec(dictionary, squares[0], squares[1], 0.04, 0.03, tuple(range(n)), legacy)


BOARDS = [
    ("DICT_6X6_250", (5, 7), False),
    ("DICT_6X6_250", (5, 6), False),
    ("DICT_6X6_250", (5, 6), True),  # an even number of rows: the legacy pattern differs
    ("DICT_4X4_50", (6, 4), True),
    ("DICT_APRILTAG_36h11", (5, 6), False),  # OpenCV 5.0 draws these turned 180° from print
    ("DICT_APRILTAG_16h5", (4, 4), True),
]


@pytest.mark.parametrize("dictionary,squares,legacy", BOARDS)
def test_opencv_board_is_agvviz_board(dictionary, squares, legacy):
    """OpenCV's board frame maps onto agvviz's by (x, y, z) → (x, H − y, −z) (the side-file
    convention, written out here independently): its chessboard corners onto
    :func:`chessboard_corners_board_m` and its markers' corners onto
    :func:`charuco_marker_corners` (as a set per marker: AprilTag corners are re-ordered to the
    printed order there). :func:`check_board_frame` finds that transform."""
    spec = spec_of(dictionary, squares, legacy)
    board = opencv_board(spec)
    H = squares[1] * spec.square_length_m
    flip = lambda p: np.column_stack([p[:, 0], H - p[:, 1], -p[:, 2]])  # noqa: E731
    chess = flip(np.asarray(board.getChessboardCorners(), float).reshape(-1, 3))
    assert np.allclose(chess, chessboard_corners_board_m(spec), atol=1e-6)
    ours = charuco_marker_corners(*squares, spec.square_length_m, spec.marker_length_m, dictionary, list(spec.ids), legacy)
    for marker_id, points in zip(np.asarray(board.getIds()).ravel(), board.getObjPoints()):
        theirs = flip(np.asarray(points, float).reshape(4, 3))
        mine = ours[int(marker_id)]
        # the same four points, in a cyclic order (a rotation of the corner list, no mirror)
        shifts = [k for k in range(4) if np.allclose(np.roll(theirs, -k, axis=0), mine, atol=1e-6)]
        assert len(shifts) == 1, (marker_id, theirs, mine)
    T = check_board_frame(spec)
    assert np.allclose(T[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-6)  # OpenCV stores float32
    assert np.allclose(T[:3, 3], [0.0, H, 0.0], atol=1e-6)


def render(spec: CharucoSpec, H: np.ndarray = H_WARP, out_size: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(warped gray image, truth pixels (N, 2) of every chessboard corner by id): the drawn
    board (pixel-centre coordinates) mapped by ``H``. Drawn and warped at 4× the size, then
    area-averaged down (an anti-aliased image, like a camera's)."""
    board = opencv_board(spec)
    size = (spec.squares_x * SQUARE_PX + 2 * MARGIN_PX, spec.squares_y * SQUARE_PX + 2 * MARGIN_PX)
    image = board.generateImage((4 * size[0], 4 * size[1]), marginSize=4 * MARGIN_PX, borderBits=1)
    # pixel-centre coordinates: big = A · small (A: ×4 about the pixel edges)
    A = np.array([[4.0, 0.0, 1.5], [0.0, 4.0, 1.5], [0.0, 0.0, 1.0]])
    out_size = out_size or (size[0] + 160, size[1] + 120)
    big = cv2.warpPerspective(image, A @ H @ np.linalg.inv(A), (4 * out_size[0], 4 * out_size[1]),
                              flags=cv2.INTER_LINEAR, borderValue=255)
    out = cv2.resize(big, out_size, interpolation=cv2.INTER_AREA)
    # OpenCV's corner (x, y) m sits at pixel MARGIN + x·SQUARE_PX/square of the unwarped image
    # (pixel edges at integers, so minus 0.5 in pixel-centre coordinates), then the warp.
    corners = np.asarray(board.getChessboardCorners(), float)[:, :2] / spec.square_length_m * SQUARE_PX + MARGIN_PX - 0.5
    h = np.c_[corners, np.ones(len(corners))] @ H.T
    return out, h[:, :2] / h[:, 2:]


def camera_view(spec: CharucoSpec, K: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """The homography drawn board pixels → image of a pinhole camera ``K`` at ``T_cam_board``
    (agvviz's board frame: OpenCV's (x, y) is (x, H − y) there)."""
    s = spec.square_length_m / SQUARE_PX
    drawn_to_opencv = np.array([[s, 0.0, (0.5 - MARGIN_PX) * s], [0.0, s, (0.5 - MARGIN_PX) * s], [0.0, 0.0, 1.0]])
    opencv_to_board = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, spec.squares_y * spec.square_length_m], [0.0, 0.0, 1.0]])
    board_to_image = K @ np.column_stack([T_cam_board[:3, 0], T_cam_board[:3, 1], T_cam_board[:3, 3]])
    return board_to_image @ opencv_to_board @ drawn_to_opencv


def detect(gray: np.ndarray, spec: CharucoSpec):
    refine = "apriltag" if "APRILTAG" in spec.dictionary else "subpix"
    markers = {d.marker_id: d.corners_px for d in detect_aruco(gray, spec.dictionary, refine=refine)}
    return markers, detect_chessboard(gray, spec, 0, markers)


@pytest.mark.parametrize("dictionary,squares,legacy", BOARDS)
def test_saddles_are_found_where_they_are(dictionary, squares, legacy):
    """Every inner saddle is found under its own id, within 0.25 px of the truth: cornerSubPix
    (7×7 window) on an anti-aliased, perspective-warped saddle is good to ≈0.1 px (measured
    ≤ 0.11 px on these boards); a wrong corner id, a turned or mirrored board would put a
    saddle a whole square (≥ 40 px here) away."""
    spec = spec_of(dictionary, squares, legacy)
    gray, truth_px = render(spec)
    markers, found = detect(gray, spec)
    assert len(markers) == len(spec.ids)
    assert found is not None and found.note == "", found and found.note
    assert sorted(found.corner_ids) == list(range(spec.n_chessboard_corners))
    error = np.linalg.norm(found.corners_px - truth_px[found.corner_ids], axis=1)
    assert error.max() < SADDLE_TOLERANCE_PX, error.max()


@pytest.mark.parametrize("dictionary,squares", [("DICT_6X6_250", (5, 6)), ("DICT_APRILTAG_36h11", (5, 6)), ("DICT_4X4_50", (6, 4))])
def test_a_wrong_legacy_flag_gives_no_saddles_and_says_why(dictionary, squares):
    """A board printed with one pattern and described with the other (even row count: the
    patterns differ): its markers are not where the described board puts them, so no saddle
    is used and the note names the layout."""
    printed = spec_of(dictionary, squares, legacy=False)
    described = spec_of(dictionary, squares, legacy=True)
    gray, _ = render(printed)
    _, found = detect(gray, described)
    assert found is not None and len(found.corner_ids) == 0
    assert "do not lie where the board places them" in found.note and "legacy_pattern" in found.note
    assert found.misplaced_ids, found.note


def test_a_board_of_odd_rows_is_the_same_in_both_patterns():
    """5×7 (the real photos' board): the legacy flag changes nothing, so either is right."""
    a, b = spec_of("DICT_6X6_250", (5, 7), False), spec_of("DICT_6X6_250", (5, 7), True)
    gray, truth_px = render(a)
    _, found = detect(gray, b)
    assert found.note == "" and len(found.corner_ids) == a.n_chessboard_corners
    assert np.linalg.norm(found.corners_px - truth_px[found.corner_ids], axis=1).max() < SADDLE_TOLERANCE_PX


def test_the_chessboard_name():
    assert chessboard_id(2) == "board2:chessboard" and is_chessboard_id("board2:chessboard")
    assert not is_chessboard_id("12")


def board_map() -> dict:
    from agvviz.recording.sidefiles import marker_map_from_document

    return marker_map_from_document({
        "dictionary": "DICT_6X6_250",
        "boards": [dict(type="charuco", squares_x=5, squares_y=6, square_length_m=0.04, marker_length_m=0.03,
                        legacy_pattern=True, pose=[1.0, 2.0, 0.0, 0.0, 0.0, 0.3826834, 0.9238795])],
    })


def test_the_map_keeps_the_board_and_its_chessboard_corners():
    """A side file's board is kept beside its 15 markers (``boards``: layout, pose, the 20
    chessboard corners in the world); the map lifted out as JSON reads back the same, and a
    board entry that disagrees with its layout or markers is refused in one line."""
    import json

    from agvviz.markers.aruco import parse_aruco_map
    from agvviz.markers.types import ArucoError
    from agvviz.recording.schemas import MARKER_MAP, validate
    from agvviz.recording.sidefiles import marker_map_from_document

    marker_map = board_map()
    assert len(marker_map["markers"]) == 15 and validate(MARKER_MAP, marker_map) == []
    (entry,) = marker_map["boards"]
    assert entry["legacy_pattern"] is True and entry["ids"] == list(range(15)) and len(entry["chessboard_corners_m"]) == 20
    lifted = json.loads(json.dumps(marker_map))
    assert marker_map_from_document(lifted) == lifted
    (board,) = parse_aruco_map(lifted).boards
    assert board.spec == spec_of("DICT_6X6_250", (5, 6), True)
    # the corner at the board's top-left inner saddle: (0.04, H − 0.04) in the board frame, turned 45° about z
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    assert np.allclose(board.corners_m[0], [1.0 + c * 0.04 - s * 0.20, 2.0 + s * 0.04 + c * 0.20, 0.0], atol=1e-6)
    assert "boards" not in marker_map_from_document({"dictionary": "DICT_6X6_250", "markers": lifted["markers"]})
    for key, value, message in [
        ("legacy_pattern", False, "not where the board puts them"),
        ("chessboard_corners_m", lifted["boards"][0]["chessboard_corners_m"][:-1], "chessboard_corners_m"),
        ("squares_x", 7, "ids must list"),
    ]:
        bad = json.loads(json.dumps(marker_map))
        bad["boards"][0][key] = value
        with pytest.raises(ArucoError, match=message):
            parse_aruco_map(bad)
        with pytest.raises(ValueError, match=message):
            marker_map_from_document(bad)


def test_detect_params_know_the_boards_and_the_cache_keeps_the_saddles(tmp_path):
    """DetectParams carry the boards (hashable, picklable; another board, another cache key);
    the detection cache stores and returns the saddles."""
    import pickle

    from agvviz.replay.detect import cache as detect_cache
    from agvviz.replay.detect.stage import DetectParams
    from agvviz.model.detections import FrameDetections
    from agvviz.replay.detect.pool import DetectedFrame
    from agvviz.markers.aruco import parse_aruco_map
    from agvviz.markers.charuco import ChessboardCorners

    specs = tuple(b.spec for b in parse_aruco_map(board_map()).boards)
    params = DetectParams(refine="subpix", aruco_dictionary="DICT_6X6_250", charuco_boards=specs)
    assert pickle.loads(pickle.dumps(params)) == params and hash(params) == hash(pickle.loads(pickle.dumps(params)))
    other = DetectParams(refine="subpix", aruco_dictionary="DICT_6X6_250", charuco_boards=(spec_of("DICT_6X6_250", (5, 6), False),))
    assert detect_cache.cache_key(params, {}) != detect_cache.cache_key(other, {})
    found = ChessboardCorners(0, np.array([3, 4]), np.array([[10.25, 20.5], [30.0, 40.125]]), "a note")
    path = tmp_path / "entry.parquet"
    detect_cache.save(path, [DetectedFrame(0, "cam", 5, FrameDetections(chessboards=(found,)))])
    (frame,) = detect_cache.load(path)
    (back,) = frame.detections.chessboards
    assert back.board_index == 0 and back.corner_ids.tolist() == [3, 4] and back.note == "a note"
    assert np.array_equal(back.corners_px, found.corners_px)


def test_a_run_with_the_wrong_legacy_flag_gives_no_pose_and_says_why(tmp_path):
    """A 5×6 board (even rows: the two patterns differ) printed in the new pattern, seen by a
    known camera, replayed with ``agvviz run``: described right, every frame is solved with the
    saddles (``board0:chessboard``) and the camera is where it was (1 mm, 0.1°: noise-free
    render, ≈0.1 px saddles); described with ``legacy_pattern: true``, no frame gets a pose
    and the run's warnings name the board, its misplaced markers and the flag to check. (Without
    that check 12 of the 15 markers agree on a pose one square off — 0.06 px RMS — and the
    joint solve would leave out the other 3: a wrong pose.)"""
    import subprocess
    import sys

    import yaml
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from agvviz.geometry import se3, so3
    from agvviz.viz import paths, readback

    spec = spec_of("DICT_6X6_250", (5, 6), False)
    K = np.array([[700.0, 0.0, 320.0], [0.0, 700.0, 240.0], [0.0, 0.0, 1.0]])
    # camera 0.45 m from the board's centre, turned 15° about x and 10° about y, looking at it
    R = so3.exp(np.radians([180.0 + 15.0, 10.0, 0.0]) * np.array([1.0, 1.0, 1.0]))
    centre = np.array([0.1, 0.12, 0.0])
    T_cam_board = se3.make(R, np.array([0.0, 0.0, 0.45]) - R @ centre)
    gray, _ = render(spec, camera_view(spec, K, T_cam_board), (640, 480))
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    Image = typestore.types["sensor_msgs/msg/CompressedImage"]
    Header, Time = typestore.types["std_msgs/msg/Header"], typestore.types["builtin_interfaces/msg/Time"]
    with Writer(tmp_path / "bag", version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/cam/image_raw/compressed", Image.__msgtype__, typestore=typestore)
        for i in range(3):
            t_ns = 1_700_000_000_000_000_000 + i * 100_000_000
            message = Image(header=Header(stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id="cam"),
                            format="png", data=np.frombuffer(cv2.imencode(".png", gray)[1].tobytes(), np.uint8))
            writer.write(connection, t_ns, typestore.serialize_cdr(message, Image.__msgtype__))
    storage = cv2.FileStorage(str(tmp_path / "calib.yml"), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    storage.write("camera_matrix", K)
    storage.write("distortion_coefficients", np.zeros(5))
    storage.release()
    outcomes = {}
    for legacy in (False, True):
        board = dict(type="charuco", squares_x=5, squares_y=6, square_length_m=0.04, marker_length_m=0.03,
                     legacy_pattern=legacy, pose=[0, 0, 0, 0, 0, 0, 1])
        (tmp_path / "board.yaml").write_text(yaml.safe_dump({"dictionary": "DICT_6X6_250", "boards": [board]}))
        out = tmp_path / f"run_{legacy}.rrd"
        done = subprocess.run(
            [sys.executable, "-m", "agvviz", "run", str(tmp_path / "bag"), "--markers", str(tmp_path / "board.yaml"),
             "--calibration", f"cam={tmp_path / 'calib.yml'}", "--extrinsic", "cam=0,0,0,0,0,0,1",
             "--jobs", "1", "--no-cache", "--out", str(out)],
            capture_output=True, text=True, timeout=600,
        )
        assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
        outcomes[legacy] = (readback.read_rrd(out), done.stdout + done.stderr)
    contents, text = outcomes[False]
    summary = readback.document_json(contents, paths.RUN_SUMMARY)
    assert summary.get("solved", summary.get("frames_solved")) == 3, summary
    frames, _, T_board_cam = readback.transforms(contents, paths.AGV_CAMERA)
    texts = [r["TextDocument:text"][0] for r in readback._rows(contents, paths.LM_THIS_FRAME, "TextDocument:text")]
    assert all("board0:chessboard" in t.split(" — ")[0] for t in texts), texts
    for T in T_board_cam:
        T = np.asarray(T, float)
        assert np.linalg.norm(T[:3, 3] - se3.inverse(T_cam_board)[:3, 3]) < 1e-3
        assert np.degrees(np.linalg.norm(so3.log(T[:3, :3] @ T_cam_board[:3, :3]))) < 0.1
    assert "board0:chessboard" not in text
    contents, text = outcomes[True]
    summary = readback.document_json(contents, paths.RUN_SUMMARY)
    assert summary.get("solved", summary.get("frames_solved")) == 0, text
    assert "board0:chessboard: saddles not used on 3 frame(s)" in text and "legacy_pattern" in text, text
    assert "markers 2, 7, 12 (3 of 15 seen) do not lie where the board places them" in text, text
    assert summary["rejected"] == {"payload_map_mismatch": 3}, summary["rejected"]


def test_saddles_left_out_are_named_apart_from_markers():
    """The run's warnings name a board's saddles left out by the χ² test on their own line
    (what to check for a board), not among the markers 'misplaced in the map'."""
    from agvviz.replay.solve import Replay
    from agvviz.settings import RunSettings

    replay = Replay(RunSettings())
    replay.markers_left_out = {"board0:chessboard": 2, "7": 3}
    lines = replay.warnings()
    (saddles,) = [line for line in lines if "board0:chessboard" in line]
    assert saddles.startswith("board0:chessboard (the board's saddle corners) left out") and "2 frame(s)" in saddles
    (markers,) = [line for line in lines if line.startswith("markers left out")]
    assert "7 (3 frames)" in markers and "chessboard" not in markers
