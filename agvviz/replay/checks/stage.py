"""The check stage itself (:class:`CheckStage`): per camera, the motion reference and the stamp
history; per time stamp, the other cameras' poses; the latest UWB fix. See :mod:`agvviz.replay.checks`."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from agvviz.geometry import so3
from agvviz.solvers.chi2 import chi2_quantile
from agvviz.model.frames import FrameResult
from agvviz.model import suspects
from agvviz.replay.checks.common import (
    CV_ACCEL_MPS2,
    CV_ANGULAR_ACCEL_RADPS2,
    NEXT_STEP,
    POSE_CHECKS,
    REANCHOR_M,
    TIME_HISTORY,
    CheckSettings,
    carried_difference_cov,
    chi2_sigma,
    odometry_cov,
    unambiguous,
    mahalanobis_d2,
    pose_difference,
    size_text,
)
from agvviz.replay.checks.timing import ClockChecks
from agvviz.replay.checks.witnesses import WitnessChecks
from agvviz.settings import RunSettings

#: Mirror flips: 2 ln of the likelihood ratio mirror pose : chosen pose against the motion witness
#: (``evidence`` in :meth:`CheckStage._ambiguity`) that names a flip — the χ²₆ 99 % quantile on its
#: own, the 90 % quantile on a frame right after a flip of the same codes (a flip lasts while the
#: vehicle sees the code from about the same side). Over 0 a frame is never the motion reference.
FLIP_EVIDENCE_D2 = float(chi2_quantile(0.99, [6])[0])  # 16.8
FLIP_PERSISTS_D2 = float(chi2_quantile(0.90, [6])[0])  # 10.6


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
    stretch_first: int | None = None  # index of its first frame
    stretch_codes: set = None  # the codes its frames used
    uwb_failed: tuple = (None, False)  # (stamp of the UWB fix last compared, whether it failed)
    #: time offset against the odometry, least squares r ≈ w·dt: Σw·r, Σw·w, Σr·r, point count
    offset_sums: list = None
    #: those clean steps, for the run-level fit: (t_ns, reference t_ns, reference T_world_agv, carried pose, residual)
    offset_steps: list = None
    solved_frames: list = None  # (index, log_time_ns) of every solved frame: what a run-level finding covers
    last_time_ns: int | None = None
    steps_ns: deque = None
    pair_counts: dict = None  # other camera -> [compared, failed]
    last_flip: tuple | None = None  # the codes of this camera's last solved frame, when it was named a mirror flip

    def __post_init__(self):
        self.steps_ns = deque(maxlen=TIME_HISTORY)
        self.pair_counts = {}
        self.offset_sums = [0.0, 0.0, 0.0, 0]
        self.stretch_codes = set()
        self.offset_steps = []
        self.solved_frames = []


class CheckStage(ClockChecks, WitnessChecks):
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
        undecided = False  # the motion does not prefer the chosen pose to its mirror: no reference
        finding = None  # (cause, message, marker_id, cam_name) of the first explained failure
        if motion is not None:
            result, delta, predicted, ref = motion
            motion_at = len(results)
            results.append(result)
            ambiguity = self._ambiguity(frame, state, predicted, result)
            if ambiguity is not None:
                ambiguity, undecided = ambiguity
                results.append(ambiguity)
                if ambiguity.failed:
                    finding = (suspects.CAUSE_MIRROR_FLIP, f"mirror-pose flip: {ambiguity.detail}", None, None)
            carried = self._persisting(frame, state, odometry, delta, result) if finding is None else None
            if carried is not None:
                results[motion_at] = carried[0]
                finding = carried[1]
                motion = (carried[0],) + motion[1:]  # the pose is doubted: its error persists
            elif result.failed and finding is None:
                finding = self._explain_motion(frame, state, ref.frame, delta, result, predicted)
        offset = self._odometry_offset(frame, state, odometry, motion)
        if offset is not None:
            results.append(offset[0])
            if offset[0].failed:
                # a stamp offset fitted over many steps outweighs a camera-level guess from one stretch
                camera_level = finding is not None and finding[2] is None and finding[0] in (
                    suspects.CAUSE_UNKNOWN, suspects.CAUSE_EXTRINSIC)
                finding = offset[1] if finding is None or camera_level else finding
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
            if undecided:
                state.last_flip = None  # doubted, not flagged: neither a reference nor a witness
            else:
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
        state.last_flip = frame.used_marker_ids if cause == suspects.CAUSE_MIRROR_FLIP else None
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
        state.last_flip = None
        state.stretch_start_odometry = None
        state.last_suspect = None
        state.last_suspect_frame = None
        state.stretch_n = 0
        state.stretch_first = None
        state.stretch_codes = set()

    def _failed(self, frame, state: _CameraState, odometry, suspect: suspects.Suspect) -> None:
        state.last_suspect = suspect
        state.last_suspect_frame, state.last_suspect_odometry = frame, odometry
        if state.stretch_n == 0:
            state.stretch_first = frame.index
        state.stretch_n += 1
        state.stretch_codes |= set(frame.used_marker_ids)
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
        """(suspects.CheckResult, delta, (predicted pose, covariance of delta), reference) or None
        (no reference, no witness). The covariance is the difference's: the two poses' own
        covariances with the sources they share cancelling (common.carried_difference_cov), plus
        the witness's noise (common.odometry_cov, or the constant-velocity model's)."""
        ref = state.reference
        if ref is None:
            return None
        cs = self.settings
        T_ref = ref.frame.T_world_agv
        common = unambiguous(frame, cs) and unambiguous(ref.frame, cs)
        if odometry is not None and ref.odometry is not None:
            step = np.linalg.inv(ref.odometry) @ odometry
            predicted = T_ref @ step
            witness_cov = odometry_cov(step, cs)
            witness = "odometry"
        elif ref.velocity is not None:
            dt = (frame.log_time_ns - ref.frame.log_time_ns) / 1e9
            if dt <= 0:
                return None
            v = ref.velocity
            predicted = T_ref.copy()
            predicted[:3, 3] = T_ref[:3, 3] + v[:3] * dt
            predicted[:3, :3] = so3.exp(v[3:] * dt) @ T_ref[:3, :3]
            witness_cov = np.diag([(0.5 * CV_ACCEL_MPS2 * dt * dt + cs.pose_floor_m) ** 2] * 3
                                  + [(0.5 * CV_ANGULAR_ACCEL_RADPS2 * dt * dt + cs.pose_floor_rad) ** 2] * 3)
            witness = "constant-velocity model"
        else:
            return None
        C = carried_difference_cov(ref.frame, predicted, frame, cs, common) + witness_cov
        # The mirror pose and the offset explanations are judged against the two covariances
        # taken as independent: the shared errors were linearised at the chosen pose, not theirs.
        C_apart = carried_difference_cov(ref.frame, predicted, frame, cs, False) + witness_cov if common else C
        delta = pose_difference(predicted, frame.T_world_agv)
        self.last_motion_d2 = mahalanobis_d2(delta, C)  # (kept for benches: bench_checks.py)
        sigma = chi2_sigma(self.last_motion_d2, len(delta))
        detail = (
            f"pose {size_text(delta)} from frame {ref.frame.index} carried by the {witness}"
        )
        return suspects.CheckResult(suspects.CHECK_MOTION, sigma, cs.limit_sigma, detail), delta, (predicted, C_apart), ref

    def _persisting(self, frame: FrameResult, state: _CameraState, odometry, delta, motion: suspects.CheckResult):
        """The suspect frame before this one, carried on by the odometry, agrees with this frame:
        its error persists here — whether or not the carried reference still sees it (its σ grows
        with the travel). (suspects.CheckResult, finding) or None.

        A map entry's (or payload's) error is tied to its code: carried on while the frame sees
        the same codes. An error of the camera's pose on the AGV — unknown at the jump, with the
        same codes in view — is carried on across changing codes: a pose that stays off the
        odometry by the same body-frame offset while the codes change is the camera's
        **extrinsic** (a map entry moves the pose only while its code is in view)."""
        last, last_frame = state.last_suspect, state.last_suspect_frame
        if last is None or last_frame is None or last.cause == suspects.CAUSE_MIRROR_FLIP:
            return None
        if not any(r.check == suspects.CHECK_MOTION and r.failed for r in last.checks):
            return None  # (its pose was not doubted: it failed a marker, payload or stamp check only)
        if not (unambiguous(frame, self.settings) and unambiguous(last_frame, self.settings)):
            return None  # near its mirror pose a frame's error need not persist: judged on its own
        camera_level = last.marker_id is None and last.cause in (suspects.CAUSE_UNKNOWN, suspects.CAUSE_EXTRINSIC)
        code_level = last.marker_id is not None and last.cause in (suspects.CAUSE_MAP_ENTRY, suspects.CAUSE_PAYLOAD)
        if not (camera_level or code_level) and set(frame.used_marker_ids) != set(last_frame.used_marker_ids):
            return None
        step = self._motion(frame, _CameraState(reference=_Reference(last_frame, state.last_suspect_odometry)), odometry)
        if step is None or step[0].failed:
            return None
        n = state.stretch_n + 1
        codes = ", ".join(frame.used_marker_ids)
        plural = "s" if len(frame.used_marker_ids) > 1 else ""
        detail = (
            f"code{plural} {codes}: a step from suspect frame {last_frame.index} that agrees with the odometry "
            f"({step[0].sigma:.1f}σ): its error persists (now {size_text(delta)} from the carried pose"
            + (f", {motion.sigma:.1f}σ)" if not motion.failed else ")")
        )
        result = suspects.CheckResult(
            suspects.CHECK_MOTION, max(float(last.sigma), motion.sigma), self.settings.limit_sigma, detail)
        if not camera_level and (not code_level or last.marker_id in frame.used_marker_ids):
            cause, marker, cam = last.cause, last.marker_id, None if last.marker_id else last.cam_name
            return result, (cause, last.message, marker, cam)
        seen = state.stretch_codes | set(frame.used_marker_ids)
        across = f"across codes {', '.join(sorted(seen))}" if len(seen) > 1 else f"with code {codes} in view"
        left = f" (code {last.marker_id} is out of view: not its {'map entry' if last.cause == suspects.CAUSE_MAP_ENTRY else 'payload'})" if code_level else ""
        message = (
            f"pose of camera {frame.cam_name} stays off the pose the odometry carries ({size_text(delta)} now) "
            f"for {n} frames since frame {state.stretch_first}, {across}{left}: camera {frame.cam_name}'s extrinsic "
            f"(mount) changed?" + self._off_floor_note(delta, state)
        )
        return result, (suspects.CAUSE_EXTRINSIC, message, None, frame.cam_name)

    def _off_the_floor(self, frame: FrameResult, marker: str, delta, C) -> bool:
        """Whether the pose's jump leaves the floor's plane (height, roll, pitch beyond the limit on
        their own, 3 dof) while code ``marker`` lies on the floor: a floor code whose map entry
        (or payload) is wrong along the floor — moved, turned — moves the pose within the plane
        (x, y, heading) only, so such a jump is not its map entry."""
        obs = next((o for o in frame.observations if o.marker_id == marker), None)
        if obs is None or obs.points_frame != "world" or len(obs.points_world_m) < 3:
            return False
        if float(np.max(np.abs(np.asarray(obs.points_world_m)[:, 2]))) > 0.01:
            return False
        out = [2, 3, 4]
        try:
            d2 = float(delta[out] @ np.linalg.solve(C[np.ix_(out, out)], delta[out]))
        except np.linalg.LinAlgError:
            return False
        return chi2_sigma(d2, 3) > self.settings.limit_sigma

    def _off_floor_note(self, delta, state: _CameraState) -> str:
        """With planar odometry an offset only along the floor (x, y, heading) could also be a wheel slip."""
        if state.reference is None or state.reference.odometry is None:
            return ""
        cs = self.settings
        tilt_z = np.array([delta[2] / max(cs.floor_height_m, 1e-9), delta[3] / max(cs.floor_tilt_rad, 1e-9),
                           delta[4] / max(cs.floor_tilt_rad, 1e-9)])
        if float(np.max(np.abs(tilt_z))) >= 3.0:
            return ""
        return " (the offset lies along the floor: a wheel slip of the odometry would look alike)"

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
        if marker is not None and (last is None or last.marker_id != marker) and predicted is not None:
            if self._off_the_floor(frame, marker, delta, predicted[1]):
                marker = None  # a code misplaced along the floor cannot tilt or lift the pose
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
        new = [m for m in frame.used_marker_ids if m not in set(ref_frame.used_marker_ids)]
        view = (
            f"with code{'s' if len(new) > 1 else ''} {', '.join(new)} new in view but off the floor's plane (a misplaced floor "
            f"code moves the pose along the floor only)" if new else
            f"with the same code{'s' if len(frame.used_marker_ids) > 1 else ''} {markers} in view"
        )
        return (
            suspects.CAUSE_UNKNOWN,
            f"pose of camera {frame.cam_name} jumped by {size} against the {result.detail.split('carried by the ')[-1]} "
            f"({result.sigma:.1f}σ) {view}: a bad detection, camera {frame.cam_name}'s extrinsic (mount) or the odometry?",
            None, frame.cam_name,
        )

    # -- (3) ambiguity --------------------------------------------------------------------------
    def _ambiguity(self, frame, state: _CameraState, predicted, motion: suspects.CheckResult):
        """The mirror pose (the IPPE branch the solver rejected) against the motion witness:
        ``(suspects.CheckResult, undecided)``, or None without a mirror pose.

        Both poses are compared with the pose the witness predicts under the motion check's
        covariance ``C``: d² = Δᵀ C⁻¹ Δ, and ``evidence`` = d²(chosen) − d²(mirror) = 2 ln of the
        likelihood ratio mirror : chosen. When the chosen pose is right, d²(chosen) is χ²₆ and
        d²(mirror) ≥ 0, so the evidence exceeds the χ²₆ q-quantile on at most 1 − q of the frames.
        A frame is a flip when

        - its IPPE ratio is under ``checks_ambiguity_ratio`` (the pixels hardly tell the two
          poses apart) and the evidence exceeds :data:`FLIP_EVIDENCE_D2` (χ²₆ 99 %), or
          :data:`FLIP_PERSISTS_D2` (χ²₆ 90 %) right after a flip of the same codes; or
        - at any ratio, the chosen pose fails the motion check and the mirror pose passes it.

        ``undecided`` (ratio under the bound, evidence > 0: the motion likes the mirror pose at
        least as well) keeps a frame that passes from becoming the motion reference: an
        unflagged flip as reference would flag the right frames after it.
        """
        ratio = frame.ambiguity_ratio
        T_ghost = frame.T_world_agv_ghost
        cs = self.settings
        if T_ghost is None or ratio is None or (ratio >= cs.ambiguity_ratio and not motion.failed):
            return None  # no mirror pose, or the pixels rule it out and the chosen pose passes
        T_pred, C = predicted
        d2_ghost = mahalanobis_d2(pose_difference(T_pred, T_ghost), C)
        evidence = mahalanobis_d2(pose_difference(T_pred, frame.T_world_agv), C) - d2_ghost
        ghost_sigma = chi2_sigma(d2_ghost, 6)
        ambiguous = ratio < cs.ambiguity_ratio
        after_flip = state.last_flip is not None and set(state.last_flip) == set(frame.used_marker_ids)
        bar_d2 = FLIP_PERSISTS_D2 if after_flip else FLIP_EVIDENCE_D2
        witness = "odometry" if motion.detail.endswith("odometry") else "motion"
        chosen = f"the chosen one {motion.sigma:.1f}σ; likelihood ratio {_likelihood_text(evidence)}"
        if ambiguous and evidence > bar_d2:
            how = "agrees with" if ghost_sigma <= cs.limit_sigma else "agrees far better with"
            detail = (f"ambiguity ratio {ratio:.2f}, the other pose {how} the {witness} ({ghost_sigma:.1f}σ, {chosen}"
                      + (", as on the frame before)" if evidence <= FLIP_EVIDENCE_D2 else ")"))
            # σ and limit of the likelihood-ratio test itself (the χ²₆ tail of the evidence)
            return suspects.CheckResult(suspects.CHECK_AMBIGUITY, chi2_sigma(evidence, 6), chi2_sigma(bar_d2, 6), detail), True
        if motion.failed and ghost_sigma <= cs.limit_sigma:
            detail = f"ambiguity ratio {ratio:.2f}, the other pose agrees with the {witness} ({ghost_sigma:.1f}σ, {chosen})"
            return suspects.CheckResult(suspects.CHECK_AMBIGUITY, motion.sigma, cs.limit_sigma, detail), True
        undecided = ambiguous and evidence > 0.0
        detail = (f"ambiguity ratio {ratio:.2f}; mirror pose {ghost_sigma:.1f}σ from the {witness}, chosen {motion.sigma:.1f}σ"
                  + ("; the motion does not prefer the chosen pose: not a reference" if undecided else ""))
        return suspects.CheckResult(suspects.CHECK_AMBIGUITY, 0.0, cs.limit_sigma, detail), undecided


def _likelihood_text(evidence_d2: float) -> str:
    """2 ln(likelihood ratio) as "e^12" / "10^117"."""
    ln_ratio = max(0.0, evidence_d2 / 2.0)
    if ln_ratio < 23:
        return f"e^{ln_ratio:.0f}"
    return f"10^{ln_ratio / math.log(10):.0f}" if ln_ratio < 100 * math.log(10) else "over 10^100"


def check_stage(settings: RunSettings, sync, ctx) -> CheckStage | None:
    """The graph's check stage under ``settings`` (None with ``checks=off``): odometry from the sync
    stage ``sync``, the marker map from the solve stage's context ``ctx``."""
    if settings.checks == "off":
        return None
    return CheckStage(CheckSettings.of(settings), sync.odometry_at, lambda: ctx.qr_map, lambda: sync.odometry.span_ns)
