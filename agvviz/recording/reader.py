"""Stream messages out of an MCAP recording, salvaging what a damaged file still holds.

The file is read front to back, one top-level record at a time, in file order (agvviz's writer
writes in log-time order), so memory stays at one chunk whatever the file size. Records are
parsed with ``mcap``'s own record classes, but the loop is ours rather than
``mcap.stream_reader.StreamReader``'s: that generator dies on the first exception and trusts
every length field, whereas here

* each chunk is decompressed and CRC-checked on its own; a bad chunk is reported and skipped,
  and the next record is read from the offset its header announced;
* a record header that cannot be right (length past the end of the file, reserved opcode) makes
  the reader scan forward for the next chunk whose CRC checks, and carry on from there;
* a truncated file yields every complete chunk before the cut;
* schemas and channels are also taken from the summary section when the file has one, so
  messages whose Channel record sat in a lost chunk can still be read.

Damage never escapes as ``ZstdError``, ``UnicodeDecodeError``, ``struct.error`` and the like:
it is written to a :class:`ReadReport`, or logged as a warning when the caller passes none.
Only a missing file or a file that is not MCAP at all raises :class:`RecordingError`.
Reading stops at the DataEnd record (the summary after it only repeats the data section).

Decoding: Foxglove protobuf messages of the recording contract become the dataclasses below,
JSON channels become ``dict`` (``agvviz.*`` payloads checked against their schema), anything
else stays ``bytes``.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import zlib
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Iterator

import lz4.frame
import numpy as np
import zstandard
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from google.protobuf.message import DecodeError
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema

from agvviz.errors import RecordingError
from agvviz.geometry import PinholeCamera, se3
from agvviz.recording.schemas import SCENARIO_METADATA, SCHEMAS, validate_payload

_log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")
_FOOTER_RECORD_BYTES = 9 + 20  # opcode, length, summary_start, summary_offset_start, crc
_MIN_CHUNK_BODY_BYTES = 8 + 8 + 8 + 4 + 4 + 8  # times, size, crc, compression len, records len
_MAX_COMPRESSION_NAME = 16  # bytes; real names are "", "zstd", "lz4"
_CHUNK_PREFIX_BYTES = _MIN_CHUNK_BODY_BYTES + _MAX_COMPRESSION_NAME
_SCAN_BLOCK_BYTES = 1 << 20
#: Exceptions that damaged bytes raise inside mcap, zstandard, lz4 and protobuf parsing.
_DAMAGE_ERRORS = (
    McapError,
    struct.error,
    UnicodeDecodeError,
    ValueError,
    OverflowError,
    KeyError,
    IndexError,
    RuntimeError,  # lz4.frame on corrupt frames
    MemoryError,
    zstandard.ZstdError,
    DecodeError,
)


class MessageDecodeError(RecordingError):
    """A message payload does not decode as its schema says (the message is skipped)."""


# -- decoded values ---------------------------------------------------------------------------
@dataclass(frozen=True)
class CompressedFrame:
    """One encoded camera frame; ``data`` is the recorded bytes, never re-encoded."""

    cam_name: str
    frame_id: str
    image_format: str  # "jpeg" | "png" (Foxglove CompressedImage.format, as recorded)
    data: bytes


@dataclass(frozen=True)
class CalibrationMsg:
    """A camera's intrinsics; ``distortion_model`` is "plumb_bob" (or "" when D is empty)."""

    cam_name: str
    frame_id: str
    camera: PinholeCamera
    distortion_model: str


@dataclass(frozen=True)
class FrameTransformMsg:
    """``T_parent_child`` (4×4): the child frame's pose in the parent frame."""

    parent_frame: str
    child_frame: str
    T_parent_child: np.ndarray


@dataclass(frozen=True)
class PoseMsg:
    """A pose ``T`` (4×4) in frame ``frame_id`` (for the AGV: ``T_<frame_id>_agv``)."""

    frame_id: str
    T: np.ndarray


@dataclass(frozen=True)
class RecordedMessage:
    """One decoded message.

    ``value`` is a :class:`CompressedFrame`, :class:`CalibrationMsg`,
    ``list[FrameTransformMsg]``, :class:`PoseMsg`, a JSON value (``dict`` for agvviz
    messages) or ``bytes`` for schemas this reader does not decode.
    """

    topic: str
    log_time_ns: int
    schema_name: str
    value: object


@dataclass
class ReadReport:
    """What a read got and what it lost: messages yielded, chunks read and lost, and one
    line per problem saying what was lost and why."""

    messages: int = 0
    chunks_ok: int = 0
    chunks_lost: int = 0
    problems: list[str] = field(default_factory=list)


