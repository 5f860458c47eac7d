"""The source stage: a recording (one ``.mcap``, a rosbag2 directory, a ROS 1 ``.bag`` or a
folder of them), its topics, its role map, and its messages with their roles and time stamps.

* :func:`open_recording` — a ``.mcap`` file, or a rosbag2 directory (``metadata.yaml`` and
  every split file in the order it lists them; MCAP storage), or a ROS 1 bag (a ``.bag`` file,
  or a folder of ``.bag`` files read one after the other in name order, numbers as numbers),
  opened by its format (:mod:`agvviz.recording.formats`). sqlite3 bags are refused with the
  conversion command.
* :func:`scan` — one streaming pass: per topic its schema, count, span and first frame id
  (what role inference needs), and the recording's sha256.
* :func:`resolve_roles` — the role map: inferred, ``--roles FILE``, ``--topic ROLE=TOPIC``.
* :func:`iter_role_messages` — the decoded messages that play a role, in file order, each
  with its ``role`` and (``time_source=header``) its header stamp.

Time: ``log`` places every message at the file's log time; ``header`` at the stamp the
message carries (ROS ``header.stamp``, Foxglove ``timestamp``), falling back to the log time
for messages without one. ``auto`` is ``log`` for agvviz's own recordings (their contract:
time = log time) and ``header`` for other files.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator

from agvviz.errors import RecordingError
from agvviz.model.messages import CalibrationMsg, CompressedFrame, FrameTransformMsg, PoseMsg, RecordedMessage
from agvviz.model.topics import camera_of_role
from agvviz.recording.formats import decode, format_of
from agvviz.recording.raw import MessageDecodeError, RawMessage, RawMetadata, ReadReport, Recording, SkipCounter
from agvviz.recording.roles import (
    CALIBRATION_TYPES,
    IMAGE_TYPES,
    POSE_TYPES,
    TRANSFORM_TYPES,
    RoleMap,
    TopicInfo,
    infer_roles,
    read_roles_file,
)


def require_recording_path(path) -> Path:
    """``path`` as a Path; :class:`RecordingError` (one line, what to do) when nothing is there —
    checked before any work starts (and before a progress bar is drawn)."""
    path = Path(path)
    if not path.exists():
        raise RecordingError(
            f"{path}: no such file or directory; give an .mcap recording, a rosbag2 directory or a ROS 1 .bag"
        )
    return path


def open_recording(path) -> Recording:
    """A :class:`Recording` for a ``.mcap`` file, a rosbag2 directory, a ROS 1 ``.bag`` or a
    folder of them: the first format of :data:`agvviz.recording.formats.FORMATS` that
    recognises ``path`` opens it.

    Raises :class:`RecordingError` with what to do when it is none of them.
    """
    path = require_recording_path(path)
    return format_of(path).open_recording(path)


@dataclass
class Scan:
    """What one pass over a recording found, per topic."""

    topics: dict[str, TopicInfo] = field(default_factory=dict)
    first_ns: dict[str, int] = field(default_factory=dict)
    last_ns: dict[str, int] = field(default_factory=dict)
    first_problem: dict[str, str] = field(default_factory=dict)  # topic -> why its first message failed
    tf_frames: set[str] = field(default_factory=set)
    metadata: list[RawMetadata] = field(default_factory=list)
    #: Every message the sync stage may need (calibrations, poses, transforms, marker maps),
    #: kept undecoded so the first pass of a run needs no second read of the file.
    context: list[RawMessage] = field(default_factory=list)


_PROBED = IMAGE_TYPES + CALIBRATION_TYPES + POSE_TYPES + TRANSFORM_TYPES
#: Schemas whose messages feed the sync stage (:class:`agvviz.replay.sync.SyncState`).
CONTEXT_TYPES = CALIBRATION_TYPES + POSE_TYPES + TRANSFORM_TYPES + ("agvviz.MarkerMap",)


def scan(recording: Recording, report: ReadReport | None = None) -> Scan:
    """Topics, counts and first frame ids in one streaming pass (images decoded once per topic);
    the same pass computes the recording's sha256 (:meth:`Recording.sha256` then reads nothing)."""
    report = report if report is not None else ReadReport()
    out = Scan()
    digest = hashlib.sha256()
    for item in recording.iter_raw(report, digest=digest):
        if isinstance(item, RawMetadata):
            out.metadata.append(item)
            continue
        info = out.topics.get(item.topic)
        if info is None:
            info = TopicInfo(item.topic, item.schema_name, item.message_encoding)
            out.topics[item.topic] = info
            out.first_ns[item.topic] = item.log_time_ns
            out.last_ns[item.topic] = item.log_time_ns
        info.count += 1
        if item.schema_name in CONTEXT_TYPES:
            out.context.append(item)
        out.first_ns[item.topic] = min(out.first_ns[item.topic], item.log_time_ns)
        out.last_ns[item.topic] = max(out.last_ns[item.topic], item.log_time_ns)
        probe_tf = item.schema_name in TRANSFORM_TYPES
        if item.schema_name in _PROBED and (probe_tf or (not info.frame_id and item.topic not in out.first_problem)):
            try:
                value = decode(item)
            except MessageDecodeError as exc:
                out.first_problem.setdefault(item.topic, str(exc))
                continue
            out.first_problem.pop(item.topic, None)
            if isinstance(value, (CompressedFrame, CalibrationMsg)):
                info.frame_id = value.frame_id
            elif isinstance(value, PoseMsg):
                info.frame_id, info.child_frame = value.frame_id, value.child_frame
            elif isinstance(value, list):
                for tf in value:
                    if isinstance(tf, FrameTransformMsg):
                        out.tf_frames.update((tf.parent_frame, tf.child_frame))
    recording.remember_sha256(digest.hexdigest())
    return out


