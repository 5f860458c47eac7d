"""Entity paths and timeline names of a run ``.rrd`` — one tree for every run.

Every run uses the same tree so that two runs overlay in one viewer and diff column by
column. Transforms in Rerun are hierarchical, so the truth pose and the camera-pipeline
estimate are siblings directly under ``world/agv`` (neither inherits the other) and the
camera hangs under the *estimated* AGV pose (its frustum shows where the pipeline thinks
the camera is).

::

    world                                   ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/markers                           marker outlines + labels (static)
    world/markers/fill                      faint marker faces (static)
    world/agv/truth                         Transform3D T_world_agv (truth)
    world/agv/truth/body                    AGV body box
    world/agv/camera                        Transform3D T_world_agv (camera pipeline estimate)
    world/agv/camera/body                   AGV body box (grey on rejected frames)
    world/agv/camera/cam_<name>             Transform3D T_agv_cam + Pinhole (static)
    world/agv/camera/cam_<name>/image       EncodedImage (recorded bytes)
    world/agv/camera/cam_<name>/image/detected      Points2D detected corners
    world/agv/camera/cam_<name>/image/reprojected   Points2D reprojected corners
    world/trajectory/truth|camera           LineStrips3D, growing over time
    solver/lm/cost_per_iteration            BarChart: cost of each LM iteration of the frame
    solver/lm/cost|reproj_rms_px|damping|step_norm   Scalars on timelines lm_iter + frame + time
    errors/position_mm|heading_deg|pitch_deg|roll_deg|reproj_rms_px   Scalars per frame (when known)
    errors/rejected                         Scalars 0.0 on rejected frames (a marker in plots)
    events/rejections                       TextLog (WARN) with reason and detail
    run/manifest, run/summary               TextDocument (static, markdown + JSON block)
"""

from __future__ import annotations

from agvviz.conventions import camera_frame

# -- timelines ------------------------------------------------------------------------------
#: Recording time (timestamp timeline, from ``FrameResult.log_time_ns``).
TIMELINE_TIME = "time"
#: Frame index (sequence timeline, ``FrameResult.index``).
TIMELINE_FRAME = "frame"
#: Time since the recording's first stamp (duration timeline, seconds): what the time panel
#: shows, so no wall-clock date from the log appears. ``time`` keeps the absolute stamps.
TIMELINE_ELAPSED = "elapsed"
#: LM iteration index (sequence timeline, only on ``solver/lm/*`` scalar columns).
TIMELINE_LM_ITER = "lm_iter"

# -- 3D world -------------------------------------------------------------------------------
WORLD = "world"
MARKERS = "world/markers"
MARKERS_FILL = "world/markers/fill"
AGV_TRUTH = "world/agv/truth"
AGV_TRUTH_BODY = "world/agv/truth/body"
AGV_CAMERA = "world/agv/camera"
AGV_CAMERA_BODY = "world/agv/camera/body"
TRAJECTORY_TRUTH = "world/trajectory/truth"
TRAJECTORY_CAMERA = "world/trajectory/camera"

# -- solver, errors, events, run ------------------------------------------------------------
LM_COST_PER_ITERATION = "solver/lm/cost_per_iteration"
LM_COST = "solver/lm/cost"
LM_REPROJ_RMS_PX = "solver/lm/reproj_rms_px"
LM_DAMPING = "solver/lm/damping"
LM_STEP_NORM = "solver/lm/step_norm"
ERROR_POSITION_MM = "errors/position_mm"
ERROR_HEADING_DEG = "errors/heading_deg"
ERROR_PITCH_DEG = "errors/pitch_deg"
ERROR_ROLL_DEG = "errors/roll_deg"
ERROR_REPROJ_RMS_PX = "errors/reproj_rms_px"
ERROR_REJECTED = "errors/rejected"
EVENTS_REJECTIONS = "events/rejections"
RUN_MANIFEST = "run/manifest"
RUN_SUMMARY = "run/summary"


