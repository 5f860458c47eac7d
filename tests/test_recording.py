"""Recording contract: writer → reader round trips, salvage of damaged files, inspector."""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.reader import make_reader

from agvviz.geometry import PinholeCamera, se3, so3
from agvviz.errors import RecordingError
from agvviz.model.messages import CalibrationMsg, CompressedFrame, PoseMsg
from agvviz.recording.contract import format_report, inspect_recording
from agvviz.recording.mcap_stream import read_scenario_metadata
from agvviz.recording.raw import ReadReport
from agvviz.recording.reader import iter_messages
from agvviz.recording.writer import RecordingWriter

SCENARIO = {"name": "unit", "seed": 7, "options": {"speed_m_s": 0.5, "cams": ["front"], "n": 3}}
CAMERA = PinholeCamera(
    np.array([[812.25, 0.5, 641.125], [0.0, 809.75, 511.0625], [0.0, 0.0, 1.0]]),
    np.array([-0.21, 0.043, 0.0011, -0.0007, -0.0032]),
    1280,
    1024,
)


def random_pose(rng) -> np.ndarray:
    return se3.make(so3.exp(rng.normal(size=3)), rng.normal(scale=5.0, size=3))


def image_times(path, report=None) -> list[int]:
    return [m.log_time_ns for m in iter_messages(path, topics={"/cam/front/image"}, report=report)]


