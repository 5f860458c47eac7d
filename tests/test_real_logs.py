"""A robot's own log: files written by independent writers (rosbags, the Foxglove SDK), as a
robot would write them, replay to the same per-frame errors as agvviz's own recording.

One tiny qr_floor recording (4 frames, 640×512) is the source of truth; its content is
re-written as

* a ROS 2 bag (``rosbags``, MCAP storage, split over two files) with the camera publishing
  both ``sensor_msgs/Image`` bgr8 and ``CompressedImage``, ``CameraInfo``, a three-link camera
  chain on ``/tf_static``, ``/tf``, ``PoseStamped`` truth and ``nav_msgs/Odometry``, all on ROS
  topic and frame names, log times later than the header stamps;
* a Foxglove SDK file with ``RawImage`` mono8 frames;
* a Foxglove SDK file whose images come before their calibration and truth within each
  stamp, and whose ``/tf_static`` is the last message.

The bgr8 / mono8 frames are the native JPEG decoded to grey (a monochrome camera), so the
pipeline sees exactly the native grey values and the errors agree to 1e-6 m.
"""

from __future__ import annotations

import dataclasses

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from agvviz.cli.main import app
from agvviz.errors import InputError, RecordingError, RunError
from agvviz.geometry import se3
from agvviz.model.messages import FrameTransformMsg, PoseMsg
from agvviz.recording.reader import iter_messages
from agvviz.recording.source import open_recording, scan
from agvviz.recording.contract import inspect_recording
from agvviz.app.run import run_recording
from agvviz.replay.run import SideInputs, prepare, replay_frames
from agvviz.settings import RunSettings

rosbags = pytest.importorskip("rosbags", reason="rosbags (test extra) not installed")
foxglove = pytest.importorskip("foxglove", reason="foxglove-sdk (test extra) not installed")
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
T_ = TS.types
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rosbag2_mcap"
LATENCY_NS = 7_000_000  # bag log time = header stamp + 7 ms (arrival at the recorder)
#: base_link → camera_link is split at an arbitrary mount; camera_link → optical is REP 103's.
T_LINK_OPTICAL = se3.from_quaternion_xyzw(np.array([-0.5, 0.5, -0.5, 0.5]), np.zeros(3))
T_BASE_MOUNT = se3.make(
    cv2.Rodrigues(np.array([0.0, 0.0, 0.3]))[0], np.array([0.1, 0.2, 0.3])
)


# -- the native recording and its content -----------------------------------------------------------
@pytest.fixture(scope="module")
def native(qr_small) -> Path:
    """The shared small qr_floor recording (tests/conftest.py ``QR_SMALL``)."""
    return qr_small


@pytest.fixture(scope="module")
def content(qr_small_content) -> dict:
    return qr_small_content


def frame_errors(path, settings: RunSettings | None = None, **kw) -> dict[int, tuple]:
    """time → (rejection, position error m) of every frame, through the run's own stages.

    Every frame is detected in full (``tracking=False``): these files compare another writer's
    copy of a recording with the native one, and some copies carry no odometry, from which
    tracking predicts codes — a tracked frame's corners (within ECC's tolerance of a full
    detection's) would differ between them at the 0.1 mm level, which says nothing about
    the readers under test."""
    settings = dataclasses.replace(settings or RunSettings(), tracking=False)
    return {r.log_time_ns: (r.rejected, r.position_error_m) for r in replay_frames(path, settings, **kw)}


@pytest.fixture(scope="module")
def native_errors(native) -> dict:
    errors = frame_errors(native)
    assert len(errors) == 4 and all(rej is None and e is not None for rej, e in errors.values()), errors
    return errors


def assert_same_errors(errors: dict, native_errors: dict) -> None:
    assert sorted(errors) == sorted(native_errors)
    for t, (rejected, error) in native_errors.items():
        assert errors[t][0] == rejected, (t, errors[t])
        assert abs(errors[t][1] - error) < 1e-6, (t, errors[t][1], error)


def grey(jpeg: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)


