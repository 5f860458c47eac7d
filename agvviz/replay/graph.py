"""The replay graph, composed once from the settings and driven over a recording's messages.

    source ──► sync ──► detect ──► solve ──► fuse ──► correct ──► sinks
    (readers,  (calibration,  (corners,   (pose and     (camera fixes  (multi-frame   (.rrd, statistics,
     roles)     transforms,    ids,        its           + UWB)         windows)       summary)
                truth)         payloads)   diagnostics)

* source — :mod:`agvviz.recording.source` (readers, role map) opened by :func:`agvviz.replay.run.prepare`;
* sync — :class:`agvviz.replay.sync.SyncState`, filled by a first pass over the non-image messages;
* detect — :mod:`agvviz.replay.detect.stage` (frame → :class:`~agvviz.replay.detect.stage.FrameDetections`),
  computed ahead by :class:`agvviz.replay.detect.pool.DetectionFeed` or read from the cache;
* solve — :class:`agvviz.replay.solve.Replay` (detections → :class:`~agvviz.model.frames.FrameResult`);
* fuse — :class:`agvviz.replay.fuse.FusionReplay`;
* correct — :class:`agvviz.replay.correct.CorrectionReplay` (when ``correction`` is not ``none``);
* sinks — :class:`agvviz.replay.sinks.RunSinks`.

Messages flow in file order; every stage sees every message (a stage ignores what is not its
own) plus what the stage before it made of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

from agvviz.replay.correct import CorrectionReplay, CorrectionSettings
from agvviz.replay.detect.pool import DetectionFeed
from agvviz.replay.fuse import FusionReplay
from agvviz.replay.sinks import RunSinks
from agvviz.replay.solve import Replay
from agvviz.model.frames import REJECT_TIME
from agvviz.model.messages import CalibrationMsg, RecordedMessage
from agvviz.settings import RunSettings


@dataclass
class ReplayGraph:
    """The stages of one run, wired. Build it with :meth:`compose`, then :meth:`run`."""

    detect: DetectionFeed
    solve: Replay
    fuse: FusionReplay
    correct: CorrectionReplay | None
    sinks: RunSinks

    @classmethod
    def compose(cls, settings: RunSettings, detect: DetectionFeed, solve: Replay, sinks: RunSinks) -> "ReplayGraph":
        """The stages ``settings`` ask for, sharing the sync stage's camera state."""
        correct = None
        if settings.correction != "none":
            correct = CorrectionReplay(
                CorrectionSettings(
                    solver=settings.correction, update=settings.cnoem_update,
                    cycle_distance_m=settings.cycle_distance_m, max_reproj_px=settings.max_reproj_px,
                ),
                solve.ctx.cameras,
                solve.sync,
            )
        return cls(detect, solve, FusionReplay(settings, solve.ctx.cameras, solve.sync), correct, sinks)

    def run(self, messages: Iterable[RecordedMessage]) -> None:
        """Drive every message through the stages, in file order, then flush them."""
        self.sinks.cameras_changed()
        with self.detect as feed:
            for message, detections in feed.annotate(messages):
                self._step(message, self.solve.feed(message, detections))
        for item in self.fuse.finish():
            self.sinks.fused(item, self.fuse)
        if self.correct is not None:
            for step in self.correct.finish():
                self.sinks.corrected(step)

    def _step(self, message: RecordedMessage, frame) -> None:
        if frame is not None and frame.rejected == REJECT_TIME:
            # A frame that cannot be placed in time (repeated or reversed time stamp) is logged
            # and counted on its own, never grouped with the frames of its time stamp.
            self.sinks.frame(frame)
            frame = None
        if frame is not None or isinstance(message.value, (CalibrationMsg, list)):
            self.sinks.cameras_changed()
        for item in self.fuse.feed(message, frame):
            self.sinks.fused(item, self.fuse)
        if self.correct is not None:
            for step in self.correct.feed(message, frame):
                self.sinks.corrected(step)
