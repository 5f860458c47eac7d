"""The check stage: every solved pose checked against what else the log knows, truth not needed (issue 25).

Runs in the graph right after solve (:mod:`agvviz.replay.graph`), before a frame reaches the
sinks, and sets :attr:`~agvviz.model.frames.FrameResult.suspect` on a frame that fails a check.
It never reads ground truth (a frame's ``T_world_agv_truth`` and errors are not looked at), so
``truth=ignore`` gives the same suspects. Each check compares the pose with one independent
witness and turns the disagreement into standard deviations (σ): a Mahalanobis distance d² with
k degrees of freedom is given as the normal quantile of its χ²_k tail (:func:`chi2_sigma`), so
every check has one scale and one limit (``checks_limit_sigma``). A check without a witness on a
frame is skipped.

1. **motion** — the pose against the last clean pose of the same camera carried forward by the
   odometry (``SyncState.odometry_at``), or by a constant-velocity model without odometry: the
   6-DoF difference (position in the world, rotation vector) against both poses' covariances,
   each with a systematic floor (``checks_pose_floor_m`` / ``_deg``: today's covariance models
   pixel noise only), plus the odometry's noise per metre and per degree turned. A failing
   frame does not become the reference, so a stretch of frames on a wrong map entry keeps
   failing (a rigid error of the map leaves frame-to-frame steps intact: only the carried
   reference sees it). After ``REANCHOR_M`` of travel in one failing stretch the reference
   moves on (the odometry itself may have jumped).
2. **markers** — the joint solve's χ² test of each marker against the joint pose
   (:class:`~agvviz.solvers.joint.MarkerCheck`): a marker left out names itself.
3. **ambiguity** — with an IPPE ratio under ``checks_ambiguity_ratio``, the rejected mirror pose
   (``T_world_agv_ghost``) against the same motion witness: when it agrees and the chosen one
   does not, the cause is a mirror flip.
4. **payload** — each used code's payload coordinates against its map entry (σ of a map entry
   ``checks_map_sigma_m``); a motion failure that a code explains is blamed on its map entry, or
   on its payload when the code has no map entry (payload-only recordings).
5. **cameras** — on a rig, a camera's pose against the other cameras' poses at the same stamp;
   a disagreement along the motion whose size follows the speed is a time offset, else the
   camera's extrinsic ("on every frame" once it persists).
6. **uwb** — the camera position against the latest UWB fix (at most ``UWB_MAX_DT_NS`` older),
   2-D, with the fix's covariance (or ``uwb_sigma_m``) and the motion in between.
7. **time** — each camera's stamp step against its frame period (the median of the steps so
   far): a step off every whole number of periods, or a repeated frame, fails (a whole number of
   periods is frames dropped: noted, not failed).

:func:`suspect_stretches` groups consecutive suspects of one cause (what the terminal lists and
the plots mark); :func:`suspects_summary` is the run summary's ``suspects`` entry.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Iterable, Mapping

import numpy as np
from scipy.special import chdtrc, ndtri

from agvviz.geometry import so3
from agvviz.model.frames import FrameResult
from agvviz.model.suspects import (
    CAUSE_EXTRINSIC,
    CAUSE_MAP_ENTRY,
    CAUSE_MIRROR_FLIP,
    CAUSE_PAYLOAD,
    CAUSE_TIME_OFFSET,
    CAUSE_TIME_STAMPS,
    CAUSE_UNKNOWN,
    CAUSE_UWB,
    CAUSES,
    CHECK_AMBIGUITY,
    CHECK_CAMERAS,
    CHECK_MARKERS,
    CHECK_MOTION,
    CHECK_PAYLOAD,
    CHECK_TIME,
    CHECK_UWB,
    CHECKS,
    CheckResult,
    Suspect,
    SuspectStretch,
)
from agvviz.settings import RunSettings

#: A failing stretch longer than this (metres of odometry travel) moves the motion check's reference on.
REANCHOR_M = 5.0
#: Without odometry: the constant-velocity model's σ of acceleration (m/s², rad/s²).
CV_ACCEL_MPS2 = 2.0
CV_ANGULAR_ACCEL_RADPS2 = 2.0
#: The UWB fix a frame is compared with is at most this much older than the frame.
UWB_MAX_DT_NS = 200_000_000
#: A camera disagreeing with the others on at least this share of at least this many stamps: "on every frame".
PERSISTENT_SHARE = 0.8
PERSISTENT_MIN = 5
#: Frame-period estimate: steps remembered per camera; a stamp step is judged with a jitter σ of
#: max(TIME_JITTER_S, TIME_JITTER_SHARE × period).
TIME_HISTORY = 50
TIME_JITTER_S = 0.002
TIME_JITTER_SHARE = 0.05
#: A time offset explains a camera disagreement when the offset fitted to it lies within these bounds (s).
TIME_OFFSET_MIN_S = 0.003
TIME_OFFSET_MAX_S = 0.5

#: Checks whose failure doubts the pose itself (a failing frame is then no reference for the next).
POSE_CHECKS = (CHECK_MOTION, CHECK_AMBIGUITY, CHECK_CAMERAS, CHECK_UWB)

NEXT_STEP = {
    CAUSE_MAP_ENTRY: "`agvviz audit` can estimate where it is",
    CAUSE_PAYLOAD: "compare the code's payload with the marker map (`agvviz inspect`), re-print the code",
    CAUSE_MIRROR_FLIP: "try `--set ambiguity=odometry`, or look at the code more squarely",
    CAUSE_EXTRINSIC: "`agvviz audit` can estimate the camera's extrinsic",
    CAUSE_TIME_OFFSET: "check the camera's time stamps (driver latency); `--set time_source=header` if the headers are right",
    CAUSE_TIME_STAMPS: "check the recording for dropped or repeated frames (`agvviz inspect`)",
    CAUSE_UWB: "look at the UWB ranges of this stretch (NLOS?) and the camera's markers",
    CAUSE_UNKNOWN: "look at the frame's markers and the odometry around it",
}


def chi2_sigma(d2: float, dof: int) -> float:
    """A χ²_dof value as the normal σ of the same upper tail (≥ 0): 1 dof gives √d²; 6 dof at
    d² = 41.0 gives 5 σ. Exact (scipy.special) while the tail is representable, then the
    Wilson–Hilferty approximation (slightly low there: conservative)."""
    if not math.isfinite(d2):
        return math.inf
    if d2 <= 0:
        return 0.0
    if dof == 1:
        return math.sqrt(d2)
    p = float(chdtrc(dof, d2))
    if p > 1e-300:
        return max(0.0, float(-ndtri(p)))
    k = float(dof)
    z = ((d2 / k) ** (1.0 / 3.0) - (1.0 - 2.0 / (9.0 * k))) / math.sqrt(2.0 / (9.0 * k))
    return max(0.0, z)


@dataclass(frozen=True)
class CheckSettings:
    """The check stage's parameters (``checks_*`` run settings, docs/suspects.md)."""

    limit_sigma: float = 5.0
    pose_floor_m: float = 0.002
    pose_floor_rad: float = math.radians(0.1)
    odom_m_per_m: float = 0.02
    odom_rad_per_m: float = math.radians(0.5)
    odom_rad_per_rad: float = 0.02
    ambiguity_ratio: float = 4.0
    map_sigma_m: float = 0.005
    uwb_sigma_m: float = 0.1

    @classmethod
    def of(cls, settings: RunSettings) -> "CheckSettings":
        return cls(
            limit_sigma=settings.checks_limit_sigma, pose_floor_m=settings.checks_pose_floor_m,
            pose_floor_rad=math.radians(settings.checks_pose_floor_deg), odom_m_per_m=settings.checks_odom_m_per_m,
            odom_rad_per_m=math.radians(settings.checks_odom_deg_per_m),
            odom_rad_per_rad=settings.checks_odom_deg_per_deg, ambiguity_ratio=settings.checks_ambiguity_ratio,
            map_sigma_m=settings.checks_map_sigma_m, uwb_sigma_m=settings.uwb_sigma_m,
        )


