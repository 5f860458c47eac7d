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
   6-DoF difference (position in the world, rotation vector) against the covariance of the
   difference — the two poses' covariances with the sources they share cancelling (the camera's
   calibration and extrinsic, the shared codes' map entries and corners:
   ``FrameResult.cov_common_factors``), each pose with a small floor (``checks_pose_floor_m`` /
   ``_deg``) — plus the odometry's noise per metre and per degree turned, in the floor's plane
   only for a planar (wheel) odometry step, whose roll, pitch and height stay the reference's up
   to the floor's flatness (``checks_floor_tilt_deg``, ``checks_floor_height_m``). A failing frame
   does not become the reference, so a stretch of frames on a wrong map entry keeps failing (a
   rigid error of the map leaves frame-to-frame steps intact: only the carried reference sees
   it); a frame whose step from the suspect frame before it agrees with the odometry carries its
   error on — a code's error while the code is in view, a camera-level offset across changing
   codes as the camera's **extrinsic**. After ``REANCHOR_M`` of travel in one failing stretch the
   reference moves on (the odometry itself may have jumped).
2. **markers** — the joint solve's χ² test of each marker against the joint pose
   (:class:`~agvviz.solvers.joint.MarkerCheck`): a marker left out names itself.
3. **ambiguity** — the rejected mirror pose (``T_world_agv_ghost``) and the chosen one against
   the same motion witness: with an IPPE ratio under ``checks_ambiguity_ratio``, a flip when the
   likelihood ratio mirror : chosen exceeds the χ²₆ 99 % quantile (90 % right after a flip of
   the same codes); at any ratio, when the mirror pose passes the motion check and the chosen one
   fails it. A frame whose mirror pose the motion likes at least as well is no reference.
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

**Run-level findings**: a fault of the whole log is stated once, at the end of the run
(:meth:`CheckStage.run_findings`, handed to the sinks in the graph's outcome): a camera's stamp
offset against the odometry, estimated from all its clean steps, covers every solved frame of
the camera (a constant offset misplaces each of them, but shows only where the twist changes).
The summary counts the frames it covers and lists it as one stretch (:func:`all_stretches`).
"""

from agvviz.replay.checks.common import NEXT_STEP, CheckSettings, chi2_sigma, mahalanobis_sigma, pose_cov, pose_difference
from agvviz.replay.checks.stage import CheckStage, check_stage
from agvviz.replay.checks.stretches import (
    all_stretches,
    finding_dict,
    finding_stretch,
    stretch_dict,
    suspect_stretches,
    suspects_summary,
)

__all__ = [
    "NEXT_STEP", "CheckSettings", "CheckStage", "check_stage", "chi2_sigma", "mahalanobis_sigma", "pose_cov",
    "pose_difference", "all_stretches", "finding_dict", "finding_stretch", "stretch_dict", "suspect_stretches",
    "suspects_summary",
]
