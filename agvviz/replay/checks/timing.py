"""The check stage's clock checks (mixed into :class:`agvviz.replay.checks.stage.CheckStage`):
a camera's stamps against its frame period, and its time offset against the odometry or, on a
rig, against another camera. See :mod:`agvviz.replay.checks`."""

from __future__ import annotations

import math

import numpy as np

from agvviz.geometry import so3
from agvviz.model.frames import FrameResult
from agvviz.model.suspects import CAUSE_TIME_OFFSET, CHECK_TIME, CheckResult, RunFinding
from agvviz.replay.checks.common import (
    NEXT_STEP,
    ODOMETRY_OFFSET_MIN_S,
    ODOMETRY_OFFSET_MIN_STEPS,
    OFFSET_TURNING_TWIST,
    OFFSET_WEIGHT,
    RUN_OFFSET_MIN_TURNING,
    RUN_OFFSET_EPS_S,
    RUN_OFFSET_ITERATIONS,
    TIME_JITTER_S,
    TIME_JITTER_SHARE,
    TIME_OFFSET_MAX_S,
    TIME_OFFSET_MIN_S,
    ODOMETRY_VELOCITY_NS,
    angle_deg,
    mahalanobis_sigma,
    pose_difference,
)


def offset_estimate(sums) -> tuple[float, float, int] | None:
    """(dt s, its σ s, steps) of the least-squares stamp offset from the sums Σw·r, Σw·w, Σr·r and
    the count of scalar residuals (6 per step); σ from the fit's scatter, inf without one. None
    before any step."""
    num, den, rr, n = sums
    if n == 0 or den <= 0:
        return None
    dt = num / den
    s2 = max(rr - dt * num, 0.0) / max(n - 1, 1)
    sigma_dt = math.sqrt(s2 / den) if s2 > 0 else math.inf
    return dt, sigma_dt, n // 6


