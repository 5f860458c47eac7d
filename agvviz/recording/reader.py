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

Integrity beyond chunk CRCs:

* the DataEnd record's ``data_section_crc`` (CRC32 of every byte from the start of the file,
  magic included, up to the DataEnd record; agvviz writes it, 0 means "not set") is checked;
  a mismatch when no chunk was found damaged means a record *outside* chunks — the header, the
  ``agvviz.scenario`` metadata, a schema or channel — is damaged, and is reported
  (:data:`DATA_SECTION_CRC_PROBLEM`) so its metadata is not trusted silently;
* the footer, the closing magic and the summary section (its CRC when the footer has one) are
  checked, and damage there is reported too (the summary's schemas and channels are then not
  used);
* a message that repeats an earlier one exactly (same topic, log time and bytes), or a chunk
  that repeats an earlier chunk, is dropped and reported: a part of the file written twice
  must not be replayed twice.

Camera calibrations are refused (the message is skipped and reported) when their image size
is not 1..:data:`MAX_IMAGE_SIDE_PX` pixels per side.

Decoding: Foxglove protobuf messages of the recording contract become the dataclasses below,
JSON channels become ``dict`` (``agvviz.*`` payloads checked against their schema), anything
else stays ``bytes``.
"""

from __future__ import annotations

import json
import logging
import os
import stat
import struct
import zlib
from collections import OrderedDict
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
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.message import DecodeError
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema

from agvviz.errors import RecordingError
from agvviz.geometry import PinholeCamera, se3
from agvviz.recording.images import ImageEncodingError, compressed_format, raw_to_png
from agvviz.recording.schemas import SCENARIO_METADATA, SCHEMAS, validate_payload
from agvviz.recording.topics import CAMERA_TOPIC_RE, is_camera_image_topic, native_role

_log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")
_FOOTER_RECORD_BYTES = 9 + 20  # opcode, length, summary_start, summary_offset_start, crc
_MIN_CHUNK_BODY_BYTES = 8 + 8 + 8 + 4 + 4 + 8  # times, size, crc, compression len, records len
_MAX_COMPRESSION_NAME = 16  # bytes; real names are "", "zstd", "lz4"
_CHUNK_PREFIX_BYTES = _MIN_CHUNK_BODY_BYTES + _MAX_COMPRESSION_NAME
_SCAN_BLOCK_BYTES = 1 << 20
#: Largest uncompressed chunk read (bytes). Writers cut chunks at ~1 MiB (agvviz, Foxglove SDK,
#: rosbag2); 256 MiB leaves room for chunks of raw 4K frames and keeps a bomb from exhausting memory.
MAX_CHUNK_BYTES = 256 << 20
#: Largest image side (px) a calibration may declare and a frame may have. Real machine-vision
#: sensors stay below 16384 px (16k line-scan cameras are the largest); beyond it an image
#: would only allocate gigabytes (undistortion maps of a 2^32-1 px wide image: terabytes).
MAX_IMAGE_SIDE_PX = 16384
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
    stamp_ns: int = field(default=0, compare=False)  # the message's own stamp (header), 0 when none
    source_encoding: str = ""  # for an uncompressed frame: its encoding (the PNG is lossless)


@dataclass(frozen=True)
class CalibrationMsg:
    """A camera's intrinsics; ``distortion_model`` is "plumb_bob", "rational_polynomial" (or
    "" when D is empty)."""

    cam_name: str
    frame_id: str
    camera: PinholeCamera
    distortion_model: str
    stamp_ns: int = field(default=0, compare=False)  # the message's own stamp (header), 0 when none


@dataclass(frozen=True)
class FrameTransformMsg:
    """``T_parent_child`` (4×4): the child frame's pose in the parent frame."""

    parent_frame: str
    child_frame: str
    T_parent_child: np.ndarray
    stamp_ns: int = field(default=0, compare=False)  # the message's own stamp (header), 0 when none


