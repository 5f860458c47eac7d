"""The recording contract (MCAP, DESIGN §4): writer, streaming reader with salvage, inspector.

- :mod:`agvviz.recording.writer` — :class:`RecordingWriter` (atomic, Foxglove protobuf + agvviz JSON).
- :mod:`agvviz.recording.reader` — :func:`iter_messages` (streaming, salvages damaged files),
  :func:`read_scenario_metadata`.
- :mod:`agvviz.recording.contract` — :func:`inspect_recording`, :func:`format_report`.
- :mod:`agvviz.recording.schemas` — the ``agvviz.*`` JSON Schemas and their checker.
- :mod:`agvviz.recording.topics` — every topic name and the roles the replay consumes.
- :mod:`agvviz.recording.source` — a recording (``.mcap`` or rosbag2 directory), its scan and
  its messages with roles and stamps; :mod:`agvviz.recording.roles` — the role map.
- :mod:`agvviz.recording.ros2` — ROS 2 CDR messages through ``mcap-ros2-support``;
  :mod:`agvviz.recording.images` — uncompressed frames; :mod:`agvviz.recording.sidefiles`.

This package is the only place in agvviz that imports ``mcap`` and the ROS 2 decoders.
"""

from agvviz.recording.contract import InspectReport, TopicSummary, format_report, inspect_recording
from agvviz.recording.reader import (
    CalibrationMsg,
    CompressedFrame,
    FrameTransformMsg,
    PoseMsg,
    ReadReport,
    RecordedMessage,
    RecordingError,
    iter_messages,
    read_scenario_metadata,
)
from agvviz.recording.writer import RecordingWriter

__all__ = [
    "RecordingWriter",
    "RecordingError",
    "CompressedFrame",
    "CalibrationMsg",
    "FrameTransformMsg",
    "PoseMsg",
    "RecordedMessage",
    "ReadReport",
    "iter_messages",
    "read_scenario_metadata",
    "InspectReport",
    "TopicSummary",
    "inspect_recording",
    "format_report",
]
