"""The recording contract (MCAP, DESIGN §4): writer, streaming reader with salvage, inspector.

- :mod:`agvviz.recording.writer` — :class:`RecordingWriter` (atomic, Foxglove protobuf + agvviz JSON).
- :mod:`agvviz.recording.reader` — :func:`iter_messages` (streaming, salvages damaged files),
  :func:`read_scenario_metadata`.
- :mod:`agvviz.recording.contract` — :func:`inspect_recording`, :func:`format_report`.
- :mod:`agvviz.recording.schemas` — the ``agvviz.*`` JSON Schemas and their checker.

This package is the only place in agvviz that imports ``mcap``.
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