def add_offset_step(sums: list, w: np.ndarray, delta: np.ndarray) -> None:
    """Add one step (direction ``w``, residual ``delta``) to the sums of :func:`offset_estimate`."""
    r = delta * OFFSET_WEIGHT
    wr = w * OFFSET_WEIGHT
    sums[0] += float(wr @ r)
    sums[1] += float(wr @ wr)
    sums[2] += float(r @ r)
    sums[3] += 6


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
        |dt| / σ exceeds the limit after ODOMETRY_OFFSET_MIN_STEPS steps. (CheckResult, finding) or None.
        The same sums give the run-level finding at the end (:meth:`_run_offset_finding`)."""
        if motion is None or odometry is None or "odometry" not in motion[0].detail:
            return None
        result, delta, (_, C), ref = motion
        w = self._offset_direction(frame.log_time_ns, frame.T_world_agv, ref.frame.log_time_ns, ref.frame.T_world_agv)
        if w is not None and not result.failed:
            add_offset_step(state.offset_sums, w, delta)
            state.offset_steps.append((frame.log_time_ns, ref.frame.log_time_ns, ref.frame.T_world_agv, motion[2][0], delta))
        estimate = offset_estimate(state.offset_sums)
        if estimate is None or estimate[2] < ODOMETRY_OFFSET_MIN_STEPS:
            return None
        dt, sigma_dt, steps = estimate
        z = self._offset_sigma(dt, sigma_dt)
        detail = (f"camera {frame.cam_name}'s poses {'lag' if dt > 0 else 'lead'} the odometry by "
                  f"{abs(dt) * 1000:.0f} ± {sigma_dt * 1000:.0f} ms (from {steps} steps)")
        return CheckResult(CHECK_TIME, z, self.settings.limit_sigma, detail), (
            CAUSE_TIME_OFFSET, f"time offset: {detail}: its stamps are {'late' if dt > 0 else 'early'}", None, frame.cam_name,
        )

    def _offset_sigma(self, dt: float, sigma_dt: float) -> float:
        """|dt| in its σ, held at the limit while |dt| < ODOMETRY_OFFSET_MIN_S (a few ms is what
        rolling shutters and odometry filters do: no fault)."""
        z = abs(dt) / sigma_dt if math.isfinite(sigma_dt) and sigma_dt > 0 else 0.0
        if abs(dt) < ODOMETRY_OFFSET_MIN_S:
            z = min(z, self.settings.limit_sigma)
        return z

    def _run_offset_finding(self, cam_name: str, state) -> RunFinding | None:
        """The run-level time offset of camera ``cam_name`` (at the end of the run), from all its
        clean steps. The streaming fit is linear in the twist over ±ODOMETRY_VELOCITY_NS around
        each stamp; a turn that starts between two odometry samples, though, puts its twist change
        and its pose change in different steps (measured on qr_floor: 30 ms came out as 20–38 ms).
        Here the model is exact: under an offset dt a pose is where the reference, carried by the
        odometry from t_ref − dt to t − dt, puts it (:meth:`_offset_residual`); dt by Gauss–Newton
        from the streaming fit, σ from the scatter about it (≈ 0.7 ms of CPU per step: skipped when
        the streaming fit is under half the size and half the σ of a finding). A finding when |dt| ≥
        ODOMETRY_OFFSET_MIN_S, |dt|/σ is over the limit and at least RUN_OFFSET_MIN_TURNING steps
        have a change of twist (|∂r/∂dt| ≥ OFFSET_TURNING_TWIST) — a constant stamp offset
        misplaces every frame, so it covers every solved frame of the camera. None otherwise."""
        estimate = offset_estimate(state.offset_sums)
        if estimate is None or not state.solved_frames:
            return None
        if abs(estimate[0]) < ODOMETRY_OFFSET_MIN_S / 2 and self._offset_sigma(*estimate[:2]) < self.settings.limit_sigma / 2:
            return None  # the streaming fit is far from a finding (it errs by a third at most): skip the exact one
        dt = min(max(estimate[0], -TIME_OFFSET_MAX_S), TIME_OFFSET_MAX_S)
        for _ in range(RUN_OFFSET_ITERATIONS):
            fit = self._offset_gauss_newton(state.offset_steps, dt)
            if fit is None:
                return None
            dt = min(max(dt + fit[0], -TIME_OFFSET_MAX_S), TIME_OFFSET_MAX_S)
        fit = self._offset_gauss_newton(state.offset_steps, dt)
        if fit is None:
            return None
        _, sigma_dt, steps, turning = fit
        z = self._offset_sigma(dt, sigma_dt)
        if steps < ODOMETRY_OFFSET_MIN_STEPS or turning < RUN_OFFSET_MIN_TURNING or z <= self.settings.limit_sigma:
            return None
        lag = "lag" if dt > 0 else "lead"
        message = (
            f"camera {cam_name}'s poses {lag} the odometry by {abs(dt) * 1000:.0f} ± {sigma_dt * 1000:.0f} ms "
            f"(from {steps} steps, {turning} of them turning, starting or stopping): its stamps {lag}? "
            "A constant offset misplaces every frame of the camera, also where driving straight hides it"
        )
        indices, times = zip(*state.solved_frames)
        return RunFinding(
            cam_name=cam_name, check=CHECK_TIME, cause=CAUSE_TIME_OFFSET, sigma=float(z),
            limit_sigma=self.settings.limit_sigma, message=message, next_step=NEXT_STEP[CAUSE_TIME_OFFSET],
            offset_s=float(dt), offset_sigma_s=float(sigma_dt), steps=steps,
            frame_indices=tuple(indices), times_ns=tuple(times),
        )

    def _offset_gauss_newton(self, steps, dt: float):
        """One Gauss–Newton step of the offset fit at ``dt`` (s): (the step to add, σ of dt from the
        scatter of the residuals at ``dt``, steps used, steps with |∂r/∂dt| ≥ OFFSET_TURNING_TWIST),
        or None without a usable step. ∂r/∂dt by central differences over ±RUN_OFFSET_EPS_S."""
        num = den = ee = 0.0
        n = turning = 0
        odometry: dict[int, np.ndarray | None] = {}  # stamp -> odometry_at(stamp): a reference's stamp is the step before's
        for step in steps:
            r0 = self._offset_residual(step, dt, odometry)
            r_plus = self._offset_residual(step, dt + RUN_OFFSET_EPS_S, odometry)
            r_minus = self._offset_residual(step, dt - RUN_OFFSET_EPS_S, odometry)
            if len(odometry) > 64:
                odometry.clear()
            if r0 is None or r_plus is None or r_minus is None:
                continue
            J = (r_plus - r_minus) * OFFSET_WEIGHT / (2 * RUN_OFFSET_EPS_S)
            e = (step[4] - r0) * OFFSET_WEIGHT
            num += float(J @ e)
            den += float(J @ J)
            ee += float(e @ e)
            n += 1
            turning += float(np.linalg.norm(J)) >= OFFSET_TURNING_TWIST
        if n == 0 or den <= 0:
            return None
        s2 = ee / max(6 * n - 1, 1)
        return num / den, math.sqrt(s2 / den) if s2 > 0 else math.inf, n, turning

    def _offset_residual(self, step, dt: float, odometry: dict) -> np.ndarray | None:
        """(6,) what pose − carried pose of a clean ``step`` would be with the stamps ``dt`` late
        (s): the reference carried by the odometry from t_ref − dt to t − dt, against the pose the
        odometry carries it to from t_ref to t (exact at the odometry's samples; None outside the
        odometry's span). ``odometry`` caches the odometry's poses by stamp."""
        t_ns, t_ref_ns, T_ref, T_carried, _ = step
        dt_ns = int(round(dt * 1e9))
        span = self.odometry_span()
        if span is not None and not (span[0] <= min(t_ns, t_ref_ns) - dt_ns and max(t_ns, t_ref_ns) - dt_ns <= span[1]):
            return None
        for t in (t_ref_ns - dt_ns, t_ns - dt_ns):
            if t not in odometry:
                odometry[t] = self.odometry_at(t)
        a, b = odometry[t_ref_ns - dt_ns], odometry[t_ns - dt_ns]
        if a is None or b is None:
            return None
        return pose_difference(T_carried, T_ref @ np.linalg.inv(a) @ b)

    def _offset_direction(self, t_ns: int, T_world_agv: np.ndarray, t_ref_ns: int, T_ref: np.ndarray) -> np.ndarray | None:
        """(6,) w with (pose − carried pose) ≈ w·dt for a stamp ``dt`` late: −(twist now − twist at
        the reference) + (ω_ref × the step, 0), twists (velocity, angular velocity) from the
        odometry, in the world (first order in dt)."""
        now = self._odometry_twist(t_ns, T_world_agv)
        then = self._odometry_twist(t_ref_ns, T_ref)
        if now is None or then is None:
            return None
        w = -(now - then)
        # the reference's own heading lag swings the carried step: + ω_ref × (p − p_ref)
        # (np.cross of two 3-vectors written out in Python floats: the same products and differences)
        (a0, a1, a2), (b0, b1, b2) = then[3:].tolist(), (T_world_agv[:3, 3] - T_ref[:3, 3]).tolist()
        w[:3] += (a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)
        return w

    def _odometry_twist(self, t_ns: int, T_world_agv: np.ndarray) -> np.ndarray | None:
        """(6,) the vehicle's velocity (m/s) and angular velocity (rad/s) at ``t_ns`` in the world:
        the odometry's step over ±ODOMETRY_VELOCITY_NS, turned into the world by the pose's
        rotation; None unless that window lies inside the odometry's span (past its ends
        ``odometry_at`` holds the end pose: a vehicle driving through the log's start or end would
        seem to start or stop). The body-frame twist is kept per stamp (a reference's is asked for
        again)."""
        h = ODOMETRY_VELOCITY_NS
        span = self.odometry_span()
        if span is not None and not (span[0] <= t_ns - h and t_ns + h <= span[1]):
            return None
        local = self._twists.get(t_ns, False)
        if local is False:
            a = self.odometry_at(t_ns - h)
            b = self.odometry_at(t_ns + h)
            mid = self.odometry_at(t_ns)
            local = None
            if a is not None and b is not None and mid is not None:
                step = np.linalg.inv(a) @ b
                R = mid[:3, :3].T @ a[:3, :3]  # body at t ← odometry frame at t − h
                local = np.concatenate([R @ step[:3, 3], R @ so3.log(step[:3, :3])]) / (2 * h / 1e9)
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
        w = self._offset_direction(frame.log_time_ns, frame.T_world_agv, ref.frame.log_time_ns, ref.frame.T_world_agv)
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
            period_ns = _median(steps)
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


def _median(values) -> float:
    """np.median of a few integers (a frame's last steps, ns), without its per-call cost: the
    middle value, or the mean of the two middle ones (each exact as a double, so their sum is)."""
    ordered = sorted(values)
    n = len(ordered)
    if n % 2:
        return float(ordered[n // 2])
    return (float(ordered[n // 2 - 1]) + float(ordered[n // 2])) / 2.0