# -- a ROS 2 bag written by rosbags -----------------------------------------------------------------
def _header(t_ns: int, frame: str):
    return T_["std_msgs/msg/Header"](
        stamp=T_["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=frame
    )


def _pose(T: np.ndarray):
    q = se3.to_quaternion_xyzw(T)
    return T_["geometry_msgs/msg/Pose"](
        position=T_["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        orientation=T_["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def _tf(parent: str, child: str, T: np.ndarray, t_ns: int):
    q = se3.to_quaternion_xyzw(T)
    return T_["geometry_msgs/msg/TransformStamped"](
        header=_header(t_ns, parent), child_frame_id=child,
        transform=T_["geometry_msgs/msg/Transform"](
            translation=T_["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=T_["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )


def _camera_info(camera, t_ns: int, model: str = "plumb_bob", d=None):
    roi = T_["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    P = np.zeros(12)
    P[[0, 1, 2, 4, 5, 6, 10]] = camera.K.ravel()[[0, 1, 2, 3, 4, 5, 8]]
    return T_["sensor_msgs/msg/CameraInfo"](
        header=_header(t_ns, "camera_optical_frame"), height=camera.height_px, width=camera.width_px,
        distortion_model=model, d=np.asarray(camera.dist if d is None else d, dtype=np.float64),
        k=camera.K.ravel().astype(np.float64), r=np.eye(3).ravel(), p=P, binning_x=0, binning_y=0, roi=roi,
    )


def ros_messages(content: dict, calibration: bool = True) -> list[tuple[str, str, int, object]]:
    """(topic, type, log time, message) of the bag, in the order a robot's recorder writes them."""
    T_link = se3.inverse(T_BASE_MOUNT) @ content["T_agv_cam"] @ se3.inverse(T_LINK_OPTICAL)
    t0 = content["images"][0][0]
    out = [(
        "/tf_static", "tf2_msgs/msg/TFMessage", t0,
        T_["tf2_msgs/msg/TFMessage"](transforms=[
            _tf("base_link", "camera_mount", T_BASE_MOUNT, 0),
            _tf("camera_mount", "camera_link", T_link, 0),
            _tf("camera_link", "camera_optical_frame", T_LINK_OPTICAL, 0),
        ]),
    )]
    twist = T_["geometry_msgs/msg/TwistWithCovariance"](
        twist=T_["geometry_msgs/msg/Twist"](
            linear=T_["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=T_["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        ),
        covariance=np.zeros(36),
    )
    for (t, jpeg), (_, T_truth), (_, T_odom) in zip(content["images"], content["truth"], content["odometry"]):
        g = grey(jpeg)
        bgr = np.ascontiguousarray(np.repeat(g[:, :, None], 3, axis=2))
        out += [
            ("/front/image_raw", "sensor_msgs/msg/Image", t + LATENCY_NS, T_["sensor_msgs/msg/Image"](
                header=_header(t, "camera_optical_frame"), height=g.shape[0], width=g.shape[1],
                encoding="bgr8", is_bigendian=0, step=g.shape[1] * 3, data=bgr.ravel())),
            ("/front/image_raw/compressed", "sensor_msgs/msg/CompressedImage", t + LATENCY_NS,
             T_["sensor_msgs/msg/CompressedImage"](
                 header=_header(t, "camera_optical_frame"), format="bgr8; jpeg compressed bgr8",
                 data=np.frombuffer(jpeg, np.uint8))),
            ("/ground_truth/pose", "geometry_msgs/msg/PoseStamped", t + 2 * LATENCY_NS,
             T_["geometry_msgs/msg/PoseStamped"](header=_header(t, "map"), pose=_pose(T_truth))),
            ("/odom", "nav_msgs/msg/Odometry", t + LATENCY_NS, T_["nav_msgs/msg/Odometry"](
                header=_header(t, "odom"), child_frame_id="base_link",
                pose=T_["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(T_odom), covariance=np.zeros(36)),
                twist=twist)),
            ("/tf", "tf2_msgs/msg/TFMessage", t + LATENCY_NS,
             T_["tf2_msgs/msg/TFMessage"](transforms=[_tf("odom", "base_link", T_odom, t)])),
        ]
        if calibration:
            out.append(("/front/camera_info", "sensor_msgs/msg/CameraInfo", t + LATENCY_NS,
                        _camera_info(content["calibration"], t)))
    return sorted(out, key=lambda m: m[2])


def write_bag(directory: Path, messages: list, split: int | None = None) -> Path:
    """A rosbag2 directory written by rosbags; with ``split`` (a message index) the second
    part is a second file listed after the first in metadata.yaml, as rosbag2's splitting does."""
    parts = [messages] if split is None else [messages[:split], messages[split:]]
    metas = []
    for k, part in enumerate(parts):
        bag = directory.parent / f"{directory.name}_part{k}"
        with Writer(bag, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
            connections = {}
            for topic, msgtype, t, msg in part:
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=TS)
                writer.write(connections[topic], t, TS.serialize_cdr(msg, msgtype))
        metas.append((bag, yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]))
    directory.mkdir()
    info = metas[0][1]
    names, counts = [], {}
    for k, (bag, meta) in enumerate(metas):
        name = f"{directory.name}_{k}.mcap"
        (bag / meta["relative_file_paths"][0]).rename(directory / name)
        names.append(name)
        for entry in meta["topics_with_message_count"]:
            key = entry["topic_metadata"]["name"]
            if key in counts:
                counts[key]["message_count"] += entry["message_count"]
            else:
                counts[key] = entry
    info["relative_file_paths"] = names
    info["message_count"] = sum(m["message_count"] for _, m in metas)
    info["topics_with_message_count"] = list(counts.values())
    info.pop("files", None)
    (directory / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}))
    return directory


@pytest.fixture(scope="module")
def bag(content, tmp_path_factory) -> Path:
    messages = ros_messages(content)
    return write_bag(tmp_path_factory.mktemp("bag") / "robot_bag", messages, split=len(messages) // 2)


def test_rosbag2_directory_split_over_two_files_replays_like_native(bag, native_errors):
    recording = open_recording(bag)
    assert recording.kind == "rosbag2" and [f.name for f in recording.files] == ["robot_bag_0.mcap", "robot_bag_1.mcap"]
    prepared = prepare(bag, RunSettings())
    roles = prepared.roles.roles
    # the uncompressed stream is kept, the compressed twin listed with why
    assert roles["front.image"] == "/front/image_raw"
    assert "same camera as /front/image_raw" in prepared.roles.unplaced["/front/image_raw/compressed"]
    assert roles["front.calibration"] == "/front/camera_info"
    assert (roles["truth"], roles["odometry"]) == ("/ground_truth/pose", "/odom")
    assert (roles["tf_static"], roles["tf"]) == ("/tf_static", "/tf")
    assert (prepared.body_frame, prepared.time_source) == ("base_link", "header")
    assert prepared.usable_cameras == ["front"] and prepared.causes == []
    # the three-link chain gives the native extrinsic
    np.testing.assert_allclose(
        prepared.replay.sync.tf.lookup("base_link", "camera_optical_frame"),
        prepared.replay.sync.tf.lookup("base_link", "camera_optical_frame", 0), atol=0,
    )
    assert_same_errors(frame_errors(bag), native_errors)
    # the compressed stream, chosen by --topic, gives the same
    assert_same_errors(frame_errors(bag, topics={"front.image": "/front/image_raw/compressed"}), native_errors)


def test_rosbag2_run_and_inspect_on_the_command_line(bag, tmp_path):
    out = tmp_path / "bag.rrd"
    roles_file = tmp_path / "roles.yaml"
    inspected = CliRunner().invoke(app, ["inspect", str(bag), "--write-roles", str(roles_file)])
    assert inspected.exit_code == 0, inspected.stdout
    assert "front.image            /front/image_raw" in inspected.stdout
    assert "note: no 'agvviz.scenario' metadata" in inspected.stdout
    assert "rosbag2 directory: robot_bag_0.mcap, robot_bag_1.mcap" in inspected.stdout
    assert yaml.safe_load(roles_file.read_text())["roles"]["truth"] == "/ground_truth/pose"
    ran = CliRunner().invoke(app, ["run", str(bag), "--roles", str(roles_file),
                                   "--topic", "front.image=/front/image_raw/compressed", "--out", str(out)])
    assert ran.exit_code == 0, ran.stdout
    assert out.is_file()


def test_bag_without_calibration_fails_loudly_and_writes_nothing(content, tmp_path, native):
    bag = write_bag(tmp_path / "nocal", ros_messages(content, calibration=False))
    out = tmp_path / "nocal.rrd"
    with pytest.raises(RunError) as excinfo:
        run_recording(bag, RunSettings(), out)
    message = str(excinfo.value)
    assert "camera front (/front/image_raw): no calibration" in message and "--calibration front=FILE" in message
    assert not out.exists() and not list(tmp_path.glob("*.rrd*"))
    # inspect says the same and exits 1
    inspected = CliRunner().invoke(app, ["inspect", str(bag)])
    assert inspected.exit_code == 1
    assert "replay: camera front (/front/image_raw): no calibration" in inspected.stdout
    # a calibration side file makes it run (H6's loader of a ROS camera_info YAML)
    calib = tmp_path / "front.yaml"
    cam = content["calibration"]
    calib.write_text(yaml.safe_dump({
        "image_width": cam.width_px, "image_height": cam.height_px, "camera_name": "front",
        "camera_matrix": {"rows": 3, "cols": 3, "data": cam.K.ravel().tolist()},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": cam.dist.tolist()},
    }))
    from agvviz.recording.sidefiles import load_calibration

    errors = frame_errors(bag, side=SideInputs(calibrations={"front": load_calibration("front", calib)}))
    assert all(rej is None for rej, _ in errors.values()), errors


def test_side_files_override_the_recording(bag, content, native_errors, tmp_path):
    from agvviz.recording.sidefiles import load_marker_map, parse_extrinsic

    markers = tmp_path / "map.json"
    markers.write_text(json.dumps(content["marker_map"]))
    q = se3.to_quaternion_xyzw(content["T_agv_cam"])
    t = content["T_agv_cam"][:3, 3]
    text = ",".join(repr(float(v)) for v in [*t, *q])
    side = SideInputs(
        marker_map=load_marker_map(markers),
        extrinsics={"front": parse_extrinsic("front", text, "base_link")},
    )
    prepared = prepare(bag, RunSettings(), side=side)
    assert prepared.replay.ctx.qr_map  # the side map is in use
    errors = frame_errors(bag, side=side)
    for time_ns, (_, error) in native_errors.items():
        assert abs(errors[time_ns][1] - error) < 1e-6  # quaternion text round trip: ≪ 1 µm


# -- Foxglove SDK files -----------------------------------------------------------------------------
def _ts(t_ns: int):
    return foxglove.messages.Timestamp(t_ns // 10**9, t_ns % 10**9)


def _fx_pose(T):
    q = se3.to_quaternion_xyzw(T)
    m = foxglove.messages
    return m.Pose(position=m.Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                  orientation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))


def _fx_calibration(camera, t_ns: int):
    return foxglove.messages.CameraCalibration(
        timestamp=_ts(t_ns), frame_id="cam_front", width=camera.width_px, height=camera.height_px,
        distortion_model="plumb_bob", D=camera.dist.tolist(), K=camera.K.ravel().tolist(),
    )


def _fx_tf_static(content, t_ns: int):
    m = foxglove.messages
    T = content["T_agv_cam"]
    q = se3.to_quaternion_xyzw(T)
    return m.FrameTransforms(transforms=[m.FrameTransform(
        timestamp=_ts(t_ns), parent_frame_id="agv", child_frame_id="cam_front",
        translation=m.Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]), rotation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
    )])


def test_foxglove_sdk_raw_images_replay_like_native(content, native_errors, tmp_path):
    path = tmp_path / "fox.mcap"
    m = foxglove.messages
    with foxglove.open_mcap(path, allow_overwrite=True):
        t0 = content["images"][0][0]
        foxglove.log("/tf_static", _fx_tf_static(content, t0), log_time=t0)
        for (t, jpeg), (_, T_truth) in zip(content["images"], content["truth"]):
            g = grey(jpeg)
            foxglove.log("/front/calibration", _fx_calibration(content["calibration"], t), log_time=t)
            foxglove.log("/front/image", m.RawImage(
                timestamp=_ts(t), frame_id="cam_front", width=g.shape[1], height=g.shape[0], encoding="mono8",
                step=g.shape[1], data=g.tobytes()), log_time=t)
            foxglove.log("/ground_truth", m.PoseInFrame(timestamp=_ts(t), frame_id="world", pose=_fx_pose(T_truth)),
                         log_time=t)
    prepared = prepare(path, RunSettings())
    assert prepared.roles.roles["front.image"] == "/front/image"
    assert prepared.roles.roles["truth"] == "/ground_truth"
    assert prepared.body_frame == "agv"  # no base_link in its transforms
    report = inspect_recording(path)
    assert report.ok and not report.native and any("agvviz.scenario" in n for n in report.notes)
    assert_same_errors(frame_errors(path), native_errors)


def test_images_before_their_calibration_and_truth(content, native_errors, tmp_path):
    """Within each stamp the image comes first; /tf_static is the file's last message."""
    path = tmp_path / "late.mcap"
    m = foxglove.messages
    with foxglove.open_mcap(path, allow_overwrite=True):
        for (t, jpeg), (_, T_truth) in zip(content["images"], content["truth"]):
            foxglove.log("/front/compressed", m.CompressedImage(
                timestamp=_ts(t), frame_id="cam_front", format="jpeg", data=jpeg), log_time=t)
            foxglove.log("/front/camera_info", _fx_calibration(content["calibration"], t), log_time=t)
            foxglove.log("/vicon/agv/pose", m.PoseInFrame(timestamp=_ts(t), frame_id="world", pose=_fx_pose(T_truth)),
                         log_time=t)
        t_last = content["images"][-1][0]
        foxglove.log("/tf_static", _fx_tf_static(content, t_last), log_time=t_last)
    assert_same_errors(frame_errors(path), native_errors)
    # the same with log times instead of header stamps
    assert_same_errors(frame_errors(path, RunSettings(time_source="log")), native_errors)


# -- roles, settings, inputs -------------------------------------------------------------------------
def test_role_overrides_are_checked(bag):
    with pytest.raises(InputError, match="no topic '/nope'"):
        prepare(bag, RunSettings(), topics={"truth": "/nope"})
    with pytest.raises(InputError, match="needs"):
        prepare(bag, RunSettings(), topics={"truth": "/front/image_raw"})
    prepared = prepare(bag, RunSettings(), topics={"odometry": "/ground_truth/pose", "truth": "/odom"})
    assert (prepared.roles.roles["truth"], prepared.roles.roles["odometry"]) == ("/odom", "/ground_truth/pose")


def test_body_frame_setting(bag):
    prepared = prepare(bag, RunSettings(body_frame="camera_mount"))
    T = prepared.replay.ctx.cameras["front"].T_agv_cam
    np.testing.assert_allclose(T, prepared.replay.sync.tf.lookup("camera_mount", "camera_optical_frame"), atol=1e-12)


def test_not_a_recording(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="without metadata.yaml"):
        open_recording(tmp_path / "empty")
    sqlite = tmp_path / "db"
    sqlite.mkdir()
    (sqlite / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "storage_identifier": "sqlite3", "relative_file_paths": ["db_0.db3"]}}))
    with pytest.raises(RecordingError, match="ros2 bag convert"):
        open_recording(sqlite)


# -- the real bags in ../shared/data ----------------------------------------------------------------
def _real_bags() -> list[Path]:
    return sorted(p.parent for p in DATA.rglob("metadata.yaml")) if DATA.is_dir() else []


@pytest.mark.skipif(not _real_bags(), reason=f"real rosbag2 bags not found at {DATA} (../shared/data absent)")
@pytest.mark.parametrize("bag_dir", _real_bags(), ids=lambda p: p.name)
def test_real_bags_inspect_counts_and_run_refuses(bag_dir, tmp_path):
    info = yaml.safe_load((bag_dir / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    report = inspect_recording(bag_dir)
    counts = {t.topic: t.count for t in report.topics}
    assert sum(counts.values()) == info["message_count"]
    for entry in info["topics_with_message_count"]:
        assert counts.get(entry["topic_metadata"]["name"], 0) == entry["message_count"]
    assert not report.damage, report.damage
    out = tmp_path / "x.rrd"
    with pytest.raises(RunError, match="no camera images"):
        run_recording(bag_dir, RunSettings(), out)
    assert not out.exists()


# -- decoders: image encodings, distortion models, roles ------------------------------------------
def _png_pixels(png: bytes, flags=cv2.IMREAD_UNCHANGED) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), flags)


def test_raw_image_encodings():
    from agvviz.recording.images import ImageEncodingError, raw_to_png

    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    np.testing.assert_array_equal(_png_pixels(raw_to_png("bgr8", 8, 6, 24, bgr.tobytes())), bgr)
    np.testing.assert_array_equal(_png_pixels(raw_to_png("rgb8", 8, 6, 24, bgr[:, :, ::-1].tobytes())), bgr)
    bgra = np.dstack([bgr, np.full((6, 8), 7, np.uint8)])
    np.testing.assert_array_equal(_png_pixels(raw_to_png("bgra8", 8, 6, 32, bgra.tobytes())), bgr)
    rgba = np.dstack([bgr[:, :, ::-1], np.full((6, 8), 7, np.uint8)])
    np.testing.assert_array_equal(_png_pixels(raw_to_png("rgba8", 8, 6, 32, rgba.tobytes())), bgr)
    mono = bgr[:, :, 0]
    padded = np.hstack([mono, np.zeros((6, 4), np.uint8)])  # step 12 > width 8
    np.testing.assert_array_equal(_png_pixels(raw_to_png("mono8", 8, 6, 12, padded.tobytes())), mono)
    # mono16 (a 12-bit sensor), both byte orders: scaled by 255 / max
    m16 = (mono.astype(np.uint16) * 16)
    expected = np.rint(m16 * (255.0 / m16.max())).astype(np.uint8)
    np.testing.assert_array_equal(_png_pixels(raw_to_png("mono16", 8, 6, 16, m16.astype("<u2").tobytes())), expected)
    np.testing.assert_array_equal(
        _png_pixels(raw_to_png("mono16", 8, 6, 16, m16.astype(">u2").tobytes(), big_endian=True)), expected
    )
    # an equal-channel bgr8 image is its grey values exactly
    grey3 = np.repeat(mono[:, :, None], 3, axis=2)
    np.testing.assert_array_equal(_png_pixels(raw_to_png("bgr8", 8, 6, 24, grey3.tobytes()), cv2.IMREAD_GRAYSCALE), mono)
    with pytest.raises(ImageEncodingError, match="'yuv422' is not supported"):
        raw_to_png("yuv422", 8, 6, 16, bytes(96))
    with pytest.raises(ImageEncodingError, match="needs"):
        raw_to_png("bgr8", 8, 6, 24, bytes(100))


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_demosaic_follows_the_ros_pattern_name(pattern):
    """A smooth colour image mosaicked with the ROS pattern comes back (cv_bridge's mapping)."""
    from agvviz.recording.images import raw_to_png

    y, x = np.mgrid[0:32, 0:32]
    bgr = np.dstack([40 + 2 * x, 120 + 0 * x, 200 - 2 * y]).astype(np.uint8)  # B, G, R
    channel = {"b": 0, "g": 1, "r": 2}
    mosaic = np.zeros((32, 32), np.uint8)
    for k, c in enumerate(pattern):
        dy, dx = divmod(k, 2)
        mosaic[dy::2, dx::2] = bgr[dy::2, dx::2, channel[c]]
    out = _png_pixels(raw_to_png(f"bayer_{pattern}8", 32, 32, 32, mosaic.tobytes())).astype(int)
    inner = (slice(4, -4), slice(4, -4))
    assert np.abs(out[inner] - bgr[inner]).max() <= 3, pattern


def test_camera_info_distortion_models():
    from agvviz.recording.raw import MessageDecodeError
    from agvviz.recording.values import calibration

    K = [500.0, 0, 320, 0, 500.0, 240, 0, 0, 1]
    rational = calibration("/c/camera_info", "c", K, [0.1, -0.05, 0.001, 0.002, 0.01, 0.2, -0.01, 0.003],
                           "rational_polynomial", 640, 480)
    assert rational.camera.is_rational and rational.camera.dist.size == 8
    # the rational model agrees with OpenCV's projectPoints
    pts = np.array([[0.3, -0.2, 1.0], [-0.5, 0.4, 2.0]])
    cv_px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), rational.camera.K, rational.camera.dist)
    np.testing.assert_allclose(rational.camera.project(pts), cv_px.reshape(-1, 2), atol=1e-9)
    # its Jacobian agrees with finite differences
    _, J = rational.camera.project_with_jacobian(pts)
    h = 1e-7
    for i in range(3):
        step = np.zeros(3)
        step[i] = h
        fd = (rational.camera.project(pts + step) - rational.camera.project(pts - step)) / (2 * h)
        np.testing.assert_allclose(J[:, :, i], fd, atol=1e-4)
    with pytest.raises(MessageDecodeError, match="fisheye"):
        calibration("/c/camera_info", "c", K, [0.1, 0.01, 0.0, 0.0], "equidistant", 640, 480)
    with pytest.raises(MessageDecodeError, match="not calibrated"):
        calibration("/c/camera_info", "c", [0.0] * 9, [], "", 640, 480)


