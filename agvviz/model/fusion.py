"""The fuse stage's values (paper 003): a time stamp's camera fix, one UWB range, one UWB fix.

Produced by :class:`agvviz.replay.fuse.FusionReplay` (and :func:`agvviz.replay.multicam.select_camera_fix`
for :class:`CameraSelection`), read by the UWB logger (:mod:`agvviz.viz.log_uwb`) and the
fusion statistics (:mod:`agvviz.evaluation.fusion_summary`). Frozen: each is built complete.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agvviz.fusion import FusionStep
from agvviz.model.frames import FrameResult
from agvviz.uwb import UwbFix


@dataclass(frozen=True)
class CameraSelection:
    """The outcome of one time stamp: ``primary`` (None when no camera solved), the cameras
    that solved and those whose corners made the fix (``used``), and the time stamp's
    ``frames`` as the fix leaves them (a joint fix replaces the primary's pose and errors and
    every frame's reprojected corners; frames are immutable, so these are new frames)."""

    primary: FrameResult | None
    solved: list[str] = field(default_factory=list)
    used: list[str] = field(default_factory=list)
    note: str = ""
    frames: list[FrameResult] = field(default_factory=list)


@dataclass(frozen=True)
class FrameSetResult:
    """The frames of one time stamp, the camera fix made of them and what fusion did with it.

    ``scored`` is the frame that stands for the time stamp in statistics and plots: the primary
    (chosen) frame, or the first frame when no camera solved.
    """

    frames: list[FrameResult]
    selection: CameraSelection
    step: FusionStep
    camera_available: bool
    fused_error_m: float | None = None  # 2-D error of step.fused against truth

    @property
    def scored(self) -> FrameResult:
        return self.selection.primary if self.selection.primary is not None else self.frames[0]


@dataclass(frozen=True)
class RangeResult:
    """One UWB range: the recorded ``range_m``, eq 1 on its timestamps, ranges predicted from
    the true pose and from the current estimate, and the Kalman gate's verdict (if any)."""

    log_time_ns: int
    anchor_id: str
    range_m: float
    tof_range_m: float
    predicted_truth_m: float | None
    predicted_estimate_m: float | None
    step: FusionStep
    camera_available: bool
    fused_error_m: float | None = None


@dataclass(frozen=True)
class UwbFixResult:
    """One UWB fix, its 2-D error against truth (when known) and what fusion did with it."""

    fix: UwbFix
    truth_xy_m: np.ndarray | None
    step: FusionStep
    camera_available: bool
    fused_error_m: float | None = None

    @property
    def error_m(self) -> float | None:
        if self.truth_xy_m is None:
            return None
        return float(np.linalg.norm(self.fix.position_m[:2] - self.truth_xy_m))
