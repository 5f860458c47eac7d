"""Issue 10, bad recordings: files that are readable but wrong, and damage a CRC must catch.

Every case here used to crash ``run``, or give wrong numbers with exit 0 and nothing said. Each
must now be a per-frame rejection with a reason, a warning in the run summary, or a refusal —
and ``inspect`` and ``run`` must name the same problem (they share one check).

The bad recordings are a small ``qr_floor`` recording rewritten message by message with
``mcap``'s own Writer (as another tool would write them: no DataEnd CRC), or patched bytes.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from agvviz.errors import RunError
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from mcap.reader import make_reader
from mcap.records import DataEnd

from agvviz import scenarios as scenario_registry
from agvviz.geometry import PinholeCamera, se3
from agvviz.markers import qr
from agvviz.markers.qr import detect_qr_codes
from agvviz.replay.solve import Replay
from agvviz.model.frames import REJECT_CALIBRATION_SIZE, REJECT_IMAGE, REJECT_MAP_MISMATCH, REJECT_TIME
from agvviz.recording.checks import (
    PAYLOAD_MAP_TOLERANCE_M,
    frame_problem,
    image_header_size,
    payload_map_problem,
)
from agvviz.recording.contract import inspect_recording
from agvviz.errors import RecordingError
from agvviz.model.messages import CalibrationMsg, CompressedFrame, FrameTransformMsg, RecordedMessage
from agvviz.recording.mcap_records import DATA_SECTION_CRC_PROBLEM
from agvviz.recording.raw import ReadReport
from agvviz.recording.reader import iter_messages
from agvviz.recording.values import MAX_IMAGE_SIDE_PX
from agvviz.model.frames import REJECT_NO_CALIBRATION, REJECT_PAYLOAD
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings

REAL_PHOTO = Path(__file__).resolve().parents[2] / "shared" / "data" / "zxing_qrcode" / "qrcode-2" / "31.png"
HOUR_NS = 3600 * 10**9


# -- the base recording and rewriting ---------------------------------------------------------
@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A 3-frame qr_floor recording (1280x1024, distortion, truth, odometry, QR map)."""
    path = tmp_path_factory.mktemp("base") / "base.mcap"
    scenario_registry.record("qr_floor", path, seed=1, overrides=["duration_s=0.6", "rate_hz=5", "realism=ideal"])
    return path


@pytest.fixture(scope="module")
def base_run(base, tmp_path_factory):
    return run_recording(base, RunSettings(), tmp_path_factory.mktemp("base_run") / "base.rrd")


def rewrite(src: Path, dst: Path, mutate) -> Path:
    """Copy ``src`` message by message through ``mutate(topic, schema, log_time, data) -> list of
    (log_time, data)`` with mcap's Writer (its default: no DataEnd CRC, like other tools)."""
    from mcap.writer import CompressionType, Writer

    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        header = reader.get_header()
        writer = Writer(f_out, chunk_size=1024 * 1024, compression=CompressionType.NONE)
        writer.start(profile=header.profile, library=header.library)
        for md in reader.iter_metadata():
            writer.add_metadata(md.name, dict(md.metadata))
        schema_ids, channel_ids = {}, {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channel_ids:
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_ids.get(channel.schema_id, 0)
                )
            for log_time, data in mutate(channel.topic, schema.name if schema else "", message.log_time, message.data):
                writer.add_message(
                    channel_ids[channel.id], log_time=log_time, data=data, publish_time=log_time,
                    sequence=message.sequence,
                )
        writer.finish()
    return dst


def image_times(path: Path) -> list[int]:
    with open(path, "rb") as f:
        return [m.log_time for _, c, m in make_reader(f).iter_messages(log_time_order=False) if c.topic.endswith("/image")]


def _images(fn):
    """A mutation applying ``fn(t, CompressedImage) -> list of (t, message)`` to images only."""

    def mutate(topic, schema, t, data):
        if schema != "foxglove.CompressedImage":
            return [(t, data)]
        return [(t2, msg.SerializeToString()) for t2, msg in fn(t, CompressedImage.FromString(data))]

    return mutate


