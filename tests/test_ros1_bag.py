"""ROS 1 bags (``.bag``) written by ``rosbags``' ROS 1 writer replay like agvviz's own recording.

One tiny qr_floor recording (4 frames, 640×512) is the source of truth; its content is
re-written as a ROS 1 bag with ``rosbags.rosbag1.Writer`` and the ROS 1 Noetic type store
(``sensor_msgs/CompressedImage`` with the recorded JPEG bytes, ``sensor_msgs/CameraInfo`` with
ROS 1's upper-case ``K``/``D``/``R``/``P``, a latched ``/tf_static`` ``tf2_msgs/TFMessage``
with a three-link camera chain, ``geometry_msgs/PoseStamped`` truth, ``nav_msgs/Odometry`` and
``/tf``), on ROS topic and frame names, log times 7 ms after the header stamps; the marker map
travels as a ``--markers`` side file. The recorded JPEG bytes are replayed as they are, so the
per-frame errors must equal the native ones to 1e-6 m (the same pixels, the same numbers:
only the transform chain's float round trip differs, ≪ 1 µm).

Also: a folder of split bags, every compression, bags cut short at several points (what is
intact is read, the rest is said lost), a connection with a message definition that does not
parse and a message with damaged bytes (skipped with topic and reason), a file that is not a
bag (one line), ROS 2 bags converted from the ROS 1 bag with ``rosbags``' converter under both
its default (copied ROS 1 definitions) and a ROS 2 type store.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from agvviz.cli.main import app
from agvviz.errors import RecordingError
from agvviz.geometry import se3
from agvviz.recording.contract import format_report, inspect_recording
from agvviz.recording.raw import ReadReport
from agvviz.recording.source import iter_role_messages, open_recording
from agvviz.replay.run import SideInputs, prepare
from agvviz.settings import RunSettings
from test_real_logs import frame_errors  # noqa: E402  (tests/ is on sys.path under pytest)

rosbags = pytest.importorskip("rosbags", reason="rosbags (test extra) not installed")
from rosbags.rosbag1 import Writer  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

TS1 = get_typestore(Stores.ROS1_NOETIC)
# rosbags' Noetic store lacks tf2_msgs and tf: their ROS 1 definitions (tf2_msgs/TFMessage.msg,
# tf/tfMessage.msg) are one line each.
TS1.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
TS1.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf/msg/tfMessage"))
T1 = TS1.types
LATENCY_NS = 7_000_000  # bag log time = header stamp + 7 ms (arrival at the recorder)
T_LINK_OPTICAL = se3.from_quaternion_xyzw(np.array([-0.5, 0.5, -0.5, 0.5]), np.zeros(3))  # REP 103
T_BASE_MOUNT = se3.make(cv2.Rodrigues(np.array([0.0, 0.0, 0.3]))[0], np.array([0.1, 0.2, 0.3]))
IMAGE_TOPIC = "/front/image_raw/compressed"


# -- the native recording and its content ------------------------------------------------------
@pytest.fixture(scope="module")
def native(qr_small) -> Path:
    """The shared small qr_floor recording (tests/conftest.py ``QR_SMALL``)."""
    return qr_small


@pytest.fixture(scope="module")
def content(qr_small_content) -> dict:
    return qr_small_content


@pytest.fixture(scope="module")
def markers(content, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("map") / "map.json"
    path.write_text(json.dumps(content["marker_map"]))
    return path


@pytest.fixture(scope="module")
def native_errors(native) -> dict:
    errors = frame_errors(native)
    assert len(errors) == 4 and all(rej is None and e is not None for rej, e in errors.values()), errors
    return errors


def side(markers: Path) -> SideInputs:
    from agvviz.recording.sidefiles import load_marker_map

    return SideInputs(marker_map=load_marker_map(markers))


def assert_same_errors(errors: dict, native_errors: dict, tol_m: float = 1e-6) -> None:
    assert sorted(errors) == sorted(native_errors)
    for t, (rejected, error) in native_errors.items():
        assert errors[t][0] == rejected, (t, errors[t])
        assert abs(errors[t][1] - error) < tol_m, (t, errors[t][1], error)


# -- a ROS 1 bag written by rosbags -------------------------------------------------------------
def _header(t_ns: int, frame: str, seq: int = 0):
    return T1["std_msgs/msg/Header"](
        seq=seq, stamp=T1["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=frame
    )


def _pose(T: np.ndarray):
    q = se3.to_quaternion_xyzw(T)
    return T1["geometry_msgs/msg/Pose"](
        position=T1["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        orientation=T1["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def _tf(parent: str, child: str, T: np.ndarray, t_ns: int):
    q = se3.to_quaternion_xyzw(T)
    return T1["geometry_msgs/msg/TransformStamped"](
        header=_header(t_ns, parent), child_frame_id=child,
        transform=T1["geometry_msgs/msg/Transform"](
            translation=T1["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=T1["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )


def _camera_info(camera, t_ns: int):
    roi = T1["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    P = np.zeros(12)
    P[[0, 1, 2, 4, 5, 6, 10]] = camera.K.ravel()[[0, 1, 2, 3, 4, 5, 8]]
    return T1["sensor_msgs/msg/CameraInfo"](
        header=_header(t_ns, "camera_optical_frame"), height=camera.height_px, width=camera.width_px,
        distortion_model="plumb_bob", D=np.asarray(camera.dist, dtype=np.float64),
        K=camera.K.ravel().astype(np.float64), R=np.eye(3).ravel(), P=P, binning_x=0, binning_y=0, roi=roi,
    )


def ros1_messages(content: dict) -> list[tuple[str, str, int, object]]:
    """(topic, type, log time, message) of the bag, in the order a robot's recorder writes them:
    the camera chain base_link → camera_mount → camera_link → camera_optical_frame (latched
    /tf_static), then per frame the compressed image, its CameraInfo, PoseStamped truth,
    Odometry and /tf odom → base_link."""
    T_link = se3.inverse(T_BASE_MOUNT) @ content["T_agv_cam"] @ se3.inverse(T_LINK_OPTICAL)
    t0 = content["images"][0][0]
    out = [("/tf_static", "tf2_msgs/msg/TFMessage", t0, T1["tf2_msgs/msg/TFMessage"](transforms=[
        _tf("base_link", "camera_mount", T_BASE_MOUNT, 0),
        _tf("camera_mount", "camera_link", T_link, 0),
        _tf("camera_link", "camera_optical_frame", T_LINK_OPTICAL, 0),
    ]))]
    zero = T1["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twist = T1["geometry_msgs/msg/TwistWithCovariance"](
        twist=T1["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36))
    truth = dict(content["truth"])
    odometry = dict(content["odometry"])
    for seq, (t, jpeg) in enumerate(content["images"]):
        out.append((IMAGE_TOPIC, "sensor_msgs/msg/CompressedImage", t + LATENCY_NS,
                    T1["sensor_msgs/msg/CompressedImage"](header=_header(t, "camera_optical_frame", seq), format="jpeg",
                                                          data=np.frombuffer(jpeg, np.uint8))))
        out.append(("/front/camera_info", "sensor_msgs/msg/CameraInfo", t + LATENCY_NS,
                    _camera_info(content["calibration"], t)))
        if t in truth:
            out.append(("/ground_truth/pose", "geometry_msgs/msg/PoseStamped", t + 2 * LATENCY_NS,
                        T1["geometry_msgs/msg/PoseStamped"](header=_header(t, "map", seq), pose=_pose(truth[t]))))
        if t in odometry:
            out.append(("/odom", "nav_msgs/msg/Odometry", t + LATENCY_NS, T1["nav_msgs/msg/Odometry"](
                header=_header(t, "odom", seq), child_frame_id="base_link",
                pose=T1["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(odometry[t]), covariance=np.zeros(36)),
                twist=twist)))
            out.append(("/tf", "tf2_msgs/msg/TFMessage", t + LATENCY_NS,
                        T1["tf2_msgs/msg/TFMessage"](transforms=[_tf("odom", "base_link", odometry[t], t)])))
    return sorted(out, key=lambda m: m[2])


def write_ros1_bag(path: Path, messages: list, compression: str | None = None,
                   chunk_bytes: int | None = None) -> Path:
    """A ROS 1 bag written by ``rosbags.rosbag1.Writer``; ``/tf_static`` latched, as ROS 1's
    static transform publisher does. ``chunk_bytes`` smaller chunks (more of them)."""
    writer = Writer(path)
    if compression:
        writer.set_compression(Writer.CompressionFormat[compression.upper()])
    if chunk_bytes:
        writer.chunk_threshold = chunk_bytes
    with writer:
        connections = {}
        for topic, msgtype, t, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(
                    topic, msgtype, typestore=TS1, latching=1 if topic == "/tf_static" else None)
            writer.write(connections[topic], t, TS1.serialize_ros1(msg, msgtype))
    return path


@pytest.fixture(scope="module")
def bag(content, tmp_path_factory) -> Path:
    return write_ros1_bag(tmp_path_factory.mktemp("ros1") / "robot.bag", ros1_messages(content), chunk_bytes=40_000)


# -- replay -------------------------------------------------------------------------------------
def test_ros1_bag_replays_like_native(bag, markers, native_errors):
    recording = open_recording(bag)
    assert recording.kind == "rosbag1" and recording.files == [bag]
    prepared = prepare(bag, RunSettings(), side=side(markers))
    roles = prepared.roles.roles
    assert roles["front.image"] == IMAGE_TOPIC and roles["front.calibration"] == "/front/camera_info"
    assert (roles["truth"], roles["odometry"], roles["tf_static"], roles["tf"]) == (
        "/ground_truth/pose", "/odom", "/tf_static", "/tf")
    assert (prepared.body_frame, prepared.time_source) == ("base_link", "header")
    assert prepared.usable_cameras == ["front"] and prepared.causes == []
    assert_same_errors(frame_errors(bag, side=side(markers)), native_errors)


def test_ros1_calibration_and_chain_are_the_recorded_ones(bag, content):
    """CameraInfo's upper-case K and D and the three-link /tf_static chain give the native
    calibration and T_agv_cam (independently of the pose pipeline)."""
    msgs = {m.topic: m.value for m in iter_role_messages(
        open_recording(bag), prepare(bag, RunSettings()).roles, "header", ReadReport())}
    calib = msgs["/front/camera_info"]
    np.testing.assert_array_equal(calib.camera.K, content["calibration"].K)
    np.testing.assert_array_equal(calib.camera.dist, content["calibration"].dist)
    sync = prepare(bag, RunSettings()).replay.sync
    np.testing.assert_allclose(sync.tf.lookup("base_link", "camera_optical_frame"), content["T_agv_cam"], atol=1e-12)


def test_folder_of_split_bags_and_every_compression(content, markers, native_errors, tmp_path):
    messages = ros1_messages(content)
    folder = tmp_path / "split"
    folder.mkdir()
    half = len(messages) // 2
    # names sort as numbers: _2 before _10
    write_ros1_bag(folder / "robot_2.bag", messages[:half], compression="bz2")
    write_ros1_bag(folder / "robot_10.bag", messages[half:], compression="lz4")
    recording = open_recording(folder)
    assert recording.kind == "rosbag1" and [f.name for f in recording.files] == ["robot_2.bag", "robot_10.bag"]
    assert_same_errors(frame_errors(folder, side=side(markers)), native_errors)
    report = inspect_recording(folder)
    assert report.damage == [] and "ROS 1 bags: robot_2.bag, robot_10.bag" in format_report(report)


def test_cli_inspect_and_run_on_a_bag(bag, markers, tmp_path):
    inspected = CliRunner().invoke(app, ["inspect", str(bag), "--markers", str(markers)])
    assert inspected.exit_code == 0, inspected.stdout
    assert "sensor_msgs/msg/CameraInfo [ros1]" in inspected.stdout
    assert "damage:" not in inspected.stdout
    out = tmp_path / "bag.rrd"
    ran = CliRunner().invoke(app, ["run", str(bag), "--markers", str(markers), "--out", str(out)])
    assert ran.exit_code == 0, ran.stdout
    assert out.is_file()


# -- damage -------------------------------------------------------------------------------------
@pytest.mark.parametrize("fraction", [0.005, 0.05, 0.3, 0.55, 0.8, 0.97, 0.9995])
def test_cut_short_bag_salvages_what_is_intact(bag, markers, native_errors, tmp_path, fraction):
    """Cut at several points (inside the 4 kB bag header record, inside chunks, inside the index):
    no traceback; what is read is a prefix of the messages; every frame read gives the native
    error; the loss is said (inspect prints it)."""
    data = bag.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: int(len(data) * fraction)])
    full = [(m.topic, m.log_time_ns) for m in _raw(bag)]
    report = ReadReport()
    got = [(m.topic, m.log_time_ns) for m in open_recording(cut).iter_raw(report)]
    assert got == full[: len(got)] and len(got) < len(full) + 1
    assert report.problems and any("lost" in p for p in report.problems), report.problems
    inspected = CliRunner().invoke(app, ["inspect", str(cut)])
    assert "Traceback" not in inspected.stdout and "damage:" in inspected.stdout, inspected.stdout
    try:
        errors = frame_errors(cut, side=side(markers))
    except Exception as exc:  # no frame read yet: a clear one-line error
        assert type(exc).__name__ in ("RunError", "InputError", "RecordingError"), exc
        return
    for t, (rejected, error) in errors.items():
        if rejected is None:
            assert abs(error - native_errors[t][1]) < 1e-6


def _raw(path):
    return list(open_recording(path).iter_raw(ReadReport()))


def test_undecodable_messages_are_skipped_with_topic_and_reason(content, markers, native_errors, tmp_path):
    """A connection whose message definition does not parse, a type without a definition and a
    message with damaged bytes: each skipped with its topic and why; the frames still solve."""
    path = tmp_path / "bad.bag"
    messages = ros1_messages(content)
    last_odom_ns = max(t for topic, _, t, _ in messages if topic == "/odom")
    writer = Writer(path)
    with writer:
        connections = {}
        for topic, msgtype, t, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=TS1)
            data = TS1.serialize_ros1(msg, msgtype)
            if topic == "/odom" and t == last_odom_ns:
                data = data[:40]  # damaged: cut inside the pose
            writer.write(connections[topic], t, data)
        bad_def = writer.add_connection("/robot/pose", "geometry_msgs/msg/PoseStamped",
                                        msgdef="this is not a message definition !!", md5sum="0" * 32)
        no_def = writer.add_connection("/tracker/pose", "geometry_msgs/msg/PoseWithCovarianceStamped",
                                       msgdef="", md5sum="f" * 32)
        pose = TS1.serialize_ros1(T1["geometry_msgs/msg/PoseStamped"](header=_header(1, "map"), pose=_pose(np.eye(4))),
                                  "geometry_msgs/msg/PoseStamped")
        writer.write(bad_def, messages[-1][2], pose)
        writer.write(no_def, messages[-1][2], pose)
    report = ReadReport()
    prepared = prepare(path, RunSettings(tracking=False), side=side(markers),
                       topics={"truth": "/robot/pose", "odometry": "/tracker/pose"})
    for _ in iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, report):
        pass
    lines = report.problems
    assert any(line.startswith("/robot/pose:") and "unknown message definition" in line for line in lines), lines
    assert any(line.startswith("/tracker/pose:") and "no message definition" in line and "md5sum" in line
               for line in lines), lines
    report = ReadReport()
    prepared = prepare(path, RunSettings(tracking=False), side=side(markers))
    for _ in iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, report):
        pass
    assert any(line.startswith("/odom: 1 message(s) skipped") and "does not decode" in line
               for line in report.problems), report.problems
    assert_same_errors(frame_errors(path, side=side(markers)), native_errors)
    inspected = CliRunner().invoke(app, ["inspect", str(path), "--topic", "truth=/robot/pose"])
    assert "Traceback" not in inspected.stdout
    assert "/robot/pose: payload does not match geometry_msgs/msg/PoseStamped" in inspected.stdout


def test_not_a_bag_is_one_line(tmp_path):
    text = tmp_path / "notes.bag"
    text.write_text("hello, not a bag\n")
    with pytest.raises(RecordingError, match=r"not a ROS 1 bag \(starts with") as excinfo:
        open_recording(text)
    assert "\n" not in str(excinfo.value)
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match="not a ROS 1 bag .is empty"):
        open_recording(empty)
    old = tmp_path / "old.bag"
    old.write_bytes(b"#ROSBAG V1.2\n" + b"\0" * 100)
    with pytest.raises(RecordingError, match="format 1.2.*rosbag fix"):
        open_recording(old)
    # a bag header naming an encryptor (rosbag's encrypted bags): refused with the command
    import struct

    fields = b"".join(struct.pack("<I", len(f)) + f for f in (
        b"op=\x03", b"index_pos=" + struct.pack("<Q", 0), b"conn_count=" + struct.pack("<I", 0),
        b"chunk_count=" + struct.pack("<I", 0), b"encryptor=rosbag/AesCbcEncryptor"))
    encrypted = tmp_path / "secret.bag"
    encrypted.write_bytes(b"#ROSBAG V2.0\n" + struct.pack("<I", len(fields)) + fields + struct.pack("<I", 0))
    with pytest.raises(RecordingError, match="encrypted ROS 1 bag .*rosbag decrypt"):
        open_recording(encrypted)
    inspected = CliRunner().invoke(app, ["inspect", str(text)])
    assert inspected.exit_code != 0 and "Traceback" not in inspected.stdout
    assert "not a ROS 1 bag" in inspected.stdout + str(inspected.stderr if inspected.stderr_bytes else "")


# -- converted to ROS 2 ---------------------------------------------------------------------------
@pytest.mark.parametrize("dst_store", [None, Stores.ROS2_HUMBLE], ids=["copied_ros1_definitions", "ros2_humble"])
def test_ros2_bag_converted_from_ros1_reads_the_same(bag, content, markers, native_errors, tmp_path, dst_store):
    """``rosbags``' converter, default (definitions copied from ROS 1: ``float64[9] K``,
    ``float64[] D``, Header ``seq`` — which mcap_ros2's parser refuses) and into a ROS 2 type
    store; both read as the ROS 1 bag does."""
    from rosbags.convert import convert

    out = tmp_path / "converted"
    convert([bag], out, "mcap", 8, None, "file", None,
            get_typestore(dst_store) if dst_store else None, [], [], [], [])
    assert open_recording(out).kind == "rosbag2"
    report = inspect_recording(out)
    assert report.damage == [] and report.violations == [], (report.damage, report.violations)
    np.testing.assert_array_equal(report.cameras["front"].camera.K, content["calibration"].K)
    np.testing.assert_array_equal(report.cameras["front"].camera.dist, content["calibration"].dist)
    assert_same_errors(frame_errors(out, side=side(markers)), native_errors)
    inspected = CliRunner().invoke(app, ["inspect", str(out)])
    assert inspected.exit_code == 0 and "Traceback" not in inspected.stdout, inspected.stdout


def test_mcap_with_the_ros1_profile_reads_like_the_bag(content, markers, native_errors, tmp_path):
    """An MCAP file of the ROS 1 profile (what ``mcap convert x.bag`` writes: ``ros1msg``
    schemas named ``pkg/Type``, ``ros1`` message encoding), written with the ``mcap`` library
    from the bag's own connections and bytes."""
    from mcap.writer import Writer as McapWriter
    from rosbags.rosbag1 import Reader

    bag = write_ros1_bag(tmp_path / "src.bag", ros1_messages(content))
    path = tmp_path / "ros1_profile.mcap"
    with open(path, "wb") as f, Reader(bag) as reader:
        writer = McapWriter(f)
        writer.start(profile="ros1", library="test")
        channels = {}
        for connection in reader.connections:
            ros1_name = connection.msgtype.replace("/msg/", "/")
            schema = writer.register_schema(ros1_name, "ros1msg", connection.msgdef.data.encode())
            channels[connection.id] = writer.register_channel(connection.topic, "ros1", schema)
        for connection, t_ns, data in reader.messages():
            writer.add_message(channels[connection.id], t_ns, bytes(data), t_ns)
        writer.finish()
    recording = open_recording(path)
    assert recording.kind == "mcap" and recording.profile == "ros1"
    assert_same_errors(frame_errors(path, side=side(markers)), native_errors)


