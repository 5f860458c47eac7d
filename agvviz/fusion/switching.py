"""Camera-primary switching: :class:`CameraOnly` and paper 003's :class:`MeanCompensation`.

Paper 003 §2.3: the camera fix is the AGV's position whenever a camera sees the marker; when
the cameras are blocked the UWB fixes take over, corrected by the offset between the two at
the moment of the switch (eqs 13–16):

    (x_c, y_c) = mean of the last three camera fixes                 (eqs 13, 14)
    (x_u, y_u) = mean of the last three UWB fixes (same moment)
    (δx, δy)   = (x_c − x_u, y_c − y_u)                               (eq 15)
    (x_r, y_r) = (x_m + δx, y_m + δy) for every later UWB fix         (eq 16)

At 0.2 m/s the three fixes of each sensor are taken as one position (the paper's argument).
The switch back to the camera happens at its first fix. Each switch is a :class:`SwitchEvent`
with the offset and the fused position's jump.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from agvviz.fusion.common import FusedFix, FusionStep, SwitchEvent, UwbPosition

#: Number of fixes of each sensor averaged for the offset (paper 003: three).
COMPENSATION_FIXES = 3


class CameraOnly:
    """The camera fixes as they come; UWB is ignored (nothing is output while blocked)."""

    def camera(self, log_time_ns: int, position_xy_m: np.ndarray | None) -> FusionStep:
        if position_xy_m is None:
            return FusionStep()
        return FusionStep(FusedFix(int(log_time_ns), np.asarray(position_xy_m, float)[:2].copy(), "camera"))

    def uwb_fix(self, fix: UwbPosition) -> FusionStep:
        return FusionStep()

    def uwb_range(self, log_time_ns: int, anchor_id: str, range_m: float) -> FusionStep:
        return FusionStep()


class MeanCompensation:
    """Paper 003's switching with mean compensation (module docstring)."""

    def __init__(self):
        self._camera: deque[np.ndarray] = deque(maxlen=COMPENSATION_FIXES)
        self._uwb: deque[np.ndarray] = deque(maxlen=COMPENSATION_FIXES)
        self._source = "camera"
        self._offset_m = np.zeros(2)
        self._last_output: np.ndarray | None = None
        self._switch_pending = False  # camera lost; the switch happens at the next UWB fix

    @property
    def offset_m(self) -> np.ndarray:
        """The current compensation offset (δx, δy)."""
        return self._offset_m.copy()

    def camera(self, log_time_ns: int, position_xy_m: np.ndarray | None) -> FusionStep:
        if position_xy_m is None:
            if self._source == "camera":
                self._switch_pending = True
            return FusionStep()
        xy = np.asarray(position_xy_m, dtype=float)[:2].copy()
        step = FusionStep(FusedFix(int(log_time_ns), xy, "camera"))
        self._switch_pending = False
        if self._source == "uwb":
            jump = float(np.linalg.norm(xy - self._last_output)) if self._last_output is not None else 0.0
            step.events.append(SwitchEvent(int(log_time_ns), "uwb", "camera", None, jump))
            self._source = "camera"
            self._camera.clear()  # the offset is computed from fixes after this switch only
            self._uwb.clear()
        self._camera.append(xy)
        self._last_output = xy
        return step

    def uwb_fix(self, fix: UwbPosition) -> FusionStep:
        xy = np.asarray(fix.position_m, dtype=float)[:2].copy()
        step = FusionStep()
        if self._source == "camera" and self._switch_pending:
            detail = (
                f"offset from the last {len(self._camera)} camera and {len(self._uwb)} UWB fixes"
            )
            if self._camera and self._uwb:
                self._offset_m = np.mean(self._camera, axis=0) - np.mean(self._uwb, axis=0)  # eqs 13–15
            else:
                self._offset_m = np.zeros(2)
                detail = "no camera/UWB fix before the switch: UWB used uncompensated"
            self._source = "uwb"
            self._switch_pending = False
            corrected = xy + self._offset_m  # eq 16
            jump = float(np.linalg.norm(corrected - self._last_output)) if self._last_output is not None else 0.0
            step.events.append(SwitchEvent(fix.log_time_ns, "camera", "uwb", self._offset_m.copy(), jump, detail))
        if self._source == "uwb":
            corrected = xy + self._offset_m
            step.fused = FusedFix(int(fix.log_time_ns), corrected, "uwb")
            self._last_output = corrected
        else:
            self._uwb.append(xy)
        return step

    def uwb_range(self, log_time_ns: int, anchor_id: str, range_m: float) -> FusionStep:
        return FusionStep()