def _stamp(msg, t):
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(t, 10**9)
    return msg


def _calibration(width, height):
    def mutate(topic, schema, t, data):
        if schema != "foxglove.CameraCalibration":
            return [(t, data)]
        msg = CameraCalibration.FromString(data)
        msg.width, msg.height = width, height
        return [(t, msg.SerializeToString())]

    return mutate


def run(path: Path, tmp_path: Path, **settings) -> dict:
    outcome = run_recording(path, RunSettings(**settings), tmp_path / f"{path.stem}.rrd")
    return outcome.summary


def test_base_recording_is_clean(base, base_run):
    """No false alarm: the unmodified recording passes every new check and solves every frame."""
    assert inspect_recording(base).ok
    summary = base_run.summary
    assert summary["frames"] == 3 and summary["solved"] == 3, summary
    assert summary["warnings"] == [] and summary["recording_damage"] == []
    assert summary["position_error_mm"]["n"] == 3


# -- A: recordings that crashed run ---------------------------------------------------------------
@pytest.mark.parametrize("width,height", [(2**32 - 1, 1024), (1280, 2**31 - 1)], ids=["width_2^32-1", "height_2^31-1"])
def test_absurd_calibration_size_is_refused_not_allocated(base, tmp_path, width, height):
    bad = rewrite(base, tmp_path / "calib.mcap", _calibration(width, height))
    report = inspect_recording(bad)
    assert not report.ok
    assert any(f"outside 1..{MAX_IMAGE_SIDE_PX} px per side" in v for v in report.violations), report.violations
    # No frame can be used: the run fails loudly, one line per cause, and writes no .rrd.
    with pytest.raises(RunError) as excinfo:
        run(bad, tmp_path)
    assert "camera front (/cam/front/image): no usable calibration" in str(excinfo.value)
    assert f"outside 1..{MAX_IMAGE_SIDE_PX}" in str(excinfo.value)
    assert not list(tmp_path.glob("*.rrd*"))


def test_replay_refuses_absurd_calibration_from_any_source():
    """The replay's own bound (calibrations need not come through the reader)."""
    camera = PinholeCamera(np.array([[1000.0, 0, 640], [0, 1000.0, 512], [0, 0, 1]]), np.array([-0.05, 0.01, 0, 0, 0]), 1280, 2**31 - 1)
    engine = Replay(RunSettings())
    engine.feed(RecordedMessage("/cam/front/calibration", 0, "", CalibrationMsg("front", "cam_front", camera, "plumb_bob")))
    engine.feed(RecordedMessage("/tf_static", 0, "", [FrameTransformMsg("agv", "cam_front", np.eye(4))]))
    frame = engine.feed(RecordedMessage("/cam/front/image", 1, "", CompressedFrame("front", "cam_front", "jpeg", b"\xff\xd8")))
    assert frame.rejected == REJECT_NO_CALIBRATION
    assert "calibration refused" in frame.reject_detail and str(MAX_IMAGE_SIDE_PX) in frame.reject_detail


@pytest.mark.parametrize(
    "name,fn,expected",
    [
        ("empty", lambda t, m: (setattr(m, "data", b""), [(t, m)])[1], "is empty (0 bytes)"),
        ("bmp", lambda t, m: (setattr(m, "format", "bmp"), [(t, m)])[1], "image format 'bmp' is not in the recording contract"),
        # inspect said "contract: OK" for frames of random bytes that run rejected.
        ("random", lambda t, m: (setattr(m, "data", np.random.default_rng(t).integers(0, 256, 4000, dtype=np.uint8)
                                         .tobytes()), [(t, m)])[1], "no readable JPEG header"),
    ],
)
def test_unusable_image_is_a_rejection(base, tmp_path, name, fn, expected):
    bad = rewrite(base, tmp_path / f"{name}.mcap", _images(fn))
    report = inspect_recording(bad)
    assert any(REJECT_IMAGE in v and expected in v for v in report.violations), report.violations
    with pytest.raises(RunError) as excinfo:  # no frame can be used: no .rrd
        run(bad, tmp_path)
    assert f"3 frame(s) rejected as {REJECT_IMAGE}" in str(excinfo.value) and expected in str(excinfo.value)
    assert not list(tmp_path.glob("*.rrd*"))


