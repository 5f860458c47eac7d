"""An MCAP file as a stream of raw messages and metadata records, in file order, salvaged
(:mod:`agvviz.recording.mcap_records`): what the MCAP and ROS 2 formats read
(:mod:`agvviz.recording.formats`), plus the file's header and its metadata records read
without opening a chunk."""

from __future__ import annotations

import json
import zlib
from collections import OrderedDict
from typing import Iterator

from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema

from agvviz.errors import RecordingError
from agvviz.recording.mcap_records import chunk_records, open_mcap, read_tail, top_level_records
from agvviz.recording.raw import DAMAGE_ERRORS, RawMessage, RawMetadata, ReadReport
from agvviz.recording.schemas import REALISM_METADATA, SCENARIO_METADATA

#: Most recent message keys remembered for duplicate detection (bounded memory; a chunk
#: written twice further apart than this is still caught by its chunk signature).
DUPLICATE_WINDOW_MESSAGES = 65536


class _Duplicates:
    """Drops messages that repeat an earlier one exactly (same topic, log time, bytes — and
    publish time and sequence number, so distinct messages that merely carry equal data at one
    time, as in the MCAP conformance suite, are kept) and chunks that repeat an earlier chunk
    (same time range, size and CRC): a part of the file written twice would otherwise be
    replayed and counted twice."""

    def __init__(self):
        self._recent: OrderedDict = OrderedDict()
        self._chunks: dict[tuple, int] = {}  # chunk signature -> byte offset of its first copy
        self._dropped: dict[str, list] = {}  # topic -> [count, first log time]
        self.problems: list[str] = []

    @staticmethod
    def _chunk_key(chunk: Chunk) -> tuple:
        return (chunk.message_start_time, chunk.message_end_time, chunk.uncompressed_size, chunk.uncompressed_crc)

    def remember_chunk(self, chunk: Chunk, offset: int) -> None:
        """Note a chunk whose messages were all read (without a CRC, chunks cannot be told
        equal cheaply: the message check still applies to them)."""
        if chunk.uncompressed_crc != 0:
            self._chunks.setdefault(self._chunk_key(chunk), offset)

    def chunk_seen(self, chunk: Chunk, offset: int) -> bool:
        """True (and a problem noted) when ``chunk`` repeats a chunk read before."""
        first = self._chunks.get(self._chunk_key(chunk)) if chunk.uncompressed_crc != 0 else None
        if first is None or first == offset:
            return False
        self.problems.append(
            f"chunk at byte {offset} repeats the chunk at byte {first} (same log times "
            f"{chunk.message_start_time}-{chunk.message_end_time} ns, size and CRC): part of the "
            "file was written twice; the copy was dropped"
        )
        return True

    def message_seen(self, topic: str, message: Message) -> bool:
        data = message.data
        key = (topic, message.log_time, message.publish_time, message.sequence, len(data), zlib.crc32(data))
        log_time_ns = message.log_time
        if key in self._recent:
            entry = self._dropped.setdefault(topic, [0, log_time_ns])
            entry[0] += 1
            return True
        self._recent[key] = None
        if len(self._recent) > DUPLICATE_WINDOW_MESSAGES:
            self._recent.popitem(last=False)
        return False

    def lines(self) -> list[str]:
        return self.problems + [
            f"{topic}: {count} duplicate message(s) dropped (same topic, log time, sequence number "
            f"and bytes as an earlier message; first at log time {first_ns} ns): part of the file was written twice"
            for topic, (count, first_ns) in self._dropped.items()
        ]


def iter_raw(
    path, topics: set[str] | None = None, report: ReadReport | None = None, digest=None, verified: bool = False,
) -> Iterator:
    """Stream :class:`RawMessage` and :class:`RawMetadata` items in file order.

    Messages on topics outside ``topics`` (when given) are not yielded. A message that repeats
    an earlier one exactly (same topic, log time and bytes) is dropped and reported. With
    ``verified`` (the file was read whole before and found intact, without a repeated message,
    and is unchanged since: :meth:`agvviz.recording.raw.Recording.mark_verified`) the CRCs are
    not computed again and messages are not searched for repeats: that read found none. Damage is
    written to ``report`` (``report.messages`` is left to the caller), including a data
    section CRC mismatch and damage after the data section (summary, footer). Raises
    :class:`RecordingError` when the file is missing or not MCAP. With ``digest`` (a
    ``hashlib`` object) every byte of the file goes into it once the stream has ended
    (:class:`~agvviz.recording.raw.HashedReads`).
    """
    report = report if report is not None else ReadReport()
    f, size = open_mcap(path, digest)
    with f:
        tail = read_tail(f, size)
        schemas, channels = tail.schemas, tail.channels
        orphans: dict[int, int] = {}  # channel id -> messages skipped (Channel record lost)
        duplicates = _Duplicates()

        def raw(message: Message):
            channel = channels.get(message.channel_id)
            if channel is None:
                orphans[message.channel_id] = orphans.get(message.channel_id, 0) + 1
                return None
            if topics is not None and channel.topic not in topics:
                return None
            if not verified and duplicates.message_seen(channel.topic, message):
                return None
            schema = schemas.get(channel.schema_id)
            schema_name = schema.name if schema else ""
            if channel.message_encoding == "ros1" and schema_name.count("/") == 1:
                # MCAP's ROS 1 profile (`mcap convert x.bag`): pkg/Type → pkg/msg/Type, as a .bag's (ros1.py)
                schema_name = schema_name.replace("/", "/msg/")
            return RawMessage(
                topic=channel.topic,
                log_time_ns=message.log_time,
                schema_name=schema_name,
                schema_encoding=schema.encoding if schema else "",
                message_encoding=channel.message_encoding,
                data=message.data,
                schema_data=schema.data if schema else b"",
            )

        def define(record) -> None:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record

        anything_read = False
        try:
            for offset, record in top_level_records(f, size, report, tail=tail, check_crc=not verified):
                anything_read = True
                if isinstance(record, Chunk):
                    try:
                        inner = chunk_records(record, check_crc=not verified)
                    except DAMAGE_ERRORS as exc:
                        report.chunks_lost += 1
                        report.problems.append(
                            f"chunk at byte {offset} (log time {record.message_start_time}-"
                            f"{record.message_end_time} ns) is damaged, its messages are lost: {exc}"
                        )
                        continue
                    report.chunks_ok += 1
                    if duplicates.chunk_seen(record, offset):
                        continue
                    orphans_before = sum(orphans.values())
                    for item in inner:
                        define(item)
                        if isinstance(item, Message) and (out := raw(item)) is not None:
                            yield out
                    if sum(orphans.values()) == orphans_before:
                        # Only a chunk whose every message could be read stands for its copies.
                        duplicates.remember_chunk(record, offset)
                elif isinstance(record, Message):
                    if (out := raw(record)) is not None:
                        yield out
                elif isinstance(record, Metadata):
                    yield RawMetadata(record.name, dict(record.metadata))
                else:
                    define(record)
            if not anything_read:
                raise RecordingError(
                    f"{path}: has the MCAP magic but no readable record ({report.problems[-1]}); "
                    "the file is damaged right after its start — re-record or re-copy it"
                )
            if digest is not None:
                f.finish()
        finally:
            for channel_id, count in orphans.items():
                report.problems.append(
                    f"{count} message(s) on channel id {channel_id} skipped: that channel's "
                    "definition was in a lost part of the file"
                )
            report.problems.extend(duplicates.lines())


