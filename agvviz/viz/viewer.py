"""Sending a run ``.rrd`` as it is (its recording and its blueprint) to a running Rerun viewer,
for ``agvviz view --connect``."""

from __future__ import annotations

from pathlib import Path

import rerun as rr
from rerun.chunk import RrdReader

from agvviz.errors import InputError


def send_rrd(run_file: Path, url: str) -> None:
    """Send ``run_file`` to the viewer at ``url`` (``rerun+http://host:port/proxy``) under the
    run's own application and recording id, so the viewer shows the run, not an empty sender.
    :class:`~agvviz.errors.InputError` when the file cannot be read or the sending fails."""
    try:
        recordings = RrdReader(run_file).recordings()
    except (RuntimeError, ValueError, OSError) as exc:
        raise InputError(f"cannot read {run_file}: {' '.join(str(exc).split())}; write it again with `agvviz run`")
    if not recordings:
        raise InputError(f"{run_file} holds no recording; write it again with `agvviz run`")
    entry = recordings[0]
    stream = rr.RecordingStream(entry.application_id, recording_id=entry.recording_id)
    try:
        stream.connect_grpc(url)
        stream.log_file_from_path(run_file)  # the .rrd as it is: recording and blueprint
        stream.flush(timeout_sec=120)
    except (RuntimeError, ValueError) as exc:
        raise InputError(f"sending {run_file} to {url} failed: {' '.join(str(exc).split())}")
    finally:
        stream.disconnect()