# -- pose arithmetic ------------------------------------------------------------------------------
def pose_cov(frame: FrameResult, cs: CheckSettings) -> np.ndarray:
    """(6, 6) covariance of (position in the world, rotation vector) of the frame's AGV pose:
    its own (position block and rotation block; none: zeros) plus the systematic floors."""
    C = np.zeros((6, 6))
    if frame.cov_world_agv is not None and np.all(np.isfinite(frame.cov_world_agv)):
        C[3:, 3:] = frame.cov_world_agv[3:, 3:]
        if frame.position_cov_world_m2 is not None:
            C[:3, :3] = frame.position_cov_world_m2
        else:
            C[:3, :3] = frame.cov_world_agv[:3, :3]
    C[:3, :3] += np.eye(3) * cs.pose_floor_m**2
    C[3:, 3:] += np.eye(3) * cs.pose_floor_rad**2
    return C


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """(6,) ``T_b`` − ``T_a``: position difference in the world and the rotation vector of R_b R_aᵀ."""
    return np.concatenate([T_b[:3, 3] - T_a[:3, 3], so3.log(T_b[:3, :3] @ T_a[:3, :3].T)])


def mahalanobis_sigma(delta: np.ndarray, cov: np.ndarray) -> float:
    """The difference ``delta`` against ``cov`` as σ (:func:`chi2_sigma` of d², dof = its length)."""
    try:
        d2 = float(delta @ np.linalg.solve(cov, delta))
    except np.linalg.LinAlgError:
        d2 = float(delta @ np.linalg.pinv(cov) @ delta)
    return chi2_sigma(d2, len(delta))