# -- raw records ------------------------------------------------------------------------------
@dataclass(frozen=True)
class RawMessage:
    """A message before decoding, with its channel's schema and encodings."""

    topic: str
    log_time_ns: int
    schema_name: str  # "" when the channel has no schema
    schema_encoding: str
    message_encoding: str
    data: bytes


@dataclass(frozen=True)
class RawMetadata:
    """An MCAP Metadata record."""

    name: str
    values: dict[str, str]


class _ExactStream(ReadDataStream):
    """``ReadDataStream`` that raises on a short read instead of returning fewer bytes."""

    def read(self, length: int) -> bytes:
        data = super().read(length)
        if len(data) != length:
            raise EndOfFile()
        return data


def _stream(data: bytes) -> _ExactStream:
    return _ExactStream(BytesIO(data))


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name
    except ValueError:
        return f"opcode 0x{opcode:02x}"


def _parse_record(opcode: int, body: bytes):
    """The mcap record in ``body`` (``None`` for record kinds the reader does not use)."""
    stream = _stream(body)
    if opcode == Opcode.MESSAGE:
        return Message.read(stream, len(body))
    parser = {
        Opcode.HEADER: Header.read,
        Opcode.SCHEMA: Schema.read,
        Opcode.CHANNEL: Channel.read,
        Opcode.CHUNK: Chunk.read,
        Opcode.METADATA: Metadata.read,
        Opcode.DATA_END: DataEnd.read,
        Opcode.FOOTER: Footer.read,
    }.get(opcode)
    return parser(stream) if parser else None