def test_image_header_sizes():
    gray = np.zeros((24, 40), np.uint8)
    assert image_header_size(cv2.imencode(".png", gray)[1].tobytes(), "png") == (40, 24)
    assert image_header_size(cv2.imencode(".jpg", gray)[1].tobytes(), "jpeg") == (40, 24)
    assert image_header_size(b"\xff\xd8\xff", "jpeg") is None
    huge = bytearray(cv2.imencode(".png", gray)[1].tobytes())
    struct.pack_into(">II", huge, 16, 100_000, 24)  # a header claiming a 100000 px wide image
    reason, detail = frame_problem("png", bytes(huge), None)
    assert reason == REJECT_IMAGE and "100000x24" in detail


# -- B: a real QR photo whose payload is not UTF-8 ------------------------------------------------
@pytest.mark.skipif(not REAL_PHOTO.is_file(), reason=f"real zxing photo {REAL_PHOTO} not present (../shared/data ships only qrcode-1; the synthetic non-UTF-8 test below covers the same path)")
def test_non_utf8_payload_on_real_photo_is_a_rejection():
    gray = cv2.imread(str(REAL_PHOTO), cv2.IMREAD_GRAYSCALE)
    detections = detect_qr_codes(gray)  # raised UnicodeDecodeError (Shift-JIS payload)
    assert len(detections) == 1 and detections[0].text is None and detections[0].payload_bytes
    h, w = gray.shape
    camera = PinholeCamera(np.array([[500.0, 0, w / 2], [0, 500.0, h / 2], [0, 0, 1]]), np.zeros(5), w, h)
    engine = Replay(RunSettings())
    engine.feed(RecordedMessage("/cam/front/calibration", 0, "", CalibrationMsg("front", "cam_front", camera, "")))
    engine.feed(RecordedMessage("/tf_static", 0, "", [FrameTransformMsg("agv", "cam_front", np.eye(4))]))
    frame = engine.feed(RecordedMessage("/cam/front/image", 1, "", CompressedFrame("front", "cam_front", "png", REAL_PHOTO.read_bytes())))
    assert frame.rejected == REJECT_PAYLOAD and "payload refused" in frame.reject_detail


def test_non_utf8_payload_bytes_are_refused_by_the_pipeline(monkeypatch):
    """The same path without the photo: a detection carrying bytes that are not UTF-8."""
    gray = np.full((64, 64), 255, np.uint8)
    raw = qr._RawCode(b"\x8d\xa1\x93x\x82\xcc", np.array([[10.0, 10], [50, 10], [50, 50], [10, 50]]), None)
    assert raw.text is None
    detection = qr._refine(gray, raw, "none")
    assert detection.text is None and detection.payload_bytes == raw.data
    monkeypatch.setattr("agvviz.markers.qr.detect_qr_codes", lambda *a, **k: [detection])
    camera = PinholeCamera(np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]), np.zeros(5), 64, 64)
    engine = Replay(RunSettings(tracking=False))  # the detect stage calls detect_qr_codes itself
    engine.feed(RecordedMessage("/cam/front/calibration", 0, "", CalibrationMsg("front", "cam_front", camera, "")))
    engine.feed(RecordedMessage("/tf_static", 0, "", [FrameTransformMsg("agv", "cam_front", np.eye(4))]))
    png = cv2.imencode(".png", gray)[1].tobytes()
    frame = engine.feed(RecordedMessage("/cam/front/image", 1, "", CompressedFrame("front", "cam_front", "png", png)))
    assert frame.rejected == REJECT_PAYLOAD and "payload refused" in frame.reject_detail


