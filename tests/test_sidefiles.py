"""Side files: marker maps (YAML / JSON, markers, QR payloads, ChArUco boards), calibrations
(ROS camera_info, CameraInfo dumps, OpenCV FileStorage) and extrinsics; every bad file is one
InputError line naming the file."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from agvviz.errors import InputError
from agvviz.geometry import se3
from agvviz.markers.aruco import aruco_modules, detect_aruco, parse_aruco_map
from agvviz.markers.charuco import charuco_marker_corners
from agvviz.markers.payload import QrPayload, encode_payload
from agvviz.model.messages import CalibrationMsg, FrameTransformMsg
from agvviz.recording.sidefiles import (
    APRILTAG_DICTIONARIES,
    SideFileError,
    load_calibration,
    load_marker_map,
    parse_extrinsic,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CHARUCO_CALIBRATION = DATA / "opencv_contrib_aruco" / "tutorial_camera_charuco.yml"


def write(tmp_path: Path, name: str, document) -> Path:
    path = tmp_path / name
    if isinstance(document, str):
        path.write_text(document)
    elif name.endswith(".json"):
        path.write_text(json.dumps(document))
    else:
        path.write_text(yaml.safe_dump(document))
    return path


def refused(path_or_call, match: str):
    """The SideFileError raised, after checking it is one line naming what was wrong."""
    with pytest.raises(SideFileError, match=match) as info:
        path_or_call()
    message = str(info.value)
    assert "\n" not in message and isinstance(info.value, InputError)
    return message


def square(centre, side, z=0.0):
    x, y = centre
    h = side / 2
    return [[x - h, y + h, z], [x + h, y + h, z], [x + h, y - h, z], [x - h, y - h, z]]


# -- marker maps ---------------------------------------------------------------------------------
def qr_code(marker_id: str, centre, side=0.5) -> dict:
    corners = np.array(square(centre, side))
    payload = encode_payload(QrPayload(marker_id, corners))
    return {"id": marker_id, "side_m": side, "corners_world_m": corners.tolist(), "payload": payload}


def test_recorded_map_json_is_accepted_as_is(tmp_path):
    recorded = {"dictionary": "qr", "markers": [qr_code("A1", (1.0, 2.0)), qr_code("A2", (2.0, 2.0))]}
    assert load_marker_map(write(tmp_path, "map.json", recorded)) == recorded
    # The same document as YAML (a superset of JSON).
    assert load_marker_map(write(tmp_path, "map.yaml", json.dumps(recorded))) == recorded
    aruco = {
        "dictionary": "DICT_5X5_50",
        "markers": [
            {"id": "3", "side_m": 0.2, "corners_world_m": square((0.0, 0.0), 0.2, 2.5)},
            {"id": "4", "side_m": 0.2, "corners_world_m": square((0.0, 0.0), 0.2, 0.1), "frame": "agv"},
        ],
    }
    assert load_marker_map(write(tmp_path, "aruco.json", aruco)) == aruco


def test_qr_codes_by_payload_alone(tmp_path):
    code = qr_code("Q7", (3.0, -1.0))
    loaded = load_marker_map(write(tmp_path, "qr.yaml", {"dictionary": "qr", "markers": [{"payload": code["payload"]}]}))
    (marker,) = loaded["markers"]
    assert marker["id"] == "Q7" and marker["payload"] == code["payload"]
    np.testing.assert_allclose(marker["corners_world_m"], code["corners_world_m"], atol=1e-9)
    assert marker["side_m"] == pytest.approx(0.5)


@pytest.mark.parametrize(
    "entry, match",
    [
        ({"payload": "AGV1;id=Q7;mm=0,0;1,0"}, "payload refused"),
        ({"payload": "hello"}, "payload refused: not an agvviz payload"),
        ({"id": "Q8", "payload": "AGV1;id=Q7;mm=-250,250;250,250;250,-250;-250,-250"}, "differs from the payload"),
        (
            {"payload": "AGV1;id=Q7;mm=-250,250;250,250;250,-250;-250,-250", "corners_world_m": square((0.1, 0.0), 0.5)},
            "from the payload's vertices",
        ),
        ({"id": "Q9"}, "needs corners_world_m or a pose"),
    ],
)
def test_bad_qr_entries(tmp_path, entry, match):
    path = write(tmp_path, "qr.yaml", {"dictionary": "qr", "markers": [entry]})
    assert str(path) in refused(lambda: load_marker_map(path), match)


def test_aruco_markers_by_pose_and_integer_ids(tmp_path):
    # A marker on a wall: its face looks along world -y (marker z = world -y), top edge up.
    R = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # columns: marker x, y, z in the world
    q = se3.to_quaternion_xyzw(R)
    document = {
        "dictionary": "DICT_APRILTAG_36h11",
        "markers": [
            {"id": 586, "side_m": 0.16, "pose": [2.0, 5.0, 1.2, *map(float, q)]},
            {"id": 12, "side_m": 0.1, "corners_world_m": square((0.0, 0.0), 0.1)},
        ],
    }
    loaded = load_marker_map(write(tmp_path, "tags.yaml", document))
    first = np.array(loaded["markers"][0]["corners_world_m"])
    assert loaded["markers"][0]["id"] == "586"
    np.testing.assert_allclose(first[0], [1.92, 5.0, 1.28], atol=1e-12)  # TL: left and up
    np.testing.assert_allclose(first[2], [2.08, 5.0, 1.12], atol=1e-12)  # BR
    aruco_map = parse_aruco_map(loaded)
    np.testing.assert_allclose(aruco_map.markers[586].T_frame_marker[:3, 2], [0, -1, 0], atol=1e-12)


@pytest.mark.parametrize(
    "document, match",
    [
        ({"dictionary": "DICT_7X7_5", "markers": [{"id": 0, "side_m": 0.1, "pose": [0, 0, 0, 0, 0, 0, 1]}]}, "unknown ArUco dictionary"),
        ({"dictionary": "DICT_APRILTAG_36h11", "markers": [{"id": 587, "side_m": 0.1, "pose": [0, 0, 0, 0, 0, 0, 1]}]}, r"not an id of DICT_APRILTAG_36h11 \(0..586\)"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": -1, "side_m": 0.1, "pose": [0, 0, 0, 0, 0, 0, 1]}]}, r"id -1 is not an id of DICT_4X4_50"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": True, "side_m": 0.1, "pose": [0, 0, 0, 0, 0, 0, 1]}]}, "non-negative integer"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "side_m": 0.1, "pose": [0, 0, 0, 0, 0, 0, 1]}] * 2}, "appears twice"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "side": 0.1}]}, r"unknown key\(s\) \['side'\]"),
        ({"dictionary": "DICT_4X4_50", "marker": []}, r"unknown key\(s\) \['marker'\]"),
        ({"dictionary": "DICT_4X4_50", "markers": []}, "no markers and no boards"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "pose": [0, 0, 0, 0, 0, 0, 1]}]}, "side_m is required"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "side_m": 0.1, "pose": [0, 0, 0, 0, 0, 0, 2]}]}, "norm 2"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "side_m": 0.1, "pose": [0, 0, 0, 0, 0, 0]}]}, "7 numbers"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "side_m": 0.1, "pose": [float("nan"), 0, 0, 0, 0, 0, 1]}]}, "finite"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "side_m": 0.2, "corners_world_m": square((0, 0), 0.1)}]}, "do not match a square of side 0.2"),
        (
            {"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "corners_world_m": [square((0, 0), 0.1)[i] for i in (0, 1, 3, 2)]}]},
            "not a convex quadrilateral",
        ),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "corners_world_m": [[0, 0, 0]] * 4}]}, "coincide"),
        (
            {"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "corners_world_m": [[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0.01], [0, 0.1, 0]]}]},
            "not coplanar",
        ),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "corners_world_m": square((0, 0), 0.1)[:3]}]}, "4 points"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": 1, "side_m": 0.1, "pose": [0, 0, 0, 0, 0, 0, 1], "frame": "map"}]}, "frame 'map'"),
        ([1, 2, 3], "expected a mapping"),
    ],
)
def test_bad_aruco_maps(tmp_path, document, match):
    path = write(tmp_path, "map.yaml", document)
    assert str(path) in refused(lambda: load_marker_map(path), match)


def test_unreadable_map_files(tmp_path):
    refused(lambda: load_marker_map(tmp_path / "missing.yaml"), "no such file")
    bad_yaml = write(tmp_path, "bad.yaml", "dictionary: [unclosed\n")
    refused(lambda: load_marker_map(bad_yaml), r"not valid YAML \(line")
    bad_json = write(tmp_path, "bad.json", "{'dictionary': 1}")
    refused(lambda: load_marker_map(bad_json), r"not valid JSON \(line 1")


def test_charuco_board_expands_to_opencv_marker_layout(tmp_path):
    """A 5×7 board (the opencv_contrib tutorial board): 17 markers, ids 0..16, each corner
    where OpenCV's board puts it, mapped by the documented (x, H − y, −z), then by the pose."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    board = cv2.aruco.CharucoBoard((5, 7), 0.04, 0.02, dictionary)
    expected = {int(i): np.asarray(p, float).reshape(4, 3) for i, p in zip(board.getIds().ravel(), board.getObjPoints())}
    ours = charuco_marker_corners(5, 7, 0.04, 0.02, "DICT_6X6_250")
    assert sorted(ours) == list(range(17))
    for marker_id, corners in ours.items():
        cv = expected[marker_id]
        np.testing.assert_allclose(corners, np.column_stack([cv[:, 0], 0.28 - cv[:, 1], -cv[:, 2]]), atol=1e-7)
    T_world_board = se3.from_quaternion_xyzw(np.array([0.0, 0.0, np.sin(0.25), np.cos(0.25)]), np.array([1.0, 2.0, 0.0]))
    q = [0.0, 0.0, float(np.sin(0.25)), float(np.cos(0.25))]
    document = {
        "dictionary": "DICT_6X6_250",
        "boards": [{"type": "charuco", "squares_x": 5, "squares_y": 7, "square_length_m": 0.04,
                    "marker_length_m": 0.02, "pose": [1.0, 2.0, 0.0, *q]}],
    }
    loaded = load_marker_map(write(tmp_path, "board.yaml", document))
    assert [m["id"] for m in loaded["markers"]] == [str(i) for i in range(17)]
    for marker in loaded["markers"]:
        assert marker["side_m"] == 0.02
        np.testing.assert_allclose(
            marker["corners_world_m"], se3.transform_points(T_world_board, ours[int(marker["id"])]), atol=1e-12
        )
    # Every marker frame faces up (z out of the printed face) like the board's.
    for marker in parse_aruco_map(loaded).markers.values():
        np.testing.assert_allclose(marker.T_frame_marker[:3, 2], [0, 0, 1], atol=1e-9)
    # Marker 0 sits in the top row (OpenCV's first row), second square.
    np.testing.assert_allclose(ours[0][0], [0.05, 0.27, 0.0], atol=1e-12)


