"""The ROS 2 format: a rosbag2 directory (``metadata.yaml`` and every split file in the order
it lists them; MCAP storage, read by :mod:`agvviz.recording.mcap_stream`), and the decoding of
ROS 2 CDR messages wherever they are stored (a rosbag2 split file given alone is an ``.mcap``:
:mod:`agvviz.recording.formats.mcap` opens it, this module decodes its messages). sqlite3
bags are refused with the conversion command.

The CDR bytes are decoded by ``mcap_ros2``'s dynamic decoder, built from the ``ros2msg``
schema text the file itself carries (every rosbag2 MCAP file embeds its message definitions),
so no message layout is hand-written here. A definition ``mcap_ros2`` refuses — a bag
converted from ROS 1 by ``rosbags-convert`` with its default type store keeps ROS 1's
upper-case ``CameraInfo`` fields ``K``, ``D``, ``R``, ``P`` and ``std_msgs/Header``'s ``seq``,
and ``mcap_ros2`` accepts lower-case field names only — is decoded by ``rosbags``' CDR
deserialiser built from the same text. The decoded message becomes a value by
:func:`agvviz.recording.ros_messages.ros_value` (the table there).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import sys
from pathlib import Path

from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from agvviz.errors import RecordingError
from agvviz.recording.mcap_stream import iter_raw, read_file_header  # noqa: F401 — iter_raw is this format's
from agvviz.recording.raw import MessageDecodeError, RawMessage, Recording
from agvviz.recording.ros_messages import DECODED_TYPES, ros_value

#: The recording kind this format reads (:attr:`agvviz.recording.raw.Recording.kind`).
NAME = "rosbag2"

_factory = DecoderFactory()
_decoders: dict[tuple[str, str], object] = {}


def recognises(path: Path) -> bool:
    """A directory the ROS 1 format did not take (one without ``metadata.yaml`` is refused
    when opened, naming the ``.mcap`` files it holds)."""
    return path.is_dir()


def open_recording(path: Path) -> Recording:
    """The recording of a rosbag2 directory: its split files in ``metadata.yaml``'s order and
    its message counts. Raises :class:`RecordingError` with what to do when it cannot be read."""
    info = _read_bag_metadata(path)
    storage = str(info.get("storage_identifier", ""))
    if storage != "mcap":
        raise RecordingError(
            f"{path}: a rosbag2 bag with {storage or 'unknown'} storage; agvviz reads MCAP storage — "
            f"convert it with: ros2 bag convert -i {path} -o out.yaml (storage_id: mcap)"
        )
    if info.get("compression_mode") == "file" or str(info.get("compression_format", "")) not in ("", "None"):
        if info.get("compression_mode", "") == "file":
            raise RecordingError(
                f"{path}: files compressed as a whole ({info.get('compression_format')}); "
                f"decompress them first (ros2 bag decompress {path})"
            )
    names = info.get("relative_file_paths") or [f.get("path") for f in info.get("files", []) if isinstance(f, dict)]
    if not names:
        raise RecordingError(f"{path}/metadata.yaml lists no files (relative_file_paths)")
    files = [path / str(n) for n in names]
    missing = [str(f.name) for f in files if not f.is_file()]
    if missing:
        raise RecordingError(f"{path}: metadata.yaml lists {', '.join(missing)}, which the directory does not hold")
    counts = {}
    for entry in info.get("topics_with_message_count", []) or []:
        try:
            counts[str(entry["topic_metadata"]["name"])] = int(entry["message_count"])
        except (KeyError, TypeError, ValueError):
            continue
    total = info.get("message_count")
    recording = Recording(path, files, sys.modules[__name__],
                          bag_message_count=int(total) if total is not None else None,
                          bag_topic_counts=counts, hashed_first=[path / "metadata.yaml"])
    recording.profile, recording.library, recording.scenario = read_file_header(files[0])
    return recording


def _read_bag_metadata(directory: Path) -> dict:
    import yaml

    meta_path = directory / "metadata.yaml"
    if not meta_path.is_file():
        mcaps = sorted(p.name for p in directory.glob("*.mcap"))
        hint = (
            f"; it holds {', '.join(mcaps[:5])} — give one of those files instead" if mcaps
            else "; give an .mcap file, a rosbag2 directory or a folder of ROS 1 .bag files"
        )
        raise RecordingError(f"{directory}: a directory without metadata.yaml, so not a rosbag2 bag{hint}")
    try:
        data = yaml.safe_load(meta_path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise RecordingError(f"{meta_path}: cannot be read as YAML ({exc})") from None
    info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        raise RecordingError(f"{meta_path}: no 'rosbag2_bagfile_information' mapping; not a rosbag2 metadata file")
    return info


def describe(files: list[str]) -> str:
    """What ``inspect`` adds after the path: the directory's files."""
    return f" (rosbag2 directory: {', '.join(files)})"


def decodes(raw: RawMessage) -> bool:
    """True for ROS 2 CDR messages with their ``ros2msg`` definition."""
    return raw.message_encoding == "cdr" and raw.schema_encoding == "ros2msg"


def decode(raw: RawMessage) -> object:
    """The value of a CDR message (:func:`agvviz.recording.ros_messages.ros_value`); ``bytes``
    for other types.

    Raises :class:`MessageDecodeError` (or an exception of the damage list, which
    :func:`agvviz.recording.formats.decode` turns into one) when the bytes do not decode.
    """
    if raw.schema_name not in DECODED_TYPES:
        return raw.data
    return ros_value(raw.schema_name, _decoder(raw)(raw.data), raw.topic)


def _decoder(raw: RawMessage):
    """A decoder of ``raw``'s CDR bytes built from the schema text the file carries:
    ``mcap_ros2``'s, or — for a definition it refuses, such as the ROS 1 ``float64[9] K`` and
    ``float64[] D`` of a bag converted from ROS 1 with ``rosbags-convert``'s default (copied)
    type store: ``mcap_ros2`` allows lower-case field names only — ``rosbags``' CDR
    deserialiser built from the same text."""
    key = (raw.schema_name, hashlib.sha1(raw.schema_data).hexdigest())
    decoder = _decoders.get(key)
    if decoder is None:
        schema = Schema(id=len(_decoders) + 1, name=raw.schema_name, encoding="ros2msg", data=raw.schema_data)
        try:
            with contextlib.redirect_stderr(io.StringIO()):  # its parser prints the error too
                decoder = _factory.decoder_for("cdr", schema)
        except Exception as exc:  # mcap_ros2's parser raises NameError, ValueError, its own errors
            decoder = _rosbags_decoder(raw, exc)
        if decoder is None:
            decoder = MessageDecodeError(f"no CDR decoder for {raw.schema_name}")
        _decoders[key] = decoder
    if isinstance(decoder, MessageDecodeError):
        raise decoder
    return decoder


def _rosbags_decoder(raw: RawMessage, why: Exception):
    """``rosbags``' CDR deserialiser for ``raw``'s schema text, or a :class:`MessageDecodeError`
    saying why neither decoder can read it."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    try:
        store = get_typestore(Stores.EMPTY)
        store.register(get_types_from_msg(raw.schema_data.decode("utf-8"), raw.schema_name))
    except Exception as exc:
        return MessageDecodeError(
            f"the message definition of {raw.schema_name} does not parse (mcap_ros2: {why}; rosbags: {exc})"
        )
    name = raw.schema_name

    def decode(data: bytes):
        try:
            return store.deserialize_cdr(data, name)
        except Exception as exc:  # damaged bytes
            raise MessageDecodeError(f"payload does not decode as {name}: {type(exc).__name__}: {exc}") from None

    return decode
