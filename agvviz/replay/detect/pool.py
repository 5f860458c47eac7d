"""Detect ahead of the replay: frame-parallel detection in a process pool, results in order.

:class:`DetectionFeed` reads the recording's message stream ahead of the replay, cuts each
camera's frames into segments (:class:`agvviz.replay.detect.stage.DetectParams.segment_frames`
consecutive frames; a segment is one task and keeps its own tracking state), runs the segments
on ``jobs`` worker processes and hands every message back *in file order* together with its
frame's :class:`~agvviz.model.detections.FrameDetections`. At most ``2·jobs + 1`` segments are in
flight and every message read ahead is held only until the replay takes it, so memory stays flat
however long the recording. With ``jobs = 1`` the segments run in this process, by the same
code, with the same results; detections from the cache (:mod:`agvviz.replay.detect.cache`) are
handed out without any detection at all.

Segments are cut by each camera's own frame count, never by timing, so detections (and the
``.rrd``) do not depend on the number of workers. One exception keeps memory bounded on odd
recordings: when :data:`MAX_READ_AHEAD` messages are waiting for one camera's segment to fill
(a camera far slower than the others), that segment is cut short there — also a property of
the file alone, not of timing.
"""

from __future__ import annotations

import os
from collections import deque
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

from agvviz.errors import RunError
from agvviz.replay.detect.stage import DetectParams, FrameJob, detect_segment
from agvviz.replay.detect.workers import init_worker, pool_context
from agvviz.model.detections import FrameDetections
from agvviz.model.messages import CompressedFrame, RecordedMessage

#: Messages read ahead of the replay before a slow camera's unfinished segment is cut short.
MAX_READ_AHEAD = 4096