def test_role_inference_rules():
    from agvviz.recording.roles import TopicInfo, infer_roles

    def topics(*rows):
        return {t: TopicInfo(t, schema, "cdr", 1, frame) for t, schema, frame in rows}

    roles = infer_roles(topics(
        ("/left/image_raw/compressed", "sensor_msgs/msg/CompressedImage", "left_optical"),
        ("/right/image_rect", "sensor_msgs/msg/Image", "right_optical"),
        ("/left/camera_info", "sensor_msgs/msg/CameraInfo", "left_optical"),
        ("/calib/right", "sensor_msgs/msg/CameraInfo", "right_optical"),  # paired by frame id
        ("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image", "depth"),
        ("/vicon/agv/agv", "geometry_msgs/msg/TransformStamped", "world"),
        ("/odometry/filtered", "nav_msgs/msg/Odometry", "odom"),
        ("/wheel/odom", "nav_msgs/msg/Odometry", "odom"),
        ("/goal_pose", "geometry_msgs/msg/PoseStamped", "map"),
        ("/rosout", "rcl_interfaces/msg/Log", ""),
    ))
    assert roles.roles["left.image"] == "/left/image_raw/compressed"
    assert roles.roles["right.image"] == "/right/image_rect"
    assert roles.roles["left.calibration"] == "/left/camera_info"
    assert roles.roles["right.calibration"] == "/calib/right"
    assert roles.roles["truth"] == "/vicon/agv/agv"
    assert "depth image" in roles.unplaced["/camera/depth/image_rect_raw"]
    assert "one of 2 candidates for odometry" in roles.unplaced["/wheel/odom"]
    assert "--topic truth=/goal_pose" in roles.unplaced["/goal_pose"]
    assert "not used by the replay" in roles.unplaced["/rosout"]
    assert "odometry" not in roles.roles


