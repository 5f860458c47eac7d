"""Run statistics and the run summary: counts, rejections, errors against truth, timing.

:class:`RunStatistics` is the graph's statistics sink (:class:`agvviz.replay.sinks.Sink`): the
pipeline's :class:`~agvviz.model.frames.FrameResult` s are reduced to small :class:`FrameScore`
records as they stream past, so memory does not grow with images; UWB fusion, correction and a
study's outcome are counted beside them. :meth:`RunStatistics.summary` is the one place a run's
summary is assembled (it is stored in the run ``.rrd`` and printed by ``agvviz run``).
:func:`summarize` depends only on the data (the ``.rrd`` must be reproducible); :func:`timing`
holds the wall-clock figures, which are printed, never stored.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Callable

import numpy as np

from agvviz.evaluation.fusion_summary import FusionStats
from agvviz.model.frames import FrameResult
from agvviz.model.suspects import Suspect
from agvviz.replay.checks import suspects_summary
from agvviz.replay.correct import CorrectionStats
from agvviz.replay.fuse import FrameSetResult
from agvviz.replay.sinks import GraphOutcome, NullSink
from agvviz.settings import RunSettings


@dataclass(frozen=True)
class CheckedFrame:
    """What the suspects' summary needs of one solve-stage frame (:func:`agvviz.replay.checks.suspects_summary`)."""

    index: int
    cam_name: str
    solved: bool
    suspect: Suspect | None


@dataclass(frozen=True)
class FrameScore:
    """What a summary needs of one frame."""

    index: int
    rejected: str | None
    position_error_m: float | None
    heading_error_deg: float | None
    reproj_rms_px: float | None
    total_s: float
    detect_s: float
    solve_s: float
    pitch_error_deg: float | None = None
    roll_error_deg: float | None = None

    @classmethod
    def of(cls, frame: FrameResult) -> "FrameScore":
        return cls(
            index=frame.index,
            rejected=frame.rejected,
            position_error_m=frame.position_error_m,
            heading_error_deg=frame.heading_error_deg,
            reproj_rms_px=frame.reproj_rms_px,
            total_s=frame.total_s,
            detect_s=frame.detect_s,
            solve_s=frame.solve_s,
            pitch_error_deg=frame.pitch_error_deg,
            roll_error_deg=frame.roll_error_deg,
        )


def _stats(values: np.ndarray, scale: float) -> dict:
    if values.size == 0:
        return {"rmse": None, "median": None, "p95": None, "max": None, "n": 0}
    v = np.abs(values) * scale
    return {
        "rmse": float(np.sqrt(np.mean(v**2))),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(np.max(v)),
        "n": int(v.size),
    }


def summarize(scores: list[FrameScore]) -> dict:
    """Summary of a run: frames, solved, rejected by reason, and the statistics (RMSE, median,
    p95, max of the absolute value) of the position (mm), heading, pitch and roll (deg) errors
    and of the reprojection RMS (px) over the solved frames. No wall-clock figures."""
    solved = [s for s in scores if s.rejected is None]

    def values(attr: str) -> np.ndarray:
        return np.array([getattr(s, attr) for s in solved if getattr(s, attr) is not None], dtype=float)

    return {
        "frames": len(scores),
        "solved": len(solved),
        "rejected": dict(sorted(Counter(s.rejected for s in scores if s.rejected).items())),
        "position_error_mm": _stats(values("position_error_m"), 1000.0),
        "heading_error_deg": _stats(values("heading_error_deg"), 1.0),
        "pitch_error_deg": _stats(values("pitch_error_deg"), 1.0),
        "roll_error_deg": _stats(values("roll_error_deg"), 1.0),
        "reproj_rms_px": _stats(values("reproj_rms_px"), 1.0),
    }


