"""Solver-level types: what one solver step reports, shared by every solver and by the frame
results that carry it (:mod:`agvviz.model.frames`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LmIteration:
    """One Levenberg–Marquardt iteration: cost ½‖f‖² of the chosen objective after the
    step, the RMS reprojection error in pixels, the damping λ and the step norm."""

    cost: float
    reproj_rms_px: float
    damping: float
    step_norm: float
    accepted: bool
