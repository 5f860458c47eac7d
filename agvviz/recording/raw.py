"""What every recording format's reader shares, below the formats: raw (undecoded) messages
and metadata, the read report, the decode error, the damage a parser may raise, and
:class:`Recording` — a recording's files, the format that reads them and the sha256 of its
bytes (computed during the scan's pass, :class:`HashedReads`, and kept for the process)."""

from __future__ import annotations

import hashlib
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import zstandard
from google.protobuf.message import DecodeError
from mcap.exceptions import McapError

from agvviz.conventions import AGV_FRAME
from agvviz.errors import RecordingError
from agvviz.recording.file_identity import files_key

#: Largest uncompressed chunk read (bytes). Writers cut chunks at ~1 MiB (agvviz, Foxglove SDK,
#: rosbag2); 256 MiB leaves room for chunks of raw 4K frames and keeps a bomb from exhausting memory.
MAX_CHUNK_BYTES = 256 << 20
#: Exceptions that damaged bytes raise inside mcap, zstandard, lz4 and protobuf parsing.
DAMAGE_ERRORS = (
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
#: The body frame of ROS recordings (REP 105).
ROS_BODY_FRAME = "base_link"
_HASH_BLOCK_BYTES = 1 << 20


class MessageDecodeError(RecordingError):
    """A message payload does not decode as its schema says (the message is skipped)."""


@dataclass
class ReadReport:
    """What a read got and what it lost: messages yielded, chunks read and lost, and one
    line per problem saying what was lost and why."""

    messages: int = 0
    chunks_ok: int = 0
    chunks_lost: int = 0
    problems: list[str] = field(default_factory=list)


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


class HashedReads:
    """A binary file whose bytes go into ``digest`` as far as they are read front to back: a
    read that continues (or overlaps the end of) what was hashed extends the hash, reads
    elsewhere (a look at the end of the file, a resync scan) do not. :meth:`finish` hashes the
    bytes no read reached, so the digest is always that of the whole file — after one pass of
    a reader that reads the file in order, only its unread remainder (an MCAP summary) is read
    again."""

    def __init__(self, f, digest):
        self._f = f
        self.digest = digest
        self._hashed_to = 0

    def _take(self, at: int, data: bytes) -> None:
        end = at + len(data)
        if at <= self._hashed_to < end:
            self.digest.update(memoryview(data)[self._hashed_to - at :])
            self._hashed_to = end

    def read(self, size: int = -1) -> bytes:
        at = self._f.tell()
        data = self._f.read(size)
        self._take(at, data)
        return data

    def readline(self, size: int = -1) -> bytes:
        at = self._f.tell()
        data = self._f.readline(size)
        self._take(at, data)
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def fileno(self) -> int:
        return self._f.fileno()

    def close(self) -> None:
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._f.close()

    def finish(self) -> None:
        """Hash the bytes after the last one hashed, to the end of the file."""
        self._f.seek(self._hashed_to)
        for block in iter(lambda: self._f.read(_HASH_BLOCK_BYTES), b""):
            self.digest.update(block)
            self._hashed_to += len(block)


def hashed(f, digest):
    """``f`` wrapped in :class:`HashedReads` when a ``digest`` is given, else ``f``."""
    return f if digest is None else HashedReads(f, digest)


def hash_file(path: Path, digest) -> None:
    """Every byte of ``path`` into ``digest``."""
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_HASH_BLOCK_BYTES), b""):
            digest.update(block)


#: sha256 of recordings read in this process, by their files' (path, size, mtime_ns).
_SHA256_CACHE: dict[tuple, str] = {}


