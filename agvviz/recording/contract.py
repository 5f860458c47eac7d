"""Check a recording against the recording contract (DESIGN §4) in one streaming pass.

:func:`inspect_recording` summarises topics, cameras, static transforms and the scenario, and
lists *violations* (the file is readable but breaks the contract) separately from *damage*
(parts of the file could not be read). :func:`format_report` renders it for the CLI. The
checks a replay applies too are :mod:`agvviz.recording.checks`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.model.messages import CalibrationMsg, CompressedFrame, FrameTransformMsg, PoseMsg
from agvviz.model.topics import (
    CAMERA_TOPIC_RE,
    CORNERS_TOPIC,
    GROUND_TRUTH_TOPIC,
    MARKER_MAP_TOPIC,
    ODOMETRY_TOPIC,
    TF_STATIC_TOPIC,
    UWB_ANCHORS_TOPIC,
    UWB_RANGE_TOPIC,
    ROLE_MARKER_MAP,
    ROLE_TF_STATIC,
    ROLE_TRUTH,
    camera_calibration_topic,
    camera_of_role,
)
from agvviz.recording.checks import TimeChecks, format_ns, span_text, frame_problem, payload_map_problem, qr_map_of
from agvviz.recording.formats import by_name, decode
from agvviz.recording.mcap_stream import parse_scenario_metadata
from agvviz.recording.raw import MessageDecodeError, RawMetadata, ReadReport
from agvviz.recording.schemas import SCENARIO_METADATA, SCHEMAS

_CAMERA_TOPIC = CAMERA_TOPIC_RE

#: Fixed topics of the contract → (accepted schema names, message encoding).
_FIXED_TOPICS = {
    TF_STATIC_TOPIC: (("foxglove.FrameTransforms",), "protobuf"),
    GROUND_TRUTH_TOPIC: (("foxglove.PoseInFrame",), "protobuf"),
    ODOMETRY_TOPIC: (("foxglove.PoseInFrame",), "protobuf"),
    UWB_RANGE_TOPIC: (("agvviz.UwbRange",), "json"),
    UWB_ANCHORS_TOPIC: (("agvviz.UwbAnchors",), "json"),
    MARKER_MAP_TOPIC: (("agvviz.MarkerMap",), "json"),
    CORNERS_TOPIC: (("agvviz.CornerObservations",), "json"),
}
_CAMERA_TOPICS = {
    "image": (("foxglove.CompressedImage", "foxglove.RawImage"), "protobuf"),
    "calibration": (("foxglove.CameraCalibration",), "protobuf"),
}
#: Most examples quoted per violation kind (the count is always given).
_MAX_EXAMPLES = 1


@dataclass
class TopicSummary:
    """One topic: its schema and encoding, message count and log-time span (ns)."""

    topic: str
    schema_name: str
    encoding: str
    count: int
    first_ns: int
    last_ns: int


@dataclass
class InspectReport:
    """Everything :func:`inspect_recording` found. ``ok`` when no violation and no damage."""

    path: Path
    topics: list[TopicSummary] = field(default_factory=list)
    start_ns: int | None = None
    end_ns: int | None = None
    cameras: dict[str, CalibrationMsg] = field(default_factory=dict)
    transforms: list[FrameTransformMsg] = field(default_factory=list)
    scenario: dict | None = None
    violations: list[str] = field(default_factory=list)
    damage: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # worth knowing, not a violation
    native: bool = True  # an agvviz recording (the contract's naming applies)
    kind: str = "mcap"  # the format's NAME (agvviz.recording.formats): "mcap" | "rosbag2" | "rosbag1"
    files: list[str] = field(default_factory=list)
    bag_message_count: int | None = None  # rosbag2 metadata.yaml
    bag_topic_counts: dict[str, int] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.violations and not self.damage


def _expected_channel(topic: str) -> tuple[tuple[str, ...], str] | None:
    """(accepted schema names, encoding) the contract fixes for ``topic``, or ``None``."""
    if topic in _FIXED_TOPICS:
        return _FIXED_TOPICS[topic]
    match = _CAMERA_TOPIC.match(topic)
    return _CAMERA_TOPICS[match.group(2)] if match else None


class _Tally:
    """Counts repeated per-message violations so each kind is reported once with a count."""

    def __init__(self):
        self._entries: dict[str, list] = {}

    def add(self, key: str, example: str) -> None:
        entry = self._entries.setdefault(key, [0, []])
        entry[0] += 1
        if len(entry[1]) < _MAX_EXAMPLES:
            entry[1].append(example)

    def lines(self) -> list[str]:
        return [
            f"{key} ({count} message{'s' if count != 1 else ''}; e.g. {'; '.join(examples)})"
            for key, (count, examples) in self._entries.items()
        ]


def inspect_recording(path, roles=None, time_source: str = "auto") -> InspectReport:
    """Summarise ``path`` (an ``.mcap`` or a rosbag2 directory) and check it (one streaming
    pass): against the recording contract for agvviz's own recordings; for other files
    (ROS 2 bags, Foxglove SDK files) the contract's naming does not apply — their topics are
    read through the role map ``roles`` (:class:`agvviz.recording.roles.RoleMap`, inferred
    when not given) and a missing ``agvviz.scenario`` record is a note. Image time checks use
    the time a run uses (``time_source``: ``header`` stamps or ``log`` times; ``auto`` as a run).

    Raises :class:`agvviz.errors.RecordingError` when the path is missing or not a
    recording.
    """
    from agvviz.recording.source import open_recording, resolve_roles, scan

    recording = open_recording(path)
    if roles is None:
        roles = resolve_roles(scan(recording, ReadReport()))
    role_of = roles.role_of()
    native = recording.native
    header_time = recording.time_source(time_source) == "header"
    report = InspectReport(
        path=Path(path), native=native, kind=recording.kind, files=[f.name for f in recording.files],
        bag_message_count=recording.bag_message_count, bag_topic_counts=dict(recording.bag_topic_counts),
    )
    read = ReadReport()
    summaries: dict[str, TopicSummary] = {}
    channel_checked: set[tuple[str, str, str]] = set()
    tally = _Tally()
    image_cameras: set[str] = set()
    transforms: dict[tuple[str, str], FrameTransformMsg] = {}
    scenario_seen = False
    time_checks = TimeChecks()

    for item in recording.iter_raw(read):
        if isinstance(item, RawMetadata):
            if item.name == SCENARIO_METADATA:
                scenario_seen = True
                try:
                    report.scenario = parse_scenario_metadata(item.values)
                except ValueError as exc:
                    report.violations.append(
                        f"metadata: {exc}; expected string values name, seed, "
                        "options (JSON object), agvviz_version"
                    )
            continue
        topic, t_ns = item.topic, item.log_time_ns
        role = role_of.get(topic, "")
        cam_role = camera_of_role(role)
        is_image = cam_role is not None and cam_role[1] == "image"
        # images: reported by time_checks.problems(); with header time, checked once decoded
        checked_time = False
        if not (header_time and role):
            time_checks.message(topic, t_ns, is_image, is_truth=role == ROLE_TRUTH)
            checked_time = True
        summary = summaries.get(topic)
        if summary is None:
            summary = TopicSummary(topic, item.schema_name, item.message_encoding, 0, t_ns, t_ns)
            summaries[topic] = summary
        elif t_ns < summary.last_ns and not is_image:
            tally.add(
                f"{topic}: log time goes backwards; expected non-decreasing log times per topic",
                f"{t_ns} ns after {summary.last_ns} ns",
            )
        summary.count += 1
        summary.last_ns = max(summary.last_ns, t_ns)
        summary.first_ns = min(summary.first_ns, t_ns)

        channel_key = (topic, item.schema_name, item.message_encoding)
        if channel_key not in channel_checked:
            channel_checked.add(channel_key)
            if native:
                report.violations += _channel_violations(topic, item.schema_name, item.message_encoding)
        if not role and not native:
            continue  # a topic the replay does not use: listed, not decoded

        try:
            value = decode(item)
        except MessageDecodeError as exc:
            schema = item.schema_name or item.message_encoding
            tally.add(f"{topic}: payload does not match {schema}", f"at {t_ns} ns: {exc}")
            if not checked_time:
                time_checks.message(topic, t_ns, is_image, is_truth=role == ROLE_TRUTH)
            continue
        if not checked_time:
            stamp = getattr(value, "stamp_ns", 0) or (
                value[0].stamp_ns if isinstance(value, list) and value and isinstance(value[0], FrameTransformMsg) else 0
            )
            time_checks.message(topic, stamp or t_ns, is_image, is_truth=role == ROLE_TRUTH)
        if isinstance(value, CompressedFrame) and is_image:
            cam_name = cam_role[0]
            image_cameras.add(cam_name)
            if native and value.frame_id != camera_frame(cam_name):
                expected = camera_frame(cam_name)
                tally.add(f"{topic}: image frame_id is not {expected!r}", f"got {value.frame_id!r}")
            calibration = report.cameras.get(cam_name)
            problem = frame_problem(value.image_format, value.data, calibration.camera if calibration else None)
            if problem is not None:
                reason, detail = problem
                tally.add(f"{topic}: frames a replay rejects as {reason}", f"at {t_ns} ns: {detail}")
        elif isinstance(value, CalibrationMsg) and cam_role is not None and cam_role[1] == "calibration":
            cam_name = cam_role[0]
            if native and value.frame_id != camera_frame(cam_name):
                expected = camera_frame(cam_name)
                tally.add(f"{topic}: calibration frame_id is not {expected!r}", f"got {value.frame_id!r}")
            report.cameras[cam_name] = value
        elif role == ROLE_TF_STATIC and isinstance(value, list):
            for tf in value:
                transforms[(tf.parent_frame, tf.child_frame)] = tf
        elif role == ROLE_TRUTH and isinstance(value, PoseMsg) and value.frame_id != WORLD_FRAME and native:
            tally.add(f"{topic}: frame_id is not {WORLD_FRAME!r}", f"got {value.frame_id!r}")
        elif role == ROLE_MARKER_MAP and isinstance(value, dict):
            for problem in _marker_map_payload_problems(value):
                tally.add(f"{topic}: a code's payload disagrees with its map entry", problem)

    report.topics = sorted(summaries.values(), key=lambda s: s.topic)
    if summaries:
        report.start_ns = min(s.first_ns for s in summaries.values())
        report.end_ns = max(s.last_ns for s in summaries.values())
    report.transforms = list(transforms.values())
    report.violations += tally.lines()
    report.violations += time_checks.problems()
    for cam_name in sorted(image_cameras) if native else []:
        if cam_name not in report.cameras:
            report.violations.append(
                f"camera {cam_name}: images but no valid calibration; expected "
                f"{camera_calibration_topic(cam_name)} (foxglove.CameraCalibration)"
            )
        if not any((parent, camera_frame(cam_name)) in transforms for parent in (AGV_FRAME, WORLD_FRAME)):
            report.violations.append(
                f"camera {cam_name}: no /tf_static transform {AGV_FRAME} -> {camera_frame(cam_name)} "
                f"or {WORLD_FRAME} -> {camera_frame(cam_name)}; expected the camera's mounting pose "
                "T_agv_cam (on the AGV) or T_world_cam (fixed in the world)"
            )
    if not scenario_seen and native:
        report.violations.append(
            f"metadata: no {SCENARIO_METADATA!r} record; expected the scenario name, seed, "
            "options and agvviz version (written by RecordingWriter)"
        )
    elif not scenario_seen:
        report.notes.append(
            f"no {SCENARIO_METADATA!r} metadata: not an agvviz recording (written by "
            f"{recording.library or 'an unnamed writer'}{', profile ' + recording.profile if recording.profile else ''}); "
            "its topics are read through the role map below"
        )
    if recording.bag_message_count is not None:
        read_total = sum(s.count for s in summaries.values())
        mismatched = [
            f"{t}: metadata.yaml {n}, read {summaries[t].count if t in summaries else 0}"
            for t, n in sorted(recording.bag_topic_counts.items())
            if (summaries[t].count if t in summaries else 0) != n
        ]
        if read_total != recording.bag_message_count or mismatched:
            report.damage.append(
                f"metadata.yaml counts {recording.bag_message_count} messages, the files hold {read_total}"
                + (f" ({'; '.join(mismatched[:5])})" if mismatched else "")
            )
    report.damage += list(read.problems)
    return report


def _marker_map_payload_problems(marker_map: dict) -> list[str]:
    """Map entries whose ``payload`` (the text printed on the code) disagrees with the entry's
    own id or corners, by the replay's rule (:func:`payload_map_problem`)."""
    from agvviz.markers.payload import PayloadError, parse_payload

    qr_map = qr_map_of(marker_map)
    problems = []
    for entry in marker_map.get("markers", []) if qr_map else []:
        text, marker_id = entry.get("payload"), str(entry.get("id"))
        if not isinstance(text, str) or marker_id not in qr_map:
            continue
        try:
            payload = parse_payload(text)
        except PayloadError as exc:
            problems.append(f"code {marker_id}: payload refused: {exc}")
            continue
        if payload.marker_id != marker_id:
            problems.append(f"map entry {marker_id} carries the payload of code {payload.marker_id}")
            continue
        problem = payload_map_problem(marker_id, payload.points_world_m, {marker_id: qr_map[marker_id]})
        if problem:
            problems.append(problem)
    return problems