def test_charuco_ids_and_mixed_maps(tmp_path):
    base = {"type": "charuco", "squares_x": 3, "squares_y": 3, "square_length_m": 0.1, "marker_length_m": 0.07,
            "pose": [0, 0, 0, 0, 0, 0, 1]}
    document = {
        "dictionary": "DICT_4X4_50",
        "boards": [dict(base, first_id=10), dict(base, ids=[20, 21, 22, 23], pose=[1, 0, 0, 0, 0, 0, 1], frame="agv")],
        "markers": [{"id": 0, "side_m": 0.1, "pose": [5, 5, 0, 0, 0, 0, 1]}],
    }
    loaded = load_marker_map(write(tmp_path, "mixed.yaml", document))
    assert [m["id"] for m in loaded["markers"]] == ["0", "10", "11", "12", "13", "20", "21", "22", "23"]
    assert all(m.get("frame") == "agv" for m in loaded["markers"][5:])
    bad = [
        (dict(base, marker_length_m=0.1), "marker_length_m"),
        (dict(base, squares_x=1), "squares_x"),
        (dict(base, ids=[1, 2]), "a 3x3 board has 4 markers"),
        (dict(base, first_id=48), r"outside DICT_4X4_50"),
        (dict(base, dictionary="DICT_5X5_50"), "differs from the map's"),
        (dict(base, type="gridboard"), "only 'charuco'"),
        ({k: v for k, v in base.items() if k != "pose"}, "pose"),
        (dict(base, first_id=0, ids=[0, 1, 2, 3]), "not both"),
    ]
    for board, match in bad:
        path = write(tmp_path, "bad_board.yaml", {"dictionary": "DICT_4X4_50", "boards": [board]})
        refused(lambda: load_marker_map(path), match)
    overlap = write(tmp_path, "overlap.yaml", {"dictionary": "DICT_4X4_50", "boards": [base, base]})
    refused(lambda: load_marker_map(overlap), "appears twice")
    qr_board = write(tmp_path, "qr_board.yaml", {"dictionary": "qr", "boards": [base]})
    refused(lambda: load_marker_map(qr_board), "cannot hold them")