def resolve_roles(
    recording_scan: Scan,
    topic_options: dict[str, str] | None = None,
    roles_file: Path | None = None,
) -> RoleMap:
    """The role map: a roles file (authoritative: only its roles) or inference, then the
    ``--topic`` options on top. Raises InputError for a bad role or topic."""
    topics = recording_scan.topics
    if roles_file is not None:
        fixed = read_roles_file(roles_file)
        fixed.update(topic_options or {})
        return infer_roles(topics, fixed, fixed_origin=f"roles file {Path(roles_file).name}", infer=False)
    return infer_roles(topics, topic_options or {}, fixed_origin="--topic")


def iter_role_messages(
    recording: Recording,
    roles: RoleMap,
    time_source: str,
    report: ReadReport,
    images: bool = True,
    skipped: SkipCounter | None = None,
    raw: list | None = None,
) -> Iterator[RecordedMessage]:
    """Decoded messages that play a role, in file order, with ``role`` set and (``header``
    time) ``stamp_ns`` set from the message's own stamp. ``images=False`` leaves camera
    frames out (the first pass). ``raw`` (e.g. :attr:`Scan.context`) is read instead of the
    file. Undecodable messages are skipped and, unless ``skipped`` collects them, reported in
    ``report.problems`` when the pass ends."""
    role_of = roles.role_of()
    wanted = set(role_of)
    if not images:
        wanted -= roles.image_topics()
    own = skipped is None
    skipped = skipped if skipped is not None else SkipCounter()
    try:
        source = recording.iter_raw(report, wanted) if raw is None else raw
        for item in source:
            if isinstance(item, RawMetadata) or item.topic not in wanted:
                continue
            try:
                value = decode(item)
            except MessageDecodeError as exc:
                skipped.add(item, exc)
                continue
            role = role_of[item.topic]
            cam = camera_of_role(role)
            if cam is not None and isinstance(value, (CompressedFrame, CalibrationMsg)) and value.cam_name != cam[0]:
                value = replace(value, cam_name=cam[0])
            stamp = None
            if time_source == "header":
                own_stamp = getattr(value, "stamp_ns", 0)
                if isinstance(value, list) and value and isinstance(value[0], FrameTransformMsg):
                    own_stamp = value[0].stamp_ns
                stamp = own_stamp or None
            report.messages += 1
            yield RecordedMessage(item.topic, item.log_time_ns, item.schema_name, value, role=role, stamp_ns=stamp)
    finally:
        if own:
            report.problems += skipped.lines()