def test_damaged_chunk_header_is_skipped_and_reading_goes_on(bag, tmp_path):
    """A chunk whose record header is overwritten: reported, the reader finds the next chunk
    and reads on; what it reads is the full bag's messages less that chunk's, in order."""
    data = bytearray(bag.read_bytes())
    chunk_ops = [i for i in range(len(data)) if data.startswith(b"op=\x05", i)]
    assert len(chunk_ops) >= 3
    second = chunk_ops[1]
    start = data.rfind(b"\x04\x00\x00\x00op=\x05", 0, second + 1)  # rosbags writes op first
    header_at = start - 4
    data[header_at:header_at + 4] = b"\xff\xff\xff\x7f"  # a header length past the end of the file
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(bytes(data))
    report = ReadReport()
    got = [(m.topic, m.log_time_ns) for m in open_recording(damaged).iter_raw(report)]
    full = [(m.topic, m.log_time_ns) for m in _raw(bag)]
    assert 0 < len(got) < len(full)
    assert all(item in full for item in got) and got == sorted(got, key=full.index)
    assert any(f"record at byte {header_at} is damaged" in p for p in report.problems), report.problems
    assert any("reading on from the next chunk" in p for p in report.problems), report.problems
    assert any("index lists" in p and "lost" in p for p in report.problems), report.problems


def test_old_tf_tfmessage_reads_like_tf2(content, markers, native_errors, tmp_path):
    """ROS 1's original ``tf/tfMessage`` (before tf2) on /tf_static and /tf."""
    messages = [
        (topic, "tf/msg/tfMessage" if msgtype == "tf2_msgs/msg/TFMessage" else msgtype, t,
         T1["tf/msg/tfMessage"](transforms=msg.transforms) if msgtype == "tf2_msgs/msg/TFMessage" else msg)
        for topic, msgtype, t, msg in ros1_messages(content)
    ]
    path = write_ros1_bag(tmp_path / "old_tf.bag", messages)
    prepared = prepare(path, RunSettings(), side=side(markers))
    assert (prepared.roles.roles["tf_static"], prepared.roles.roles["tf"]) == ("/tf_static", "/tf")
    assert_same_errors(frame_errors(path, side=side(markers)), native_errors)
