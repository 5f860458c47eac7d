"""The check stage itself (:class:`CheckStage`): per camera, the motion reference and the stamp
history; per time stamp, the other cameras' poses; the latest UWB fix. See :mod:`agvviz.replay.checks`."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from agvviz.geometry import so3
from agvviz.model.frames import FrameResult
from agvviz.model import suspects
from agvviz.replay.checks.common import (
    CV_ACCEL_MPS2,
    CV_ANGULAR_ACCEL_RADPS2,
    NEXT_STEP,
    PERSISTENT_MIN,
    PERSISTENT_SHARE,
    POSE_CHECKS,
    REANCHOR_M,
    TIME_HISTORY,
    UWB_MAX_DT_NS,
    CheckSettings,
    chi2_sigma,
    mahalanobis_sigma,
    pose_cov,
    pose_difference,
    size_text,
)
from agvviz.replay.checks.timing import ClockChecks
from agvviz.settings import RunSettings


# -- per-camera state ------------------------------------------------------------------------------
@dataclass
class _Reference:
    """The last clean pose of a camera: what the motion check carries forward."""

    frame: FrameResult
    odometry: np.ndarray | None  # T_odom_agv at its stamp
    velocity: np.ndarray | None = None  # (6,) per second, from the clean pose before it (no odometry)


@dataclass
class _CameraState:
    reference: _Reference | None = None
    stretch_start_odometry: np.ndarray | None = None  # odometry where the current failing stretch began
    last_suspect: suspects.Suspect | None = None
    last_suspect_frame: FrameResult | None = None
    last_suspect_odometry: np.ndarray | None = None
    stretch_n: int = 0  # suspect frames in the current failing stretch
    uwb_failed: tuple = (None, False)  # (stamp of the UWB fix last compared, whether it failed)
    #: time offset against the odometry, least squares r ≈ w·dt: Σw·r, Σw·w, Σr·r, point count
    offset_sums: list = None
    #: those clean steps, for the run-level fit: (t_ns, reference t_ns, reference T_world_agv, carried pose, residual)
    offset_steps: list = None
    solved_frames: list = None  # (index, log_time_ns) of every solved frame: what a run-level finding covers
    last_time_ns: int | None = None
    steps_ns: deque = None
    pair_counts: dict = None  # other camera -> [compared, failed]

    def __post_init__(self):
        self.steps_ns = deque(maxlen=TIME_HISTORY)
        self.pair_counts = {}
        self.offset_sums = [0.0, 0.0, 0.0, 0]
        self.offset_steps = []
        self.solved_frames = []


class CheckStage(ClockChecks):
    """The check stage (module docstring). :meth:`check` takes each solve-stage frame in file order
    and returns it, with ``suspect`` set when a check failed; :meth:`uwb_fix` takes the fuse stage's
    UWB fixes; :meth:`run_findings`, at the end of the run, the findings about the whole run.
    ``odometry_at(t_ns)`` the sync stage's odometry (``T_odom_agv`` or None);
    ``qr_map()`` the marker map in use (id → world corners), read at each frame;
    ``odometry_span()`` the (first, last) stamp of the odometry (ns) or None — a velocity is taken
    from the odometry only inside it (before and after it, ``odometry_at`` holds the end pose)."""

    def __init__(self, settings: CheckSettings, odometry_at=None, qr_map=None, odometry_span=None):
        self.settings = settings
        self.odometry_at = odometry_at if odometry_at is not None else (lambda t_ns: None)
        self.odometry_span = odometry_span if odometry_span is not None else (lambda: None)
        self.qr_map = qr_map if qr_map is not None else (lambda: {})
        self.cameras: dict[str, _CameraState] = {}
        self._stamp_ns: int | None = None
        self._at_stamp: list[FrameResult] = []  # undoubted solved frames at the current stamp
        self._uwb: tuple[int, np.ndarray, np.ndarray] | None = None  # (t_ns, xy, cov 2x2)
        self._twists: dict[int, np.ndarray | None] = {}  # stamp -> body-frame twist from the odometry
        self.frames_checked = 0
        self.frames_suspect = 0

    # -- inputs ---------------------------------------------------------------------------------
    def uwb_fix(self, t_ns: int, position_m: np.ndarray, covariance_m2: np.ndarray | None) -> None:
        """A UWB fix (the fuse stage's :class:`~agvviz.model.fusion.UwbFixResult`)."""
        cov = np.asarray(covariance_m2, dtype=float) if covariance_m2 is not None else None
        if cov is None or cov.shape != (2, 2) or not np.all(np.isfinite(cov)):
            cov = np.eye(2) * self.settings.uwb_sigma_m**2
        self._uwb = (int(t_ns), np.asarray(position_m, dtype=float)[:2].copy(), cov)

    def check(self, frame: FrameResult) -> FrameResult:
        """``frame``, with ``suspect`` set when one of its checks failed (never reads truth)."""
        state = self.cameras.setdefault(frame.cam_name, _CameraState())
        if frame.log_time_ns != self._stamp_ns:
            self._stamp_ns, self._at_stamp = frame.log_time_ns, []
        results: list[suspects.CheckResult] = []
        time_result = self._time(frame, state)
        if not frame.solved or frame.T_world_agv is None:
            return frame
        self.frames_checked += 1
        state.solved_frames.append((frame.index, frame.log_time_ns))
        if time_result is not None:
            results.append(time_result)
        odometry = self.odometry_at(frame.log_time_ns)
        motion = self._motion(frame, state, odometry)
        finding = None  # (cause, message, marker_id, cam_name) of the first explained failure
        if motion is not None:
            result, delta, predicted, ref = motion
            results.append(result)
            ambiguity = self._ambiguity(frame, predicted, ref, odometry, result)
            if ambiguity is not None:
                results.append(ambiguity)
                if ambiguity.failed:
                    finding = (suspects.CAUSE_MIRROR_FLIP, f"mirror-pose flip: {ambiguity.detail}", None, None)
            if result.failed and finding is None:
                finding = self._explain_motion(frame, state, ref.frame, delta, result, predicted)
            elif not result.failed:
                inherited = self._persisting(frame, state, odometry, delta)
                if inherited is not None:
                    results[-1] = inherited[0]
                    finding = inherited[1]
        offset = self._odometry_offset(frame, state, odometry, motion)
        if offset is not None:
            results.append(offset[0])
            if offset[0].failed:
                finding = finding or offset[1]
        marker_results, marker_finding = self._markers(frame)
        results += marker_results
        motion_failed = motion is not None and motion[0].failed
        if marker_finding is not None and not motion_failed:
            finding = marker_finding  # the pose passed: the marker left out names itself
        elif marker_finding is not None and finding is not None and finding[0] in (suspects.CAUSE_MAP_ENTRY, suspects.CAUSE_PAYLOAD):
            # The pose fails the motion check although the joint solve left a marker out: the
            # markers it kept are the wrong ones; the left-out one agrees with the motion.
            left_out = marker_finding[2]
            offset = next((c.own_offset_m for c in frame.marker_checks if c.marker_id == left_out), None)
            by = f" by {offset:.2f} m" if offset is not None and offset >= 1.0 else (
                f" by {offset * 1000:.0f} mm" if offset is not None else "")
            blamed = finding[2]
            where = "map entry is" if finding[0] == suspects.CAUSE_MAP_ENTRY else "payload coordinates are"
            finding = (
                finding[0],
                f"code {blamed} disagrees with {left_out}{by} and with the "
                f"{'odometry' if 'odometry' in motion[0].detail else 'motion'} by {size_text(motion[1])} "
                f"({motion[0].sigma:.1f}σ): {blamed}'s {where} likely wrong",
                blamed, None,
            )
        elif marker_finding is not None and finding is None:
            finding = marker_finding
        payload = self._payload(frame)
        if payload is not None:
            results.append(payload[0])
            if payload[0].failed:
                finding = finding or payload[1]
        cameras = self._cameras(frame, state)
        if cameras is not None:
            results.append(cameras[0])
            if cameras[0].failed:
                finding = finding or cameras[1]
        uwb = self._uwb_check(frame, state)
        if uwb is not None and uwb.failed and cameras is not None and not cameras[0].failed:
            # another camera agrees with this one at this stamp: the UWB fix is the odd one out
            uwb = suspects.CheckResult(suspects.CHECK_UWB, min(uwb.sigma, uwb.limit_sigma), uwb.limit_sigma,
                              f"{uwb.detail} ({uwb.sigma:.1f}σ), but camera {frame.cam_name} agrees with the "
                              "other cameras: the UWB fix is likely off (NLOS ranges?)")
        if uwb is not None:
            results.append(uwb)
            if uwb.failed:
                finding = finding or (suspects.CAUSE_UWB, f"camera {frame.cam_name} and UWB disagree: {uwb.detail}", None, None)
        if time_result is not None and time_result.failed:
            finding = finding or (suspects.CAUSE_TIME_STAMPS, f"time stamps: {time_result.detail}", None, frame.cam_name)
        failed = [r for r in results if r.failed]
        if not failed:
            self._clean(frame, state, odometry)
            self._at_stamp.append(frame)
            return frame
        worst = max(failed, key=lambda r: r.sigma / r.limit_sigma)
        cause, message, marker_id, cam_name = finding or (
            suspects.CAUSE_UNKNOWN, f"{worst.check} check failed by {worst.sigma:.1f}σ: {worst.detail}", None, None
        )
        suspect = suspects.Suspect(
            frame_index=frame.index, log_time_ns=frame.log_time_ns, cam_name=cam_name or frame.cam_name,
            check=worst.check, sigma=float(worst.sigma), cause=cause, message=message,
            next_step=NEXT_STEP.get(cause, ""), marker_id=marker_id, checks=tuple(results),
        )
        if any(r.check in POSE_CHECKS and r.failed for r in results):
            self._failed(frame, state, odometry, suspect)
        else:
            self._clean(frame, state, odometry)  # the pose itself passed: a marker, payload or stamp is suspect
            self._at_stamp.append(frame)  # (a doubted pose is no witness for the other cameras)
        self.frames_suspect += 1
        return replace(frame, suspect=suspect)

    def run_findings(self) -> tuple[suspects.RunFinding, ...]:
        """The findings about the whole run, from every frame checked so far (the graph asks at
        the end): each camera's stamp offset against the odometry, when significant
        (:meth:`~agvviz.replay.checks.timing.ClockChecks._run_offset_finding`). By camera name."""
        found = (self._run_offset_finding(name, self.cameras[name]) for name in sorted(self.cameras))
        return tuple(f for f in found if f is not None)

    # -- bookkeeping ----------------------------------------------------------------------------
    def _clean(self, frame: FrameResult, state: _CameraState, odometry: np.ndarray | None) -> None:
        velocity = None
        ref = state.reference
        if ref is not None and odometry is None:
            dt = (frame.log_time_ns - ref.frame.log_time_ns) / 1e9
            if dt > 0:
                velocity = pose_difference(ref.frame.T_world_agv, frame.T_world_agv) / dt
        state.reference = _Reference(frame, odometry, velocity)
        state.stretch_start_odometry = None
        state.last_suspect = None
        state.last_suspect_frame = None
        state.stretch_n = 0

    def _failed(self, frame, state: _CameraState, odometry, suspect: suspects.Suspect) -> None:
        state.last_suspect = suspect
        state.last_suspect_frame, state.last_suspect_odometry = frame, odometry
        state.stretch_n += 1
        if odometry is None or state.reference is None:
            if state.reference is None:
                state.reference = _Reference(frame, odometry)
            return
        if state.stretch_start_odometry is None:
            state.stretch_start_odometry = odometry
        travelled = float(np.linalg.norm(odometry[:3, 3] - state.stretch_start_odometry[:3, 3]))
        if travelled > REANCHOR_M:
            state.reference = _Reference(frame, odometry)
            state.stretch_start_odometry = None

    # -- (1) motion -----------------------------------------------------------------------------
    def _motion(self, frame: FrameResult, state: _CameraState, odometry: np.ndarray | None):
        """(suspects.CheckResult, delta, predicted pose, reference) or None (no reference, no witness)."""
        ref = state.reference
        if ref is None:
            return None
        cs = self.settings
        C = pose_cov(frame, cs) + pose_cov(ref.frame, cs)
        T_ref = ref.frame.T_world_agv
        if odometry is not None and ref.odometry is not None:
            step = np.linalg.inv(ref.odometry) @ odometry
            predicted = T_ref @ step
            distance_m = float(np.linalg.norm(step[:3, 3]))
            turned_rad = float(np.linalg.norm(so3.log(step[:3, :3])))
            sigma_rot = cs.odom_rad_per_m * distance_m + cs.odom_rad_per_rad * turned_rad
            sigma_pos = cs.odom_m_per_m * distance_m + distance_m * sigma_rot
            # the reference's own heading error swings the carried step
            ref_rot_var = float(np.trace(pose_cov(ref.frame, cs)[3:, 3:]))
            C[:3, :3] += np.eye(3) * (sigma_pos**2 + distance_m**2 * ref_rot_var)
            C[3:, 3:] += np.eye(3) * sigma_rot**2
            witness = "odometry"
        elif ref.velocity is not None:
            dt = (frame.log_time_ns - ref.frame.log_time_ns) / 1e9
            if dt <= 0:
                return None
            v = ref.velocity
            predicted = T_ref.copy()
            predicted[:3, 3] = T_ref[:3, 3] + v[:3] * dt
            predicted[:3, :3] = so3.exp(v[3:] * dt) @ T_ref[:3, :3]
            C[:3, :3] += np.eye(3) * (0.5 * CV_ACCEL_MPS2 * dt * dt + cs.pose_floor_m) ** 2
            C[3:, 3:] += np.eye(3) * (0.5 * CV_ANGULAR_ACCEL_RADPS2 * dt * dt + cs.pose_floor_rad) ** 2
            witness = "constant-velocity model"
        else:
            return None
        delta = pose_difference(predicted, frame.T_world_agv)
        sigma = mahalanobis_sigma(delta, C)
        detail = (
            f"pose {size_text(delta)} from frame {ref.frame.index} carried by the {witness}"
        )
        return suspects.CheckResult(suspects.CHECK_MOTION, sigma, cs.limit_sigma, detail), delta, (predicted, C), ref

    def _persisting(self, frame: FrameResult, state: _CameraState, odometry, delta):
        """A frame that passes the motion check only because the odometry's σ grew, while it sees
        the same codes as the suspect frame before it and its step from that frame agrees with the
        odometry: the suspect frame's error is carried on (a wrong map entry or mount moves every
        pose of the stretch alike). (suspects.CheckResult, finding) or None."""
        last, last_frame = state.last_suspect, state.last_suspect_frame
        if last is None or last_frame is None or last.cause == suspects.CAUSE_MIRROR_FLIP or last.check != suspects.CHECK_MOTION:
            return None
        if set(frame.used_marker_ids) != set(last_frame.used_marker_ids):
            return None
        step = self._motion(frame, _CameraState(reference=_Reference(last_frame, state.last_suspect_odometry)), odometry)
        if step is None or step[0].failed:
            return None
        detail = (
            f"same code{'s' if len(frame.used_marker_ids) > 1 else ''} {', '.join(frame.used_marker_ids)} as suspect frame "
            f"{last_frame.index} and a step that agrees with it ({step[0].sigma:.1f}σ): its error persists "
            f"(now {size_text(delta)} from the carried pose)"
        )
        result = suspects.CheckResult(suspects.CHECK_MOTION, float(last.sigma), self.settings.limit_sigma, detail)
        cause, marker, cam = last.cause, last.marker_id, None if last.marker_id else last.cam_name
        message = last.message
        if cause == suspects.CAUSE_UNKNOWN and marker is None and state.stretch_n + 1 >= 3:
            cause = suspects.CAUSE_EXTRINSIC
            message = (
                f"pose of camera {frame.cam_name} stays {size_text(delta)} off the pose the odometry carries for "
                f"{state.stretch_n + 1} frames with the same codes in view: camera {frame.cam_name}'s extrinsic (mount)?"
            )
        return result, (cause, message, marker, cam)

    def _explain_motion(self, frame, state: _CameraState, ref_frame: FrameResult, delta, result: suspects.CheckResult, predicted=None):
        """(cause, message, marker id, camera) of a motion failure."""
        used = set(frame.used_marker_ids)
        last = state.last_suspect
        if last is not None and last.marker_id is not None and last.marker_id in used:
            marker = last.marker_id
        else:
            new = [m for m in frame.used_marker_ids if m not in set(ref_frame.used_marker_ids)]
            marker = new[0] if len(new) == 1 else (frame.used_marker_id if new else None)
        size = size_text(delta)
        if marker is not None:
            others = ", ".join(m for m in ref_frame.used_marker_ids if m != marker) or "the codes before"
            mapped = marker in self.qr_map()
            where = "map entry" if mapped else "payload coordinates"
            return (
                suspects.CAUSE_MAP_ENTRY if mapped else suspects.CAUSE_PAYLOAD,
                f"code {marker} disagrees with {others} (frame {ref_frame.index}) by {size} as carried by the "
                f"{'odometry' if 'odometry' in result.detail else 'motion'} ({result.sigma:.1f}σ): "
                f"{marker}'s {where} {'is' if mapped else 'are'} likely wrong",
                marker, None,
            )
        markers = ", ".join(frame.used_marker_ids)
        if predicted is not None:
            offset_s = self._explained_by_offset(frame, state.reference, delta, predicted[1])
            if offset_s is not None:
                return (
                    suspects.CAUSE_TIME_OFFSET,
                    f"camera {frame.cam_name}'s pose is {size_text(delta)} off the odometry ({result.sigma:.1f}σ) the way a "
                    f"stamp {abs(offset_s) * 1000:.0f} ms {'late' if offset_s > 0 else 'early'} puts it: "
                    f"its time stamps {'lag' if offset_s > 0 else 'lead'}?",
                    None, frame.cam_name,
                )
        return (
            suspects.CAUSE_UNKNOWN,
            f"pose of camera {frame.cam_name} jumped by {size} against the {result.detail.split('carried by the ')[-1]} "
            f"({result.sigma:.1f}σ) with the same code{'s' if len(frame.used_marker_ids) > 1 else ''} {markers} in view: "
            f"a bad detection, camera {frame.cam_name}'s extrinsic (mount) or the odometry?",
            None, frame.cam_name,
        )

    # -- (3) ambiguity --------------------------------------------------------------------------
    def _ambiguity(self, frame, predicted, ref, odometry, motion: suspects.CheckResult) -> suspects.CheckResult | None:
        ratio = frame.ambiguity_ratio
        if frame.T_world_agv_ghost is None or ratio is None:
            return None
        if ratio >= self.settings.ambiguity_ratio and not motion.failed:
            return None
        T_pred, C = predicted
        ghost_sigma = mahalanobis_sigma(pose_difference(T_pred, frame.T_world_agv_ghost), C)
        flipped = motion.failed and ghost_sigma <= self.settings.limit_sigma
        detail = (
            f"ambiguity ratio {ratio:.2f}, the other pose agrees with the motion ({ghost_sigma:.1f}σ, "
            f"the chosen one {motion.sigma:.1f}σ)" if flipped else
            f"ambiguity ratio {ratio:.2f}; mirror pose {ghost_sigma:.1f}σ from the motion, chosen {motion.sigma:.1f}σ"
        )
        return suspects.CheckResult(suspects.CHECK_AMBIGUITY, motion.sigma if flipped else 0.0, self.settings.limit_sigma, detail)

    # -- (2) markers ----------------------------------------------------------------------------
    def _markers(self, frame: FrameResult):
        results, finding = [], None
        points = {o.marker_id: len(o.corners_px) for o in frame.observations}
        for check in frame.marker_checks:
            sigma = chi2_sigma(check.chi2, 2 * points.get(check.marker_id, 4))
            left_out = not check.used
            offset = f", its own pose {check.own_offset_m * 1000:.0f} mm away" if check.own_offset_m is not None else ""
            detail = f"code {check.marker_id}: RMS {check.rms_px:.2f} px at the joint pose, χ² {check.chi2:.3g}{offset}"
            # a marker the joint solve kept is, by its own test, consistent: it does not fail here
            results.append(suspects.CheckResult(suspects.CHECK_MARKERS, sigma if left_out else min(sigma, self.settings.limit_sigma), self.settings.limit_sigma, detail))
            if left_out and sigma > self.settings.limit_sigma and finding is None:
                mapped = check.marker_id in self.qr_map()
                kept = ", ".join(frame.used_marker_ids)
                finding = (
                    suspects.CAUSE_MAP_ENTRY if mapped else suspects.CAUSE_PAYLOAD,
                    f"code {check.marker_id} disagrees with {kept}{offset} (χ² {check.chi2:.3g}, left out of the pose): "
                    f"{check.marker_id}'s {'map entry is' if mapped else 'payload coordinates are'} likely wrong",
                    check.marker_id, None,
                )
        return results, finding

    # -- (4) payload ----------------------------------------------------------------------------
    def _payload(self, frame: FrameResult):
        qr_map = self.qr_map()
        if not qr_map:
            return None
        worst = None
        for obs in frame.observations:
            if obs.marker_id not in frame.used_marker_ids or obs.marker_id not in qr_map:
                continue
            mapped = np.asarray(qr_map[obs.marker_id], dtype=float)
            if mapped.shape != (4, 3) or len(obs.points_world_m) < 4:
                continue
            off = float(np.max(np.linalg.norm(np.asarray(obs.points_world_m[:4]) - mapped, axis=1)))
            if worst is None or off > worst[1]:
                worst = (obs.marker_id, off)
        if worst is None:
            return None
        marker, off = worst
        sigma = off / (math.sqrt(2.0) * self.settings.map_sigma_m)
        result = suspects.CheckResult(suspects.CHECK_PAYLOAD, sigma, self.settings.limit_sigma,
                             f"code {marker}'s payload lies {off * 1000:.0f} mm from its map entry")
        finding = (suspects.CAUSE_PAYLOAD, f"code {marker}'s payload coordinates lie {off * 1000:.0f} mm from its map entry: "
                   f"one of the two is wrong", marker, None)
        return result, finding

    # -- (5) cameras ----------------------------------------------------------------------------
    def _cameras(self, frame: FrameResult, state: _CameraState):
        others = [f for f in self._at_stamp if f.cam_name != frame.cam_name and f.T_world_agv is not None]
        if not others:
            return None
        cs = self.settings
        best = None
        for other in others:
            delta = pose_difference(other.T_world_agv, frame.T_world_agv)
            sigma = mahalanobis_sigma(delta, pose_cov(frame, cs) + pose_cov(other, cs))
            if best is None or sigma > best[0]:
                best = (sigma, other, delta)
        sigma, other, delta = best
        counts = state.pair_counts.setdefault(other.cam_name, [0, 0])
        counts[0] += 1
        counts[1] += sigma > cs.limit_sigma
        detail = f"camera {frame.cam_name} {size_text(delta)} from camera {other.cam_name}"
        result = suspects.CheckResult(suspects.CHECK_CAMERAS, sigma, cs.limit_sigma, detail)
        if not result.failed:
            return result, None
        if frame.T_world_agv_ghost is not None:
            ghost_sigma = mahalanobis_sigma(
                pose_difference(other.T_world_agv, frame.T_world_agv_ghost), pose_cov(frame, cs) + pose_cov(other, cs)
            )
            if ghost_sigma <= cs.limit_sigma:
                ratio = f"ambiguity ratio {frame.ambiguity_ratio:.2f}, " if frame.ambiguity_ratio is not None else ""
                return result, (
                    suspects.CAUSE_MIRROR_FLIP,
                    f"mirror-pose flip: {ratio}the other pose agrees with camera {other.cam_name} ({ghost_sigma:.1f}σ, "
                    f"the chosen one {sigma:.1f}σ)", None, frame.cam_name,
                )
        offset_s = self._time_offset(frame, state, delta)
        if offset_s is not None:
            return result, (
                suspects.CAUSE_TIME_OFFSET,
                f"camera {frame.cam_name} disagrees with {other.cam_name} by {size_text(delta)} along its motion: "
                f"its stamps {'lag' if offset_s > 0 else 'lead'} by about {abs(offset_s) * 1000:.0f} ms",
                None, frame.cam_name,
            )
        every = counts[0] >= PERSISTENT_MIN and counts[1] >= PERSISTENT_SHARE * counts[0]
        return result, (
            suspects.CAUSE_EXTRINSIC,
            f"camera {frame.cam_name} disagrees with {other.cam_name} by {size_text(delta)} ({sigma:.1f}σ)"
            + (f" on every frame ({counts[1]} of {counts[0]})" if every else "") + ": its extrinsic?",
            None, frame.cam_name,
        )

    # -- (6) uwb --------------------------------------------------------------------------------
    def _uwb_check(self, frame: FrameResult, state: _CameraState) -> suspects.CheckResult | None:
        if self._uwb is None:
            return None
        t_ns, xy, cov = self._uwb
        dt_s = (frame.log_time_ns - t_ns) / 1e9
        if not 0 <= dt_s * 1e9 <= UWB_MAX_DT_NS:
            return None
        C = cov + pose_cov(frame, self.settings)[:2, :2]
        ref = state.reference
        if ref is not None and frame.log_time_ns > ref.frame.log_time_ns:
            speed = float(np.linalg.norm(frame.T_world_agv[:2, 3] - ref.frame.T_world_agv[:2, 3])) / (
                (frame.log_time_ns - ref.frame.log_time_ns) / 1e9)
            C = C + np.eye(2) * (speed * dt_s) ** 2
        delta = frame.T_world_agv[:2, 3] - xy
        sigma = mahalanobis_sigma(delta, C)
        detail = f"camera fix {float(np.linalg.norm(delta)) * 1000:.0f} mm from the UWB fix {dt_s * 1000:.0f} ms before"
        # One UWB fix off is what an NLOS range does (a few % of ranges): the check fails only
        # when this camera's previous comparison, with an earlier fix, failed too.
        before, state.uwb_failed = state.uwb_failed, (t_ns, sigma > self.settings.limit_sigma)
        if sigma > self.settings.limit_sigma and not (before[1] and before[0] != t_ns):
            return suspects.CheckResult(suspects.CHECK_UWB, self.settings.limit_sigma, self.settings.limit_sigma,
                               f"{detail} ({sigma:.1f}σ, a single fix: NLOS?)")
        return suspects.CheckResult(suspects.CHECK_UWB, sigma, self.settings.limit_sigma, detail)

def check_stage(settings: RunSettings, sync, ctx) -> CheckStage | None:
    """The graph's check stage under ``settings`` (None with ``checks=off``): odometry from the sync
    stage ``sync``, the marker map from the solve stage's context ``ctx``."""
    if settings.checks == "off":
        return None
    return CheckStage(CheckSettings.of(settings), sync.odometry_at, lambda: ctx.qr_map, lambda: sync.odometry.span_ns)
