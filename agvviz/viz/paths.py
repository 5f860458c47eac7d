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
    errors/position_m|heading_deg|reproj_rms_px      Scalars per frame (when known)
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
ERROR_POSITION_M = "errors/position_m"
ERROR_HEADING_DEG = "errors/heading_deg"
ERROR_REPROJ_RMS_PX = "errors/reproj_rms_px"
ERROR_REJECTED = "errors/rejected"
EVENTS_REJECTIONS = "events/rejections"
RUN_MANIFEST = "run/manifest"
RUN_SUMMARY = "run/summary"


def camera(cam_name: str) -> str:
    """Entity of camera ``cam_name`` (extrinsic + Pinhole), under the estimated AGV pose."""
    return f"{AGV_CAMERA}/{camera_frame(cam_name)}"


def image(cam_name: str) -> str:
    """Entity of the recorded image of camera ``cam_name``."""
    return f"{camera(cam_name)}/image"


def detected(cam_name: str) -> str:
    """Entity of the detected corners (Points2D, image pixels) of camera ``cam_name``."""
    return f"{image(cam_name)}/detected"


def reprojected(cam_name: str) -> str:
    """Entity of the reprojected corners (Points2D, image pixels) of camera ``cam_name``."""
    return f"{image(cam_name)}/reprojected"