def camera(cam_name: str, fixed: bool = False) -> str:
    """Entity of camera ``cam_name`` (extrinsic + Pinhole): under the estimated AGV pose, or
    under ``world/cameras`` for a camera ``fixed`` in the world (paper 003's wall cameras)."""
    return f"{FIXED_CAMERAS if fixed else AGV_CAMERA}/{camera_frame(cam_name)}"


def image(cam_name: str, fixed: bool = False) -> str:
    """Entity of the recorded image of camera ``cam_name``."""
    return f"{camera(cam_name, fixed)}/image"


def detected(cam_name: str, fixed: bool = False) -> str:
    """Entity of the detected corners (Points2D, image pixels) of camera ``cam_name``."""
    return f"{image(cam_name, fixed)}/detected"


def reprojected(cam_name: str, fixed: bool = False) -> str:
    """Entity of the reprojected corners (Points2D, image pixels) of camera ``cam_name``."""
    return f"{image(cam_name, fixed)}/reprojected"


# -- UWB and camera–UWB fusion (paper 003) ----------------------------------------------------
#: World-fixed cameras: ``world/cameras/cam_<name>`` (Transform3D T_world_cam + Pinhole, static).
FIXED_CAMERAS = "world/cameras"
UWB_ANCHORS = "world/uwb/anchors"  # Points3D with ids (static)
AGV_UWB = "world/agv/uwb"  # Transform3D: the latest UWB fix (position only)
AGV_FUSED = "world/agv/fused"  # Transform3D: the latest fused position
TRAJECTORY_UWB = "world/trajectory/uwb"
TRAJECTORY_FUSED = "world/trajectory/fused"
UWB_GDOP = "uwb/gdop"  # Scalars per UWB fix
ERROR_UWB_POSITION_M = "errors/uwb_position_m"  # 2-D error of each UWB fix
ERROR_FUSED_POSITION_M = "errors/fused_position_m"  # 2-D error of each fused output
EVENTS_FUSION = "events/fusion"  # TextLog: every switch, with its offset and jump
EVENTS_UWB_GATE = "events/uwb_gate"  # TextLog: every range a gate removed
FUSION_CAMERA_USED = "fusion/camera_used"  # Scalars: index of the camera used (−1: none)
UWB_RANGE_KINDS = ("measured", "predicted_truth", "predicted_estimate", "gated")


def uwb_range(anchor_id: str, kind: str) -> str:
    """``uwb/range/<anchor>/<kind>`` Scalars, kind one of :data:`UWB_RANGE_KINDS` (m); "gated"
    repeats the measured range of every range a gate (residual or Kalman) removed."""
    return f"uwb/range/{anchor_id}/{kind}"


def uwb_gate(anchor_id: str) -> str:
    """``uwb/gate/<anchor>`` Scalars per UWB fix: 1 the range was used, 0 the gate removed it."""
    return f"uwb/gate/{anchor_id}"


# -- pose uncertainty and planar ambiguity ----------------------------------------------------
#: Ellipsoids3D under the estimated AGV pose (AGV frame): the 3σ position covariance
#: magnified by ``run_logger.POSITION_COV_SCALE`` (sub-millimetre otherwise); cleared when none.
AGV_CAMERA_POSITION_COV = "world/agv/camera/position_cov"
#: Transform3D T_world_agv of the rejected ambiguity candidate (the ghost) + its body box.
AGV_GHOST = "world/agv/ghost"
AGV_GHOST_BODY = "world/agv/ghost/body"
ERROR_NEES = "errors/nees"  # Scalars: NEES of T_world_agv vs truth (expected 6; 3 for planar)
ERROR_POSITION_OVER_CRLB = "errors/position_over_crlb"  # Scalars: position error ÷ CRLB
ERROR_CRLB_POSITION_M = "errors/crlb_position_m"  # Scalars: CRLB sqrt(trace) at the true pose
ERROR_POSITION_SIGMA_M = "errors/position_sigma_m"  # Scalars: sqrt(trace) of the covariance
SOLVER_AMBIGUITY_RATIO = "solver/ambiguity_ratio"  # Scalars: IPPE rms(other)/rms(best), capped
EVENTS_FLIPS = "events/flips"  # TextLog (WARN): frames whose pose flipped branch