# -- round trip ---------------------------------------------------------------------------
def test_round_trip_every_message_kind(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "rt.mcap"
    T_agv_cam = random_pose(rng)
    T_world_anchor = random_pose(rng)
    truth = [random_pose(rng) for _ in range(3)]
    odometry = [random_pose(rng) for _ in range(3)]
    jpegs = [rng.integers(0, 256, size=5000 + i, dtype=np.uint8).tobytes() for i in range(3)]
    png = rng.integers(0, 256, size=777, dtype=np.uint8).tobytes()
    marker_map = {
        "dictionary": "qr",
        "markers": [
            {
                "id": "A1",
                "side_m": 0.53,
                "corners_world_m": [[0, 0.265, 0], [0.265, 0.265, 0], [0.265, -0.265, 0], [0, -0.265, 0]],
                "payload": "agvviz:1;A1",
            },
            {"id": "7", "side_m": 0.2, "corners_world_m": rng.normal(size=(4, 3))},  # numpy → lists
        ],
    }
    uwb_range = {"tag": "T0", "anchor": "105", "t1_ns": 10, "t2_ns": 1_000_017, "t3_ns": 1_200_017, "t4_ns": 200_034, "range_m": 5.1}
    anchors = {"anchors": [{"id": "105", "position_m": [-0.02, -0.01, 2.0]}]}
    corners = {"cam_name": "front", "markers": [{"id": "A1", "corners_px": [[1.5, 2.5]] * 4}]}

    with RecordingWriter(path, scenario=SCENARIO) as w:
        w.write_calibration("front", CAMERA, 0)
        w.write_tf_static([("agv", "cam_front", T_agv_cam), ("world", "anchor_105", T_world_anchor)], 0)
        w.write_marker_map(marker_map, 0)
        w.write_json("/uwb/anchors", "agvviz.UwbAnchors", anchors, 0)
        for i in range(3):
            t = 100_000_000 * (i + 1)
            w.write_image("front", jpegs[i], "jpeg", t)
            w.write_image("side", png, "png", t)
            w.write_pose("/agv/ground_truth", truth[i], "world", t)
            w.write_pose("/agv/odometry", odometry[i], "odom", t)
            w.write_json("/uwb/range", "agvviz.UwbRange", uwb_range, t + 1)
            w.write_json("/markers/corners", "agvviz.CornerObservations", corners, t + 2)

    report = ReadReport()
    messages = list(iter_messages(path, report=report))
    assert report == ReadReport(messages=len(messages), chunks_ok=1, chunks_lost=0, problems=[])
    by_topic: dict[str, list] = {}
    for m in messages:
        by_topic.setdefault(m.topic, []).append(m)
    assert {t: len(v) for t, v in by_topic.items()} == {
        "/cam/front/calibration": 1, "/tf_static": 1, "/markers/map": 1, "/uwb/anchors": 1,
        "/cam/front/image": 3, "/cam/side/image": 3, "/agv/ground_truth": 3, "/agv/odometry": 3,
        "/uwb/range": 3, "/markers/corners": 3,
    }

    calib = by_topic["/cam/front/calibration"][0].value
    assert isinstance(calib, CalibrationMsg)
    assert (calib.cam_name, calib.frame_id, calib.distortion_model) == ("front", "cam_front", "plumb_bob")
    # doubles travel unchanged through protobuf: exact equality
    np.testing.assert_array_equal(calib.camera.K, CAMERA.K)
    np.testing.assert_array_equal(calib.camera.dist, CAMERA.dist)
    assert (calib.camera.width_px, calib.camera.height_px) == (1280, 1024)

    tfs = by_topic["/tf_static"][0].value
    assert [(tf.parent_frame, tf.child_frame) for tf in tfs] == [("agv", "cam_front"), ("world", "anchor_105")]
    # matrix → quaternion → matrix loses only a few ulps; 1e-12 leaves ample margin
    np.testing.assert_allclose(tfs[0].T_parent_child, T_agv_cam, atol=1e-12)
    np.testing.assert_allclose(tfs[1].T_parent_child, T_world_anchor, atol=1e-12)

    for i, m in enumerate(by_topic["/cam/front/image"]):
        assert m.log_time_ns == 100_000_000 * (i + 1)
        assert m.value == CompressedFrame("front", "cam_front", "jpeg", jpegs[i])
    assert all(m.value == CompressedFrame("side", "cam_side", "png", png) for m in by_topic["/cam/side/image"])

    for topic, frame, poses in (("/agv/ground_truth", "world", truth), ("/agv/odometry", "odom", odometry)):
        for m, T in zip(by_topic[topic], poses):
            assert isinstance(m.value, PoseMsg) and m.value.frame_id == frame
            np.testing.assert_allclose(m.value.T, T, atol=1e-12)

    expected_map = {**marker_map, "markers": [marker_map["markers"][0], {**marker_map["markers"][1], "corners_world_m": marker_map["markers"][1]["corners_world_m"].tolist()}]}
    assert by_topic["/markers/map"][0].value == expected_map
    assert by_topic["/markers/map"][0].schema_name == "agvviz.MarkerMap"
    assert by_topic["/uwb/anchors"][0].value == anchors
    assert all(m.value == uwb_range for m in by_topic["/uwb/range"])
    assert all(m.value == corners for m in by_topic["/markers/corners"])


def test_scenario_metadata_round_trip(tmp_path):
    import agvviz

    path = tmp_path / "meta.mcap"
    with RecordingWriter(path, scenario=SCENARIO) as w:
        w.write_pose("/agv/ground_truth", np.eye(4), "world", 0)
    assert read_scenario_metadata(path) == {**SCENARIO, "agvviz_version": agvviz.__version__}
    with open(path, "rb") as f:  # independent reader: the raw string record
        (record,) = list(make_reader(f).iter_metadata())
    assert record.name == "agvviz.scenario"
    assert record.metadata["seed"] == "7" and record.metadata["name"] == "unit"


def test_topics_filter(tmp_path):
    path = tmp_path / "f.mcap"
    with RecordingWriter(path, scenario=SCENARIO) as w:
        for i in range(4):
            w.write_image("front", b"x", "jpeg", i)
            w.write_pose("/agv/ground_truth", np.eye(4), "world", i)
    assert [m.topic for m in iter_messages(path, topics={"/agv/ground_truth"})] == ["/agv/ground_truth"] * 4


# -- writer refusals and atomicity ----------------------------------------------------------
def test_exception_inside_with_leaves_nothing(tmp_path):
    path = tmp_path / "out.mcap"
    with pytest.raises(KeyError):
        with RecordingWriter(path, scenario=SCENARIO) as w:
            w.write_image("front", b"abc", "jpeg", 0)
            raise KeyError("boom")
    assert os.listdir(tmp_path) == []


def test_failed_rewrite_keeps_previous_file(tmp_path):
    path = tmp_path / "out.mcap"
    with RecordingWriter(path, scenario=SCENARIO) as w:
        w.write_image("front", b"first", "jpeg", 0)
    before = path.read_bytes()
    with pytest.raises(RuntimeError):
        with RecordingWriter(path, scenario=SCENARIO) as w:
            w.write_image("front", b"second", "jpeg", 0)
            raise RuntimeError("stop")
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["out.mcap"]


def test_writer_refuses_bad_input(tmp_path):
    with pytest.raises(ValueError):  # the whole recording is discarded
        with RecordingWriter(tmp_path / "bad.mcap", scenario=SCENARIO) as w:
            w.write_pose("/agv/ground_truth", np.eye(4), "world", 10)
            with pytest.raises(ValueError, match="non-decreasing"):
                w.write_pose("/agv/ground_truth", np.eye(4), "world", 9)
            T = np.eye(4)
            T[0, 0] = 2.0
            with pytest.raises(ValueError, match="rigid"):
                w.write_pose("/agv/ground_truth", T, "world", 11)
            with pytest.raises(ValueError, match="range_m"):
                w.write_json("/uwb/range", "agvviz.UwbRange", {"tag": "t", "anchor": "a", "t1_ns": 1, "t2_ns": 2, "t3_ns": 3, "t4_ns": 4}, 0)
            with pytest.raises(ValueError, match="side_m"):
                w.write_marker_map({"dictionary": "qr", "markers": [{"id": "a", "side_m": -1.0, "corners_world_m": [[0, 0, 0]] * 4}]}, 0)
            with pytest.raises(ValueError, match="format"):
                w.write_image("front", b"x", "bmp", 0)
            raise ValueError("discard")
    assert os.listdir(tmp_path) == []


# -- damaged files ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def chunked_recording(tmp_path_factory):
    """A recording of 24 image messages of 300 kB (≈ 3 per 1 MiB chunk), image i at i ns.

    Returns the path, the chunk indexes (from mcap's own summary reader) and the image bytes.
    """
    rng = np.random.default_rng(5)
    path = tmp_path_factory.mktemp("chunks") / "many.mcap"
    images = [rng.integers(0, 256, size=300_000, dtype=np.uint8).tobytes() for _ in range(24)]
    with RecordingWriter(path, scenario=SCENARIO) as w:
        for i, data in enumerate(images):
            w.write_image("front", data, "jpeg", i)
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 5
    return path, chunks, images


def test_truncated_file_yields_earlier_chunks(chunked_recording, tmp_path):
    path, chunks, images = chunked_recording
    cut_chunk = chunks[3]
    cut_at = cut_chunk.chunk_start_offset + cut_chunk.chunk_length // 2
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(path.read_bytes()[:cut_at])

    report = ReadReport()
    messages = list(iter_messages(damaged, report=report))
    expected = [i for i in range(len(images)) if i < cut_chunk.message_start_time]
    assert [m.log_time_ns for m in messages] == expected
    assert all(m.value.data == images[m.log_time_ns] for m in messages)
    assert report.messages == len(expected) and report.chunks_ok == 3 and report.chunks_lost == 1
    assert any("truncated" in p for p in report.problems)


def test_byte_flip_loses_only_its_chunk(chunked_recording, tmp_path):
    path, chunks, images = chunked_recording
    bad = chunks[2]
    data = bytearray(path.read_bytes())
    data[bad.chunk_start_offset + bad.chunk_length // 2] ^= 0x10
    damaged = tmp_path / "flip.mcap"
    damaged.write_bytes(bytes(data))

    report = ReadReport()
    times = image_times(damaged, report)
    lost = set(range(bad.message_start_time, bad.message_end_time + 1))
    assert times == [i for i in range(len(images)) if i not in lost]
    assert report.chunks_lost == 1 and report.chunks_ok == len(chunks) - 1
    assert len(report.problems) == 1 and "CRC" in report.problems[0]


@pytest.mark.parametrize("new_length", [lambda n: n | (0x7F << 56), lambda n: n - 1000], ids=["past_eof", "short"])
def test_damaged_chunk_length_resyncs_at_next_chunk(chunked_recording, tmp_path, new_length):
    path, chunks, images = chunked_recording
    bad = chunks[1]
    data = bytearray(path.read_bytes())
    at = bad.chunk_start_offset + 1  # the chunk's u64 record length, after its opcode
    (length,) = struct.unpack_from("<Q", data, at)
    struct.pack_into("<Q", data, at, new_length(length))
    damaged = tmp_path / "len.mcap"
    damaged.write_bytes(bytes(data))

    report = ReadReport()
    times = image_times(damaged, report)
    lost = set(range(bad.message_start_time, bad.message_end_time + 1))
    assert times == [i for i in range(len(images)) if i not in lost]
    assert report.chunks_lost == 1
    assert any(f"resumed at the next intact chunk at byte {chunks[2].chunk_start_offset}" in p for p in report.problems)


def test_random_damage_never_raises_nor_yields_bad_data(chunked_recording, tmp_path):
    path, _, images = chunked_recording
    original = path.read_bytes()
    rng = np.random.default_rng(11)
    damaged = tmp_path / "fuzz.mcap"
    for case in range(40):
        data = bytearray(original)
        if case % 2:
            data = data[: int(rng.integers(0, len(data)))]
        else:
            for at in rng.integers(0, len(data), size=3):
                data[at] ^= int(rng.integers(1, 256))
        damaged.write_bytes(bytes(data))
        report = ReadReport()
        try:
            messages = list(iter_messages(damaged, report=report))
        except RecordingError:
            continue  # magic or first record hit: allowed, with a clear message
        assert all(m.value.data == images[m.log_time_ns] for m in messages)
        assert report.messages == len(messages)
        assert len(messages) == len(images) or report.problems  # no silent loss


def test_undecodable_payload_is_skipped_and_reported(tmp_path):
    path = tmp_path / "garbage.mcap"
    with RecordingWriter(path, scenario=SCENARIO) as w:
        w.write_image("front", b"good", "jpeg", 0)
        channel_id = w._channels["/cam/front/image"][0]  # the public API cannot write garbage
        w._add("/cam/front/image", channel_id, b"\xff\xff\xff\xff", 1)
        w.write_image("front", b"good again", "jpeg", 2)
    report = ReadReport()
    assert image_times(path, report) == [0, 2]
    assert report.messages == 2
    assert len(report.problems) == 1 and "/cam/front/image: 1 message(s) skipped" in report.problems[0]


def test_not_an_mcap_file(tmp_path):
    text = tmp_path / "notes.mcap"
    text.write_text("hello, this is not a recording\n")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        list(iter_messages(text))
    with pytest.raises(RecordingError, match="no such file"):
        list(iter_messages(tmp_path / "missing.mcap"))
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_scenario_metadata(text)


# -- contract inspector -----------------------------------------------------------------------
def _camera_jpeg() -> bytes:
    """A real JPEG of the calibration's size (inspect reads the size from the header)."""
    import cv2

    ok, data = cv2.imencode(".jpg", np.zeros((CAMERA.height_px, CAMERA.width_px), np.uint8))
    assert ok
    return data.tobytes()


def write_camera_recording(path, *, calibration=True, tf=True, image_frame="cam_front", truth_frame="world"):
    with RecordingWriter(path, scenario=SCENARIO) as w:
        if calibration:
            w.write_calibration("front", CAMERA, 0)
        if tf:
            w.write_tf_static([("agv", "cam_front", np.eye(4))], 0)
        for i in range(3):
            msg = CompressedImage(frame_id=image_frame, data=_camera_jpeg(), format="jpeg")
            w._write_protobuf("/cam/front/image", msg, 10 + i)  # lets the test break the frame id
            w.write_pose("/agv/ground_truth", np.eye(4), truth_frame, 10 + i)


def test_inspect_good_recording(tmp_path):
    path = tmp_path / "good.mcap"
    write_camera_recording(path)
    report = inspect_recording(path)
    assert report.ok, format_report(report)
    assert [(t.topic, t.count, t.first_ns, t.last_ns) for t in report.topics] == [
        ("/agv/ground_truth", 3, 10, 12),
        ("/cam/front/calibration", 1, 0, 0),
        ("/cam/front/image", 3, 10, 12),
        ("/tf_static", 1, 0, 0),
    ]
    assert (report.start_ns, report.end_ns) == (0, 12)
    np.testing.assert_array_equal(report.cameras["front"].camera.K, CAMERA.K)
    assert report.scenario["name"] == "unit"
    assert format_report(report).endswith("contract: OK")


@pytest.mark.parametrize(
    "kwargs, expected",
    [
        ({"calibration": False}, "camera front: images but no valid calibration"),
        ({"tf": False}, "camera front: no /tf_static transform agv -> cam_front"),
        ({"image_frame": "camera"}, "/cam/front/image: image frame_id is not 'cam_front' (3 messages; e.g. got 'camera')"),
        ({"truth_frame": "map"}, "/agv/ground_truth: frame_id is not 'world'"),
    ],
)
def test_inspect_reports_violation(tmp_path, kwargs, expected):
    path = tmp_path / "bad.mcap"
    write_camera_recording(path, **kwargs)
    report = inspect_recording(path)
    assert not report.ok
    assert len(report.violations) == 1 and report.violations[0].startswith(expected), report.violations
    assert f"violation: {report.violations[0]}" in format_report(report)


def test_inspect_reports_damage(chunked_recording, tmp_path):
    path, chunks, _ = chunked_recording
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(path.read_bytes()[: chunks[-1].chunk_start_offset + 100])
    report = inspect_recording(damaged)
    assert not report.ok and report.damage and any("truncated" in d for d in report.damage)


def test_header_reader_ends_on_a_truncated_file(chunked_recording, tmp_path):
    """read_file_header skips chunks unread: a truncated last chunk must not send its resync
    scan back to an earlier chunk for ever (it looped before). Checked in a subprocess with a
    timeout so a regression fails instead of hanging the suite."""
    import subprocess
    import sys

    path, chunks, _ = chunked_recording
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(path.read_bytes()[: chunks[-1].chunk_start_offset + 100])
    code = (
        "from agvviz.recording.mcap_stream import read_file_header; import sys; "
        f"print(read_file_header(sys.argv[1])[1])"
    )
    done = subprocess.run([sys.executable, "-c", code, str(damaged)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.startswith("agvviz"), done.stderr