@pytest.mark.parametrize("name", APRILTAG_DICTIONARIES)
def test_aruco_detection_accepts_apriltag_dictionaries(name):
    """A tag of each AprilTag family, drawn as printed (the AprilTag library's module grid; not
    OpenCV's generator, which turns them 180°) at 20 px per module under a perspective warp, is
    found with its id and ECC-refined corners within 0.05 px of the warped truth."""
    modules = aruco_modules(name, 3)
    n = len(modules)
    tag = np.kron(np.where(modules, 0, 255), np.ones((20, 20))).astype(np.uint8)
    tag = cv2.copyMakeBorder(tag, 60, 60, 60, 60, cv2.BORDER_CONSTANT, value=255)
    H = np.array([[1.0, 0.1, 10.0], [0.05, 1.0, 5.0], [2e-4, 1e-4, 1.0]])
    # Supersampled warp (8x) so pixels are area averages in OpenCV's pixel-centre convention.
    S = np.diag([8.0, 8.0, 1.0])
    shift = np.array([[1.0, 0, 3.5], [0, 1.0, 3.5], [0, 0, 1.0]])  # pixel centres of the 8x grid
    big = cv2.warpPerspective(tag, shift @ S @ H, ((tag.shape[1] + 80) * 8, (tag.shape[0] + 80) * 8),
                              flags=cv2.INTER_LINEAR, borderValue=255)
    image = cv2.resize(big, (tag.shape[1] + 80, tag.shape[0] + 80), interpolation=cv2.INTER_AREA)
    edge = 60 - 0.5
    truth = cv2.perspectiveTransform(
        np.array([[[edge, edge], [edge + n * 20, edge], [edge + n * 20, edge + n * 20], [edge, edge + n * 20]]]), H
    )[0]
    detections = detect_aruco(cv2.GaussianBlur(image, (0, 0), 0.7), name, refine="ecc")
    assert [d.marker_id for d in detections] == [3]
    assert detections[0].refine_method == "ecc"
    assert np.max(np.linalg.norm(detections[0].corners_px - truth, axis=1)) < 0.05