def _chunk_records(chunk: Chunk) -> list:
    """Schemas, channels and messages inside ``chunk``, after decompression and CRC check.

    Raises one of ``_DAMAGE_ERRORS`` when any of it is damaged (the whole chunk is then lost:
    without a matching CRC nothing in it can be trusted).
    """
    if chunk.compression == "":
        data = chunk.data
    elif chunk.compression == "zstd":
        data = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size
        )
    elif chunk.compression == "lz4":
        data = lz4.frame.decompress(chunk.data)
    else:
        raise ValueError(f"unsupported chunk compression {chunk.compression!r}")
    if len(data) != chunk.uncompressed_size:
        raise ValueError(
            f"chunk holds {len(data)} bytes after decompression, its header says {chunk.uncompressed_size}"
        )
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch (the chunk's bytes are damaged)")
    records = []
    offset = 0
    while offset < len(data):
        opcode, length = _RECORD_HEADER.unpack_from(data, offset)
        start = offset + _RECORD_HEADER.size
        if start + length > len(data):
            raise ValueError(f"{_opcode_name(opcode)} record inside the chunk runs past its end")
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            records.append(_parse_record(opcode, data[start : start + length]))
        offset = start + length
    return records


def _open(path) -> tuple:
    """Open ``path`` and check the MCAP magic. Returns (file, size in bytes)."""
    path = Path(path)
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file; give the path of an .mcap recording") from None
    except (IsADirectoryError, PermissionError, OSError) as exc:
        raise RecordingError(f"{path}: cannot open ({exc.strerror or exc})") from None
    size = os.fstat(f.fileno()).st_size
    head = f.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC:
        f.close()
        what = "is empty" if size == 0 else f"starts with {head[:8]!r}, not the MCAP magic"
        raise RecordingError(
            f"{path}: not an MCAP file ({what}); give a recording written by "
            "'agvviz record' or another MCAP writer"
        )
    return f, size


def _chunk_header_problem(f, body_at: int, length: int) -> str | None:
    """Why the chunk record whose body (``length`` bytes) starts at ``body_at`` cannot be one,
    judged from its first fields only (so a damaged length is caught before reading), or
    ``None`` when they are consistent.

    Chunk body: start and end time (u64 each), uncompressed size (u64), uncompressed CRC (u32),
    compression (u32-prefixed string), records (u64-prefixed bytes), optional padding.
    """
    if length < _MIN_CHUNK_BODY_BYTES:
        return f"is {length} bytes long, shorter than any chunk"
    f.seek(body_at)
    prefix = f.read(min(length, _CHUNK_PREFIX_BYTES))
    (compression_len,) = struct.unpack_from("<I", prefix, 28)
    if compression_len > _MAX_COMPRESSION_NAME:
        return f"names a compression of {compression_len} characters"
    records_at = 32 + compression_len
    if len(prefix) < records_at + 8:
        return "is too short for its compression name and records length"
    (records_len,) = struct.unpack_from("<Q", prefix, records_at)
    if records_len > length - records_at - 8:
        return f"holds {records_len} bytes of records in a {length}-byte body"
    return None


def _is_valid_chunk_at(f, offset: int, size: int) -> bool:
    """True when a complete chunk with a CRC that checks starts at ``offset``."""
    f.seek(offset)
    header = f.read(_RECORD_HEADER.size)
    if len(header) < _RECORD_HEADER.size:
        return False
    opcode, length = _RECORD_HEADER.unpack(header)
    body_at = offset + _RECORD_HEADER.size
    if opcode != Opcode.CHUNK or length > size - body_at or _chunk_header_problem(f, body_at, length):
        return False
    try:
        f.seek(body_at)
        chunk = _parse_record(opcode, f.read(length))
        if chunk.uncompressed_crc == 0:
            return False  # without a CRC a lucky byte pattern could pass for a chunk
        _chunk_records(chunk)
    except _DAMAGE_ERRORS:
        return False
    return True


def _find_next_chunk(f, start: int, size: int) -> int | None:
    """Offset of the first intact chunk at or after ``start`` (scanning), or ``None``."""
    block_start = start
    while block_start < size:
        f.seek(block_start)
        block = f.read(_SCAN_BLOCK_BYTES)
        at = block.find(bytes([Opcode.CHUNK]))
        while at >= 0:
            if _is_valid_chunk_at(f, block_start + at, size):
                return block_start + at
            at = block.find(bytes([Opcode.CHUNK]), at + 1)
        block_start += _SCAN_BLOCK_BYTES
    return None


def _summary_definitions(f, size: int) -> tuple[dict[int, Schema], dict[int, Channel]]:
    """Schemas and channels repeated in the summary section, when the file has an intact one.

    Best effort: any damage here just means the data section's own records are used.
    """
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    footer_at = size - len(MCAP_MAGIC) - _FOOTER_RECORD_BYTES
    if footer_at < len(MCAP_MAGIC):
        return schemas, channels
    try:
        f.seek(size - len(MCAP_MAGIC))
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            return schemas, channels
        f.seek(footer_at)
        opcode, length = _RECORD_HEADER.unpack(f.read(_RECORD_HEADER.size))
        if opcode != Opcode.FOOTER or length != 20:
            return schemas, channels
        footer = _parse_record(opcode, f.read(length))
        offset = footer.summary_start
        if not len(MCAP_MAGIC) <= offset < footer_at:
            return schemas, channels
        while offset < footer_at:
            f.seek(offset)
            opcode, length = _RECORD_HEADER.unpack(f.read(_RECORD_HEADER.size))
            if length > footer_at - offset:
                break
            if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                record = _parse_record(opcode, f.read(length))
                target = schemas if opcode == Opcode.SCHEMA else channels
                target[record.id] = record
            offset += _RECORD_HEADER.size + length
    except _DAMAGE_ERRORS:
        pass
    return schemas, channels


def _top_level_records(f, size: int, report: ReadReport, read_chunks: bool = True):
    """Yield the parsed top-level records of the data section in file order, salvaging.

    Chunks are yielded as ``Chunk`` records (or skipped unread when ``read_chunks`` is
    False). Damage is written to ``report``. Stops after DataEnd or Footer.
    """
    offset = len(MCAP_MAGIC)
    while True:
        f.seek(offset)
        header = f.read(_RECORD_HEADER.size)
        if len(header) < _RECORD_HEADER.size:
            report.problems.append(
                f"file ends at byte {size} without a DataEnd record: it was truncated "
                "(anything written after that point is lost)"
            )
            break
        opcode, length = _RECORD_HEADER.unpack(header)
        body_at = offset + _RECORD_HEADER.size
        if opcode == 0 or 0x10 <= opcode < 0x80:
            why = "has a reserved opcode"
        elif length > size - body_at:
            why = f"needs {length} bytes but only {size - body_at} remain"
        elif opcode == Opcode.CHUNK:
            why = _chunk_header_problem(f, body_at, length)
        else:
            why = None
        if why is not None:
            if opcode == Opcode.CHUNK:
                report.chunks_lost += 1
            resume = _find_next_chunk(f, offset + 1, size)
            if resume is None:
                report.problems.append(
                    f"{_opcode_name(opcode)} record at byte {offset} {why}: bytes {offset}-{size} "
                    "are lost (file truncated or damaged there)"
                )
                break
            report.problems.append(
                f"{_opcode_name(opcode)} record at byte {offset} {why}: bytes {offset}-{resume} "
                f"are lost (damaged); reading resumed at the next intact chunk at byte {resume}"
            )
            offset = resume
            continue
        next_offset = body_at + length
        wanted = opcode in (
            Opcode.HEADER, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.METADATA,
            Opcode.DATA_END, Opcode.FOOTER,
        ) or (opcode == Opcode.CHUNK and read_chunks)
        if wanted:
            try:
                f.seek(body_at)
                record = _parse_record(opcode, f.read(length))
            except _DAMAGE_ERRORS as exc:
                if opcode == Opcode.CHUNK:
                    report.chunks_lost += 1
                report.problems.append(
                    f"{_opcode_name(opcode)} record at byte {offset} is damaged and was skipped ({exc})"
                )
                offset = next_offset
                continue
            yield offset, record
            if isinstance(record, (DataEnd, Footer)):
                break
        offset = next_offset


def iter_raw(path, topics: set[str] | None = None, report: ReadReport | None = None) -> Iterator:
    """Stream :class:`RawMessage` and :class:`RawMetadata` items in file order.

    Messages on topics outside ``topics`` (when given) are not yielded. Damage is written to
    ``report`` (``report.messages`` is left to the caller). Raises :class:`RecordingError`
    when the file is missing or not MCAP.
    """
    report = report if report is not None else ReadReport()
    f, size = _open(path)
    with f:
        schemas, channels = _summary_definitions(f, size)
        orphans: dict[int, int] = {}  # channel id -> messages skipped (Channel record lost)

        def raw(message: Message):
            channel = channels.get(message.channel_id)
            if channel is None:
                orphans[message.channel_id] = orphans.get(message.channel_id, 0) + 1
                return None
            if topics is not None and channel.topic not in topics:
                return None
            schema = schemas.get(channel.schema_id)
            return RawMessage(
                topic=channel.topic,
                log_time_ns=message.log_time,
                schema_name=schema.name if schema else "",
                schema_encoding=schema.encoding if schema else "",
                message_encoding=channel.message_encoding,
                data=message.data,
            )

        def define(record) -> None:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record

        anything_read = False
        try:
            for offset, record in _top_level_records(f, size, report):
                anything_read = True
                if isinstance(record, Chunk):
                    try:
                        inner = _chunk_records(record)
                    except _DAMAGE_ERRORS as exc:
                        report.chunks_lost += 1
                        report.problems.append(
                            f"chunk at byte {offset} (log time {record.message_start_time}-"
                            f"{record.message_end_time} ns) is damaged, its messages are lost: {exc}"
                        )
                        continue
                    report.chunks_ok += 1
                    for item in inner:
                        define(item)
                        if isinstance(item, Message) and (out := raw(item)) is not None:
                            yield out
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
        finally:
            for channel_id, count in orphans.items():
                report.problems.append(
                    f"{count} message(s) on channel id {channel_id} skipped: that channel's "
                    "definition was in a lost part of the file"
                )


# -- decoding ---------------------------------------------------------------------------------
def _cam_name(topic: str, frame_id: str) -> str:
    """``<name>`` of ``/cam/<name>/...``; otherwise the frame id without ``cam_``."""
    parts = topic.split("/")
    if len(parts) == 4 and parts[0] == "" and parts[1] == "cam":
        return parts[2]
    return frame_id.removeprefix("cam_") or topic


def _matrix_from_pose(position, orientation, what: str) -> np.ndarray:
    t = np.array([position.x, position.y, position.z], dtype=float)
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=float)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))) or np.linalg.norm(q) < 1e-9:
        raise MessageDecodeError(f"{what}: translation/quaternion must be finite with a non-zero quaternion")
    return se3.from_quaternion_xyzw(q, t)


