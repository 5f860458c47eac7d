"""A recording's scan and sha256 kept on disk, so a second run of the same file reads it once
(issue 27: a warm run re-read and re-hashed the whole recording before its one real pass).

One entry per recording file set: ``<cache dir>/scans/<key>.scan``, where the key hashes each
file's resolved path, size, mtime_ns, ctime_ns and inode (a rosbag2 bag: metadata.yaml and
every data file). A file written, replaced, touched or moved is a different key: its entry is
never read again (a stale one is only replaced when the same key comes back). The entry stores
its own key fields and agvviz's version and is used only when both still match; anything
unreadable, truncated or foreign is ignored and the recording is scanned as usual.

Layout of an entry (written atomically, :func:`agvviz.recording.outputs.atomic_write_bytes`):
``MAGIC``, an 8-byte little-endian length, that many bytes of JSON (key, version, sha256,
``intact``, the :class:`~agvviz.recording.source.Scan` fields, the context messages' headers with
their payload lengths), then the payloads back to back (message data, schema data).

``intact``: the scan read every byte and found no damage, no CRC mismatch and no repeated
message. A recording loaded from such an entry is marked verified
(:meth:`~agvviz.recording.raw.Recording.mark_verified`): the run's later reads of it skip those
checks, which could find nothing new in the same bytes. A damaged file is checked at every read.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
from pathlib import Path
from typing import TYPE_CHECKING

from agvviz import __version__
from agvviz.errors import OutputError
from agvviz.recording import outputs
from agvviz.recording.file_identity import files_key

if TYPE_CHECKING:
    from agvviz.recording.raw import Recording

# Only the standard library at import; the readers (zstandard, protobuf, mcap) come later.

#: The cache folder's environment variable (detections and scans share the folder).
CACHE_ENV = "AGVVIZ_CACHE_DIR"
MAGIC = b"agvviz-scan-1\n"
#: Bump when :class:`~agvviz.recording.source.Scan` or what :func:`scan` puts in it changes.
SCAN_REVISION = 2
_LENGTH = struct.Struct("<Q")


def default_cache_dir() -> Path:
    """The cache folder: ``$AGVVIZ_CACHE_DIR``, else ``$XDG_CACHE_HOME/agvviz/detections``,
    else ``~/.cache/agvviz/detections``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = Path(os.environ["XDG_CACHE_HOME"]) if os.environ.get("XDG_CACHE_HOME") else Path.home() / ".cache"
    return base / "agvviz" / "detections"


def cache_folder(cache_dir: Path | None | bool) -> Path | None:
    """The cache folder a run's ``cache_dir`` names: a path; None or True: the default
    (:func:`default_cache_dir`); False: none (None)."""
    if cache_dir is False:
        return None
    return Path(cache_dir) if cache_dir not in (None, True) else default_cache_dir()


def entry_path(cache_dir: Path, key: list[list]) -> Path:
    digest = hashlib.sha256(json.dumps(key).encode()).hexdigest()[:32]
    return Path(cache_dir) / "scans" / f"{digest}.scan"


def _encode(key: list[list], sha256: str, scan, intact: bool) -> bytes:
    payloads: list[bytes] = []
    schemas: dict[bytes, int] = {}  # one copy of each schema text, not one per message
    messages = []
    for m in scan.context:
        if m.schema_data not in schemas:
            schemas[m.schema_data] = len(schemas)
        messages.append([m.topic, m.log_time_ns, m.schema_name, m.schema_encoding, m.message_encoding,
                         len(m.data), schemas[m.schema_data], m.schema_hash])
    schema_texts = list(schemas)
    payloads += schema_texts
    payloads += [m.data for m in scan.context]
    header = {
        "version": __version__, "revision": SCAN_REVISION, "key": key, "sha256": sha256, "intact": intact,
        "topics": [[i.topic, i.schema_name, i.encoding, i.count, i.frame_id, i.child_frame]
                   for i in scan.topics.values()],
        "first_ns": scan.first_ns, "last_ns": scan.last_ns, "first_problem": scan.first_problem,
        "tf_frames": sorted(scan.tf_frames),
        "metadata": [[m.name, m.values] for m in scan.metadata],
        "schemas": [len(s) for s in schema_texts],
        "messages": messages,
    }
    text = json.dumps(header).encode()
    return b"".join([MAGIC, _LENGTH.pack(len(text)), text, *payloads])