def test_chunk_copy_before_its_channel_does_not_hide_the_original(tmp_path):
    """A copy of chunk 1 placed before chunk 0 (which defines the channel) cannot be read; the
    original must still be replayed, not dropped as a duplicate of the unreadable copy."""
    path, chunks = _chunked(tmp_path)
    data = path.read_bytes()
    first, second = chunks[0], chunks[1]
    copy = data[second.chunk_start_offset : second.chunk_start_offset + second.chunk_length]
    at = first.chunk_start_offset
    moved = tmp_path / "copy_first.mcap"
    moved.write_bytes(data[:at] + copy + data[at:])
    report = ReadReport()
    assert [m.log_time_ns for m in iter_messages(moved, report=report)] == list(range(8))
    assert report.problems  # the unreadable copy is reported


def test_damaged_message_index_length_does_not_skip_an_intact_chunk(tmp_path):
    """A MessageIndex record (not CRC-checked) whose length jumps 1 MiB forward, into the middle
    of the next chunk: the resync scan starts after the last chunk read, so that next chunk
    (intact) is still found."""
    path, chunks = _chunked(tmp_path)
    data = bytearray(path.read_bytes())
    index_at = chunks[0].chunk_start_offset + chunks[0].chunk_length  # the MessageIndex after chunk 0
    assert data[index_at] == 0x07
    (length,) = struct.unpack_from("<Q", data, index_at + 1)
    struct.pack_into("<Q", data, index_at + 1, length + 2**19)  # lands inside chunk 1
    assert index_at + 9 + length + 2**19 < chunks[1].chunk_start_offset + chunks[1].chunk_length
    damaged = tmp_path / "index_len.mcap"
    damaged.write_bytes(bytes(data))
    report = ReadReport()
    assert [m.log_time_ns for m in iter_messages(damaged, report=report)] == list(range(8))
    assert report.chunks_lost == 0 and report.problems


# -- C: wrong numbers with exit 0 -----------------------------------------------------------------
def _shared_line(report, summary, needle: str) -> str:
    """The one line both inspect (violation) and run (warning) give, containing ``needle``."""
    lines = [v for v in report.violations if needle in v]
    assert lines, report.violations
    assert lines[0] in summary["warnings"], (lines[0], summary["warnings"])
    return lines[0]


def test_reversed_image_times(base, tmp_path):
    times = image_times(base)
    t0, t1 = min(times), max(times)
    bad = rewrite(base, tmp_path / "reversed.mcap", _images(lambda t, m: [(t0 + t1 - t, _stamp(m, t0 + t1 - t))]))
    summary = run(bad, tmp_path)
    assert summary["frames"] == 3 and summary["rejected"].get(REJECT_TIME) == 2, summary
    # the one frame left is scored: truth comes from the whole recording (first pass)
    assert summary["position_error_mm"]["n"] == 1
    _shared_line(inspect_recording(bad), summary, "not after the previous image's")


def test_images_at_one_time(base, tmp_path):
    t0 = min(image_times(base))
    bad = rewrite(base, tmp_path / "one_time.mcap", _images(lambda t, m: [(t0, _stamp(m, t0))]))
    summary = run(bad, tmp_path)
    assert summary["frames"] == 3 and summary["rejected"].get(REJECT_TIME) == 2, summary
    assert summary["position_error_mm"]["n"] <= 1
    _shared_line(inspect_recording(bad), summary, "all 3 images share one log time")


def test_every_log_time_zero(base, tmp_path):
    bad = rewrite(base, tmp_path / "zero.mcap", lambda topic, schema, t, data: [(0, data)])
    summary = run(bad, tmp_path)
    assert summary["frames"] == 3, summary  # was: 1 frame of 3 replayed, nothing said
    assert summary["rejected"].get(REJECT_TIME) == 2
    _shared_line(inspect_recording(bad), summary, "has log time 0")