def _angle_deg(delta: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(delta[3:])))


def _size(delta: np.ndarray) -> str:
    """"2.78 m, 90.0°" / "42 mm, 0.3°"."""
    d = float(np.linalg.norm(delta[:3]))
    return (f"{d:.2f} m" if d >= 1.0 else f"{d * 1000:.0f} mm") + f", {_angle_deg(delta):.1f}°"


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
    last_suspect: Suspect | None = None
    last_suspect_frame: FrameResult | None = None
    last_suspect_odometry: np.ndarray | None = None
    stretch_n: int = 0  # suspect frames in the current failing stretch
    last_time_ns: int | None = None
    steps_ns: deque = None
    pair_counts: dict = None  # other camera -> [compared, failed]

    def __post_init__(self):
        self.steps_ns = deque(maxlen=TIME_HISTORY)
        self.pair_counts = {}


class CheckStage:
    """The check stage (module docstring). :meth:`check` takes each solve-stage frame in file order
    and returns it, with ``suspect`` set when a check failed; :meth:`uwb_fix` takes the fuse stage's
    UWB fixes. ``odometry_at(t_ns)`` the sync stage's odometry (``T_odom_agv`` or None);
    ``qr_map()`` the marker map in use (id → world corners), read at each frame."""

    def __init__(self, settings: CheckSettings, odometry_at=None, qr_map=None):
        self.settings = settings
        self.odometry_at = odometry_at if odometry_at is not None else (lambda t_ns: None)
        self.qr_map = qr_map if qr_map is not None else (lambda: {})
        self.cameras: dict[str, _CameraState] = {}
        self._stamp_ns: int | None = None
        self._at_stamp: list[FrameResult] = []  # solved frames of other cameras at the current stamp
        self._uwb: tuple[int, np.ndarray, np.ndarray] | None = None  # (t_ns, xy, cov 2x2)
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
        results: list[CheckResult] = []
        time_result = self._time(frame, state)
        if not frame.solved or frame.T_world_agv is None:
            return frame
        self.frames_checked += 1
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
                    finding = (CAUSE_MIRROR_FLIP, f"mirror-pose flip: {ambiguity.detail}", None, None)
            if result.failed and finding is None:
                finding = self._explain_motion(frame, state, ref.frame, delta, result)
            elif not result.failed:
                inherited = self._persisting(frame, state, odometry, delta)
                if inherited is not None:
                    results[-1] = inherited[0]
                    finding = inherited[1]
        marker_results, marker_finding = self._markers(frame)
        results += marker_results
        if marker_finding is not None and (finding is None or finding[0] != CAUSE_MIRROR_FLIP):
            finding = marker_finding  # a marker left out names itself: better evidence than a step
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
        if uwb is not None:
            results.append(uwb)
            if uwb.failed:
                finding = finding or (CAUSE_UWB, f"camera {frame.cam_name} and UWB disagree: {uwb.detail}", None, None)
        if time_result is not None and time_result.failed:
            finding = finding or (CAUSE_TIME_STAMPS, f"time stamps: {time_result.detail}", None, frame.cam_name)
        self._at_stamp.append(frame)
        failed = [r for r in results if r.failed]
        if not failed:
            self._clean(frame, state, odometry)
            return frame
        worst = max(failed, key=lambda r: r.sigma / r.limit_sigma)
        cause, message, marker_id, cam_name = finding or (
            CAUSE_UNKNOWN, f"{worst.check} check failed by {worst.sigma:.1f}σ: {worst.detail}", None, None
        )
        suspect = Suspect(
            frame_index=frame.index, log_time_ns=frame.log_time_ns, cam_name=cam_name or frame.cam_name,
            check=worst.check, sigma=float(worst.sigma), cause=cause, message=message,
            next_step=NEXT_STEP.get(cause, ""), marker_id=marker_id, checks=tuple(results),
        )
        if any(r.check in POSE_CHECKS and r.failed for r in results):
            self._failed(frame, state, odometry, suspect)
        else:
            self._clean(frame, state, odometry)  # the pose itself passed: a marker, payload or stamp is suspect
        self.frames_suspect += 1
        return replace(frame, suspect=suspect)

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

    def _failed(self, frame, state: _CameraState, odometry, suspect: Suspect) -> None:
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
        """(CheckResult, delta, predicted pose, reference) or None (no reference, no witness)."""
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
            f"pose {_size(delta)} from frame {ref.frame.index} carried by the {witness}"
        )
        return CheckResult(CHECK_MOTION, sigma, cs.limit_sigma, detail), delta, (predicted, C), ref

    def _persisting(self, frame: FrameResult, state: _CameraState, odometry, delta):
        """A frame that passes the motion check only because the odometry's σ grew, while it sees
        the same codes as the suspect frame before it and its step from that frame agrees with the
        odometry: the suspect frame's error is carried on (a wrong map entry or mount moves every
        pose of the stretch alike). (CheckResult, finding) or None."""
        last, last_frame = state.last_suspect, state.last_suspect_frame
        if last is None or last_frame is None or last.cause == CAUSE_MIRROR_FLIP or last.check != CHECK_MOTION:
            return None
        if set(frame.used_marker_ids) != set(last_frame.used_marker_ids):
            return None
        step = self._motion(frame, _CameraState(reference=_Reference(last_frame, state.last_suspect_odometry)), odometry)
        if step is None or step[0].failed:
            return None
        detail = (
            f"same code{'s' if len(frame.used_marker_ids) > 1 else ''} {', '.join(frame.used_marker_ids)} as suspect frame "
            f"{last_frame.index} and a step that agrees with it ({step[0].sigma:.1f}σ): its error persists "
            f"(now {_size(delta)} from the carried pose)"
        )
        result = CheckResult(CHECK_MOTION, float(last.sigma), self.settings.limit_sigma, detail)
        cause, marker, cam = last.cause, last.marker_id, None if last.marker_id else last.cam_name
        message = last.message
        if cause == CAUSE_UNKNOWN and marker is None and state.stretch_n + 1 >= 3:
            cause = CAUSE_EXTRINSIC
            message = (
                f"pose of camera {frame.cam_name} stays {_size(delta)} off the pose the odometry carries for "
                f"{state.stretch_n + 1} frames with the same codes in view: camera {frame.cam_name}'s extrinsic (mount)?"
            )
        return result, (cause, message, marker, cam)

    def _explain_motion(self, frame, state: _CameraState, ref_frame: FrameResult, delta, result: CheckResult):
        """(cause, message, marker id, camera) of a motion failure."""
        used = set(frame.used_marker_ids)
        last = state.last_suspect
        if last is not None and last.marker_id is not None and last.marker_id in used:
            marker = last.marker_id
        else:
            new = [m for m in frame.used_marker_ids if m not in set(ref_frame.used_marker_ids)]
            marker = new[0] if len(new) == 1 else (frame.used_marker_id if new else None)
        size = _size(delta)
        if marker is not None:
            others = ", ".join(m for m in ref_frame.used_marker_ids if m != marker) or "the codes before"
            mapped = marker in self.qr_map()
            where = "map entry" if mapped else "payload coordinates"
            return (
                CAUSE_MAP_ENTRY if mapped else CAUSE_PAYLOAD,
                f"code {marker} disagrees with {others} (frame {ref_frame.index}) by {size} as carried by the "
                f"{'odometry' if 'odometry' in result.detail else 'motion'} ({result.sigma:.1f}σ): "
                f"{marker}'s {where} {'is' if mapped else 'are'} likely wrong",
                marker, None,
            )
        markers = ", ".join(frame.used_marker_ids)
        return (
            CAUSE_UNKNOWN,
            f"pose of camera {frame.cam_name} jumped by {size} against the {result.detail.split('carried by the ')[-1]} "
            f"({result.sigma:.1f}σ) with the same code{'s' if len(frame.used_marker_ids) > 1 else ''} {markers} in view: "
            f"a bad detection, camera {frame.cam_name}'s extrinsic (mount) or the odometry?",
            None, frame.cam_name,
        )

    # -- (3) ambiguity --------------------------------------------------------------------------
    def _ambiguity(self, frame, predicted, ref, odometry, motion: CheckResult) -> CheckResult | None:
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
        return CheckResult(CHECK_AMBIGUITY, motion.sigma if flipped else 0.0, self.settings.limit_sigma, detail)

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
            results.append(CheckResult(CHECK_MARKERS, sigma if left_out else min(sigma, self.settings.limit_sigma), self.settings.limit_sigma, detail))
            if left_out and sigma > self.settings.limit_sigma and finding is None:
                mapped = check.marker_id in self.qr_map()
                kept = ", ".join(frame.used_marker_ids)
                finding = (
                    CAUSE_MAP_ENTRY if mapped else CAUSE_PAYLOAD,
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
        result = CheckResult(CHECK_PAYLOAD, sigma, self.settings.limit_sigma,
                             f"code {marker}'s payload lies {off * 1000:.0f} mm from its map entry")
        finding = (CAUSE_PAYLOAD, f"code {marker}'s payload coordinates lie {off * 1000:.0f} mm from its map entry: "
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
        detail = f"camera {frame.cam_name} {_size(delta)} from camera {other.cam_name}"
        result = CheckResult(CHECK_CAMERAS, sigma, cs.limit_sigma, detail)
        if not result.failed:
            return result, None
        if frame.T_world_agv_ghost is not None:
            ghost_sigma = mahalanobis_sigma(
                pose_difference(other.T_world_agv, frame.T_world_agv_ghost), pose_cov(frame, cs) + pose_cov(other, cs)
            )
            if ghost_sigma <= cs.limit_sigma:
                ratio = f"ambiguity ratio {frame.ambiguity_ratio:.2f}, " if frame.ambiguity_ratio is not None else ""
                return result, (
                    CAUSE_MIRROR_FLIP,
                    f"mirror-pose flip: {ratio}the other pose agrees with camera {other.cam_name} ({ghost_sigma:.1f}σ, "
                    f"the chosen one {sigma:.1f}σ)", None, frame.cam_name,
                )
        offset_s = self._time_offset(frame, state, delta)
        if offset_s is not None:
            return result, (
                CAUSE_TIME_OFFSET,
                f"camera {frame.cam_name} disagrees with {other.cam_name} by {_size(delta)} along its motion: "
                f"its stamps {'lag' if offset_s > 0 else 'lead'} by about {abs(offset_s) * 1000:.0f} ms",
                None, frame.cam_name,
            )
        every = counts[0] >= PERSISTENT_MIN and counts[1] >= PERSISTENT_SHARE * counts[0]
        return result, (
            CAUSE_EXTRINSIC,
            f"camera {frame.cam_name} disagrees with {other.cam_name} by {_size(delta)} ({sigma:.1f}σ)"
            + (f" on every frame ({counts[1]} of {counts[0]})" if every else "") + f": its extrinsic?",
            None, frame.cam_name,
        )

    def _time_offset(self, frame: FrameResult, state: _CameraState, delta: np.ndarray) -> float | None:
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
        if _angle_deg(delta) > 0.5 + math.degrees(float(np.linalg.norm(pose_difference(ref.frame.T_world_agv, frame.T_world_agv)[3:])) * abs(offset) / dt):
            return None  # a rotation the motion does not explain: a mount, not a clock
        return offset

    # -- (6) uwb --------------------------------------------------------------------------------
    def _uwb_check(self, frame: FrameResult, state: _CameraState) -> CheckResult | None:
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
        return CheckResult(CHECK_UWB, sigma, self.settings.limit_sigma,
                           f"camera fix {float(np.linalg.norm(delta)) * 1000:.0f} mm from the UWB fix {dt_s * 1000:.0f} ms before")

    # -- (7) time -------------------------------------------------------------------------------
    def _time(self, frame: FrameResult, state: _CameraState) -> CheckResult | None:
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


# -- stretches and the summary ------------------------------------------------------------------
def suspect_stretches(frames: Iterable) -> list[SuspectStretch]:
    """Consecutive suspect frames of one camera with one cause (and the same marker / camera named),
    no clean solved frame between them; rejected frames do not break a stretch. ``frames``: anything
    with ``index``, ``cam_name``, ``solved`` and ``suspect`` (a :class:`FrameResult`), in file order.
    Stretches are listed by their first frame."""
    open_: dict[str, list] = {}  # camera -> [stretch fields]
    done: list[SuspectStretch] = []

    def close(cam: str) -> None:
        s = open_.pop(cam, None)
        if s is not None:
            done.append(SuspectStretch(**s))

    for frame in frames:
        suspect = frame.suspect
        cam = frame.cam_name
        if suspect is None:
            if frame.solved:
                close(cam)
            continue
        s = open_.get(cam)
        if s is not None and (s["cause"], s["marker_id"], s["cam_name"]) == (suspect.cause, suspect.marker_id, suspect.cam_name):
            s["last_frame"], s["last_time_ns"] = suspect.frame_index, suspect.log_time_ns
            s["n_frames"] += 1
            s["max_sigma"] = max(s["max_sigma"], suspect.sigma)
            continue
        close(cam)
        open_[cam] = dict(
            first_frame=suspect.frame_index, last_frame=suspect.frame_index, first_time_ns=suspect.log_time_ns,
            last_time_ns=suspect.log_time_ns, n_frames=1, cause=suspect.cause, message=suspect.message,
            next_step=suspect.next_step, cam_name=suspect.cam_name, marker_id=suspect.marker_id,
            max_sigma=float(suspect.sigma),
        )
    for cam in list(open_):
        close(cam)
    return sorted(done, key=lambda s: (s.first_frame, s.first_time_ns, s.cam_name))


def stretch_dict(stretch: SuspectStretch) -> dict:
    """A stretch as plain values (the summary stores it)."""
    return {
        "first_frame": stretch.first_frame, "last_frame": stretch.last_frame,
        "first_time_ns": stretch.first_time_ns, "last_time_ns": stretch.last_time_ns,
        "n_frames": stretch.n_frames, "cause": stretch.cause, "message": stretch.message,
        "next_step": stretch.next_step, "cam_name": stretch.cam_name, "marker_id": stretch.marker_id,
        "max_sigma": round(float(stretch.max_sigma), 3),
    }


def suspects_summary(frames: Iterable, checked: bool = True) -> dict:
    """The run summary's ``suspects`` entry: ``checked`` (the check stage ran), ``frames`` (suspect
    frames), ``solved`` (solved frames checked), ``by_cause`` and ``by_check`` (counts, every name
    of :data:`CAUSES` / :data:`CHECKS` present, zeros included), ``stretches`` (:func:`stretch_dict` each)."""
    frames = list(frames)
    suspects = [f.suspect for f in frames if f.suspect is not None]
    by_cause = {c: 0 for c in CAUSES}
    by_check = {c: 0 for c in CHECKS}
    for s in suspects:
        by_cause[s.cause] = by_cause.get(s.cause, 0) + 1
        by_check[s.check] = by_check.get(s.check, 0) + 1
    return {
        "checked": bool(checked),
        "frames": len(suspects),
        "solved": sum(1 for f in frames if f.solved),
        "by_cause": by_cause,
        "by_check": by_check,
        "stretches": [stretch_dict(s) for s in suspect_stretches(frames)],
    }


def check_stage(settings: RunSettings, sync, ctx) -> CheckStage | None:
    """The graph's check stage under ``settings`` (None with ``checks=off``): odometry from the sync
    stage ``sync``, the marker map from the solve stage's context ``ctx``."""
    if settings.checks == "off":
        return None
    return CheckStage(CheckSettings.of(settings), sync.odometry_at, lambda: ctx.qr_map)
