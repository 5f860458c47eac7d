"""The decoded messages of an MCAP recording, streamed in file order and salvaged
(:mod:`agvviz.recording.mcap_stream`), decoded by the format of their encoding
(:func:`agvviz.recording.formats.decode`) — agvviz's own recordings as the scenarios, tests
and benches read them; a run opens any recording through :mod:`agvviz.recording.source`."""

from __future__ import annotations

import logging
from typing import Iterator

from agvviz.model.messages import RecordedMessage
from agvviz.model.topics import is_camera_image_topic
from agvviz.recording.formats import decode
from agvviz.recording.mcap_stream import iter_raw
from agvviz.recording.raw import MessageDecodeError, RawMessage, RawMetadata, ReadReport, SkipCounter

_log = logging.getLogger(__name__)


def iter_messages(
    path, topics: set[str] | None = None, report: ReadReport | None = None
) -> Iterator[RecordedMessage]:
    """Stream the decoded messages of a recording in file order.

    Parameters
    ----------
    path : str or Path
        An MCAP file.
    topics : set of str, optional
        Only these topics (all when ``None``).
    report : ReadReport, optional
        Filled with counts and one line per problem (lost chunks, truncation, skipped
        undecodable messages). Without one, problems are logged as warnings.

    Raises
    ------
    RecordingError
        The file is missing or not an MCAP file. Damage inside an MCAP file never raises.
    """
    own_report = report is None
    report = ReadReport() if own_report else report
    skipped = SkipCounter()
    try:
        for item in iter_raw(path, topics, report):
            if isinstance(item, RawMetadata):
                continue
            try:
                value = decode(item)
            except MessageDecodeError as exc:
                skipped.add(item, exc)
                continue
            report.messages += 1
            yield RecordedMessage(item.topic, item.log_time_ns, item.schema_name, value)
    finally:
        report.problems += skipped.lines()
        if own_report:
            for problem in report.problems:
                _log.warning("%s: %s", path, problem)


def count_image_times(path) -> int:
    """Number of distinct time stamps among camera images (``/cam/<name>/image``): the number
    of frames a replay will produce, whatever the number of cameras; for progress bars. An
    MCAP whose summary counts the messages of its one camera topic is answered from that
    (no pass over a 10-minute log's gigabytes: ``sweep`` asks while its first run starts, and
    that run's own scan reads the file meanwhile); otherwise one streaming pass without decoding."""
    counted = _summary_image_count(path)
    if counted is not None:
        return counted
    times = set()
    for item in iter_raw(path, report=ReadReport()):
        if isinstance(item, RawMessage) and is_camera_image_topic(item.topic):
            times.add(item.log_time_ns)
    return len(times)


def _summary_image_count(path) -> int | None:
    """The message count of the one camera image topic in the MCAP summary's statistics; None
    without a summary or statistics, with another number of camera topics, or for anything that
    does not read as an MCAP summary (the streaming pass then counts)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 — a damaged or partial file: counted by the streaming pass
        return None
    if summary is None or summary.statistics is None:
        return None
    counts = summary.statistics.channel_message_counts
    cameras = [i for i, channel in summary.channels.items() if is_camera_image_topic(channel.topic)]
    if len(cameras) != 1 or cameras[0] not in counts:
        return None
    return int(counts[cameras[0]])