@dataclass
class Recording:
    """A recording to replay: its files in order, the format that reads them
    (:mod:`agvviz.recording.formats`) and what its writer says."""

    path: Path
    files: list[Path]
    format: object  # a format module of agvviz.recording.formats
    profile: str = ""
    library: str = ""
    scenario: dict | None = None
    bag_message_count: int | None = None  # metadata.yaml's total (rosbag2)
    bag_topic_counts: dict[str, int] = field(default_factory=dict)  # metadata.yaml's per topic
    #: Files whose bytes the sha256 covers before :attr:`files` (a rosbag2 directory's metadata.yaml).
    hashed_first: list[Path] = field(default_factory=list)
    #: The files' key (:meth:`file_key`) when a whole read found them
    #: intact (:meth:`mark_verified`); None: not known.
    verified_key: list | None = None

    @property
    def kind(self) -> str:
        """The format's name: ``mcap``, ``rosbag2`` or ``rosbag1``."""
        return self.format.NAME

    @property
    def native(self) -> bool:
        """An agvviz recording (written by agvviz's writer, or carrying its scenario record)."""
        return self.library.startswith("agvviz") or self.scenario is not None

    @property
    def name(self) -> str:
        return self.path.name if self.path.is_dir() else self.path.stem

    def iter_raw(self, report: ReadReport, topics: set[str] | None = None, digest=None) -> Iterator:
        """Raw messages and metadata of every file, in order (the format's ``iter_raw``). With
        ``digest`` (a ``hashlib`` object) the recording's bytes go into it on the way, in
        :meth:`sha256`'s order; the digest is complete once the iteration ends. A recording
        :meth:`mark_verified` and unchanged since is read without its CRC checks and the search
        for repeated messages (that read found nothing, and would find nothing again)."""
        if digest is not None:
            for path in self.hashed_first:
                hash_file(path, digest)
        verified = self.verified()
        for path in self.files:
            yield from self.format.iter_raw(path, topics, report, digest, verified=verified)

    def mark_verified(self, key: list) -> None:
        """A read of every byte of the files as they were under ``key`` (their
        :meth:`file_key`, taken before that read and equal after
        it) found no damage, no CRC mismatch and no repeated message: later reads of the same
        files skip those checks (issue 27: each re-read of a 43 MB recording spent ≈30 ms of its
        ≈55 ms on three CRC passes). The trust is the scan cache's: a file written, replaced or
        touched has another key, and is checked again."""
        self.verified_key = key

    def verified(self) -> bool:
        """Whether the files are still those :meth:`mark_verified` was told of (stat calls)."""
        if self.verified_key is None:
            return False
        try:
            return self.file_key() == self.verified_key
        except OSError:
            return False

    def file_key(self) -> list[list]:
        """What identifies the files on disk as they are now, in hash order
        (:func:`~agvviz.recording.file_identity.files_key`); raises ``OSError``."""
        return files_key(list(self.hashed_first) + list(self.files))

    def _hash_key(self) -> tuple:
        key = []
        for path in self.hashed_first + self.files:
            st = os.stat(path)
            key.append((str(Path(path).resolve()), st.st_size, st.st_mtime_ns))
        return tuple(key)

    def remember_sha256(self, hexdigest: str) -> None:
        """Keep the sha256 a full pass over the recording computed (:func:`scan`)."""
        _SHA256_CACHE[self._hash_key()] = hexdigest

    def sha256(self) -> str:
        """sha256 of the recording's bytes (a rosbag2 bag: metadata.yaml then each file in
        order); read once per process — by the scan when it ran, else here."""
        key = self._hash_key()
        known = _SHA256_CACHE.get(key)
        if known is None:
            digest = hashlib.sha256()
            for path in self.hashed_first + self.files:
                hash_file(path, digest)
            known = _SHA256_CACHE[key] = digest.hexdigest()
        return known

    def time_source(self, setting: str) -> str:
        if setting != "auto":
            return setting
        return "log" if self.native else "header"

    def default_body_frame(self, frames: set[str]) -> str:
        if self.native:
            return AGV_FRAME
        if ROS_BODY_FRAME not in frames and AGV_FRAME in frames:
            return AGV_FRAME
        return ROS_BODY_FRAME
