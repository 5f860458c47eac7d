"""Check a recording against the recording contract (DESIGN §4) in one streaming pass.

:func:`inspect_recording` summarises topics, cameras, static transforms and the scenario, and
lists *violations* (the file is readable but breaks the contract) separately from *damage*
(parts of the file could not be read). :func:`format_report` renders it for the CLI.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.recording.reader import (
    CalibrationMsg,
    CompressedFrame,
    FrameTransformMsg,
    MessageDecodeError,
    PoseMsg,
    RawMetadata,
    ReadReport,
    decode,
    iter_raw,
    parse_scenario_metadata,
)
from agvviz.recording.schemas import SCENARIO_METADATA, SCHEMAS

_CAMERA_TOPIC = re.compile(r"^/cam/([^/]+)/(image|calibration)$")

#: Fixed topics of the contract → (accepted schema names, message encoding).
_FIXED_TOPICS = {
    "/tf_static": (("foxglove.FrameTransforms",), "protobuf"),
    "/agv/ground_truth": (("foxglove.PoseInFrame",), "protobuf"),
    "/agv/odometry": (("foxglove.PoseInFrame",), "protobuf"),
    "/uwb/range": (("agvviz.UwbRange",), "json"),
    "/uwb/anchors": (("agvviz.UwbAnchors",), "json"),
    "/markers/map": (("agvviz.MarkerMap",), "json"),
    "/markers/corners": (("agvviz.CornerObservations",), "json"),
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


def inspect_recording(path) -> InspectReport:
    """Summarise ``path`` and check it against the recording contract (one streaming pass).

    Raises :class:`agvviz.recording.reader.RecordingError` when the file is missing or not MCAP.
    """
    report = InspectReport(path=Path(path))
    read = ReadReport()
    summaries: dict[str, TopicSummary] = {}
    channel_checked: set[tuple[str, str, str]] = set()
    tally = _Tally()
    image_cameras: set[str] = set()
    transforms: dict[tuple[str, str], FrameTransformMsg] = {}
    scenario_seen = False

    for item in iter_raw(path, report=read):
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
        summary = summaries.get(topic)
        if summary is None:
            summary = TopicSummary(topic, item.schema_name, item.message_encoding, 0, t_ns, t_ns)
            summaries[topic] = summary
        elif t_ns < summary.last_ns:
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
            report.violations += _channel_violations(topic, item.schema_name, item.message_encoding)

        try:
            value = decode(item)
        except MessageDecodeError as exc:
            schema = item.schema_name or item.message_encoding
            tally.add(f"{topic}: payload does not match {schema}", f"at {t_ns} ns: {exc}")
            continue
        match = _CAMERA_TOPIC.match(topic)
        if isinstance(value, CompressedFrame) and match and match.group(2) == "image":
            cam_name = match.group(1)
            image_cameras.add(cam_name)
            if value.frame_id != camera_frame(cam_name):
                expected = camera_frame(cam_name)
                tally.add(f"{topic}: image frame_id is not {expected!r}", f"got {value.frame_id!r}")
        elif match and match.group(2) == "image" and item.schema_name == "foxglove.RawImage":
            image_cameras.add(match.group(1))
        elif isinstance(value, CalibrationMsg) and match and match.group(2) == "calibration":
            cam_name = match.group(1)
            if value.frame_id != camera_frame(cam_name):
                expected = camera_frame(cam_name)
                tally.add(f"{topic}: calibration frame_id is not {expected!r}", f"got {value.frame_id!r}")
            report.cameras[cam_name] = value
        elif topic == "/tf_static" and isinstance(value, list):
            for tf in value:
                transforms[(tf.parent_frame, tf.child_frame)] = tf
        elif topic == "/agv/ground_truth" and isinstance(value, PoseMsg) and value.frame_id != WORLD_FRAME:
            tally.add(f"{topic}: frame_id is not {WORLD_FRAME!r}", f"got {value.frame_id!r}")

    report.topics = sorted(summaries.values(), key=lambda s: s.topic)
    if summaries:
        report.start_ns = min(s.first_ns for s in summaries.values())
        report.end_ns = max(s.last_ns for s in summaries.values())
    report.transforms = list(transforms.values())
    report.violations += tally.lines()
    for cam_name in sorted(image_cameras):
        if cam_name not in report.cameras:
            report.violations.append(
                f"camera {cam_name}: images but no valid calibration; expected "
                f"/cam/{cam_name}/calibration (foxglove.CameraCalibration)"
            )
        if not any((parent, camera_frame(cam_name)) in transforms for parent in (AGV_FRAME, WORLD_FRAME)):
            report.violations.append(
                f"camera {cam_name}: no /tf_static transform {AGV_FRAME} -> {camera_frame(cam_name)} "
                f"or {WORLD_FRAME} -> {camera_frame(cam_name)}; expected the camera's mounting pose "
                "T_agv_cam (on the AGV) or T_world_cam (fixed in the world)"
            )
    if not scenario_seen:
        report.violations.append(
            f"metadata: no {SCENARIO_METADATA!r} record; expected the scenario name, seed, "
            "options and agvviz version (written by RecordingWriter)"
        )
    report.damage = list(read.problems)
    return report


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


def _format_ns(t_ns: int | None) -> str:
    return "-" if t_ns is None else f"{t_ns / 1e9:.6f} s"


def format_report(report: InspectReport) -> str:
    """Plain multi-line text: topics, cameras, transforms, scenario, then the verdict."""
    lines = [f"recording: {report.path}"]
    span = (
        f"{_format_ns(report.start_ns)} .. {_format_ns(report.end_ns)}"
        if report.start_ns is not None
        else "no messages"
    )
    lines.append(f"time span: {span}")
    lines.append("")
    header = ("topic", "schema", "count", "first", "last")
    rows = [
        (
            s.topic,
            f"{s.schema_name or '(none)'} [{s.encoding}]",
            str(s.count),
            _format_ns(s.first_ns),
            _format_ns(s.last_ns),
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
    lines.append("transforms (/tf_static):" if report.transforms else "transforms (/tf_static): none")
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
    for problem in report.damage:
        lines.append(f"damage: {problem}")
    for violation in report.violations:
        lines.append(f"violation: {violation}")
    if report.ok:
        lines.append("contract: OK")
    else:
        lines.append(
            f"contract: {len(report.violations)} violation(s), "
            f"{len(report.damage)} damage problem(s)"
        )
    return "\n".join(lines)