@dataclass(frozen=True)
class PoseMsg:
    """A pose ``T`` (4×4) in frame ``frame_id`` (for the AGV: ``T_<frame_id>_agv``);
    ``child_frame`` is the frame posed when the message names it (``nav_msgs/Odometry``)."""

    frame_id: str
    T: np.ndarray
    stamp_ns: int = field(default=0, compare=False)  # the message's own stamp (header), 0 when none
    child_frame: str = ""


@dataclass(frozen=True)
class RecordedMessage:
    """One decoded message.

    ``value`` is a :class:`CompressedFrame`, :class:`CalibrationMsg`,
    ``list[FrameTransformMsg]``, :class:`PoseMsg`, a JSON value (``dict`` for agvviz
    messages) or ``bytes`` for schemas this reader does not decode.

    ``role`` is what the message is for the replay (:mod:`agvviz.recording.topics`); when not
    given it is the role of ``topic`` under agvviz's own naming. ``stamp_ns`` is the time the
    replay places the message at when it is not the log time (a header stamp, see
    :mod:`agvviz.recording.source`); :attr:`time_ns` is the one to use.
    """

    topic: str
    log_time_ns: int
    schema_name: str
    value: object
    role: str = ""
    stamp_ns: int | None = None

    def __post_init__(self):
        if not self.role:
            object.__setattr__(self, "role", native_role(self.topic))

    @property
    def time_ns(self) -> int:
        """The message's time on the replay's clock: ``stamp_ns`` when set, else the log time."""
        return self.log_time_ns if self.stamp_ns is None else self.stamp_ns


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
    schema_data: bytes = b""  # the schema's text (ros2msg definitions for ROS 2 messages)
    schema_hash: str = ""  # the type's md5sum (ROS 1 bags)


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
    if chunk.uncompressed_size > MAX_CHUNK_BYTES:
        raise ValueError(
            f"chunk claims {chunk.uncompressed_size} bytes uncompressed, more than the "
            f"{MAX_CHUNK_BYTES >> 20} MiB this reader accepts (a damaged size or a decompression bomb)"
        )
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
        elif opcode == 0 or 0x10 <= opcode < 0x80:
            # A chunk holds schemas, channels and messages; a reserved opcode means damage (and a
            # run of zero bytes would otherwise be walked as 10⁸ empty records).
            raise ValueError(f"{_opcode_name(opcode)} (reserved) inside the chunk at offset {offset}")
        offset = start + length
    return records


def _open(path) -> tuple:
    """Open ``path`` and check the MCAP magic. Returns (file, size in bytes)."""
    path = Path(path)
    try:
        # Only a regular file: opening a FIFO would wait for a writer for ever, and a device
        # (/dev/zero) has no end.
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise RecordingError(
                f"{path}: not a regular file (a pipe, device or socket); give the path of an .mcap recording"
            )
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
            "'agvviz record' or another MCAP writer (or a ROS 1 .bag, a rosbag2 directory)"
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


class _Tail:
    """What the end of the file says: the footer's summary section, checked, or why not."""

    def __init__(self):
        self.summary_start: int | None = None  # where the footer says the summary starts
        self.footer_at: int | None = None  # where the footer record starts
        self.problems: list[str] = []  # damage after the DataEnd record (reported at DataEnd)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}


def _crc_of_range(f, start: int, stop: int, crc: int = 0) -> int:
    """CRC32 of bytes ``start``..``stop`` of ``f``, continuing ``crc``, in 1 MiB blocks."""
    f.seek(start)
    remaining = stop - start
    while remaining > 0:
        block = f.read(min(remaining, _SCAN_BLOCK_BYTES))
        if not block:
            break
        crc = zlib.crc32(block, crc)
        remaining -= len(block)
    return crc