def test_side_file_for_an_unknown_camera_is_an_error(bag):
    side = SideInputs(extrinsics={"rear": FrameTransformMsg("base_link", "rear", np.eye(4))})
    with pytest.raises(InputError, match="no camera 'rear'; its cameras: front"):
        prepare(bag, RunSettings(), side=side)


def test_unknown_encoding_and_unplaced_images_fail_loudly(content, tmp_path):
    messages = [m for m in ros_messages(content) if m[0] != "/front/image_raw/compressed"]
    for _, msgtype, _, msg in messages:
        if msgtype == "sensor_msgs/msg/Image":
            msg.encoding = "yuv422"
    bag = write_bag(tmp_path / "yuv", messages)
    with pytest.raises(RunError, match=r"camera front \(/front/image_raw\): its frames do not decode \(image encoding 'yuv422' is not supported"):
        run_recording(bag, RunSettings(), tmp_path / "yuv.rrd")
    # images on a depth topic only: no camera role
    depth = [("/camera/depth/image_raw" if m[0] == "/front/image_raw" else m[0], *m[1:]) for m in messages]
    for _, msgtype, _, msg in depth:
        if msgtype == "sensor_msgs/msg/Image":
            msg.encoding = "mono8"
    bag = write_bag(tmp_path / "depth", depth)
    with pytest.raises(RunError, match="no camera images placed: /camera/depth/image_raw: a depth image"):
        run_recording(bag, RunSettings(), tmp_path / "depth.rrd")
    assert not list(tmp_path.glob("*.rrd*"))