def timing(scores: list[FrameScore], wall_time_s: float | None = None) -> dict:
    """Wall-clock figures of a run: mean pipeline time per frame, detection and solve time (ms)
    and, given the run's wall time, throughput including logging (frames/s). ``None`` when
    there is no frame."""
    result = {
        "time_per_frame_ms": float(np.mean([s.total_s for s in scores]) * 1000.0) if scores else None,
        "detect_ms": float(np.mean([s.detect_s for s in scores]) * 1000.0) if scores else None,
        "solve_ms": float(np.mean([s.solve_s for s in scores]) * 1000.0) if scores else None,
    }
    if wall_time_s is not None and wall_time_s > 0:
        result["wall_time_s"] = float(wall_time_s)
        result["frames_per_s"] = len(scores) / wall_time_s
    return result


class RunStatistics(NullSink):
    """The statistics sink: every scored frame (the fuse stage's scored frame of each time
    stamp, and frames scored on their own), rejections, UWB fusion, correction steps and a
    study's outcome. ``progress(frames_done)`` is called per scored frame."""

    def __init__(self, settings: RunSettings, progress: Callable[[int], None] | None = None):
        self.settings = settings
        self.progress = progress
        self.scores: list[FrameScore] = []
        self.rejections: dict[str, list] = {}  # reason -> [count, first detail]
        self.fusion_stats = FusionStats()
        self.correction_stats = CorrectionStats()
        self.study_outcome = None
        self.outcome = GraphOutcome()
        self.checked: list[CheckedFrame] = []  # every solve-stage frame, for the suspects' summary

    def solved(self, frame: FrameResult, detections) -> None:
        self.checked.append(CheckedFrame(frame.index, frame.cam_name, frame.solved, frame.suspect))

    def frame(self, frame: FrameResult) -> None:
        self._score(frame)

    def fused(self, item, uwb) -> None:
        if isinstance(item, FrameSetResult):
            self._score(item.scored)
        if uwb is not None:
            self.fusion_stats.add(item)

    def corrected(self, step) -> None:
        self.correction_stats.add(step)

    def study(self, outcome) -> None:
        self.study_outcome = outcome

    def finished(self, outcome: GraphOutcome) -> None:
        self.outcome = outcome  # whether UWB was tracked, whether the correct stage ran, run-level findings

    def _score(self, frame: FrameResult) -> None:
        self.scores.append(FrameScore.of(frame))
        if frame.rejected is not None:
            self.rejections.setdefault(frame.rejected, [0, frame.reject_detail or ""])[0] += 1
        if self.progress is not None:
            self.progress(len(self.scores))

    def summary(
        self,
        *,
        recording_damage: list[str],
        warnings: list[str],
        detection: dict | None = None,
        truth: dict | None = None,
        error_budget: dict | None = None,
    ) -> dict:
        """The run summary (stored in the ``.rrd``, printed by the CLI). A study's: its own
        summary, the recording's damage and the warnings. A camera or correction run's: the
        frame statistics (none for a correction run without camera frames), ``suspects`` (the check
        stage's findings, per frame and about the whole run, :func:`agvviz.replay.checks.suspects_summary`)
        with camera frames, ``fusion`` with
        UWB, ``correction`` when the correct stage ran, then ``recording_damage``,
        ``detection``, ``warnings``, ``truth`` and, when given, ``error_budget``."""
        if self.study_outcome is not None:
            return {**self.study_outcome.summary, "recording_damage": list(recording_damage), "warnings": list(warnings)}
        settings = self.settings
        has_uwb, corrected = self.outcome.has_uwb, self.outcome.corrected
        summary = summarize(self.scores) if self.scores or not corrected else {}
        if self.checked:
            summary["suspects"] = suspects_summary(self.checked, checked=settings.checks == "on",
                                                   findings=self.outcome.findings)
        if has_uwb:
            summary["fusion"] = {"uwb": settings.uwb, "fusion": settings.fusion, **self.fusion_stats.summary()}
        if corrected:
            summary["correction"] = {"solver": settings.correction, **self.correction_stats.summary()}
        summary["recording_damage"] = list(recording_damage)
        summary["detection"] = detection
        summary["warnings"] = list(warnings)
        summary["truth"] = truth
        if error_budget is not None:
            summary["error_budget"] = error_budget
        return summary
