"""The ROS 1 format: bags (``.bag``, format 2.0, or a folder of them read one after the other in
name order, numbers as numbers) read directly — no conversion — salvaging what a damaged or
cut-short file still holds.

Reading: the file is walked front to back, one record at a time, in file order (the order the
recorder wrote the messages), with ``rosbags``' record layout (``rosbags.rosbag1``) but our own
loop, for the reasons :mod:`agvviz.recording.mcap_records` gives for MCAP: ``rosbags.rosbag1.Reader``
needs the index the recorder writes when it *stops* (a bag whose recorder was killed, or a
copy cut short, has none and is refused whole), and dies on the first bad record. Here

* each chunk is decompressed (``none``, ``bz2``, ``lz4``) and walked on its own; a chunk that is
  damaged is reported and skipped, the next record read from the offset its header announced;
* a record header that cannot be right (a length past the end of the file, a field without
  ``=``, an unknown op) makes the reader scan forward for the next chunk header that parses,
  and carry on from there;
* a file cut short yields every message before the cut — also the complete messages at the
  start of a chunk cut in two (an uncompressed chunk, or the part of a compressed one that
  still decompresses) — and says where the cut is and what was lost;
* connections (topic, type, message definition) are also taken from the index section at
  the end of the file when it is there, so messages whose connection record sat in a lost
  chunk can still be read; when the index is there its message count is checked against
  what was read.

Only a missing file or a file that is not a ROS 1 bag raises :class:`RecordingError`.

Messages become :class:`agvviz.recording.raw.RawMessage` with ``message_encoding`` ``ros1``,
``schema_encoding`` ``ros1msg``, the type name in ROS 2 form (``sensor_msgs/CompressedImage``
→ ``sensor_msgs/msg/CompressedImage``, as ``rosbags`` normalises it, so role inference treats
ROS 1 and ROS 2 types alike) and the message definition the bag carries as ``schema_data``.
The log time is the record's ``time`` (integer ns).

Decoding (:func:`decode`): the bytes are deserialised by ``rosbags`` from the message
definition the bag itself carries (a type store per definition, ``Stores.EMPTY`` plus that
definition, so a bag's own — even custom — layout is used); a connection without a
definition falls back to ``rosbags``' ROS 1 Noetic store when its md5sum matches. The decoded
message becomes the same value as a ROS 2 one (:func:`agvviz.recording.ros_messages.ros_value`: ROS 1
field names such as ``CameraInfo.K``/``D`` included; ``tf/tfMessage`` like
``tf2_msgs/TFMessage``). A message that does not decode (a definition that does not parse, a
type without a definition, damaged bytes) raises :class:`MessageDecodeError` — a skipped
message with its topic and reason, never a traceback.

Longer than 600 lines because a format is one module (:mod:`agvviz.recording.formats`);
the salvaging bag reader is most of it.
"""

from __future__ import annotations

import bz2
import hashlib
import os
import re
import stat
import struct
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import lz4.frame

from agvviz.errors import RecordingError
from agvviz.recording.raw import MAX_CHUNK_BYTES, MessageDecodeError, RawMessage, ReadReport, Recording, hashed
from agvviz.recording.ros_messages import DECODED_TYPES, ros_value

#: The recording kind this format reads (:attr:`agvviz.recording.raw.Recording.kind`).
NAME = "rosbag1"

BAG_MAGIC = b"#ROSBAG V2.0\n"
_MAGIC_PREFIX = b"#ROSBAG V"
MESSAGE_ENCODING = "ros1"
SCHEMA_ENCODING = "ros1msg"

_OP_MSG_DATA = 0x02
_OP_BAG_HEADER = 0x03
_OP_INDEX_DATA = 0x04
_OP_CHUNK = 0x05
_OP_CHUNK_INFO = 0x06
_OP_CONNECTION = 0x07
_OPS = {_OP_MSG_DATA, _OP_BAG_HEADER, _OP_INDEX_DATA, _OP_CHUNK, _OP_CHUNK_INFO, _OP_CONNECTION}
#: Largest record header read (bytes). A connection header carries the full message
#: definition (a few kB; a deep custom type tens of kB); more than this is a damaged length.
MAX_HEADER_BYTES = 16 << 20
_U32 = struct.Struct("<I")
_RESYNC_BLOCK_BYTES = 1 << 20
_RESYNC_BACK_BYTES = 128  # a chunk header's op field lies at most this far after its start