def _decode_compressed_image(raw: RawMessage) -> CompressedFrame:
    msg = CompressedImage.FromString(raw.data)
    return CompressedFrame(_cam_name(raw.topic, msg.frame_id), msg.frame_id, msg.format, msg.data)


def _decode_calibration(raw: RawMessage) -> CalibrationMsg:
    msg = CameraCalibration.FromString(raw.data)
    K = np.array(msg.K, dtype=float)
    if K.size != 9 or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0 or K[8] != 1.0:
        raise MessageDecodeError(f"K must be 9 finite numbers with fx, fy > 0 and K[2,2] = 1, got {list(msg.K)}")
    if msg.width <= 0 or msg.height <= 0:
        raise MessageDecodeError(f"image size must be > 0, got {msg.width}x{msg.height}")
    if len(msg.D) == 0:
        dist = np.zeros(5)
    elif msg.distortion_model == "plumb_bob" and len(msg.D) == 5:
        dist = np.array(msg.D, dtype=float)
    else:
        raise MessageDecodeError(
            f"distortion {msg.distortion_model!r} with {len(msg.D)} coefficients is not supported; "
            "expected plumb_bob with 5 coefficients (k1, k2, p1, p2, k3) or none"
        )
    camera = PinholeCamera(K.reshape(3, 3), dist, int(msg.width), int(msg.height))
    return CalibrationMsg(_cam_name(raw.topic, msg.frame_id), msg.frame_id, camera, msg.distortion_model)