def _channel_violations(topic: str, schema_name: str, encoding: str) -> list[str]:
    """Schema/encoding violations of one channel."""
    expected = _expected_channel(topic)
    if expected is not None:
        names, expected_encoding = expected
        if schema_name not in names or encoding != expected_encoding:
            return [
                f"{topic}: schema {schema_name or '(none)'} with {encoding or '(no)'} encoding; "
                f"expected {' or '.join(names)} with {expected_encoding} encoding"
            ]
        return []
    if schema_name.startswith("agvviz.") and schema_name not in SCHEMAS:
        return [f"{topic}: unknown schema {schema_name}; expected one of {', '.join(SCHEMAS)}"]
    if encoding == "json" and not schema_name.startswith(("agvviz.", "foxglove.")):
        return [
            f"{topic}: JSON channel with schema {schema_name or '(none)'}; "
            "expected a JSON Schema named agvviz.*"
        ]
    return []


def format_report(report: InspectReport) -> str:
    """Plain multi-line text: topics, cameras, transforms, scenario, then the verdict."""
    lines = [f"recording: {report.path}" + by_name(report.kind).describe(report.files)]
    if report.bag_message_count is not None:
        lines.append(f"metadata.yaml: {report.bag_message_count} messages in {len(report.bag_topic_counts)} topic(s)")
    span = span_text(report.start_ns, report.end_ns) if report.start_ns is not None else "no messages"
    lines.append(f"time span: {span}")
    lines.append("")
    header = ("topic", "schema", "count", "first", "last")
    rows = [
        (
            s.topic,
            f"{s.schema_name or '(none)'} [{s.encoding}]",
            str(s.count),
            format_ns(s.first_ns, report.start_ns),
            format_ns(s.last_ns, report.start_ns),
        )
        for s in report.topics
    ]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    for row in [header, *rows]:
        lines.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
    lines.append("")
    lines.append("cameras:" if report.cameras else "cameras: none")
    for cam_name, calib in sorted(report.cameras.items()):
        cam = calib.camera
        K = cam.K
        lines.append(
            f"  {cam_name} ({calib.frame_id}): {cam.width_px}x{cam.height_px} px, "
            f"fx={K[0, 0]:.3f} fy={K[1, 1]:.3f} cx={K[0, 2]:.3f} cy={K[1, 2]:.3f} skew={K[0, 1]:.3g}, "
            f"D[{calib.distortion_model or 'none'}]=[{', '.join(f'{d:.6g}' for d in cam.dist)}]"
        )
    lines.append("transforms (tf_static):" if report.transforms else "transforms (tf_static): none")
    for tf in report.transforms:
        t = tf.T_parent_child[:3, 3]
        lines.append(f"  {tf.parent_frame} -> {tf.child_frame}: t = [{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m")
    if report.scenario is None:
        lines.append("scenario: none")
    else:
        s = report.scenario
        lines.append(
            f"scenario: {s['name']} seed={s['seed']} agvviz {s['agvviz_version']} "
            f"options={s['options']}"
        )
    lines.append("")
    for note in report.notes:
        lines.append(f"note: {note}")
    for problem in report.damage:
        lines.append(f"damage: {problem}")
    for violation in report.violations:
        lines.append(f"violation: {violation}")
    if report.ok and not report.native:
        lines.append("contract: OK (read as a third-party file: agvviz's topic naming does not apply)")
    elif report.ok:
        lines.append("contract: OK")
    else:
        lines.append(
            f"contract: {len(report.violations)} violation(s), "
            f"{len(report.damage)} damage problem(s)"
        )
    return "\n".join(lines)