# -- calibration ---------------------------------------------------------------------------------
K = [[452.5, 0.0, 317.7], [0.0, 456.8, 277.8], [0.0, 0.0, 1.0]]
D = [0.12, -1.08, 1e-4, -4e-4, 2.95]


def ros_camera_info(**overrides) -> dict:
    document = {
        "image_width": 640, "image_height": 480, "camera_name": "front",
        "camera_matrix": {"rows": 3, "cols": 3, "data": sum(K, [])},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": D},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": [1, 0, 0, 0, 1, 0, 0, 0, 1]},
        "projection_matrix": {"rows": 3, "cols": 4, "data": [452.5, 0, 317.7, 0, 0, 456.8, 277.8, 0, 0, 0, 1, 0]},
    }
    document.update(overrides)
    return document


def check_calibration(calibration: CalibrationMsg, cam_name="front"):
    assert calibration.cam_name == cam_name and calibration.frame_id == f"cam_{cam_name}"
    np.testing.assert_allclose(calibration.camera.K, K)
    np.testing.assert_allclose(calibration.camera.dist[:5], D)
    assert (calibration.camera.width_px, calibration.camera.height_px) == (640, 480)
    assert calibration.distortion_model == "plumb_bob"


def test_ros_camera_info_yaml(tmp_path):
    check_calibration(load_calibration("front", write(tmp_path, "front.yaml", ros_camera_info())))


