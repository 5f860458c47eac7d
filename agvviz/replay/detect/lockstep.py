"""Several runs of one recording in one pass (issue 27): a *lead* run reads the recording and
detects it; *follower* runs, in other threads of the same process, take each message with its
detections from the lead and only solve, under their own settings.

A sweep's settings that share their detection settings form one group
(:func:`agvviz.app.cluster.detection_groups`). Run one after the other, each follower would read
the recording again, read the detection cache and start its own process; in lockstep it costs
its solve, its checks and its logging, nothing else.

- :meth:`Lockstep.tee` wraps the lead's detect-stage feed: every ``(message, detections)`` it
  hands to the lead's graph is put, first, into each follower's queue; when the messages end,
  the lead's read report goes after them (the followers' summaries name the same damage).
- :meth:`Lockstep.follower` is a follower's feed, in place of its
  :class:`~agvviz.replay.detect.pool.DetectionFeed`: it hands out what the lead put in its queue.
  It refuses (:class:`LockstepMismatch`) a follower whose roles or clock differ from the lead's:
  the lead's messages are not the ones it would read.
- A lead that fails part-way ends its followers with :class:`LeadFailed`; they are to be run
  again on their own (the sweep does). A follower that ends — done, failed or refused — is
  :meth:`Lockstep.close`-d by its caller and the lead stops feeding it.

The queues hold at most :data:`MAX_QUEUED` messages each (the lead waits for the slowest
follower): memory stays flat however long the recording. Every message and its detections are
shared, not copied: nothing downstream of the detect stage changes them.
"""

from __future__ import annotations

import queue
import threading
from typing import Iterable, Iterator

from agvviz.errors import RunError
from agvviz.model.detections import FrameDetections
from agvviz.model.messages import RecordedMessage

#: Messages a follower's queue holds before the lead waits for it.
MAX_QUEUED = 64
#: How often a lead waiting on a full queue looks whether that follower has ended (seconds).
_PUT_POLL_S = 0.05

_END = object()  # the lead's messages ended (the value: its read report)
_ABORT = object()  # the lead stopped early


class LeadFailed(RunError):
    """The lead run of a lockstep group ended before its messages did: a follower has no more
    detections, and must be run on its own."""


class LockstepMismatch(RunError):
    """A follower's roles or clock differ from its lead's: it must be run on its own."""


class Lockstep:
    """One lead and ``followers`` followers (see the module docstring)."""

    def __init__(self, followers: int):
        self._queues = [queue.Queue(MAX_QUEUED) for _ in range(followers)]
        self._closed = [threading.Event() for _ in range(followers)]
        self._stream = threading.Event()  # set once the lead has said what it reads
        self._ended = False  # the lead's messages ended and the followers were told
        self.roles: dict | None = None
        self.time_source: str | None = None

    # -- the lead ---------------------------------------------------------------------------
    def tee(self, feed, roles: dict, time_source: str, read_report) -> "_TeeFeed":
        """The lead's detect-stage ``feed``, also feeding the followers; ``roles`` (role → topic)
        and ``time_source`` say which messages the lead reads, ``read_report`` is its read report
        (complete once the messages end)."""
        self.roles, self.time_source = dict(roles), time_source
        self._stream.set()
        return _TeeFeed(feed, self, read_report)

    def _put(self, item) -> None:
        for q, closed in zip(self._queues, self._closed):
            while not closed.is_set():
                try:
                    q.put(item, timeout=_PUT_POLL_S)
                    break
                except queue.Full:
                    continue

    def abort(self) -> None:
        """The lead ended early: its followers raise :class:`LeadFailed`."""
        self._stream.set()
        self._put((_ABORT, None))

    def lead_done(self) -> None:
        """The lead run has returned or raised: followers still waiting for messages that will
        not come (the lead failed before or while reading) raise :class:`LeadFailed`."""
        if not self._ended:
            self._ended = True
            self.abort()

    # -- a follower ---------------------------------------------------------------------------
    def follower(self, index: int, params, roles: dict, time_source: str) -> "FollowerFeed":
        """Follower ``index``'s feed (its detect parameters ``params``; its own ``roles`` and
        ``time_source``, checked against the lead's when the messages start)."""
        return FollowerFeed(self, index, params, dict(roles), time_source)

    def close(self, index: int) -> None:
        """Follower ``index`` has ended: the lead stops feeding it (and drops what is queued)."""
        self._closed[index].set()
        q = self._queues[index]
        while True:
            try:
                q.get_nowait()
            except queue.Empty:
                return


class _TeeFeed:
    """The lead's feed: its own detect-stage feed, each item also put into the followers' queues."""

    def __init__(self, inner, lockstep: Lockstep, read_report):
        self._inner, self._lockstep, self._read_report = inner, lockstep, read_report

    def __getattr__(self, name):  # params, frames, keyframes, … of the wrapped feed
        return getattr(self._inner, name)

    def __enter__(self) -> "_TeeFeed":
        self._inner.__enter__()
        return self

    def __exit__(self, exc_type, exc, tb):
        return self._inner.__exit__(exc_type, exc, tb)

    def annotate(self, messages: Iterable[RecordedMessage]) -> Iterator[tuple[RecordedMessage, FrameDetections | None]]:
        ended = False
        try:
            for item in self._inner.annotate(messages):
                self._lockstep._put(item)
                yield item
            ended = True
            self._lockstep._ended = True
            self._lockstep._put((_END, self._read_report))
        finally:
            if not ended:
                self._lockstep.lead_done()


class FollowerFeed:
    """A follower's detect-stage feed: the lead's messages and detections, in the lead's order.
    Has what a run reads of a :class:`~agvviz.replay.detect.pool.DetectionFeed` (``params``,
    ``keyframes``, ``tracked_frames``, ``jobs``, ``cache_mismatch``, ``frames``);
    :attr:`read_report` is the lead's, once the messages have ended."""

    def __init__(self, lockstep: Lockstep, index: int, params, roles: dict, time_source: str):
        self._lockstep, self._index = lockstep, index
        self.params = params
        self._roles, self._time_source = roles, time_source
        self.jobs = 0
        self.cached = None
        self.cache_mismatch = ""
        self.frames: list = []
        self.keyframes = 0
        self.tracked_frames = 0
        self.read_report = None

    def __enter__(self) -> "FollowerFeed":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self._lockstep.close(self._index)

    def annotate(self, messages: Iterable[RecordedMessage]) -> Iterator[tuple[RecordedMessage, FrameDetections | None]]:
        """The lead's ``(message, detections)``; ``messages`` (this run's own reading of the
        recording) is not read."""
        lockstep = self._lockstep
        lockstep._stream.wait()
        if lockstep.roles is not None and (lockstep.roles, lockstep.time_source) != (self._roles, self._time_source):
            lockstep.close(self._index)
            raise LockstepMismatch(
                "this setting reads other topics or another clock than its detection group's first setting"
            )
        q = lockstep._queues[self._index]
        while True:
            kind, value = q.get()
            if kind is _END:
                self.read_report = value
                return
            if kind is _ABORT:
                lockstep.close(self._index)
                raise LeadFailed("the first setting of this detection group stopped before the recording ended")
            if value is not None:
                self.keyframes += value.keyframe
                self.tracked_frames += not value.keyframe
            yield kind, value