class _Damage(Exception):
    """A record that cannot be parsed (the reason is the message)."""


@dataclass(frozen=True)
class _Connection:
    topic: str
    msgtype: str  # ROS 2 form
    msgdef: bytes  # the message definition (UTF-8 text)
    md5sum: str
    latching: bool


# -- records ----------------------------------------------------------------------------------
def _parse_header(buf: bytes) -> dict[str, bytes]:
    """A record header's ``name=value`` fields; raises :class:`_Damage`."""
    fields: dict[str, bytes] = {}
    pos = 0
    while pos < len(buf):
        if pos + 4 > len(buf):
            raise _Damage("a header field's length runs past the header")
        (n,) = _U32.unpack_from(buf, pos)
        pos += 4
        if n > len(buf) - pos:
            raise _Damage(f"a header field of {n} bytes runs past the header")
        name, sep, value = buf[pos : pos + n].partition(b"=")
        if not sep or not name:
            raise _Damage("a header field without 'name='")
        try:
            fields[name.decode("ascii")] = value
        except UnicodeDecodeError:
            raise _Damage("a header field name that is not ASCII") from None
        pos += n
    return fields


def _op(fields: dict[str, bytes]) -> int:
    op = fields.get("op")
    if op is None or len(op) != 1:
        raise _Damage("a record header without a one-byte 'op' field")
    if op[0] not in _OPS:
        raise _Damage(f"unknown record op 0x{op[0]:02x}")
    return op[0]


def _u32(fields: dict[str, bytes], name: str) -> int:
    value = fields.get(name)
    if value is None or len(value) != 4:
        raise _Damage(f"field {name!r} missing or not 4 bytes")
    return _U32.unpack(value)[0]


def _u64(fields: dict[str, bytes], name: str) -> int:
    value = fields.get(name)
    if value is None or len(value) != 8:
        raise _Damage(f"field {name!r} missing or not 8 bytes")
    return struct.unpack("<Q", value)[0]


def _time_ns(fields: dict[str, bytes], name: str) -> int:
    value = fields.get(name)
    if value is None or len(value) != 8:
        raise _Damage(f"field {name!r} missing or not 8 bytes")
    sec, nsec = struct.unpack("<II", value)
    return sec * 1_000_000_000 + nsec


def _text(fields: dict[str, bytes], name: str, default: str | None = None) -> str:
    value = fields.get(name)
    if value is None:
        if default is not None:
            return default
        raise _Damage(f"field {name!r} missing")
    try:
        return value.decode("utf-8")
    except UnicodeDecodeError:
        raise _Damage(f"field {name!r} is not UTF-8") from None


def _normalize_type(name: str) -> str:
    """``pkg/Type`` → ``pkg/msg/Type`` (``rosbags``' normalisation)."""
    from rosbags.typesys.msg import normalize_msgtype

    return normalize_msgtype(name)


def _connection(header: dict[str, bytes], data: bytes) -> tuple[int, _Connection]:
    """(id, connection) of a CONNECTION record; raises :class:`_Damage`."""
    conn_id = _u32(header, "conn")
    inner = _parse_header(data)
    topic = _text(inner, "topic", _text(header, "topic", ""))
    msgtype = _text(inner, "type")
    if not topic or not msgtype:
        raise _Damage("a connection without topic or type")
    latching = _text(inner, "latching", "0").strip() not in ("", "0")
    return conn_id, _Connection(topic, _normalize_type(msgtype), inner.get("message_definition", b""),
                                _text(inner, "md5sum", ""), latching)


def _records(buf: bytes) -> Iterator[tuple[int, dict[str, bytes], bytes]]:
    """(op, header, data) of the records in ``buf`` (a chunk's data). Stops at an incomplete
    record at the end (a chunk cut short); raises :class:`_Damage` at a record that is wrong."""
    pos = 0
    while pos < len(buf):
        if pos + 4 > len(buf):
            return
        (header_len,) = _U32.unpack_from(buf, pos)
        if header_len > len(buf) - pos - 4:
            if header_len > MAX_HEADER_BYTES:
                raise _Damage(f"a record header of {header_len} bytes at offset {pos}")
            return
        header = _parse_header(buf[pos + 4 : pos + 4 + header_len])
        op = _op(header)
        at = pos + 4 + header_len
        if at + 4 > len(buf):
            return
        (data_len,) = _U32.unpack_from(buf, at)
        if data_len > len(buf) - at - 4:
            return
        yield op, header, buf[at + 4 : at + 4 + data_len]
        pos = at + 4 + data_len