def _decode(blob: bytes, key: list[list]):
    """(sha256, Scan, intact) from an entry's bytes, or None when it is not a valid entry for
    ``key``."""
    from agvviz.recording.raw import RawMessage, RawMetadata
    from agvviz.recording.roles import TopicInfo
    from agvviz.recording.source import Scan

    if not blob.startswith(MAGIC) or len(blob) < len(MAGIC) + _LENGTH.size:
        return None
    (length,) = _LENGTH.unpack_from(blob, len(MAGIC))
    start = len(MAGIC) + _LENGTH.size
    header = json.loads(blob[start : start + length])
    if (not isinstance(header, dict) or header.get("version") != __version__
            or header.get("revision") != SCAN_REVISION or header.get("key") != key):
        return None
    at = start + length
    schema_texts = []
    for size in header["schemas"]:
        schema_texts.append(blob[at : at + size])
        at += size
    context = []
    for topic, log_time_ns, schema_name, schema_encoding, message_encoding, size, schema, schema_hash in header["messages"]:
        context.append(RawMessage(topic, log_time_ns, schema_name, schema_encoding, message_encoding,
                                  blob[at : at + size], schema_texts[schema], schema_hash))
        at += size
    if at != len(blob):  # truncated or padded: not what was written
        return None
    scan = Scan(
        topics={t[0]: TopicInfo(*t) for t in header["topics"]},
        first_ns=dict(header["first_ns"]), last_ns=dict(header["last_ns"]),
        first_problem=dict(header["first_problem"]), tf_frames=set(header["tf_frames"]),
        metadata=[RawMetadata(name, dict(values)) for name, values in header["metadata"]],
        context=context,
    )
    if not isinstance(header["sha256"], str) or len(header["sha256"]) != 64:
        return None
    return header["sha256"], scan, header.get("intact") is True


def load(cache_dir: Path, recording: Recording):
    """The cached Scan of ``recording`` (its sha256 remembered, :meth:`Recording.sha256` then
    reads nothing; marked verified when the scan found it intact), or None: no entry, a changed
    file, or an entry that does not read."""
    try:
        key = recording.file_key()
        blob = entry_path(cache_dir, key).read_bytes()
        found = _decode(blob, key)
    except (OSError, ValueError, KeyError, TypeError, IndexError, struct.error):  # absent or damaged
        return None
    if found is None:
        return None
    sha256, scan, intact = found
    recording.remember_sha256(sha256)
    if intact:
        recording.mark_verified(key)
    return scan


def store(cache_dir: Path, recording: Recording, scan, key: list[list], intact: bool = False) -> None:
    """Keep ``scan`` and the sha256 the same pass computed under ``key`` (the files' key taken
    before the pass), and whether that pass found the files ``intact`` (no damage, no repeated
    message); a cache that cannot be written is skipped (the next run scans again)."""
    try:
        blob = _encode(key, recording.sha256(), scan, intact)
        path = entry_path(cache_dir, key)
        path.parent.mkdir(parents=True, exist_ok=True)
        outputs.atomic_write_bytes(path, blob)
    except (OSError, OutputError):
        return


def cached_scan(recording: Recording, cache_dir: Path | None):
    """:func:`agvviz.recording.source.scan` of ``recording``, read from ``cache_dir`` when an
    entry for its files as they are now is there, else scanned and stored (not when a file
    changed during the pass). ``cache_dir`` None: scanned, nothing stored. Either way a
    recording the scan found intact is marked so (:meth:`Recording.mark_verified`): the run's
    later reads of it skip the CRC checks."""
    from agvviz.recording.raw import ReadReport
    from agvviz.recording.source import scan

    found = load(cache_dir, recording) if cache_dir is not None else None
    if found is not None:
        return found
    try:
        key = recording.file_key()
    except OSError:
        key = None
    report = ReadReport()
    result = scan(recording, report)
    try:
        unchanged = key is not None and recording.file_key() == key
    except OSError:
        unchanged = False
    if unchanged:
        intact = not report.problems and report.chunks_lost == 0
        if intact:
            recording.mark_verified(key)
        if cache_dir is not None:
            store(cache_dir, recording, result, key, intact)
    return result