def _read_tail(f, size: int) -> _Tail:
    """Check the footer, the closing magic and the summary section (its CRC when the footer
    has one), and take the schemas and channels the summary repeats — only when it checks.

    Damage here never stops a read: the data section carries everything; the problems are
    reported once the reader reaches the DataEnd record (a file cut before that is reported as
    truncated instead).
    """
    tail = _Tail()
    footer_at = size - len(MCAP_MAGIC) - _FOOTER_RECORD_BYTES
    if footer_at < len(MCAP_MAGIC):
        tail.problems.append("the file is too short to hold a footer and the closing magic")
        return tail
    try:
        f.seek(size - len(MCAP_MAGIC))
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            tail.problems.append(
                "the file does not end with the MCAP magic: the end of the file (footer) is damaged"
            )
            return tail
        f.seek(footer_at)
        footer_bytes = f.read(_FOOTER_RECORD_BYTES)
        opcode, length = _RECORD_HEADER.unpack_from(footer_bytes)
        if opcode != Opcode.FOOTER or length != 20:
            tail.problems.append(
                f"no footer record at byte {footer_at} (found {_opcode_name(opcode)} of length "
                f"{length}): the footer is damaged"
            )
            return tail
        footer = _parse_record(opcode, footer_bytes[_RECORD_HEADER.size :])
        tail.footer_at = footer_at
        start = footer.summary_start or footer_at
        if not len(MCAP_MAGIC) <= start <= footer_at:
            tail.problems.append(
                f"the footer points the summary section at byte {footer.summary_start}, outside "
                f"the file's {size} bytes: the footer is damaged"
            )
            return tail
        tail.summary_start = start
        if footer.summary_crc != 0:
            # MCAP spec: CRC32 of the summary section and the footer up to its summary_crc field.
            crc = _crc_of_range(f, start, footer_at)
            crc = zlib.crc32(footer_bytes[: _FOOTER_RECORD_BYTES - 4], crc)
            if crc != footer.summary_crc:
                tail.problems.append(
                    f"summary section CRC mismatch (bytes {start}-{size}): the summary section or "
                    "footer after the data is damaged; its indexes were not used (the messages "
                    "were read from the data section)"
                )
                return tail
        offset = start
        while offset < footer_at:
            f.seek(offset)
            opcode, length = _RECORD_HEADER.unpack(f.read(_RECORD_HEADER.size))
            if length > footer_at - offset - _RECORD_HEADER.size:
                tail.problems.append(
                    f"summary section record at byte {offset} runs past the footer: the summary "
                    "section is damaged; its indexes were not used"
                )
                tail.schemas, tail.channels = {}, {}
                return tail
            if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                record = _parse_record(opcode, f.read(length))
                target = tail.schemas if opcode == Opcode.SCHEMA else tail.channels
                target[record.id] = record
            offset += _RECORD_HEADER.size + length
    except _DAMAGE_ERRORS as exc:
        tail.problems.append(f"the summary section is damaged ({exc}); its indexes were not used")
        tail.schemas, tail.channels = {}, {}
    return tail


#: Problem reported when the DataEnd record's CRC does not match the data section.
DATA_SECTION_CRC_PROBLEM = (
    "data section CRC mismatch: some record outside chunks is damaged (the header, the "
    "agvviz.scenario metadata, or a schema/channel/message record written outside a chunk; "
    "or chunks were added or removed); the scenario metadata (name, seed, options) of this "
    "file cannot be trusted"
)