def test_truth_interpolated_between_samples_within_the_gap(content, native_errors, tmp_path):
    """Truth at every other frame (5 Hz): with the default gap (0.05 s) the frames between
    samples are solved but not scored, and the run says how many; with truth_max_gap_s=0.25
    they are scored against truth interpolated on SE(3) (the track's straight: exact)."""
    path = tmp_path / "sparse_truth.mcap"
    m = foxglove.messages
    with foxglove.open_mcap(path, allow_overwrite=True):
        t0 = content["images"][0][0]
        foxglove.log("/tf_static", _fx_tf_static(content, t0), log_time=t0)
        foxglove.log("/front/calibration", _fx_calibration(content["calibration"], t0), log_time=t0)
        for k, ((t, jpeg), (_, T_truth)) in enumerate(zip(content["images"], content["truth"])):
            # (the SDK keeps one channel type per topic per process: a topic of its own)
            foxglove.log("/front/jpeg", m.CompressedImage(timestamp=_ts(t), frame_id="cam_front", format="jpeg",
                                                          data=jpeg), log_time=t)
            if k % 2 == 0 or k == len(content["images"]) - 1:
                foxglove.log("/mocap/pose", m.PoseInFrame(timestamp=_ts(t), frame_id="world", pose=_fx_pose(T_truth)),
                             log_time=t)
    times = sorted(native_errors)
    outcome = run_recording(path, RunSettings(), tmp_path / "sparse.rrd")
    assert outcome.summary["solved"] == 4 and outcome.summary["position_error_mm"]["n"] == 3
    assert any("1 solved frame(s) not scored" in w for w in outcome.summary["warnings"]), outcome.summary["warnings"]
    errors = frame_errors(path, RunSettings(truth_max_gap_s=0.25))
    for t in times:
        tolerance = 1e-6 if t != times[1] else 1e-4
        assert abs(errors[t][1] - native_errors[t][1]) < tolerance, (t, errors[t][1], native_errors[t][1])