def parse_scenario_metadata(values: dict[str, str]) -> dict:
    """``{"name", "seed", "options", "agvviz_version"}`` from the ``agvviz.scenario`` record.

    Raises ``ValueError`` saying which entry is missing or malformed.
    """
    missing = [key for key in ("name", "seed", "options", "agvviz_version") if key not in values]
    if missing:
        raise ValueError(f"{SCENARIO_METADATA} metadata lacks {missing}")
    try:
        seed = int(values["seed"])
    except ValueError:
        raise ValueError(f"{SCENARIO_METADATA} seed {values['seed']!r} is not an integer") from None
    try:
        options = json.loads(values["options"])
    except json.JSONDecodeError as exc:
        raise ValueError(f"{SCENARIO_METADATA} options are not JSON ({exc})") from None
    if not isinstance(options, dict):
        raise ValueError(f"{SCENARIO_METADATA} options must be a JSON object, got {values['options']!r}")
    return {
        "name": values["name"],
        "seed": seed,
        "options": options,
        "agvviz_version": values["agvviz_version"],
    }


def read_metadata(path, name: str) -> dict[str, str] | None:
    """The values of the first Metadata record called ``name`` of an MCAP file, or ``None``
    when it has none. Reads only top-level record headers (chunks are skipped unread); raises
    :class:`RecordingError` when the file is not MCAP."""
    f, size = open_mcap(path)
    with f:
        for _, record in top_level_records(f, size, ReadReport(), read_chunks=False):
            if isinstance(record, Metadata) and record.name == name:
                return dict(record.metadata)
    return None


def read_scenario_metadata(path) -> dict | None:
    """The ``agvviz.scenario`` metadata of a recording, or ``None`` when it has none.

    Reads only top-level record headers (chunks are skipped unread). Raises
    :class:`RecordingError` when the file is not MCAP or the record is malformed.
    """
    values = read_metadata(path, SCENARIO_METADATA)
    if values is None:
        return None
    try:
        return parse_scenario_metadata(values)
    except ValueError as exc:
        raise RecordingError(f"{path}: {exc}; re-record it with 'agvviz record'") from None


def realism_draws(recording) -> dict | None:
    """The realism draws (``{"profile", "seed", "parameters", "sources"}``, written by
    :func:`agvviz.sim.realism.metadata_values`) stored in a recording's ``agvviz.realism``
    metadata record, or ``None`` when it has none: an ``ideal`` recording (no error source — its
    messages are exactly those of agvviz before the sources existed), one made before the record
    existed, or not by agvviz. ``recording``: a path. Reads only top-level records (chunks are
    skipped). Raises ``ValueError`` when the record is not valid JSON.
    """
    values = read_metadata(recording, REALISM_METADATA)
    if values is None:
        return None
    try:
        return json.loads(values["draws"])
    except (KeyError, json.JSONDecodeError) as exc:
        raise ValueError(f"{recording}: {REALISM_METADATA} metadata is malformed ({exc})") from None


def read_file_header(path) -> tuple[str, str, dict | None]:
    """``(profile, library, scenario)`` of an MCAP file: the Header record's profile
    (``ros2`` for rosbag2 files) and library (the writer, ``agvviz <version>`` for agvviz's
    own recordings), and the ``agvviz.scenario`` metadata (``None`` when absent or
    malformed). Reads only top-level record headers; never raises for damage inside."""
    profile, library, scenario = "", "", None
    f, size = open_mcap(path)
    with f:
        for _, record in top_level_records(f, size, ReadReport(), read_chunks=False):
            if isinstance(record, Header):
                profile, library = record.profile, record.library
            elif isinstance(record, Metadata) and record.name == SCENARIO_METADATA:
                try:
                    scenario = parse_scenario_metadata(record.metadata)
                except ValueError:
                    scenario = None
    return profile, library, scenario