def _top_level_records(
    f, size: int, report: ReadReport, read_chunks: bool = True, tail: _Tail | None = None
):
    """Yield the parsed top-level records of the data section in file order, salvaging.

    Chunks are yielded as ``Chunk`` records (or skipped unread when ``read_chunks`` is
    False). Damage is written to ``report``. Stops after DataEnd or Footer.

    With ``read_chunks``, every byte of the data section is read once and its CRC32 (magic
    included) compared with the DataEnd record's ``data_section_crc`` (0 = not set: other
    writers may leave it out); a mismatch with no other damage found is reported as
    :data:`DATA_SECTION_CRC_PROBLEM`. At DataEnd, ``tail`` (the checked end of the file)
    adds its problems and must agree on where the data section ends.
    """
    offset = len(MCAP_MAGIC)
    # Where a resync scan starts: the end of the last chunk read. The records after it are not
    # CRC-checked, so a damaged length among them may have jumped over an intact chunk.
    resync_from = offset
    crc = zlib.crc32(MCAP_MAGIC)
    crc_complete = read_chunks  # every byte up to ``offset`` went into ``crc``
    problems_before = len(report.problems)
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
            crc_complete = False
            resume = _find_next_chunk(f, min(offset + 1, resync_from), size)
            if resume is None:
                report.problems.append(
                    f"{_opcode_name(opcode)} record at byte {offset} {why}: bytes {offset}-{size} "
                    "are lost (file truncated or damaged there)"
                )
                break
            if resume > offset:
                report.problems.append(
                    f"{_opcode_name(opcode)} record at byte {offset} {why}: bytes {offset}-{resume} "
                    f"are lost (damaged); reading resumed at the next intact chunk at byte {resume}"
                )
            else:
                report.problems.append(
                    f"{_opcode_name(opcode)} record at byte {offset} {why}: a damaged record "
                    f"length before it skipped part of the file; reading resumed at the intact "
                    f"chunk at byte {resume}"
                )
            offset = resume
            continue
        next_offset = body_at + length
        wanted = opcode in (
            Opcode.HEADER, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.METADATA,
            Opcode.DATA_END, Opcode.FOOTER,
        ) or (opcode == Opcode.CHUNK and read_chunks)
        if opcode != Opcode.DATA_END and crc_complete:
            crc = zlib.crc32(header, crc)
        if wanted:
            f.seek(body_at)
            body = f.read(length)
            if opcode != Opcode.DATA_END and crc_complete:
                crc = zlib.crc32(body, crc)
            try:
                record = _parse_record(opcode, body)
            except _DAMAGE_ERRORS as exc:
                if opcode == Opcode.CHUNK:
                    report.chunks_lost += 1
                report.problems.append(
                    f"{_opcode_name(opcode)} record at byte {offset} is damaged and was skipped ({exc})"
                )
                offset = next_offset
                continue
            del body
            if opcode == Opcode.CHUNK:
                resync_from = next_offset
            if isinstance(record, DataEnd):
                if (
                    crc_complete
                    and record.data_section_crc != 0
                    and crc != record.data_section_crc
                    and len(report.problems) == problems_before
                ):
                    report.problems.append(DATA_SECTION_CRC_PROBLEM)
                if tail is not None:
                    report.problems.extend(tail.problems)
                    if not tail.problems and tail.summary_start is not None and tail.summary_start != next_offset:
                        report.problems.append(
                            f"the data section ends at byte {next_offset} but the footer puts the "
                            f"summary section at byte {tail.summary_start}: the footer or the "
                            "bytes between them are damaged"
                        )
            yield offset, record
            if isinstance(record, (DataEnd, Footer)):
                break
        else:
            if crc_complete:
                crc = _crc_of_range(f, body_at, next_offset, crc)
            if opcode == Opcode.CHUNK:
                # A chunk skipped unread (read_chunks=False) is passed for good: a resync scan
                # must not start before it, or a damaged record after it sends the scan back
                # to an earlier chunk again and again (an endless loop on a truncated file).
                resync_from = next_offset
        offset = next_offset


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


def iter_raw(path, topics: set[str] | None = None, report: ReadReport | None = None) -> Iterator:
    """Stream :class:`RawMessage` and :class:`RawMetadata` items in file order.

    Messages on topics outside ``topics`` (when given) are not yielded. A message that repeats
    an earlier one exactly (same topic, log time and bytes) is dropped and reported. Damage is
    written to ``report`` (``report.messages`` is left to the caller), including a data
    section CRC mismatch and damage after the data section (summary, footer). Raises
    :class:`RecordingError` when the file is missing or not MCAP.
    """
    report = report if report is not None else ReadReport()
    f, size = _open(path)
    with f:
        tail = _read_tail(f, size)
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
            if duplicates.message_seen(channel.topic, message):
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
            for offset, record in _top_level_records(f, size, report, tail=tail):
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
        finally:
            for channel_id, count in orphans.items():
                report.problems.append(
                    f"{count} message(s) on channel id {channel_id} skipped: that channel's "
                    "definition was in a lost part of the file"
                )
            report.problems.extend(duplicates.lines())


