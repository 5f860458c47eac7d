"""A recording's camera frames logged on a run's clock (issue 27): the frames of a layers-only
run (``run --images none``) that ``agvviz view`` opens beside it, and the frames a sweep
``.rrd`` holds once for all its settings.

The run's own clock decides where each image goes: every camera logs its detected corners on
every frame (:func:`agvviz.viz.readback.frame_stamps`), so ``(camera, time)`` → ``(frame,
elapsed)`` is read from the run, never re-derived; the images are the recording's bytes, logged
by :func:`agvviz.viz.encoded_image.log_encoded_image` as a run logs them.
"""

from __future__ import annotations

import os
from collections import defaultdict, deque
from pathlib import Path
from typing import Iterable

import numpy as np
import rerun as rr

from agvviz.viz import paths
from agvviz.viz.encoded_image import log_encoded_image
from agvviz.viz.rrd_file import AtomicRrd

#: One camera image of a recording: (camera, time on the replay clock [ns], image format, bytes).
RecordedImage = tuple[str, int, str, bytes]
#: A camera's clock in a run: (frame, time_ns, elapsed_ns) of each of its frames, in logging order.
CameraClock = list[tuple[int, int, int]]


def log_images(
    rec: rr.RecordingStream, images: Iterable[RecordedImage], clocks: dict[str, CameraClock],
    entity_of: dict[str, str],
) -> tuple[int, int]:
    """Log each image of ``images`` whose camera and time have a frame in ``clocks`` at
    ``entity_of[camera]`` on that frame's ``frame``, ``time`` and ``elapsed``. Returns
    (images logged, frames of ``clocks`` left without an image)."""
    pending: dict[str, dict[int, deque]] = {}
    for cam, rows in clocks.items():
        by_time: dict[int, deque] = defaultdict(deque)
        for frame, time_ns, elapsed_ns in rows:
            by_time[time_ns].append((frame, elapsed_ns))
        pending[cam] = by_time
    logged = 0
    for cam, time_ns, image_format, data in images:
        queue = pending.get(cam, {}).get(int(time_ns))
        if not queue:
            continue  # a frame the run did not log (or another recording's image)
        frame, elapsed_ns = queue.popleft()
        rec.set_time(paths.TIMELINE_FRAME, sequence=frame)
        rec.set_time(paths.TIMELINE_TIME, timestamp=np.datetime64(int(time_ns), "ns"))
        rec.set_time(paths.TIMELINE_ELAPSED, duration=np.timedelta64(int(elapsed_ns), "ns"))
        log_encoded_image(rec, entity_of[cam], image_format, data)
        logged += 1
    missing = sum(len(q) for by_time in pending.values() for q in by_time.values())
    return logged, missing


def write_frames_rrd(
    out_path: str | os.PathLike, *, recording_id: str, recording_name: str, images: Iterable[RecordedImage],
    clocks: dict[str, CameraClock], entity_of: dict[str, str], inputs: tuple = (),
) -> tuple[Path, int, int]:
    """The frames of a layers-only run as an ``.rrd`` of their own under the run's recording id,
    so a viewer given both files shows one recording. Returns (path, logged, missing)."""
    with AtomicRrd(out_path, recording_id=recording_id, recording_name=recording_name, inputs=inputs) as rrd:
        logged, missing = log_images(rrd.rec, images, clocks, entity_of)
        rrd.check()
        path = rrd.commit(None)
    return path, logged, missing