def test_camera_info_message_dump(tmp_path):
    dump = {"height": 480, "width": 640, "distortion_model": "plumb_bob", "d": D, "k": sum(K, []),
            "r": [1, 0, 0, 0, 1, 0, 0, 0, 1], "p": [0] * 12, "binning_x": 0}
    check_calibration(load_calibration("front", write(tmp_path, "info.yaml", dump)))


@pytest.mark.parametrize("name", ["cv.yml", "cv.xml"])
def test_opencv_filestorage(tmp_path, name):
    path = tmp_path / name
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    storage.write("camera_matrix", np.array(K))
    storage.write("distortion_coefficients", np.array([D]))
    storage.release()
    check_calibration(load_calibration("front", path))


def test_opencv_tutorial_calibration():
    if not CHARUCO_CALIBRATION.is_file():
        pytest.skip(f"{CHARUCO_CALIBRATION} not found (see ../shared/data/MANIFEST.md)")
    calibration = load_calibration("board_cam", CHARUCO_CALIBRATION)
    camera = calibration.camera
    assert (camera.width_px, camera.height_px) == (640, 480)
    np.testing.assert_allclose(camera.K[0, 0], 452.51072219637672)
    np.testing.assert_allclose(camera.dist[4], 2.9542589406810080)


def test_rational_polynomial(tmp_path):
    d8 = D + [0.01, 0.02, 0.03]
    info = ros_camera_info(distortion_model="rational_polynomial",
                           distortion_coefficients={"rows": 1, "cols": 8, "data": d8})
    try:
        calibration = load_calibration("front", write(tmp_path, "r.yaml", info))
    except SideFileError as exc:  # a PinholeCamera without the 8-coefficient model
        assert "coefficients" in str(exc)
    else:
        assert calibration.distortion_model == "rational_polynomial"
        np.testing.assert_allclose(calibration.camera.dist, d8)


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"distortion_model": "equidistant"}, "'equidistant' is not supported"),
        ({"image_width": 0}, "image size 0x480"),
        ({"image_width": 640.5}, "integer number of pixels"),
        ({"camera_matrix": {"rows": 3, "cols": 3, "data": [0, 0, 317.7, 0, 456.8, 277.8, 0, 0, 1]}}, "fx, fy > 0"),
        ({"camera_matrix": {"rows": 2, "cols": 3, "data": [1, 0, 1, 0, 1, 1]}}, "must have 9 numbers"),
        ({"camera_matrix": {"rows": 3, "cols": 3, "data": [1, 0, 1, 0, 1, 1, 0, 0, ".nan"]}}, "finite number"),
        ({"distortion_coefficients": {"rows": 1, "cols": 12, "data": D + [0, 0, 0, 0.1, 0, 0, 0]}}, "thin-prism"),
        ({"camera_matrix": None}, "no camera matrix"),
        ({"image_height": None}, "image size missing"),
    ],
)
def test_bad_calibrations(tmp_path, overrides, match):
    document = {k: v for k, v in ros_camera_info(**overrides).items() if v is not None}
    path = write(tmp_path, "bad.yaml", document)
    message = refused(lambda: load_calibration("front", path), match)
    assert message.startswith(f"calibration {path}")


def test_unreadable_calibration_files(tmp_path):
    refused(lambda: load_calibration("front", tmp_path / "none.yaml"), "no such file")
    refused(lambda: load_calibration("front", write(tmp_path, "list.yaml", "[1, 2]")), "camera_info")
    no_size = tmp_path / "nosize.yml"
    storage = cv2.FileStorage(str(no_size), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.array(K))
    storage.release()
    refused(lambda: load_calibration("front", no_size), "image_width and image_height")