# -- decoding ---------------------------------------------------------------------------------
def _cam_name(topic: str, frame_id: str) -> str:
    """``<name>`` of ``/cam/<name>/...``; otherwise the frame id without ``cam_`` (a role map
    gives other files' cameras their names, :mod:`agvviz.recording.roles`)."""
    match = CAMERA_TOPIC_RE.match(topic)
    if match:
        return match.group(1)
    return frame_id.removeprefix("cam_") or topic


def _stamp_ns(timestamp) -> int:
    """Nanoseconds of a ``google.protobuf.Timestamp`` (0 when unset)."""
    return int(timestamp.seconds) * 1_000_000_000 + int(timestamp.nanos)


def _matrix_from_pose(position, orientation, what: str) -> np.ndarray:
    t = np.array([position.x, position.y, position.z], dtype=float)
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=float)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))) or np.linalg.norm(q) < 1e-9:
        raise MessageDecodeError(f"{what}: translation/quaternion must be finite with a non-zero quaternion")
    return se3.from_quaternion_xyzw(q, t)


def _decode_compressed_image(raw: RawMessage) -> CompressedFrame:
    msg = CompressedImage.FromString(raw.data)
    return CompressedFrame(
        _cam_name(raw.topic, msg.frame_id), msg.frame_id, compressed_format(msg.format), msg.data,
        stamp_ns=_stamp_ns(msg.timestamp),
    )


def raw_frame(topic: str, frame_id: str, encoding: str, width: int, height: int, step: int,
              data: bytes, stamp_ns: int, big_endian: bool = False) -> CompressedFrame:
    """An uncompressed frame as a lossless PNG :class:`CompressedFrame`
    (:mod:`agvviz.recording.images`); raises :class:`MessageDecodeError`."""
    try:
        png = raw_to_png(encoding, int(width), int(height), int(step), bytes(data), bool(big_endian))
    except ImageEncodingError as exc:
        raise MessageDecodeError(str(exc)) from None
    return CompressedFrame(_cam_name(topic, frame_id), frame_id, "png", png, stamp_ns=stamp_ns,
                           source_encoding=encoding)


def _decode_raw_image(raw: RawMessage) -> CompressedFrame:
    msg = RawImage.FromString(raw.data)
    return raw_frame(raw.topic, msg.frame_id, msg.encoding, msg.width, msg.height, msg.step, msg.data,
                     _stamp_ns(msg.timestamp))


def _decode_calibration(raw: RawMessage) -> CalibrationMsg:
    msg = CameraCalibration.FromString(raw.data)
    return calibration(raw.topic, msg.frame_id, msg.K, msg.D, msg.distortion_model, msg.width, msg.height,
                       _stamp_ns(msg.timestamp))


#: Distortion models a calibration may name → accepted coefficient counts.
DISTORTION_MODELS = {"plumb_bob": (4, 5), "rational_polynomial": (8,), "": (0,)}


def calibration(topic: str, frame_id: str, K, D, distortion_model: str, width: int, height: int,
                stamp_ns: int = 0) -> CalibrationMsg:
    """A checked :class:`CalibrationMsg` from K (9), D and the image size (Foxglove
    ``CameraCalibration`` and ROS ``CameraInfo`` alike); raises :class:`MessageDecodeError`.

    ``equidistant`` (a fisheye lens) is refused by name: its model is OpenCV's ``fisheye``
    module, which the replay does not implement.
    """
    K = np.array(list(K), dtype=float)
    if K.size == 9 and np.all(K == 0):
        raise MessageDecodeError("K is all zeros: the camera is not calibrated (give --calibration CAM=FILE)")
    if K.size != 9 or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0 or K[8] != 1.0:
        raise MessageDecodeError(f"K must be 9 finite numbers with fx, fy > 0 and K[2,2] = 1, got {list(K)}")
    problem = image_size_problem(width, height)
    if problem:
        raise MessageDecodeError(f"calibration {problem}")
    D = list(D)
    model = distortion_model or ""
    if model == "equidistant" or model == "fisheye":
        raise MessageDecodeError(
            f"distortion model {model!r} (fisheye) is not supported: the replay models plumb_bob "
            "and rational_polynomial lenses; undistort the images or give a pinhole calibration"
        )
    if len(D) == 0:
        dist = np.zeros(5)
    elif model in DISTORTION_MODELS and len(D) in DISTORTION_MODELS[model]:
        dist = np.array(D, dtype=float)
    elif model == "plumb_bob" and len(D) == 8 and not any(D[5:]):
        dist = np.array(D[:5], dtype=float)  # some drivers pad plumb_bob to 8
    else:
        raise MessageDecodeError(
            f"distortion {model!r} with {len(D)} coefficients is not supported; expected "
            "plumb_bob with 5 coefficients (k1, k2, p1, p2, k3), rational_polynomial with 8, or none"
        )
    try:
        camera = PinholeCamera(K.reshape(3, 3), dist, int(width), int(height))
    except ValueError as exc:
        raise MessageDecodeError(str(exc)) from None
    return CalibrationMsg(_cam_name(topic, frame_id), frame_id, camera, model, stamp_ns=stamp_ns)