def test_every_ros2_type_decodes(tmp_path):
    """Each ROS 2 type the reader decodes, written by rosbags, read back through mcap-ros2-support."""
    from agvviz.recording.values import calibration as make_calibration

    T = se3.make(cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0], np.array([1.0, 2.0, 3.0]))
    rgb = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    camera = make_calibration("/c", "c", [400.0, 0, 3, 0, 400.0, 2, 0, 0, 1], [], "", 6, 4).camera
    messages = [
        ("/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", 5,
         T_["geometry_msgs/msg/PoseWithCovarianceStamped"](
             header=_header(5, "map"),
             pose=T_["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(T), covariance=np.zeros(36)))),
        ("/vicon/agv/agv", "geometry_msgs/msg/TransformStamped", 6, _tf("/world", "agv", T, 6)),
        ("/cam/image_raw", "sensor_msgs/msg/Image", 7, T_["sensor_msgs/msg/Image"](
            header=_header(7, "cam"), height=4, width=6, encoding="rgb8", is_bigendian=0, step=18, data=rgb.ravel())),
        ("/cam/camera_info", "sensor_msgs/msg/CameraInfo", 8,
         _camera_info(camera, 8, "rational_polynomial", [0.1, 0.01, 0.0, 0.0, 0.001, 0.05, 0.0, 0.0])),
    ]
    bag = write_bag(tmp_path / "types", messages)
    values = {m.topic: m.value for m in iter_messages(bag / "types_0.mcap")}
    amcl = values["/amcl_pose"]
    assert isinstance(amcl, PoseMsg) and amcl.frame_id == "map" and amcl.stamp_ns == 5
    np.testing.assert_allclose(amcl.T, T, atol=1e-12)
    (vicon,) = values["/vicon/agv/agv"]
    assert (vicon.parent_frame, vicon.child_frame, vicon.stamp_ns) == ("world", "agv", 6)  # ROS 1 "/" dropped
    np.testing.assert_allclose(vicon.T_parent_child, T, atol=1e-12)
    image = values["/cam/image_raw"]
    assert (image.image_format, image.source_encoding, image.frame_id) == ("png", "rgb8", "cam")
    np.testing.assert_array_equal(_png_pixels(image.data), rgb[:, :, ::-1])
    info = values["/cam/camera_info"]
    assert info.distortion_model == "rational_polynomial" and info.camera.is_rational
    prepared_roles = prepare(bag, RunSettings()).roles.roles
    assert prepared_roles["truth"] == "/vicon/agv/agv" and prepared_roles["cam.calibration"] == "/cam/camera_info"


def test_extrinsic_through_a_time_varying_link():
    """A camera on a pan unit: base_link → pan (/tf) → camera_optical_frame (/tf_static)."""
    from agvviz.model.messages import RecordedMessage
    from agvviz.replay.sync import SyncState

    sync = SyncState(body_frame="base_link")
    pan = lambda a: se3.make(cv2.Rodrigues(np.array([0.0, 0.0, a]))[0], np.array([0.0, 0.0, 1.0]))  # noqa: E731
    T_pan_cam = se3.make(np.eye(3), np.array([0.1, 0.0, 0.0]))
    sync.add(RecordedMessage("/tf_static", 0, "", [FrameTransformMsg("pan", "cam", T_pan_cam)], role="tf_static"))
    for t, a in ((0, 0.0), (100, 0.2)):
        sync.add(RecordedMessage("/tf", t, "", [FrameTransformMsg("base_link", "pan", pan(a), t)], role="tf", stamp_ns=t))
    T_body, T_world, why = sync.extrinsic("front", "cam", 50)
    np.testing.assert_allclose(T_body, pan(0.1) @ T_pan_cam, atol=1e-12)
    sync.truth_frames.add("map")
    T_body, T_world, why = sync.extrinsic("front", "cam", 5_000_000_000)  # 5 s after the last /tf
    assert T_body is None and T_world is None and "time-varying link" in why


def test_topic_names_live_in_one_module():
    """Every agvviz topic name is written once, in agvviz/model/topics.py."""
    import re

    root = Path(__file__).resolve().parents[1]
    literal = re.compile(r"""["'](/agv/ground_truth|/agv/odometry|/markers/map|/markers/corners|/uwb/range|/uwb/anchors|/tf_static|/tf|/cam/)["'/{]""")
    offenders = []
    for path in (root / "agvviz").rglob("*.py"):
        if path.name == "topics.py":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if literal.search(line) and not line.lstrip().startswith("#"):
                offenders.append(f"{path.relative_to(root)}:{number}: {line.strip()}")
    assert not offenders, "\n".join(offenders)
