"""The source stage: a recording (one ``.mcap``, a rosbag2 directory, a ROS 1 ``.bag`` or a
folder of them), its topics, its role map, and its messages with their roles and time stamps.

* :func:`open_recording` — a ``.mcap`` file, or a rosbag2 directory (``metadata.yaml`` and
  every split file in the order it lists them; MCAP storage), or a ROS 1 bag (a ``.bag`` file,
  or a folder of ``.bag`` files read one after the other in name order, numbers as numbers —
  :mod:`agvviz.recording.ros1`). sqlite3 bags are refused with the conversion command.
* :func:`scan` — one streaming pass: per topic its schema, count, span and first frame id
  (what role inference needs).
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

from agvviz.conventions import AGV_FRAME
from agvviz.errors import RecordingError
from agvviz.recording import reader
from agvviz.recording.reader import (
    CalibrationMsg,
    CompressedFrame,
    FrameTransformMsg,
    MessageDecodeError,
    PoseMsg,
    RawMessage,
    RawMetadata,
    ReadReport,
    RecordedMessage,
    SkipCounter,
    decode,
)
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
from agvviz.recording.topics import camera_of_role

ROS_BODY_FRAME = "base_link"


@dataclass
class Recording:
    """A recording to replay: its files in order, what kind it is and what its writer says."""

    path: Path
    files: list[Path]
    kind: str  # "mcap" | "rosbag2" | "rosbag1"
    profile: str = ""
    library: str = ""
    scenario: dict | None = None
    bag_message_count: int | None = None  # metadata.yaml's total (rosbag2)
    bag_topic_counts: dict[str, int] = field(default_factory=dict)  # metadata.yaml's per topic

    @property
    def native(self) -> bool:
        """An agvviz recording (written by agvviz's writer, or carrying its scenario record)."""
        return self.library.startswith("agvviz") or self.scenario is not None

    @property
    def name(self) -> str:
        return self.path.name if self.path.is_dir() else self.path.stem

    def iter_raw(self, report: ReadReport, topics: set[str] | None = None) -> Iterator:
        """Raw messages and metadata of every file, in order (see :func:`reader.iter_raw`,
        :func:`agvviz.recording.ros1.iter_raw`)."""
        if self.kind == "rosbag1":
            from agvviz.recording import ros1

            for path in self.files:
                yield from ros1.iter_raw(path, topics, report)
            return
        for path in self.files:
            yield from reader.iter_raw(path, topics, report)

    def sha256(self) -> str:
        """sha256 of the recording's bytes (a bag: metadata.yaml then each file in order)."""
        digest = hashlib.sha256()
        paths = ([self.path / "metadata.yaml"] if self.kind == "rosbag2" else []) + self.files  # rosbag1: the bags
        for path in paths:
            with open(path, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    digest.update(block)
        return digest.hexdigest()

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


def require_recording_path(path) -> Path:
    """``path`` as a Path; :class:`RecordingError` (one line, what to do) when nothing is there —
    checked before any work starts (and before a progress bar is drawn)."""
    path = Path(path)
    if not path.exists():
        raise RecordingError(
            f"{path}: no such file or directory; give an .mcap recording, a rosbag2 directory or a ROS 1 .bag"
        )
    return path


def _open_ros1(path: Path) -> Recording | None:
    """A ROS 1 recording: a ``.bag`` file (or any file with the bag magic), or a directory
    without ``metadata.yaml`` holding ``.bag`` files; ``None`` when ``path`` is neither."""
    from agvviz.recording import ros1

    if path.is_dir():
        bags = sorted((p for p in path.glob("*.bag") if p.is_file()), key=ros1.bag_order)
        if not bags or (path / "metadata.yaml").exists():
            return None
        return Recording(path, bags, "rosbag1", profile="ros1")
    if path.suffix == ".bag" or ros1.is_bag(path):
        return Recording(path, [path], "rosbag1", profile="ros1")
    return None


def open_recording(path) -> Recording:
    """A :class:`Recording` for a ``.mcap`` file, a rosbag2 directory, a ROS 1 ``.bag`` or a
    folder of them.

    Raises :class:`RecordingError` with what to do when it is none of them.
    """
    path = require_recording_path(path)
    recording = _open_ros1(path)
    if recording is not None:
        from agvviz.recording import ros1

        ros1.check_bag(recording.files[0])  # not a bag: one line now, not at the first read
        return recording
    if path.is_dir():
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
        recording = Recording(path, files, "rosbag2", bag_message_count=int(total) if total is not None else None,
                              bag_topic_counts=counts)
    else:
        recording = Recording(path, [path], "mcap")
    recording.profile, recording.library, recording.scenario = reader.read_file_header(recording.files[0])
    return recording


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
    """Topics, counts and first frame ids in one streaming pass (images decoded once per topic)."""
    report = report if report is not None else ReadReport()
    out = Scan()
    for item in recording.iter_raw(report):
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
