"""The correct stage's values (paper 002 §1.2): marker sightings, closed cycles and replay steps.

Produced by :class:`agvviz.replay.correct.CorrectionCycle` and
:class:`agvviz.replay.correct.CorrectionReplay`, read by the correction logger
(:mod:`agvviz.viz.log_correction`) and the run statistics. Frozen: each is built complete.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agvviz.solvers.cnoem import CornerWindow, WindowSolution


@dataclass(frozen=True)
class FrameSighting:
    """One marker in one camera image: ``pixels_px`` (P, 2) in the IDEAL image of matrix ``K``."""

    marker_id: str
    cam_name: str
    points_world_m: np.ndarray
    pixels_px: np.ndarray
    K: np.ndarray


@dataclass(frozen=True)
class CorrectionEvent:
    """A closed cycle.

    reason : "" when a correction was applied, else why not.
    T_world_F_before / after : the start frame by the (corrected) navigation / by the solver.
    T_world_G_before / after : the current pose before and after the correction.
    jump_m : ‖after − before‖ of the current position (0 without a correction).
    """

    log_time_ns: int
    cycle_index: int
    n_frames: int
    n_sightings: int
    reason: str
    T_world_F_before: np.ndarray
    T_world_F_after: np.ndarray | None
    T_world_G_before: np.ndarray
    T_world_G_after: np.ndarray
    jump_m: float
    position_sigma_m: float | None = None
    window: CornerWindow | None = None
    solution: WindowSolution | None = None
    frame_times_ns: list[int] = field(default_factory=list)

    @property
    def applied(self) -> bool:
        return self.reason == ""


@dataclass(frozen=True)
class CorrectionStep:
    """One frame time of the replay: raw and corrected navigation, truth (if recorded), and the
    event when a cycle closed here."""

    log_time_ns: int
    T_world_agv_nav: np.ndarray
    T_world_agv_corrected: np.ndarray
    T_world_agv_truth: np.ndarray | None
    sightings: list[FrameSighting]
    event: CorrectionEvent | None
