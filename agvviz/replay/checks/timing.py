"""The check stage's clock checks (mixed into :class:`agvviz.replay.checks.stage.CheckStage`):
a camera's stamps against its frame period, and its time offset against the odometry or, on a
rig, against another camera. See :mod:`agvviz.replay.checks`."""

from __future__ import annotations

import math

import numpy as np

from agvviz.geometry import so3
from agvviz.model.frames import FrameResult
from agvviz.model.suspects import CAUSE_TIME_OFFSET, CHECK_TIME, CheckResult
from agvviz.replay.checks.common import (
    ODOMETRY_OFFSET_MIN_S,
    ODOMETRY_OFFSET_MIN_STEPS,
    ODOMETRY_VELOCITY_NS,
    OFFSET_WEIGHT,
    TIME_JITTER_S,
    TIME_JITTER_SHARE,
    TIME_OFFSET_MAX_S,
    TIME_OFFSET_MIN_S,
    angle_deg,
    mahalanobis_sigma,
    pose_difference,
)


class ClockChecks:
    """The clock checks of :class:`~agvviz.replay.checks.stage.CheckStage` (it holds the state:
    ``settings``, ``odometry_at``, ``_twists`` and the per-camera ``_CameraState``)."""

    def _time_offset(self, frame: FrameResult, state, delta: np.ndarray) -> float | None:
        """The stamp offset (s, > 0: the pose lags) that explains a position disagreement ``delta``
        along the camera's own velocity, or None when it does not (the disagreement is across the
        motion, or the camera does not move)."""
        ref = state.reference
        if ref is None:
            return None
        dt = (frame.log_time_ns - ref.frame.log_time_ns) / 1e9
        if dt <= 0:
            return None
        v = (frame.T_world_agv[:3, 3] - ref.frame.T_world_agv[:3, 3]) / dt
        speed2 = float(v @ v)
        if speed2 < 1e-4:
            return None
        offset = -float(delta[:3] @ v) / speed2
        across = float(np.linalg.norm(delta[:3] + v * offset))
        if not TIME_OFFSET_MIN_S <= abs(offset) <= TIME_OFFSET_MAX_S or across > 0.3 * float(np.linalg.norm(delta[:3])):
            return None
        if angle_deg(delta) > 0.5 + math.degrees(float(np.linalg.norm(pose_difference(ref.frame.T_world_agv, frame.T_world_agv)[3:])) * abs(offset) / dt):
            return None  # a rotation the motion does not explain: a mount, not a clock
        return offset

    def _odometry_offset(self, frame: FrameResult, state, odometry, motion):
        """(7) The camera's stamp offset against the odometry, from every clean step so far: a
        pose stamped ``dt`` late sits where the vehicle was ``dt`` earlier, so its difference from
        the pose carried by the odometry is r ≈ −(v(t) − v(t_ref))·dt (velocities from the
        odometry, in the world): least squares over the steps, σ from the scatter of the fit
        (scale-free: no covariance needed). Fails once |dt| ≥ ODOMETRY_OFFSET_MIN_S and
        |dt| / σ exceeds the limit after ODOMETRY_OFFSET_MIN_STEPS steps. (CheckResult, finding) or None."""
        if motion is None or odometry is None or "odometry" not in motion[0].detail:
            return None
        result, delta, (_, C), ref = motion
        w = self._offset_direction(frame, ref)
        if w is not None and not result.failed:
            r = delta * OFFSET_WEIGHT
            wr = w * OFFSET_WEIGHT
            sums = state.offset_sums
            sums[0] += float(wr @ r)
            sums[1] += float(wr @ wr)
            sums[2] += float(r @ r)
            sums[3] += 6
        num, den, rr, n = state.offset_sums
        if n < 6 * ODOMETRY_OFFSET_MIN_STEPS or den <= 0:
            return None
        dt = num / den
        s2 = max(rr - dt * num, 0.0) / max(n - 1, 1)
        sigma_dt = math.sqrt(s2 / den) if s2 > 0 else math.inf
        z = abs(dt) / sigma_dt if math.isfinite(sigma_dt) and sigma_dt > 0 else 0.0
        if abs(dt) < ODOMETRY_OFFSET_MIN_S:
            z = min(z, self.settings.limit_sigma)
        detail = (f"camera {frame.cam_name}'s poses {'lag' if dt > 0 else 'lead'} the odometry by "
                  f"{abs(dt) * 1000:.0f} ± {sigma_dt * 1000:.0f} ms (from {n // 6} steps)")
        return CheckResult(CHECK_TIME, z, self.settings.limit_sigma, detail), (
            CAUSE_TIME_OFFSET, f"time offset: {detail}: its stamps are {'late' if dt > 0 else 'early'}", None, frame.cam_name,
        )

    def _offset_direction(self, frame: FrameResult, ref) -> np.ndarray | None:
        """(6,) w with (pose − carried pose) ≈ w·dt for a stamp ``dt`` late: −(twist now − twist at
        the reference) + (ω_ref × the step, 0), twists (velocity, angular velocity) from the
        odometry, in the world (first order in dt)."""
        now = self._odometry_twist(frame.log_time_ns, frame.T_world_agv)
        then = self._odometry_twist(ref.frame.log_time_ns, ref.frame.T_world_agv)
        if now is None or then is None:
            return None
        w = -(now - then)
        # the reference's own heading lag swings the carried step: + ω_ref × (p − p_ref)
        w[:3] += np.cross(then[3:], frame.T_world_agv[:3, 3] - ref.frame.T_world_agv[:3, 3])
        return w

    def _odometry_twist(self, t_ns: int, T_world_agv: np.ndarray) -> np.ndarray | None:
        """(6,) the vehicle's velocity (m/s) and angular velocity (rad/s) at ``t_ns`` in the world:
        the odometry's step over ±ODOMETRY_VELOCITY_NS, turned into the world by the pose's
        rotation. The body-frame twist is kept per stamp (a reference's is asked for again)."""
        local = self._twists.get(t_ns, False)
        if local is False:
            a = self.odometry_at(t_ns - ODOMETRY_VELOCITY_NS)
            b = self.odometry_at(t_ns + ODOMETRY_VELOCITY_NS)
            mid = self.odometry_at(t_ns)
            local = None
            if a is not None and b is not None and mid is not None:
                step = np.linalg.inv(a) @ b
                R = mid[:3, :3].T @ a[:3, :3]  # body at t ← odometry frame at t − h
                local = np.concatenate([R @ step[:3, 3], R @ so3.log(step[:3, :3])]) / (2 * ODOMETRY_VELOCITY_NS / 1e9)
            if len(self._twists) > 64:
                self._twists.clear()
            self._twists[t_ns] = local
        if local is None:
            return None
        R = T_world_agv[:3, :3]
        return np.concatenate([R @ local[:3], R @ local[3:]])

    def _explained_by_offset(self, frame: FrameResult, ref, delta: np.ndarray, C: np.ndarray) -> float | None:
        """The stamp offset (s) that alone explains a motion failure of this frame (its remainder
        passes the check), or None."""
        w = self._offset_direction(frame, ref)
        if w is None:
            return None
        ww = float((w * OFFSET_WEIGHT) @ (w * OFFSET_WEIGHT))
        if ww <= 0:
            return None
        dt = float((w * OFFSET_WEIGHT) @ (delta * OFFSET_WEIGHT)) / ww
        if not TIME_OFFSET_MIN_S <= abs(dt) <= TIME_OFFSET_MAX_S:
            return None
        return dt if mahalanobis_sigma(delta - w * dt, C) <= self.settings.limit_sigma else None

    # -- (7) time -------------------------------------------------------------------------------
    def _time(self, frame: FrameResult, state) -> CheckResult | None:
        last, state.last_time_ns = state.last_time_ns, frame.log_time_ns
        if last is None:
            return None
        step_ns = frame.log_time_ns - last
        steps = state.steps_ns
        result = None
        if len(steps) >= 3:
            period_ns = float(np.median(steps))
            jitter_ns = max(TIME_JITTER_S * 1e9, TIME_JITTER_SHARE * period_ns)
            # A step of a whole number of periods is frames dropped: the stamps are right and the
            # pose is not in doubt (said in the detail, not failed); a step off every multiple of
            # the period, or a repeated frame, fails.
            multiple = max(1, round(step_ns / period_ns))
            sigma = abs(step_ns - multiple * period_ns) / jitter_ns
            if step_ns < 0.5 * period_ns:
                sigma = max(sigma, abs(step_ns - period_ns) / jitter_ns)
            what = (
                f"{step_ns / 1e6:.0f} ms after the previous frame, frame period {period_ns / 1e6:.0f} ms"
                + (": a repeated frame?" if step_ns < 0.5 * period_ns
                   else f": {multiple - 1} frame(s) dropped" if multiple > 1 else "")
            )
            result = CheckResult(CHECK_TIME, sigma, self.settings.limit_sigma, what)
        if step_ns > 0:
            steps.append(step_ns)
        return result