def _decompress(compression: str, data: bytes, size: int, complete: bool) -> bytes:
    """A chunk's records; for a chunk cut short (``complete`` false) as much as decompresses."""
    if compression == "none":
        return data
    if compression == "bz2":
        decompressor = bz2.BZ2Decompressor()
        out = decompressor.decompress(data, max_length=size)
    elif compression == "lz4":
        decompressor = lz4.frame.LZ4FrameDecompressor()
        out = decompressor.decompress(data, max_length=size)
    else:
        raise _Damage(f"unsupported chunk compression {compression!r}")
    if complete and len(out) != size:
        raise _Damage(f"chunk holds {len(out)} bytes after decompression, its header says {size}")
    return out


# -- the file ---------------------------------------------------------------------------------
def is_bag(path) -> bool:
    """True when ``path`` is a regular file starting with the ROS 1 bag magic (any version)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return False  # opening a FIFO would wait for a writer
        with open(path, "rb") as f:
            return f.read(len(_MAGIC_PREFIX)) == _MAGIC_PREFIX
    except OSError:
        return False


def _open(path: Path, digest=None):
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise RecordingError(f"{path}: not a regular file (a pipe, device or socket); give a ROS 1 .bag file")
        f = hashed(open(path, "rb"), digest)
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file; give a ROS 1 .bag file") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open ({exc.strerror or exc})") from None
    size = os.fstat(f.fileno()).st_size
    head = f.readline(64)
    if head != BAG_MAGIC:
        f.close()
        if head.startswith(_MAGIC_PREFIX):
            version = head[len(_MAGIC_PREFIX):].strip().decode("ascii", "replace")
            raise RecordingError(
                f"{path}: a ROS 1 bag of format {version}; agvviz reads format 2.0 (ROS since 2010) — "
                f"migrate it with: rosbag fix {path.name} fixed.bag"
            )
        what = "is empty" if size == 0 else f"starts with {head[:13]!r}, not '#ROSBAG V2.0'"
        raise RecordingError(f"{path}: not a ROS 1 bag ({what}); give a .bag written by rosbag record or rosbags")
    return f, size


def check_bag(path) -> None:
    """Raise :class:`RecordingError` (one line) when ``path`` is not a ROS 1 bag of format 2.0,
    or is an encrypted one."""
    path = Path(path)
    f, size = _open(path)
    with f:
        try:
            _, header, _, _, _ = _read_top(f, len(BAG_MAGIC), size)
        except _Damage:
            return  # damage is reported by the read
        if _encryptor(header):
            raise RecordingError(
                f"{path}: an encrypted ROS 1 bag ({_encryptor(header)}); decrypt it first "
                f"(rosbag decrypt {path.name} plain.bag)"
            )


def _encryptor(header: dict[str, bytes]) -> str:
    return header.get("encryptor", b"").decode("utf-8", "replace").strip()


def _read_top(f, pos: int, size: int) -> tuple[int, dict[str, bytes], int, int, int]:
    """(op, header, data offset, data length, bytes of data present) of the top-level record at
    ``pos``. Raises :class:`_Damage` when the header itself is wrong or cut short."""
    f.seek(pos)
    raw = f.read(4)
    if len(raw) < 4:
        raise _Damage("cut short inside a record's header length")
    (header_len,) = _U32.unpack(raw)
    if header_len > MAX_HEADER_BYTES or pos + 4 + header_len > size:
        raise _Damage(f"a record header of {header_len} bytes runs past the end of the file")
    header = _parse_header(f.read(header_len))
    op = _op(header)
    raw = f.read(4)
    if len(raw) < 4:
        return op, header, pos + 8 + header_len, 0, -1
    (data_len,) = _U32.unpack(raw)
    data_at = pos + 8 + header_len
    return op, header, data_at, data_len, min(data_len, size - data_at)


def _resync(f, start: int, size: int) -> int | None:
    """Offset of the next chunk record at or after ``start`` whose header parses, or ``None``."""
    pattern = b"op=\x05"
    pos = start
    while pos < size:
        f.seek(pos)
        block = f.read(_RESYNC_BLOCK_BYTES + _RESYNC_BACK_BYTES)
        at = block.find(pattern)
        while at != -1:
            hit = pos + at
            for begin in range(max(start, hit - _RESYNC_BACK_BYTES), hit - 7):
                try:
                    op, header, _, _, _ = _read_top(f, begin, size)
                except _Damage:
                    continue
                if op == _OP_CHUNK and "compression" in header and "size" in header:
                    return begin
            at = block.find(pattern, at + 1)
        pos += _RESYNC_BLOCK_BYTES
    return None


def _index(f, index_pos: int, size: int, report: ReadReport) -> tuple[dict[int, _Connection], int | None]:
    """Connections and the message count of the index section at ``index_pos`` (``None`` when
    the chunk infos cannot all be read)."""
    connections: dict[int, _Connection] = {}
    total: int | None = 0
    pos = index_pos
    try:
        while pos < size:
            op, header, data_at, data_len, present = _read_top(f, pos, size)
            if present != data_len:
                raise _Damage("cut short")
            f.seek(data_at)
            data = f.read(data_len)
            if op == _OP_CONNECTION:
                conn_id, conn = _connection(header, data)
                connections[conn_id] = conn
            elif op == _OP_CHUNK_INFO:
                count = _u32(header, "count")
                if len(data) < 8 * count:
                    raise _Damage("a chunk info shorter than its count")
                total += sum(_U32.unpack_from(data, 8 * k + 4)[0] for k in range(count))
            pos = data_at + data_len
    except _Damage as exc:
        report.problems.append(f"the bag's index record at byte {pos} is damaged or cut short ({exc}); "
                               "the message count is not checked against it")
        total = None
    return connections, total


def iter_raw(path, topics: set[str] | None, report: ReadReport, digest=None, verified: bool = False) -> Iterator[RawMessage]:
    """The messages of a ROS 1 bag in file order (see the module docstring); problems go to
    ``report``. Raises :class:`RecordingError` only when the file is missing or not a bag.
    With ``digest`` (a ``hashlib`` object) every byte of the file goes into it once the stream
    has ended (:class:`~agvviz.recording.raw.HashedReads`). ``verified`` changes nothing here:
    a bag has no CRC to skip."""
    path = Path(path)
    f, size = _open(path, digest)
    with f:
        connections: dict[int, _Connection] = {}
        index_connections: dict[int, _Connection] = {}
        index_total: int | None = None
        index_pos = 0
        orphans: dict[int, int] = {}
        read = 0
        pos = len(BAG_MAGIC)
        anything = False

        def message(header: dict[str, bytes], data: bytes) -> RawMessage | None:
            nonlocal read
            conn_id = _u32(header, "conn")
            time_ns = _time_ns(header, "time")
            conn = connections.get(conn_id) or index_connections.get(conn_id)
            if conn is None:
                orphans[conn_id] = orphans.get(conn_id, 0) + 1
                return None
            read += 1
            if topics is not None and conn.topic not in topics:
                return None
            return RawMessage(conn.topic, time_ns, conn.msgtype, SCHEMA_ENCODING, MESSAGE_ENCODING, data,
                              conn.msgdef, schema_hash=conn.md5sum)

        while pos < size:
            try:
                op, header, data_at, data_len, present = _read_top(f, pos, size)
            except _Damage as exc:
                report.problems.append(f"record at byte {pos} is damaged or cut short ({exc})")
                resume = _resync(f, pos + 1, size)
                if resume is None:
                    report.problems.append(
                        f"no readable chunk after byte {pos}: the last {size - pos} bytes of the file are lost"
                    )
                    break
                report.problems.append(f"skipped bytes {pos}..{resume} (damaged); reading on from the next chunk")
                pos = resume
                continue
            anything = True
            complete = present == data_len
            f.seek(data_at)
            data = f.read(max(present, 0))
            try:
                if op == _OP_BAG_HEADER:
                    index_pos = _u64(header, "index_pos")
                    if 0 < index_pos < size and not index_connections:
                        index_connections, index_total = _index(f, index_pos, size, report)
                elif op == _OP_CHUNK:
                    compression = _text(header, "compression")
                    chunk_size = _u32(header, "size")
                    if chunk_size > MAX_CHUNK_BYTES:
                        raise _Damage(f"chunk claims {chunk_size} bytes uncompressed, more than this reader accepts")
                    try:
                        records = _decompress(compression, data, chunk_size, complete)
                    except (OSError, EOFError, RuntimeError, ValueError, MemoryError, zlib.error) as exc:
                        if complete:
                            raise _Damage(f"does not decompress ({exc})") from None
                        records = b""
                    got = 0
                    try:
                        for inner_op, inner_header, inner_data in _records(records):
                            if inner_op == _OP_CONNECTION:
                                conn_id, conn = _connection(inner_header, inner_data)
                                connections.setdefault(conn_id, conn)
                            elif inner_op == _OP_MSG_DATA:
                                got += 1
                                if (out := message(inner_header, inner_data)) is not None:
                                    yield out
                    except _Damage as exc:
                        report.chunks_lost += 1
                        report.problems.append(
                            f"chunk at byte {pos} is damaged after {got} message(s), the rest of it is lost: {exc}"
                        )
                    else:
                        if complete:
                            report.chunks_ok += 1
                        else:
                            report.chunks_lost += 1
                            report.problems.append(
                                f"the file is cut short at byte {size}, inside the chunk at byte {pos} "
                                f"({present} of its {data_len} bytes): {got} message(s) of it read, the rest lost"
                            )
                elif op == _OP_CONNECTION and complete:
                    conn_id, conn = _connection(header, data)
                    index_connections.setdefault(conn_id, conn)
                elif op == _OP_MSG_DATA and complete:
                    if (out := message(header, data)) is not None:
                        yield out
            except _Damage as exc:
                if op == _OP_CHUNK:
                    report.chunks_lost += 1
                report.problems.append(f"record at byte {pos} is damaged and skipped: {exc}")
            if not complete:
                if 0 < index_pos <= pos:
                    report.problems.append(
                        f"the file is cut short at byte {size}, inside the bag's index (from byte {index_pos}): "
                        "every message before it was read, part of the index is lost"
                    )
                elif op != _OP_CHUNK:
                    report.problems.append(
                        f"the file is cut short at byte {size}, inside a record at byte {pos}: "
                        "what came after it is lost"
                    )
                break
            pos = data_at + data_len
        if not anything:
            why = report.problems[-1] if report.problems else "empty"
            raise RecordingError(
                f"{path}: has the ROS 1 bag magic but no readable record ({why}); "
                "the file is damaged right after its start — re-record or re-copy it"
            )
        if index_pos == 0 or index_pos >= size:
            report.problems.append(
                "the bag has no index (written when recording stops): the recorder did not close it or the "
                f"file was cut short; everything after byte {min(pos, size)} is lost (how much is unknown)"
                if index_pos == 0 or pos >= size else
                "the bag's index lies past the end of the file: the file was cut short; what came after "
                f"byte {size} is lost"
            )
        elif index_total is not None and read < index_total:
            report.problems.append(
                f"the bag's index lists {index_total} message(s), {read} were read: {index_total - read} lost"
            )
        for conn_id, count in orphans.items():
            report.problems.append(
                f"{count} message(s) on connection {conn_id} skipped: that connection's definition was in a "
                "lost part of the file"
            )
        if digest is not None:
            f.finish()


# -- decoding ---------------------------------------------------------------------------------
_stores: dict[tuple[str, str], object] = {}


def _typestore(raw: RawMessage):
    """A ``rosbags`` type store that knows ``raw``'s type from the definition the bag carries."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    text = raw.schema_data.decode("utf-8", "replace")
    key = (raw.schema_name, hashlib.sha1(raw.schema_data + raw.schema_hash.encode()).hexdigest())
    store = _stores.get(key)
    if store is None:
        if text.strip():
            try:
                store = get_typestore(Stores.EMPTY)
                store.register(get_types_from_msg(text, raw.schema_name))
                missing = _undefined_types(store)
                if missing:
                    store = MessageDecodeError(
                        f"the bag's message definition of {raw.schema_name} uses {', '.join(missing[:3])}, "
                        "which it does not define (an unknown message definition)"
                    )
            except Exception as exc:  # rosbags raises its own and parser errors on a bad definition
                store = MessageDecodeError(f"the bag's message definition of {raw.schema_name} does not parse ({exc})")
        else:
            store = get_typestore(Stores.ROS1_NOETIC)
            if raw.schema_name not in store.types:
                store = MessageDecodeError(
                    f"the bag carries no message definition for {raw.schema_name}, an unknown type"
                )
            else:
                _, md5 = store.generate_msgdef(raw.schema_name)
                if raw.schema_hash and md5 != raw.schema_hash:
                    store = MessageDecodeError(
                        f"the bag carries no message definition for {raw.schema_name} and its md5sum "
                        f"{raw.schema_hash} is not ROS Noetic's ({md5})"
                    )
        _stores[key] = store
    if isinstance(store, MessageDecodeError):
        raise store
    return store


