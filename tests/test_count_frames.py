"""`count_image_times` (a sweep's progress total): from the MCAP summary's statistics when the
file has one camera topic, else by a streaming pass; the same number either way. Files written
with the `mcap` library's own writer (statistics on or off), and an agvviz recording."""

from __future__ import annotations

import shutil

import pytest
from mcap.writer import Writer

from agvviz.recording import reader
from agvviz.recording.mcap_stream import iter_raw
from agvviz.recording.raw import RawMessage, ReadReport


def _write(path, topics_times: dict[str, list[int]], statistics: bool = True) -> None:
    with open(path, "wb") as f:
        writer = Writer(f, use_statistics=statistics, use_summary_offsets=statistics)
        writer.start(profile="", library="test")
        schema = writer.register_schema(name="raw", encoding="", data=b"")
        for topic, times in topics_times.items():
            channel = writer.register_channel(topic=topic, message_encoding="raw", schema_id=schema)
            for t in times:
                writer.add_message(channel, log_time=t, data=b"x", publish_time=t)
        writer.finish()


def _streamed(path) -> int:
    return len({m.log_time_ns for m in iter_raw(path, report=ReadReport())
                if isinstance(m, RawMessage) and m.topic.startswith("/cam/") and m.topic.endswith("/image")})


def test_one_camera_is_counted_from_the_summary(tmp_path, monkeypatch):
    path = tmp_path / "one.mcap"
    _write(path, {"/cam/front/image": list(range(0, 70_000, 1000)), "/agv/odometry": list(range(0, 70_000, 100))})
    assert reader._summary_image_count(path) == 70
    monkeypatch.setattr(reader, "iter_raw", lambda *a, **k: pytest.fail("the summary answers: no pass"))
    assert reader.count_image_times(path) == 70


@pytest.mark.parametrize("case", ["two cameras", "no statistics", "truncated"])
def test_otherwise_a_streaming_pass_counts_distinct_stamps(tmp_path, case):
    path = tmp_path / "f.mcap"
    if case == "two cameras":  # stamps shared in part: 5 + 5 images, 7 distinct stamps
        _write(path, {"/cam/a/image": [0, 1, 2, 3, 4], "/cam/b/image": [3, 4, 5, 6, 2]})
        expected = 7
    else:
        _write(path, {"/cam/front/image": list(range(40))}, statistics=case != "no statistics")
        expected = 40
        if case == "truncated":  # no footer, no summary: what a killed recorder leaves
            data = path.read_bytes()
            path.write_bytes(data[: len(data) - 200])
            expected = _streamed(path)
    assert reader._summary_image_count(path) is None
    assert reader.count_image_times(path) == expected


def test_an_agvviz_recording_counts_the_same_both_ways(qr_small, tmp_path):
    copy = tmp_path / "qr.mcap"
    shutil.copyfile(qr_small, copy)
    assert reader._summary_image_count(copy) == _streamed(copy) > 0