def test_ground_truth_shifted_by_an_hour(base, tmp_path):
    def shift(topic, schema, t, data):
        if topic != "/agv/ground_truth":
            return [(t, data)]
        return [(t + HOUR_NS, _stamp(PoseInFrame.FromString(data), t + HOUR_NS).SerializeToString())]

    bad = rewrite(base, tmp_path / "gt_hour.mcap", shift)
    summary = run(bad, tmp_path)
    assert summary["solved"] == 3 and summary["position_error_mm"]["n"] == 0
    line = _shared_line(inspect_recording(bad), summary, "does not overlap the images")
    assert "no frame can be scored against truth" in line
    # the warning travels in the run file too
    from agvviz.viz import paths
    from agvviz.viz.readback import document_json

    stored = document_json(tmp_path / f"{bad.stem}.rrd", paths.RUN_SUMMARY)
    assert stored["warnings"] == summary["warnings"]
    # issue 23: the summary table (terminal and .rrd) says truth was given and scored nothing,
    # naming the offset between the spans (the shift above, exactly: both spans start at frames)
    from agvviz.evaluation.summary_table import summary_rows

    truth = summary["truth"]
    assert truth["given"] and truth["frames_scored"] == 0 and truth["frames_solved"] == 3
    first_truth, first_image = min(truth_times(bad)), min(image_times(bad))
    assert truth["truth_offset_s"] == pytest.approx((first_truth - first_image) / 1e9, abs=1e-9)
    assert 3599.0 < truth["truth_offset_s"] < 3601.0
    row = dict(summary_rows(summary, {}))["truth"]
    assert row.startswith("given but no frame scored — truth stamps start 3600") and "after the images" in row
    assert row.endswith("check the time base")
    assert stored["truth"] == truth
    markdown = _summary_text(tmp_path / f"{bad.stem}.rrd")
    assert "| truth |" in markdown and "check the time base" in markdown


def test_truth_that_scores_nothing_is_a_warning(base, tmp_path):
    """Truth overlapping the images in span but never within truth_max_dt_s of a frame."""

    def offset(topic, schema, t, data):
        return [(t + 50_000_000, data)] if topic == "/agv/ground_truth" else [(t, data)]

    bad = rewrite(base, tmp_path / "gt_offset.mcap", offset)
    summary = run(bad, tmp_path)
    assert summary["position_error_mm"]["n"] == 0
    assert any("no frame could be scored against it" in w for w in summary["warnings"]), summary["warnings"]
    assert summary["truth"]["frames_scored"] == 0 and "truth overlaps the images" in summary["truth"]["note"]


def test_truth_that_scores_is_no_row(base_run):
    from agvviz.evaluation.summary_table import summary_rows

    truth = base_run.summary["truth"]
    assert truth == {"given": True, "frames_solved": 3, "frames_scored": 3}
    assert "truth" not in dict(summary_rows(base_run.summary, {}))


def truth_times(path: Path) -> list[int]:
    with open(path, "rb") as f:
        return [m.log_time for _, c, m in make_reader(f).iter_messages(topics=["/agv/ground_truth"])]


def _summary_text(rrd: Path) -> str:
    """The run/summary markdown document of ``rrd``, read back with Rerun."""
    from agvviz.viz import paths
    from agvviz.viz.readback import read_rrd, text_document

    return text_document(read_rrd(rrd), paths.RUN_SUMMARY)


def test_duplicated_messages_are_dropped(base, base_run, tmp_path):
    bad = rewrite(base, tmp_path / "dup_msgs.mcap", lambda topic, schema, t, data: [(t, data), (t, data)])
    report = ReadReport()
    messages = list(iter_messages(bad, report=report))
    assert len(messages) == base_run.read_report.messages
    assert any("/cam/front/image: 3 duplicate message(s) dropped" in p for p in report.problems), report.problems
    summary = run(bad, tmp_path)
    assert summary["frames"] == 3 and summary["solved"] == 3
    assert summary["position_error_mm"] == base_run.summary["position_error_mm"]
    assert any("duplicate" in p for p in summary["recording_damage"])
    assert any("duplicate" in v for v in inspect_recording(bad).damage)


def _chunked(tmp_path):
    """8 images of 400 kB at log times 0..7 ns in several 1 MiB chunks; (path, chunk indexes)."""
    from agvviz.recording.writer import RecordingWriter

    rng = np.random.default_rng(3)
    path = tmp_path / "chunks.mcap"
    with RecordingWriter(path, scenario={"name": "t", "seed": 0, "options": {}}) as w:
        for i in range(8):
            w.write_image("front", rng.integers(0, 256, 400_000, dtype=np.uint8).tobytes(), "jpeg", i)
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 3
    return path, chunks