def image_size_problem(width: int, height: int) -> str | None:
    """Why ``width`` × ``height`` px cannot be a camera's image size, or ``None``: each side
    must be 1..:data:`MAX_IMAGE_SIDE_PX` px."""
    if not (0 < width <= MAX_IMAGE_SIDE_PX and 0 < height <= MAX_IMAGE_SIDE_PX):
        return (
            f"image size {width}x{height} px is outside 1..{MAX_IMAGE_SIDE_PX} px per side "
            "(the recording contract's bound)"
        )
    return None


def _transform(tf: FrameTransform) -> FrameTransformMsg:
    what = f"transform {tf.parent_frame_id}->{tf.child_frame_id}"
    T = _matrix_from_pose(tf.translation, tf.rotation, what)
    return FrameTransformMsg(tf.parent_frame_id, tf.child_frame_id, T, _stamp_ns(tf.timestamp))


def _decode_frame_transforms(raw: RawMessage) -> list[FrameTransformMsg]:
    return [_transform(tf) for tf in FrameTransforms.FromString(raw.data).transforms]


def _decode_frame_transform(raw: RawMessage) -> list[FrameTransformMsg]:
    return [_transform(FrameTransform.FromString(raw.data))]


def _decode_pose(raw: RawMessage) -> PoseMsg:
    msg = PoseInFrame.FromString(raw.data)
    return PoseMsg(msg.frame_id, _matrix_from_pose(msg.pose.position, msg.pose.orientation, "pose"),
                   stamp_ns=_stamp_ns(msg.timestamp))


_PROTOBUF_DECODERS = {
    "foxglove.CompressedImage": _decode_compressed_image,
    "foxglove.RawImage": _decode_raw_image,
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
        if raw.message_encoding == "cdr" and raw.schema_encoding == "ros2msg":
            from agvviz.recording.ros2 import decode_ros2

            return decode_ros2(raw)
        if raw.message_encoding == "ros1":
            from agvviz.recording.ros1 import decode_ros1

            return decode_ros1(raw)
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


class SkipCounter:
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
        if isinstance(item, RawMessage) and is_camera_image_topic(item.topic):
            times.add(item.log_time_ns)
    return len(times)


def read_file_header(path) -> tuple[str, str, dict | None]:
    """``(profile, library, scenario)`` of an MCAP file: the Header record's profile
    (``ros2`` for rosbag2 files) and library (the writer, ``agvviz <version>`` for agvviz's
    own recordings), and the ``agvviz.scenario`` metadata (``None`` when absent or
    malformed). Reads only top-level record headers; never raises for damage inside."""
    profile, library, scenario = "", "", None
    f, size = _open(path)
    with f:
        for _, record in _top_level_records(f, size, ReadReport(), read_chunks=False):
            if isinstance(record, Header):
                profile, library = record.profile, record.library
            elif isinstance(record, Metadata) and record.name == SCENARIO_METADATA:
                try:
                    scenario = parse_scenario_metadata(record.metadata)
                except ValueError:
                    scenario = None
    return profile, library, scenario
