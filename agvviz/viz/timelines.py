"""Stamping a log call on a run's timelines — one function for every logger.

Each per-frame or per-message log is placed on three timelines: ``frame`` (sequence), ``time``
(the message's absolute stamp, kept for overlays and export) and ``elapsed`` (a duration:
seconds since the recording's first stamp, what a user reads on plot axes).
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from agvviz.viz import paths


def set_stamp(rec: rr.RecordingStream, frame_index: int, log_time_ns: int, recording_start_ns: int) -> None:
    """Set ``frame``, ``time`` and ``elapsed`` on ``rec`` for the next log calls."""
    rec.set_time(paths.TIMELINE_FRAME, sequence=int(frame_index))
    rec.set_time(paths.TIMELINE_TIME, timestamp=np.datetime64(int(log_time_ns), "ns"))
    rec.set_time(paths.TIMELINE_ELAPSED, duration=elapsed_s(log_time_ns, recording_start_ns))


def elapsed_s(log_time_ns: int, recording_start_ns: int) -> float:
    """Seconds since the recording's first stamp (exact to the nanosecond below ~104 days)."""
    return (int(log_time_ns) - int(recording_start_ns)) * 1e-9