def _transform(tf: FrameTransform) -> FrameTransformMsg:
    what = f"transform {tf.parent_frame_id}->{tf.child_frame_id}"
    T = _matrix_from_pose(tf.translation, tf.rotation, what)
    return FrameTransformMsg(tf.parent_frame_id, tf.child_frame_id, T)


def _decode_frame_transforms(raw: RawMessage) -> list[FrameTransformMsg]:
    return [_transform(tf) for tf in FrameTransforms.FromString(raw.data).transforms]


def _decode_frame_transform(raw: RawMessage) -> list[FrameTransformMsg]:
    return [_transform(FrameTransform.FromString(raw.data))]


def _decode_pose(raw: RawMessage) -> PoseMsg:
    msg = PoseInFrame.FromString(raw.data)
    return PoseMsg(msg.frame_id, _matrix_from_pose(msg.pose.position, msg.pose.orientation, "pose"))


_PROTOBUF_DECODERS = {
    "foxglove.CompressedImage": _decode_compressed_image,
    "foxglove.CameraCalibration": _decode_calibration,
    "foxglove.FrameTransforms": _decode_frame_transforms,
    "foxglove.FrameTransform": _decode_frame_transform,
    "foxglove.PoseInFrame": _decode_pose,
}


def decode(raw: RawMessage) -> object:
    """The value of a raw message (see :class:`RecordedMessage`).

    Raises :class:`MessageDecodeError` when the payload does not decode as its schema says.
    """
    try:
        if raw.message_encoding == "protobuf" and raw.schema_name in _PROTOBUF_DECODERS:
            return _PROTOBUF_DECODERS[raw.schema_name](raw)
        if raw.message_encoding == "json":
            value = json.loads(raw.data)
            if raw.schema_name in SCHEMAS:
                problems = validate_payload(raw.schema_name, value)
                if problems:
                    raise MessageDecodeError("; ".join(problems[:3]) + ("; ..." if len(problems) > 3 else ""))
            return value
    except MessageDecodeError:
        raise
    except _DAMAGE_ERRORS as exc:
        what = raw.schema_name or raw.message_encoding
        raise MessageDecodeError(f"payload does not decode as {what}: {exc}") from None
    return raw.data


class _SkipCounter:
    """Aggregates skipped messages per (topic, schema): one report line each, not one per message."""

    def __init__(self):
        self._skipped: dict[tuple[str, str], list] = {}

    def add(self, raw: RawMessage, error: Exception) -> None:
        entry = self._skipped.setdefault((raw.topic, raw.schema_name), [0, raw.log_time_ns, str(error)])
        entry[0] += 1

    def lines(self) -> list[str]:
        return [
            f"{topic}: {count} message(s) skipped, payload invalid for {schema or 'its encoding'} "
            f"(first at log time {first_ns} ns: {error})"
            for (topic, schema), (count, first_ns, error) in self._skipped.items()
        ]


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
    skipped = _SkipCounter()
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


def read_scenario_metadata(path) -> dict | None:
    """The ``agvviz.scenario`` metadata of a recording, or ``None`` when it has none.

    Reads only top-level record headers (chunks are skipped unread). Raises
    :class:`RecordingError` when the file is not MCAP or the record is malformed.
    """
    f, size = _open(path)
    with f:
        for _, record in _top_level_records(f, size, ReadReport(), read_chunks=False):
            if isinstance(record, Metadata) and record.name == SCENARIO_METADATA:
                try:
                    return parse_scenario_metadata(record.metadata)
                except ValueError as exc:
                    raise RecordingError(f"{path}: {exc}; re-record it with 'agvviz record'") from None
    return None


def count_image_times(path) -> int:
    """Number of distinct time stamps among camera images (``/cam/<name>/image``): the number
    of frames a replay will produce, whatever the number of cameras. One streaming pass
    without decoding; for progress bars."""
    times = set()
    for item in iter_raw(path, report=ReadReport()):
        if isinstance(item, RawMessage) and item.topic.startswith("/cam/") and item.topic.endswith("/image"):
            times.add(item.log_time_ns)
    return len(times)
