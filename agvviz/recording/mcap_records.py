"""MCAP records read front to back, salvaging what a damaged file still holds: the record loop
below every reader of MCAP files (:mod:`agvviz.recording.mcap_stream`).

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
"""

from __future__ import annotations

import os
import stat
import struct
import zlib
from io import BytesIO
from pathlib import Path

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema

from agvviz.errors import RecordingError
from agvviz.recording.raw import DAMAGE_ERRORS, MAX_CHUNK_BYTES, ReadReport, hashed

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")
_FOOTER_RECORD_BYTES = 9 + 20  # opcode, length, summary_start, summary_offset_start, crc
_MIN_CHUNK_BODY_BYTES = 8 + 8 + 8 + 4 + 4 + 8  # times, size, crc, compression len, records len
_MAX_COMPRESSION_NAME = 16  # bytes; real names are "", "zstd", "lz4"
_CHUNK_PREFIX_BYTES = _MIN_CHUNK_BODY_BYTES + _MAX_COMPRESSION_NAME
_SCAN_BLOCK_BYTES = 1 << 20


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


#: A Message record's fixed fields: channel id, sequence, log time, publish time; then its data.
_MESSAGE_FIELDS = struct.Struct("<HIQQ")


def _message(buffer: bytes, start: int, length: int) -> Message:
    """The Message record of ``length`` bytes at ``start`` in ``buffer``: ``Message.read``'s
    fields (EndOfFile when shorter than its fixed fields, as a short read there), read in place,
    its data copied once."""
    if length < _MESSAGE_FIELDS.size:
        raise EndOfFile()
    channel_id, sequence, log_time, publish_time = _MESSAGE_FIELDS.unpack_from(buffer, start)
    data = buffer[start + _MESSAGE_FIELDS.size : start + length]
    return Message(channel_id=channel_id, log_time=log_time, data=data, publish_time=publish_time, sequence=sequence)


def parse_record(opcode: int, body: bytes):
    """The mcap record in ``body`` (``None`` for record kinds the reader does not use)."""
    if opcode == Opcode.MESSAGE:
        return _message(body, 0, len(body))
    stream = _stream(body)
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


def chunk_records(chunk: Chunk, check_crc: bool = True) -> list:
    """Schemas, channels and messages inside ``chunk``, after decompression and CRC check
    (``check_crc`` False: no CRC check, for a file read whole and found intact before, see
    :meth:`agvviz.recording.raw.Recording.mark_verified`).

    Raises one of ``DAMAGE_ERRORS`` when any of it is damaged (the whole chunk is then lost:
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
    if check_crc and chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch (the chunk's bytes are damaged)")
    records = []
    offset = 0
    while offset < len(data):
        opcode, length = _RECORD_HEADER.unpack_from(data, offset)
        start = offset + _RECORD_HEADER.size
        if start + length > len(data):
            raise ValueError(f"{_opcode_name(opcode)} record inside the chunk runs past its end")
        if opcode == Opcode.MESSAGE:
            records.append(_message(data, start, length))  # its data sliced once, not twice
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            records.append(parse_record(opcode, data[start : start + length]))
        elif opcode == 0 or 0x10 <= opcode < 0x80:
            # A chunk holds schemas, channels and messages; a reserved opcode means damage (and a
            # run of zero bytes would otherwise be walked as 10⁸ empty records).
            raise ValueError(f"{_opcode_name(opcode)} (reserved) inside the chunk at offset {offset}")
        offset = start + length
    return records


def open_mcap(path, digest=None) -> tuple:
    """Open ``path`` and check the MCAP magic. Returns (file, size in bytes); with ``digest``
    the file is a :class:`~agvviz.recording.raw.HashedReads` feeding it."""
    path = Path(path)
    try:
        # Only a regular file: opening a FIFO would wait for a writer for ever, and a device
        # (/dev/zero) has no end.
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise RecordingError(
                f"{path}: not a regular file (a pipe, device or socket); give the path of an .mcap recording"
            )
        f = hashed(open(path, "rb"), digest)
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
        chunk = parse_record(opcode, f.read(length))
        if chunk.uncompressed_crc == 0:
            return False  # without a CRC a lucky byte pattern could pass for a chunk
        chunk_records(chunk)
    except DAMAGE_ERRORS:
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


def read_tail(f, size: int) -> _Tail:
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
        footer = parse_record(opcode, footer_bytes[_RECORD_HEADER.size :])
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
                record = parse_record(opcode, f.read(length))
                target = tail.schemas if opcode == Opcode.SCHEMA else tail.channels
                target[record.id] = record
            offset += _RECORD_HEADER.size + length
    except DAMAGE_ERRORS as exc:
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


def top_level_records(
    f, size: int, report: ReadReport, read_chunks: bool = True, tail: _Tail | None = None,
    check_crc: bool = True,
):
    """Yield the parsed top-level records of the data section in file order, salvaging.

    Chunks are yielded as ``Chunk`` records (or skipped unread when ``read_chunks`` is
    False). Damage is written to ``report``. Stops after DataEnd or Footer.

    With ``read_chunks``, every byte of the data section is read once and its CRC32 (magic
    included) compared with the DataEnd record's ``data_section_crc`` (0 = not set: other
    writers may leave it out); a mismatch with no other damage found is reported as
    :data:`DATA_SECTION_CRC_PROBLEM`. At DataEnd, ``tail`` (the checked end of the file)
    adds its problems and must agree on where the data section ends. ``check_crc`` False
    skips the data section's CRC (a file read whole and found intact before).
    """
    offset = len(MCAP_MAGIC)
    # Where a resync scan starts: the end of the last chunk read. The records after it are not
    # CRC-checked, so a damaged length among them may have jumped over an intact chunk.
    resync_from = offset
    crc = zlib.crc32(MCAP_MAGIC)
    crc_complete = read_chunks and check_crc  # every byte up to ``offset`` went into ``crc``
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
                record = parse_record(opcode, body)
            except DAMAGE_ERRORS as exc:
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
