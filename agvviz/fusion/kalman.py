"""Constant-velocity Kalman filter fusing camera fixes and UWB ranges. Numpy only.

State ``s = (x, y, vx, vy, b_1 … b_N)``: the AGV's horizontal position and velocity (world
metres) and one range bias per anchor (metres; clock drift in single-sided TWR, antenna delay,
a wall the signal goes through). The ranges themselves are the UWB measurements (tightly
coupled), ``r_i = ‖(x, y, z_tag) − a_i‖ + b_i + noise``, so while a camera sees the marker the
filter learns every link's bias, and when the cameras are blocked it carries that knowledge
over — per link, where paper 003's mean compensation carries one offset for the position.

Updates are gated on the Mahalanobis distance of the innovation, ``ν² / S`` (1 dof for a
range, ``νᵀS⁻¹ν`` with 2 dof for a camera fix), against a χ² bound. A gated range is skipped
(NLOS); ``camera_reset_after`` camera fixes gated in a row re-initialise the position on the
camera (the filter had drifted, not the camera).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.fusion.common import FusedFix, FusionStep, SwitchEvent, UwbPosition


@dataclass(frozen=True)
class KalmanSettings:
    """accel_sigma_mps2 : white-acceleration noise (m/s² per √s) of the constant-velocity model.
    camera_sigma_m : camera fix standard deviation per axis.
    range_sigma_m : UWB range noise standard deviation.
    bias_walk_m_per_sqrt_s : random walk of each range bias.
    initial_bias_sigma_m : prior standard deviation of each bias.
    range_gate_chi2 : gate bound on ν²/S for a range (1 dof).
    camera_gate_chi2 : gate bound on νᵀS⁻¹ν for a camera fix (2 dof).
    camera_reset_after : consecutive gated camera fixes that re-initialise the position.
    """

    accel_sigma_mps2: float = 0.2
    camera_sigma_m: float = 0.005
    range_sigma_m: float = 0.05
    bias_walk_m_per_sqrt_s: float = 0.002
    initial_bias_sigma_m: float = 0.3
    range_gate_chi2: float = 9.0
    camera_gate_chi2: float = 13.8
    camera_reset_after: int = 3


class KalmanFusion:
    """The filter of the module docstring; feed it in time order."""

    def __init__(self, anchors_m: dict[str, np.ndarray], tag_z_m: float, settings: KalmanSettings = KalmanSettings()):
        self.settings = settings
        self.anchor_ids = sorted(anchors_m)
        self.anchors_m = np.array([np.asarray(anchors_m[a], dtype=float) for a in self.anchor_ids])
        self.tag_z_m = float(tag_z_m)
        n = 4 + len(self.anchor_ids)
        self.state = np.zeros(n)
        self.P = np.zeros((n, n))
        self._t_ns: int | None = None
        self._initialised = False
        self._source = "camera"
        self._camera_gated = 0

    # -- model ------------------------------------------------------------------------------
    def _initialise(self, log_time_ns: int, xy: np.ndarray, position_sigma_m: float) -> None:
        s = self.settings
        self.state[:] = 0.0
        self.state[:2] = xy
        self.P[:] = 0.0
        self.P[0, 0] = self.P[1, 1] = position_sigma_m**2
        self.P[2, 2] = self.P[3, 3] = 0.5**2  # up to ~1 m/s from rest
        for k in range(len(self.anchor_ids)):
            self.P[4 + k, 4 + k] = s.initial_bias_sigma_m**2
        self._t_ns = int(log_time_ns)
        self._initialised = True

    def _predict(self, log_time_ns: int) -> None:
        dt = max((int(log_time_ns) - self._t_ns) * 1e-9, 0.0)
        self._t_ns = max(int(log_time_ns), self._t_ns)
        if dt == 0.0:
            return
        n = self.state.size
        F = np.eye(n)
        F[0, 2] = F[1, 3] = dt
        q = self.settings.accel_sigma_mps2**2
        Q = np.zeros((n, n))
        for pos, vel in ((0, 2), (1, 3)):
            Q[pos, pos] = q * dt**3 / 3.0
            Q[pos, vel] = Q[vel, pos] = q * dt**2 / 2.0
            Q[vel, vel] = q * dt
        for k in range(4, n):
            Q[k, k] = self.settings.bias_walk_m_per_sqrt_s**2 * dt
        self.state = F @ self.state
        self.P = F @ self.P @ F.T + Q

    def _update(self, innovation: np.ndarray, H: np.ndarray, R: np.ndarray, bound: float) -> bool:
        """Gated update; True when applied."""
        S = H @ self.P @ H.T + R
        d2 = float(innovation @ np.linalg.solve(S, innovation))
        if d2 > bound:
            return False
        K = self.P @ H.T @ np.linalg.inv(S)
        self.state = self.state + K @ innovation
        I_KH = np.eye(self.state.size) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T  # Joseph form: stays symmetric PSD
        return True

    def _fused(self, log_time_ns: int) -> FusedFix:
        return FusedFix(int(log_time_ns), self.state[:2].copy(), "kalman")

    # -- inputs -----------------------------------------------------------------------------
    def camera(self, log_time_ns: int, position_xy_m: np.ndarray | None) -> FusionStep:
        if position_xy_m is None:
            step = FusionStep()
            if self._initialised and self._source == "camera":
                self._source = "uwb"
                step.events.append(
                    SwitchEvent(int(log_time_ns), "camera", "uwb", None, 0.0, "camera lost: ranges only, biases held")
                )
            return step
        xy = np.asarray(position_xy_m, dtype=float)[:2]
        s = self.settings
        if not self._initialised:
            self._initialise(log_time_ns, xy, s.camera_sigma_m)
            return FusionStep(self._fused(log_time_ns))
        self._predict(log_time_ns)
        before = self.state[:2].copy()
        H = np.zeros((2, self.state.size))
        H[0, 0] = H[1, 1] = 1.0
        applied = self._update(xy - before, H, np.eye(2) * s.camera_sigma_m**2, s.camera_gate_chi2)
        step = FusionStep()
        detail = ""
        if applied:
            self._camera_gated = 0
        else:
            self._camera_gated += 1
            if self._camera_gated < s.camera_reset_after:
                return step
            # The filter, not the camera, is wrong: keep the biases' knowledge, restart the
            # position on the camera.
            biases, bias_P = self.state[4:].copy(), self.P[4:, 4:].copy()
            self._initialise(log_time_ns, xy, s.camera_sigma_m)
            self.state[4:], self.P[4:, 4:] = biases, bias_P
            self._camera_gated = 0
            detail = f"{s.camera_reset_after} camera fixes gated in a row: position re-initialised"
        if self._source == "uwb" or detail:
            jump = float(np.linalg.norm(self.state[:2] - before))
            step.events.append(SwitchEvent(int(log_time_ns), self._source, "camera", None, jump, detail))
            self._source = "camera"
        step.fused = self._fused(log_time_ns)
        return step

    def uwb_fix(self, fix: UwbPosition) -> FusionStep:
        if not self._initialised:
            # No camera yet: start from the first UWB fix (biases unknown).
            self._initialise(fix.log_time_ns, np.asarray(fix.position_m)[:2], 0.3)
            self._source = "uwb"
            return FusionStep(self._fused(fix.log_time_ns))
        return FusionStep()

    def uwb_range(self, log_time_ns: int, anchor_id: str, range_m: float) -> FusionStep:
        if not self._initialised or anchor_id not in self.anchor_ids:
            return FusionStep()
        self._predict(log_time_ns)
        k = self.anchor_ids.index(anchor_id)
        position = np.array([self.state[0], self.state[1], self.tag_z_m])
        diff = position - self.anchors_m[k]
        distance = max(float(np.linalg.norm(diff)), 1e-9)
        H = np.zeros((1, self.state.size))
        H[0, :2] = diff[:2] / distance
        H[0, 4 + k] = 1.0
        predicted = distance + self.state[4 + k]
        s = self.settings
        passed = self._update(
            np.array([range_m - predicted]), H, np.array([[s.range_sigma_m**2]]), s.range_gate_chi2
        )
        return FusionStep(self._fused(log_time_ns), range_gate={anchor_id: passed})