def _undefined_types(store) -> list[str]:
    """Type names the store's definitions use but do not define."""
    from rosbags.typesys.base import Nodetype

    used: set[str] = set()

    def walk(node) -> None:
        if isinstance(node, tuple):
            if len(node) == 2 and node[0] == Nodetype.NAME and isinstance(node[1], str):
                used.add(node[1])
                return
            for item in node:
                walk(item)
        elif isinstance(node, list):
            for item in node:
                walk(item)

    for _, fields in store.fielddefs.values():
        walk(fields)
    return sorted(used - set(store.fielddefs))


def decodes(raw: RawMessage) -> bool:
    """True for ROS 1 messages (a bag's, or an MCAP file's with the ROS 1 profile)."""
    return raw.message_encoding == MESSAGE_ENCODING


def decode(raw: RawMessage) -> object:
    """The value of a ROS 1 message (:func:`agvviz.recording.ros_messages.ros_value`); ``bytes``
    for types agvviz does not use. Raises :class:`MessageDecodeError`."""
    if raw.schema_name not in DECODED_TYPES:
        return raw.data
    store = _typestore(raw)
    try:
        msg = store.deserialize_ros1(raw.data, raw.schema_name)
    except Exception as exc:  # damaged bytes: struct, index, unicode, rosbags' own errors
        raise MessageDecodeError(
            f"payload does not decode as {raw.schema_name}: {type(exc).__name__}: {exc}"
        ) from None
    return ros_value(raw.schema_name, msg, raw.topic)