def default_jobs() -> int:
    """Detection workers when none are asked for: one per CPU this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class DetectedFrame:
    """A frame's detections with where they belong: the image message's sequence number among
    the recording's frames that were detected, its camera and its time (checked against the
    cache)."""

    seq: int
    cam_name: str
    log_time_ns: int
    detections: FrameDetections


@dataclass
class _Segment:
    cam_name: str
    jobs: list[FrameJob] = field(default_factory=list)
    future: Future | None = None


class DetectionFeed:
    """Messages in file order, each image with its detections, computed ``jobs``-parallel.

    ``job_of(message)`` gives an image message's detect-stage input (None: not detected, e.g.
    no calibration at its time); ``cached`` are the detections of an earlier run of the same
    recording and detection settings, in order. After iterating, :attr:`frames` holds every
    frame's :class:`DetectedFrame` (for the cache) when ``keep`` is True.

    ``executor``: a process pool of the caller's (a local sweep's: its processes go on to solve
    the sweep's other settings) that the segments run on in place of a pool of the feed's own;
    ``jobs`` is then its number of processes. The feed never shuts it down; on an error it
    cancels its own segments that have not started.
    """

    def __init__(
        self,
        params: DetectParams,
        job_of: Callable[[RecordedMessage], FrameJob | None],
        jobs: int = 1,
        cached: list[DetectedFrame] | None = None,
        keep: bool = True,
        executor: Executor | None = None,
    ):
        self.params = params
        self.job_of = job_of
        self.jobs = max(1, int(jobs))
        self.cached = cached
        self.keep = keep
        self.frames: list[DetectedFrame] = []
        # Called once, with every frame's DetectedFrame in order (``keep``), as soon as the last
        # segment is back — before the replay has taken them all (a sweep stores its lead's
        # detections then, and its other settings start solving from them).
        self.on_complete: Callable[[list[DetectedFrame]], None] | None = None
        self.cache_mismatch = ""  # why the cached detections were abandoned part-way, if they were
        self.keyframes = 0  # frames handed out that had a full detection
        self.tracked_frames = 0  # frames handed out whose codes were tracked
        self._pool: Executor | None = None
        self._executor = executor  # the caller's pool, or None: the feed starts its own
        self._submitted: list[Future] = []  # segments sent to the caller's pool

    # -- the pool -----------------------------------------------------------------------------
    def start(self) -> None:
        """Start the worker processes (call early: they import OpenCV while the run starts)."""
        if self.jobs > 1 and self._pool is None and self.cached is None:
            if self._executor is not None:
                self._pool = self._executor
            else:
                self._pool = ProcessPoolExecutor(self.jobs, mp_context=pool_context(), initializer=init_worker)

    def close(self, cancel: bool = False) -> None:
        """Stop the workers; ``cancel`` (an error or Ctrl-C): drop queued segments and end the
        running ones at once rather than waiting seconds for them."""
        if self._pool is None:
            return
        pool, self._pool = self._pool, None
        if pool is self._executor:  # the caller's: left running, only this feed's segments dropped
            if cancel:
                for future in self._submitted:
                    future.cancel()
            self._submitted = []
            return
        if cancel:
            processes = list(getattr(pool, "_processes", {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for process in processes:
                process.terminate()
            for process in processes:
                process.join(timeout=5)
        else:
            pool.shutdown(wait=True)

    def __enter__(self) -> "DetectionFeed":
        self.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(cancel=exc_type is not None)

    def _submit(self, segment: _Segment) -> None:
        if self._pool is None:
            future: Future = Future()
            future.set_result(detect_segment(self.params, segment.jobs))
        else:
            future = self._pool.submit(detect_segment, self.params, segment.jobs)
            if self._pool is self._executor:
                self._submitted = [f for f in self._submitted if not f.done()] + [future]
        segment.future = future

    @staticmethod
    def _result(segment: _Segment) -> list[FrameDetections]:
        try:
            return segment.future.result()
        except BrokenProcessPool as exc:
            raise RunError(
                f"a detection worker process died ({exc}); if the machine ran out of memory, "
                "run again with fewer workers (--jobs)"
            ) from None

    # -- the stream ---------------------------------------------------------------------------
    def annotate(self, messages: Iterable[RecordedMessage]) -> Iterator[tuple[RecordedMessage, FrameDetections | None]]:
        for message, detections in self._annotate(messages):
            if detections is not None:
                self.keyframes += detections.keyframe
                self.tracked_frames += not detections.keyframe
            yield message, detections

    def _annotate(self, messages: Iterable[RecordedMessage]):
        if self.cached is not None:
            yield from self._from_cache(messages)
            return
        self.start()
        stream = iter(messages)
        pending: deque[tuple[RecordedMessage, FrameJob | None, _Segment | None, int]] = deque()
        filling: dict[str, _Segment] = {}
        in_flight: deque[_Segment] = deque()
        max_in_flight = 2 * self.jobs + 1
        seq = 0
        exhausted = False

        def close_segment(cam_name: str) -> None:
            segment = filling.pop(cam_name)
            self._submit(segment)
            in_flight.append(segment)

        while True:
            # Read ahead while the head cannot be handed out yet or the pool has room.
            while not exhausted:
                head_waits = bool(pending) and pending[0][2] is not None and pending[0][2].future is None
                if not head_waits and (len(in_flight) >= max_in_flight or len(pending) >= MAX_READ_AHEAD):
                    break
                if head_waits and len(pending) >= MAX_READ_AHEAD:
                    close_segment(pending[0][2].cam_name)  # a slow camera: cut its segment here
                    break
                message = next(stream, None)
                if message is None:
                    exhausted = True
                    for cam_name in list(filling):
                        close_segment(cam_name)
                    break
                job = self.job_of(message) if isinstance(message.value, CompressedFrame) else None
                if job is None:
                    pending.append((message, None, None, -1))
                    continue
                segment = filling.setdefault(job.cam_name, _Segment(job.cam_name))
                segment.jobs.append(job)
                pending.append((message, job, segment, len(segment.jobs) - 1))
                if len(segment.jobs) >= self.params.segment_frames:
                    close_segment(job.cam_name)
            if not pending:
                return
            if self.on_complete is not None and exhausted and not filling and all(s.future.done() for s in in_flight):
                self._complete(seq, pending)
            message, job, segment, position = pending.popleft()
            if segment is None:
                yield message, None
                continue
            if segment.future is None:  # cannot happen: the loop above closes it first
                close_segment(segment.cam_name)
            detections = self._result(segment)[position]
            if position == len(segment.jobs) - 1:
                in_flight.remove(segment)
            if self.keep:
                self.frames.append(DetectedFrame(seq, job.cam_name, message.time_ns, detections))
            seq += 1
            yield message, detections

    def _complete(self, seq: int, pending) -> None:
        """Every segment is back: hand :attr:`on_complete` the frames handed out so far and
        those still waiting in ``pending`` (numbered from ``seq``), unless a segment failed
        (its error is raised where the replay takes that frame)."""
        on_complete, self.on_complete = self.on_complete, None
        if not self.keep or any(s.future.exception() is not None for _, _, s, _ in pending if s is not None):
            return
        waiting = [(message, job, segment, position)
                   for message, job, segment, position in pending if segment is not None]
        on_complete(self.frames + [
            DetectedFrame(seq + k, job.cam_name, message.time_ns, segment.future.result()[position])
            for k, (message, job, segment, position) in enumerate(waiting)
        ])

    def _from_cache(self, messages: Iterable[RecordedMessage]):
        """Cached detections handed out in order; a frame that does not match its record (it
        cannot, for a cache keyed by the recording's content, unless the cache was damaged)
        ends the cache's use: that frame and the rest are detected here."""
        records = iter(self.cached)
        detectors: dict = {}
        from agvviz.replay.detect.stage import SegmentDetector

        for message in messages:
            job = self.job_of(message) if isinstance(message.value, CompressedFrame) else None
            if job is None:
                yield message, None
                continue
            record = None if self.cache_mismatch else next(records, None)
            if record is not None and (record.cam_name, record.log_time_ns) == (job.cam_name, message.time_ns):
                yield message, record.detections
                continue
            if not self.cache_mismatch:
                self.cache_mismatch = (
                    "the detection cache did not match the recording at "
                    f"{job.cam_name} t={message.time_ns} ns; the rest was detected again"
                )
            detector = detectors.setdefault(job.cam_name, SegmentDetector(self.params))
            yield message, detector.detect(job)