def test_duplicated_chunk_is_dropped(tmp_path):
    """A chunk record written twice (bytes copied): its copy is dropped and reported."""
    path, chunks = _chunked(tmp_path)
    data = path.read_bytes()
    chunk = chunks[1]
    start, end = chunk.chunk_start_offset, chunk.chunk_start_offset + chunk.chunk_length
    doubled = tmp_path / "doubled.mcap"
    doubled.write_bytes(data[:end] + data[start:end] + data[end:])
    report = ReadReport()
    times = [m.log_time_ns for m in iter_messages(doubled, report=report)]
    assert times == list(range(8))
    assert any(f"repeats the chunk at byte {start}" in p for p in report.problems), report.problems


def test_calibration_smaller_than_images(base, tmp_path):
    bad = rewrite(base, tmp_path / "calib640.mcap", _calibration(640, 480))
    report = inspect_recording(bad)
    assert any(REJECT_CALIBRATION_SIZE in v and "1280x1024 px" in v and "640x480" in v for v in report.violations), report.violations
    with pytest.raises(RunError) as excinfo:  # no frame can be used: no .rrd
        run(bad, tmp_path)
    assert f"3 frame(s) rejected as {REJECT_CALIBRATION_SIZE}" in str(excinfo.value)
    assert not list(tmp_path.glob("*.rrd*"))


def test_payloads_far_from_the_marker_map(base, tmp_path):
    def far(topic, schema, t, data):
        if topic != "/markers/map":
            return [(t, data)]
        value = json.loads(data)
        for m in value["markers"]:
            m["corners_world_m"] = [[x + 10_000.0, y, z] for x, y, z in m["corners_world_m"]]
        return [(t, json.dumps(value).encode())]

    bad = rewrite(base, tmp_path / "map_far.mcap", far)
    summary = run(bad, tmp_path)
    assert summary["solved"] == 0 and summary["rejected"] == {REJECT_MAP_MISMATCH: 3}, summary
    # inspect sees the same disagreement between the map's corners and its printed payloads
    assert any("payload vertices are up to" in v for v in inspect_recording(bad).violations)


def test_payload_map_rule():
    corners = np.array([[0.0, 0.5, 0], [0.5, 0.5, 0], [0.5, 0, 0], [0, 0, 0]])
    qr_map = {"A": corners, "B": corners + [1.5, 0, 0]}
    assert payload_map_problem("A", corners + [PAYLOAD_MAP_TOLERANCE_M / 2, 0, 0], qr_map) is None
    assert "mm from the marker map" in payload_map_problem("A", corners + [2 * PAYLOAD_MAP_TOLERANCE_M, 0, 0], qr_map)
    assert payload_map_problem("C", corners + [3.0, 0, 0], qr_map) is None  # unmapped, beside the grid
    assert "not in the marker map" in payload_map_problem("C", corners + [10_000.0, 0, 0], qr_map)
    assert payload_map_problem("A", corners + [10_000.0, 0, 0], {}) is None  # no map, no check


# -- D: silent corruption outside chunks ------------------------------------------------------------
def _data_end_crc(path: Path) -> int:
    data = path.read_bytes()
    with open(path, "rb") as f:
        from mcap.stream_reader import StreamReader

        return next(r for r in StreamReader(f, skip_magic=False).records if isinstance(r, DataEnd)).data_section_crc, data


def test_writer_sets_data_section_crc(base):
    crc, _ = _data_end_crc(base)
    assert crc != 0


def test_bit_flip_in_metadata_is_reported(base, tmp_path):
    data = bytearray(base.read_bytes())
    at = data.index(b"seed\x01\x00\x00\x001") + 8  # the seed's value "1" in the metadata record
    data[at] ^= 0x01  # "1" -> "0": still a valid seed, only the CRC can tell
    bad = tmp_path / "seed_flip.mcap"
    bad.write_bytes(bytes(data))
    report = inspect_recording(bad)
    assert not report.ok and DATA_SECTION_CRC_PROBLEM in report.damage
    outcome = run_recording(bad, RunSettings(), tmp_path / "seed_flip.rrd")
    assert DATA_SECTION_CRC_PROBLEM in outcome.summary["recording_damage"]
    assert any("manifest may be damaged" in w for w in outcome.summary["warnings"])