_SPLIT_NUMBER = re.compile(r"(\d+)")


def bag_order(path: Path) -> list:
    """Sort key of the bags of a folder: by name with numbers compared as numbers
    (``run_2.bag`` before ``run_10.bag``; ``rosbag record --split`` names its parts ``_0``,
    ``_1``, …)."""
    return [int(part) if part.isdigit() else part for part in _SPLIT_NUMBER.split(path.name)]


# -- the recording ----------------------------------------------------------------------------
def _bags_of(path: Path) -> list[Path] | None:
    """The bags of ``path``: a ``.bag`` file (or any file with the bag magic), or the ``.bag``
    files of a directory without ``metadata.yaml`` in :func:`bag_order`; ``None`` when
    ``path`` is neither."""
    if path.is_dir():
        bags = sorted((p for p in path.glob("*.bag") if p.is_file()), key=bag_order)
        if not bags or (path / "metadata.yaml").exists():
            return None
        return bags
    if path.suffix == ".bag" or is_bag(path):
        return [path]
    return None


def recognises(path: Path) -> bool:
    """A ``.bag`` file, a file with the bag magic, or a folder of ``.bag`` files without
    ``metadata.yaml``."""
    return _bags_of(path) is not None


def open_recording(path: Path) -> Recording:
    """The recording of a bag or a folder of bags; raises :class:`RecordingError` (one line)
    now, not at the first read, when the first file is not a bag of format 2.0."""
    recording = Recording(path, _bags_of(path), sys.modules[__name__], profile="ros1")
    check_bag(recording.files[0])
    return recording


def describe(files: list[str]) -> str:
    """What ``inspect`` adds after the path: the bags."""
    return f" (ROS 1 bag{'s' if len(files) > 1 else ''}: {', '.join(files)})"
