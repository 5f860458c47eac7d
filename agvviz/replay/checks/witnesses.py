"""The check stage's witness checks (mixed into :class:`agvviz.replay.checks.stage.CheckStage`):
each solved pose against the other witnesses of its own frame and stamp — (2) the frame's other
markers, (4) the payload against the map, (5) the other cameras at the same stamp, (6) the latest
UWB fix. See :mod:`agvviz.replay.checks`."""

from __future__ import annotations

import math

import numpy as np

from agvviz.model import suspects
from agvviz.model.frames import FrameResult
from agvviz.replay.checks.common import (
    PERSISTENT_MIN,
    PERSISTENT_SHARE,
    UWB_MAX_DT_NS,
    chi2_sigma,
    mahalanobis_sigma,
    pose_cov,
    pose_difference,
    size_text,
)


class WitnessChecks:
    """The witness checks of :class:`~agvviz.replay.checks.stage.CheckStage` (it holds the state:
    ``settings``, ``qr_map``, ``_at_stamp``, ``_uwb`` and the per-camera ``_CameraState``; the
    time-offset fit ``_time_offset`` comes from :class:`~agvviz.replay.checks.timing.ClockChecks`)."""

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
    def _cameras(self, frame: FrameResult, state):
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
    def _uwb_check(self, frame: FrameResult, state) -> suspects.CheckResult | None:
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