@pytest.mark.parametrize("from_end", [8 + 29 + 40, 3], ids=["summary", "magic"])
def test_damage_after_data_end_is_reported(base, tmp_path, from_end):
    data = bytearray(base.read_bytes())
    data[-from_end] ^= 0x01
    bad = tmp_path / "tail.mcap"
    bad.write_bytes(bytes(data))
    report = ReadReport()
    assert len(list(iter_messages(bad, report=report))) == len(list(iter_messages(base)))
    assert report.problems and not any(DATA_SECTION_CRC_PROBLEM == p for p in report.problems)
    assert not inspect_recording(bad).ok


# -- inputs that would hang a reader ------------------------------------------------------------
def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    import os

    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    with pytest.raises(RecordingError, match="not a regular file"):
        list(iter_messages(fifo))  # opening it would block for ever


@pytest.mark.parametrize("name", ["pipe.mcap", "pipe.bag"])
def test_inspect_and_run_refuse_a_fifo_without_waiting_for_a_writer(tmp_path, name):
    """The command line on a FIFO: one line and exit 2, at once (the recording-kind sniffing
    must not open it: that waits for a writer). A watchdog thread feeds the pipe after 20 s so
    a regression fails instead of hanging the suite."""
    import os
    import subprocess
    import sys
    import threading
    import time

    fifo = tmp_path / name
    os.mkfifo(fifo)
    done = threading.Event()

    def unblock():
        if not done.wait(20.0):
            with open(fifo, "wb"):  # lets a blocked open() return
                pass

    threading.Thread(target=unblock, daemon=True).start()
    try:
        for command in (["inspect", str(fifo)], ["run", str(fifo), "--out", str(tmp_path / "x.rrd")]):
            t0 = time.monotonic()
            result = subprocess.run([sys.executable, "-m", "agvviz", *command], capture_output=True, text=True, timeout=60)
            assert time.monotonic() - t0 < 20.0, f"{command[0]} waited on the FIFO"
            assert result.returncode == 2, (command, result.returncode, result.stderr)
            assert "not a regular file" in result.stderr and "Traceback" not in result.stderr
    finally:
        done.set()


def _zero_chunk(uncompressed_bytes: int, claimed_bytes: int | None = None) -> bytes:
    """A zstd chunk record inflating to zero bytes, with its CRC right (a decompression bomb)."""
    import zlib

    import zstandard

    zeros = bytes(uncompressed_bytes)
    data = zstandard.ZstdCompressor(level=1).compress(zeros)
    body = struct.pack("<QQQI", 0, 0, claimed_bytes or uncompressed_bytes, zlib.crc32(zeros))
    body += struct.pack("<I", 4) + b"zstd" + struct.pack("<Q", len(data)) + data
    return struct.pack("<BQ", 0x06, len(body)) + body


@pytest.mark.parametrize("claimed", [None, 1 << 40])
def test_a_decompression_bomb_chunk_is_lost_not_walked(tmp_path, claimed):
    """Zero bytes parse as reserved-opcode records of length 0: 32 MiB of them were walked one
    by one (1 GiB took two minutes); now the first one condemns the chunk. A chunk claiming more
    than MAX_CHUNK_BYTES is refused before decompression."""
    path, chunks = _chunked(tmp_path)
    data = path.read_bytes()
    at = chunks[1].chunk_start_offset
    bomb = tmp_path / "bomb.mcap"
    bomb.write_bytes(data[:at] + _zero_chunk(32 << 20, claimed) + data[at:])
    report = ReadReport()
    times = [m.log_time_ns for m in iter_messages(bomb, report=report)]
    assert times == list(range(8))  # every intact chunk still read
    assert report.chunks_lost == 1
    expected = "reserved" if claimed is None else "decompression bomb"
    assert any(expected in p for p in report.problems), report.problems