# -- extrinsic -----------------------------------------------------------------------------------
def test_parse_extrinsic():
    # base_link (REP 103: x forward, y left, z up) to an optical frame looking forward.
    tf = parse_extrinsic("front", "0.3, 0, 0.2, -0.5, 0.5, -0.5, 0.5", "base_link")
    assert isinstance(tf, FrameTransformMsg)
    assert (tf.parent_frame, tf.child_frame) == ("base_link", "cam_front")
    np.testing.assert_allclose(tf.T_parent_child[:3, 3], [0.3, 0, 0.2])
    R = tf.T_parent_child[:3, :3]
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)  # optical axis = forward
    np.testing.assert_allclose(R[:, 0], [0, -1, 0], atol=1e-12)  # image x = right
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-12)  # image y = down


@pytest.mark.parametrize(
    "text, match",
    [
        ("0,0,0,0,0,1", "7 comma-separated"),
        ("0,0,0,0,0,0,one", "numbers"),
        ("0,0,0,0,0,0,0", "norm 0"),
        ("0,0,0,0,0,0,1.1", "norm 1.1"),
        ("nan,0,0,0,0,0,1", "finite"),
    ],
)
def test_bad_extrinsics(text, match):
    message = refused(lambda: parse_extrinsic("front", text, "base_link"), match)
    assert message.startswith("--extrinsic front=")


# -- any document: a map or one SideFileError, never another exception ---------------------------
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(10**30), 10**30), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8), st.sampled_from(["DICT_4X4_50", "qr", "charuco", "world", "agv", "0", "²", "AGV1;id=A"]),
)
_documents = st.recursive(
    _scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=5),
        st.dictionaries(
            st.sampled_from(sorted({"dictionary", "markers", "boards", "id", "side_m", "corners_world_m", "pose",
                                    "payload", "frame", "type", "squares_x", "squares_y", "square_length_m",
                                    "marker_length_m", "first_id", "ids", "legacy_pattern", "camera_matrix",
                                    "distortion_coefficients", "distortion_model", "image_width", "image_height",
                                    "rows", "cols", "data", "k", "d", "width", "height", "x"})),
            children, max_size=6,
        ),
    ),
    max_leaves=25,
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(document=_documents)
def test_any_document_gives_a_map_or_one_side_file_error(tmp_path, document):
    path = tmp_path / "doc.json"
    path.write_text(json.dumps(document))
    for load in (load_marker_map, lambda p: load_calibration("front", p)):
        try:
            load(path)
        except SideFileError as exc:
            assert "\n" not in str(exc)


def _leaf_paths(value, prefix=()):
    yield prefix
    if isinstance(value, dict):
        for key, child in value.items():
            yield from _leaf_paths(child, prefix + (key,))
    elif isinstance(value, list):
        for i, child in enumerate(value):
            yield from _leaf_paths(child, prefix + (i,))


def _replace(value, path, new):
    if not path:
        return new
    copy = dict(value) if isinstance(value, dict) else list(value)
    copy[path[0]] = _replace(value[path[0]], path[1:], new)
    return copy


_VALID = [
    {"dictionary": "DICT_6X6_250", "boards": [{"type": "charuco", "squares_x": 5, "squares_y": 7, "square_length_m": 0.04,
                                               "marker_length_m": 0.02, "first_id": 0, "pose": [0, 0, 0, 0, 0, 0, 1]}],
     "markers": [{"id": 40, "side_m": 0.1, "pose": [1, 2, 0, 0, 0, 0, 1], "frame": "agv"},
                 {"id": "41", "corners_world_m": square((3.0, 3.0), 0.1)}]},
    {"dictionary": "qr", "markers": [qr_code("Q1", (1.0, 1.0)), {"payload": qr_code("Q2", (2.0, 1.0))["payload"]}]},
    ros_camera_info(),
]


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_mutated_valid_documents_give_a_map_or_one_side_file_error(tmp_path, data):
    document = data.draw(st.sampled_from(_VALID))
    path_in_doc = data.draw(st.sampled_from(list(_leaf_paths(document))))
    mutated = _replace(document, path_in_doc, data.draw(_documents))
    path = tmp_path / "doc.json"
    path.write_text(json.dumps(mutated))
    load = (lambda p: load_calibration("front", p)) if "image_width" in document else load_marker_map
    try:
        load(path)
    except SideFileError as exc:
        assert "\n" not in str(exc)
