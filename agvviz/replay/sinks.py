"""The sink protocol: the callbacks :class:`agvviz.replay.graph.ReplayGraph` makes to whatever
records a run — the ``.rrd`` logger, the statistics and summary, the audit's collector, a
detect-only count. Sinks are handed values (frozen camera snapshots, stage outputs), never a
stage object; they decide nothing about a pose. The concrete sinks live above the replay
(:mod:`agvviz.app.run`, :mod:`agvviz.evaluation.summary`, :mod:`agvviz.app.audit_collect`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Protocol, Sequence

import numpy as np

from agvviz.model.frames import FrameResult
from agvviz.model.detections import FrameDetections
from agvviz.model.cameras import CameraState
from agvviz.model.suspects import RunFinding


@dataclass(frozen=True)
class UwbSetup:
    """The UWB installation the fuse stage tracks with, handed with each fused item once it
    is known: anchor id → position (m, world), and the tag's height above the body origin."""

    anchors_m: Mapping[str, np.ndarray]
    tag_z_m: float | None


@dataclass(frozen=True)
class GraphOutcome:
    """What a graph run found besides what its sinks were handed."""

    has_uwb: bool = False  # the fuse stage started UWB tracking (anchors and tag mount known)
    corrected: bool = False  # the correct stage ran
    #: the check stage's findings about the whole run (e.g. a camera's stamp offset), each covering
    #: frames the sinks were handed before (their FrameResults keep their own suspects)
    findings: tuple[RunFinding, ...] = ()


class Sink(Protocol):
    """What the graph calls, in file order. A sink implements every callback; :class:`NullSink`
    is a base whose callbacks do nothing."""

    def cameras_changed(self, cameras: Mapping[str, CameraState]) -> None:
        """The cameras' calibration and extrinsic changed (first call: before any message)."""

    def detected(self, detections: FrameDetections) -> None:
        """A frame's detect-stage output (detect-only graphs)."""

    def solved(self, frame: FrameResult, detections: FrameDetections | None) -> None:
        """Every solve-stage result, with the detections it was solved from (None: detected in
        the solve stage itself)."""

    def frame(self, frame: FrameResult) -> None:
        """A frame logged and scored on its own (one that could not be placed in time)."""

    def fused(self, item: Any, uwb: UwbSetup | None) -> None:
        """An output of the fuse stage: a time stamp's frames (:class:`~agvviz.replay.fuse.FrameSetResult`),
        a UWB range or fix; ``uwb`` once UWB tracking has started."""

    def corrected(self, step: Any) -> None:
        """A correct-stage step (:class:`~agvviz.replay.correct.CorrectionStep`)."""

    def study(self, outcome: Any) -> None:
        """A study's outcome (every trial solved and scored)."""

    def finished(self, outcome: GraphOutcome) -> None:
        """Every message went through the stages (the graph's last call); ``outcome.findings``
        the check stage's run-level findings, over frames handed before."""

    def close(self) -> None:
        """The run is over (called by whoever made the sink, after the graph ran)."""


class NullSink:
    """A sink that ignores every callback: the base of sinks that listen to a few."""

    def cameras_changed(self, cameras: Mapping[str, CameraState]) -> None:
        pass

    def detected(self, detections: FrameDetections) -> None:
        pass

    def solved(self, frame: FrameResult, detections: FrameDetections | None) -> None:
        pass

    def frame(self, frame: FrameResult) -> None:
        pass

    def fused(self, item: Any, uwb: UwbSetup | None) -> None:
        pass

    def corrected(self, step: Any) -> None:
        pass

    def study(self, outcome: Any) -> None:
        pass

    def finished(self, outcome: GraphOutcome) -> None:
        pass

    def close(self) -> None:
        pass


class FanOut:
    """Several sinks as one: each callback goes to every sink, in the given order."""

    def __init__(self, sinks: Sequence[Sink]):
        self.sinks = tuple(sinks)

    def cameras_changed(self, cameras: Mapping[str, CameraState]) -> None:
        for sink in self.sinks:
            sink.cameras_changed(cameras)

    def detected(self, detections: FrameDetections) -> None:
        for sink in self.sinks:
            sink.detected(detections)

    def solved(self, frame: FrameResult, detections: FrameDetections | None) -> None:
        for sink in self.sinks:
            sink.solved(frame, detections)

    def frame(self, frame: FrameResult) -> None:
        for sink in self.sinks:
            sink.frame(frame)

    def fused(self, item: Any, uwb: UwbSetup | None) -> None:
        for sink in self.sinks:
            sink.fused(item, uwb)

    def corrected(self, step: Any) -> None:
        for sink in self.sinks:
            sink.corrected(step)

    def study(self, outcome: Any) -> None:
        for sink in self.sinks:
            sink.study(outcome)

    def finished(self, outcome: GraphOutcome) -> None:
        for sink in self.sinks:
            sink.finished(outcome)

    def close(self) -> None:
        for sink in self.sinks:
            sink.close()
