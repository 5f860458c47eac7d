"""Entity paths and timeline names of every ``.rrd`` agvviz writes — the only module that spells them.

Every logger and every blueprint (:mod:`agvviz.viz.blueprints`) takes its entity paths from here
(``tests/test_viz_paths.py`` fails on an entity-path literal anywhere else in ``agvviz/``).

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
    world/agv/camera/cam_<name>/image/marker_ids    Points2D: each code's id at its centre
    world/agv/camera/cam_<name>/image/lm_iteration  Points2D per LM iteration (lm_iter columns)
    world/agv/camera/cam_<name>/image/lm_path       LineStrips2D: each point's LM start → final
    world/markers_seen                      LineStrips3D: outlines + ids of this frame's codes
    zoom/cam_<name>/image[/detected|/reprojected]   crop around a small code (≈15 px) + corners
    world/trajectory/truth|camera           LineStrips3D, growing over time
    solver/lm/log10_cost|log10_damping|log10_step_norm_per_iteration   BarChart of the frame's LM
    solver/lm/this_frame                    TextDocument: the frame's solve (or "closed-form")
    solver/lm/iterations                    Scalars per frame: LM trial steps
    solver/lm/cost|log10_cost|reproj_rms_px|damping|step_norm   Scalars on lm_iter + frame + time
    errors/position_mm|heading_deg|pitch_deg|roll_deg|reproj_rms_px   Scalars per frame (when known;
                                            a Clear on rejected frames breaks the line)
    errors/reproj_threshold_px              Scalars per frame: the max_reproj_px setting
    errors/rejected/<series>/<reason>       Scalars on rejected frames only, one entity per plotted
                                            series and reason: a red cross at the limit the frame broke
                                            (max_reproj_px on the reprojection plot) or at the top of
                                            the plot's axis; its series name says why (hover)
    errors/suspect/position_mm|heading_deg|pitch_deg|roll_deg|reproj_rms_px   Scalars on suspect
                                            frames only: the frame's value (a marker on each plot)
    events/rejections                       TextLog (WARN) with reason and detail
    events/suspects                         TextLog (WARN) per suspect frame: check, σ, cause, message
    run/manifest, run/summary               TextDocument (static, markdown + JSON block)
    run/no_truth                            TextDocument (static): a run without ground truth says so
"""

from __future__ import annotations

import re

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
#: BarCharts of the current frame's LM iterations (log10 values; the x axis is the iteration).
LM_LOG10_COST_PER_ITERATION = "solver/lm/log10_cost_per_iteration"
LM_LOG10_DAMPING_PER_ITERATION = "solver/lm/log10_damping_per_iteration"
LM_LOG10_STEP_NORM_PER_ITERATION = "solver/lm/log10_step_norm_per_iteration"
#: TextDocument per frame: what the solver did (iterations, cost start → final; or closed-form).
LM_THIS_FRAME = "solver/lm/this_frame"
LM_ITERATIONS = "solver/lm/iterations"  # Scalars per frame: LM trial steps
LM_COST = "solver/lm/cost"
LM_LOG10_COST = "solver/lm/log10_cost"  # lm_iter columns: log10 of the cost
LM_REPROJ_RMS_PX = "solver/lm/reproj_rms_px"
LM_DAMPING = "solver/lm/damping"
LM_STEP_NORM = "solver/lm/step_norm"
ERROR_POSITION_MM = "errors/position_mm"
ERROR_HEADING_DEG = "errors/heading_deg"
ERROR_PITCH_DEG = "errors/pitch_deg"
ERROR_ROLL_DEG = "errors/roll_deg"
ERROR_REPROJ_RMS_PX = "errors/reproj_rms_px"
#: Parent of the rejected-frame markers: ``errors/rejected/<series>/<reason>`` (:func:`error_rejected`).
ERROR_REJECTED = "errors/rejected"
ERROR_REPROJ_THRESHOLD_PX = "errors/reproj_threshold_px"  # the max_reproj_px setting per frame
MARKERS_SEEN = "world/markers_seen"  # LineStrips3D: outlines and ids of this frame's codes
ZOOM = "zoom"
EVENTS_REJECTIONS = "events/rejections"
#: TextLog (WARN), one row per suspect frame (issue 25): the check, its σ, the likely cause, the
#: marker or camera it names, the finding and the next step.
EVENTS_SUSPECTS = "events/suspects"
#: Parent of the suspect markers on the error plots: ``errors/suspect/<series>`` holds, on suspect
#: frames only, the value of ``errors/<series>`` (:func:`error_suspect`).
ERROR_SUSPECT = "errors/suspect"
#: The error series whose plots mark the suspect frames.
SUSPECT_MARKED = (ERROR_POSITION_MM, ERROR_HEADING_DEG, ERROR_PITCH_DEG, ERROR_ROLL_DEG, ERROR_REPROJ_RMS_PX)


def error_suspect(error_entity: str) -> str:
    """``errors/suspect/<name>``: the suspect-frame markers of the error series ``errors/<name>``."""
    return f"{ERROR_SUSPECT}/{error_entity.rsplit('/', 1)[-1]}"


def error_rejected(series_entity: str, reason: str) -> str:
    """``errors/rejected/<series>/<reason>``: the markers of the frames rejected for ``reason`` on the
    plot of ``series_entity`` (a rejected frame has no value in any series: the marker stands in)."""
    return f"{ERROR_REJECTED}/{series_entity.rsplit('/', 1)[-1]}/{reason}"


def error_rejected_all(series_entity: str) -> str:
    """Query of every rejection marker on the plot of ``series_entity`` (all reasons)."""
    return f"{ERROR_REJECTED}/{series_entity.rsplit('/', 1)[-1]}/**"


RUN_MANIFEST = "run/manifest"
RUN_SUMMARY = "run/summary"  # TextDocument (static): the terminal's table (mm, °, px), damage, warnings
RUN_SUMMARY_JSON = "run/summary_json"  # TextDocument (static): the whole summary as a ```json block
#: TextDocument (static), only in a run whose frames carried no ground truth: why its error plots
#: are not there and what the run knows instead (shown where the error plots would be).
RUN_NO_TRUTH = "run/no_truth"


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


def marker_ids(cam_name: str, fixed: bool = False) -> str:
    """Entity of the code ids drawn at each detected code's centre (Points2D with labels)."""
    return f"{image(cam_name, fixed)}/marker_ids"


def lm_iteration(cam_name: str, fixed: bool = False) -> str:
    """Entity of the reprojected points at each LM iteration (Points2D columns on ``lm_iter``)."""
    return f"{image(cam_name, fixed)}/lm_iteration"


def lm_path(cam_name: str, fixed: bool = False) -> str:
    """Entity of each point's path over the frame's LM iterations (LineStrips2D, start → final)."""
    return f"{image(cam_name, fixed)}/lm_path"


def image_overlays(cam_name: str, fixed: bool = False) -> list[str]:
    """The 2D entities drawn over the image of ``cam_name`` (kept out of 3D views)."""
    return [
        f(cam_name, fixed) for f in (detected, reprojected, marker_ids, lm_iteration, lm_path)
    ]


def zoom(cam_name: str) -> str:
    """Root of the zoomed view of ``cam_name``: ``<root>/image`` is a crop around a small code
    (an EncodedImage), ``<root>/image/detected|reprojected`` its corners in crop pixels."""
    return f"{ZOOM}/{camera_frame(cam_name)}"


def zoom_image(cam_name: str) -> str:
    """The crop around ``cam_name``'s smallest code (EncodedImage)."""
    return f"{zoom(cam_name)}/image"


def zoom_detected(cam_name: str) -> str:
    """The detected corners in the crop's pixels (Points2D)."""
    return f"{zoom_image(cam_name)}/detected"


def zoom_reprojected(cam_name: str) -> str:
    """The reprojected corners in the crop's pixels (Points2D)."""
    return f"{zoom_image(cam_name)}/reprojected"


# -- UWB and camera–UWB fusion (paper 003) ----------------------------------------------------
#: World-fixed cameras: ``world/cameras/cam_<name>`` (Transform3D T_world_cam + Pinhole, static).
FIXED_CAMERAS = "world/cameras"
UWB_ANCHORS = "world/uwb/anchors"  # Points3D with ids (static)
UWB_ROOM = "world/uwb/room"  # LineStrips3D (static): the room's outline, from the anchors' extent
AGV_UWB = "world/agv/uwb"  # Transform3D: the latest UWB fix (position only)
AGV_FUSED = "world/agv/fused"  # Transform3D: the latest fused position
TRAJECTORY_UWB = "world/trajectory/uwb"
TRAJECTORY_FUSED = "world/trajectory/fused"
UWB_GDOP = "uwb/gdop"  # Scalars per UWB fix
ERROR_UWB_POSITION_MM = "errors/uwb_position_mm"  # 2-D error of each UWB fix (mm)
ERROR_FUSED_POSITION_MM = "errors/fused_position_mm"  # 2-D error of each fused output (mm)
#: StateChange: what the fused estimate comes from. The state timeline's lane is named by the
#: entity path (Rerun 0.41: no lane name; a space in a path shows escaped, ``/fusion/fused\ from``),
#: so the path reads as words: "fused_from".
FUSION_SOURCE = "fusion/fused_from"
EVENTS_FUSION = "events/fusion"  # TextLog: every switch, with its offset and jump
EVENTS_UWB_GATE = "events/uwb_gate"  # TextLog: every range a gate removed
FUSION_CAMERA_USED = "fusion/camera_used"  # StateChange: camera used ('none': none), logged on change
UWB_RANGE_KINDS = ("measured", "predicted_truth", "predicted_estimate", "gated")


UWB_RANGE = "uwb/range"
UWB_RANGE_KEY = "uwb/range_key"  # TextDocument (static): the colour key of the range plots
UWB_GATE = "uwb/gate"


def uwb_ranges(anchor_id: str) -> str:
    """``uwb/range/<anchor>``: parent of the range series of one anchor (:func:`uwb_range`)."""
    return f"{UWB_RANGE}/{anchor_id}"


def uwb_range(anchor_id: str, kind: str) -> str:
    """``uwb/range/<anchor>/<kind>`` Scalars, kind one of :data:`UWB_RANGE_KINDS` (m); "gated"
    repeats the measured range of every range a gate (residual or Kalman) removed."""
    return f"{uwb_ranges(anchor_id)}/{kind}"


def uwb_gate(anchor_id: str) -> str:
    """``uwb/gate/<anchor>`` Scalars per UWB fix: 1 the range was used, 0 the gate removed it."""
    return f"{UWB_GATE}/{anchor_id}"


# -- pose uncertainty and planar ambiguity ----------------------------------------------------
#: Ellipsoids3D under the estimated AGV pose (AGV frame): the 3σ position covariance
#: magnified by the one constant ``log_uncertainty.COV_MAGNIFICATION`` (its label gives it),
#: drawn above the body; cleared when none.
AGV_CAMERA_POSITION_COV = "world/agv/camera/position_cov"
#: Transform3D T_world_agv of the rejected ambiguity candidate (the ghost) + its body box.
AGV_GHOST = "world/agv/ghost"
AGV_GHOST_BODY = "world/agv/ghost/body"
ERROR_NEES = "errors/nees"  # Scalars: NEES of T_world_agv vs truth (expected 6; 3 for planar)
ERROR_NEES_EXPECTED = "errors/nees_expected"  # Scalars per frame with a NEES: its dof (χ²'s mean)
ERROR_NEES_BOUND_99 = "errors/nees_bound_99"  # Scalars per frame with a NEES: χ²(dof)'s 99 % quantile
ERROR_POSITION_OVER_CRLB = "errors/position_over_crlb"  # Scalars: position error ÷ CRLB
ERROR_CRLB_POSITION_M = "errors/crlb_position_m"  # Scalars: CRLB sqrt(trace) at the true pose
ERROR_POSITION_SIGMA_M = "errors/position_sigma_m"  # Scalars: sqrt(trace) of the covariance
SOLVER_AMBIGUITY_RATIO = "solver/ambiguity_ratio"  # Scalars: IPPE rms(other)/rms(best), capped
EVENTS_FLIPS = "events/flips"  # TextLog (WARN): frames whose pose flipped branch

#: The per-frame value series of a run's time-series plots: a rejected frame has no value in any of
#: them (the line breaks) and each of their plots marks it (:func:`error_rejected`).
REJECTION_MARKED = (
    ERROR_POSITION_MM, ERROR_HEADING_DEG, ERROR_PITCH_DEG, ERROR_ROLL_DEG, ERROR_REPROJ_RMS_PX,
    ERROR_POSITION_OVER_CRLB, ERROR_NEES, SOLVER_AMBIGUITY_RATIO, LM_ITERATIONS,
)
#: Reference lines drawn on every frame (a setting or a bound, not a frame's value).
LIMIT_LINES = (ERROR_REPROJ_THRESHOLD_PX,)


# -- agvviz audit (agvviz/viz/log_audit.py) ---------------------------------------------------------
#: ``agvviz audit``'s .rrd: the report, the map as recorded and as estimated, the solved vehicle
#: path and camera mounting, and per-marker corner residuals (timelines ``frame`` and ``time``).
AUDIT_REPORT = "audit/report"  # TextDocument (static): the audit table as markdown
AUDIT_MARKERS_RECORDED = "world/audit/markers/recorded"  # LineStrips3D (static): outlines as mapped
AUDIT_MARKERS_ESTIMATED = "world/audit/markers/estimated"  # LineStrips3D (static): outlines as estimated
AUDIT_MARKERS_FLAGGED = "world/audit/markers/flagged"  # Points3D + labels (static): flagged markers
AUDIT_MARKERS_SHIFT = "world/audit/markers/shift"  # Arrows3D (static): mapped → estimated centre, flagged
AUDIT_TRAJECTORY_ESTIMATED = "world/audit/trajectory/estimated"  # LineStrips3D (static): solved vehicle path
AUDIT_TRAJECTORY_START = "world/audit/trajectory/start"  # LineStrips3D (static): the solve's start
AUDIT_TRAJECTORY_TRUTH = "world/audit/trajectory/truth"  # LineStrips3D (static): ground truth, when recorded
AUDIT_AGV = "world/audit/agv"  # Transform3D per frame: the solved vehicle pose
AUDIT_RESIDUALS = "audit/residuals"  # parent of the per-marker corner residual series
AUDIT_ODOMETRY = "audit/odometry"  # parent of the odometry step residual series
AUDIT_ODOMETRY_XY_MM = f"{AUDIT_ODOMETRY}/xy_mm"  # Scalars per frame: odometry step residual (mm)
AUDIT_ODOMETRY_HEADING_DEG = f"{AUDIT_ODOMETRY}/heading_deg"  # Scalars per frame: heading step residual (deg)


def audit_camera(cam_name: str, which: str) -> str:
    """``world/audit/agv/cam_<name>/<which>``: Transform3D (static) of the camera as
    ``recorded`` or ``estimated`` under the solved vehicle, with its axes."""
    return f"{AUDIT_AGV}/{camera_frame(cam_name)}/{which}"


def audit_camera_label(cam_name: str, which: str) -> str:
    """``world/audit/agv/cam_<name>/<which>/label``: Points3D (static), the camera's labelled dot."""
    return f"{audit_camera(cam_name, which)}/label"


def audit_marker_residual(marker_id: str) -> str:
    """``audit/residuals/<marker>``: Scalars per frame, RMS corner residual (px) of the marker."""
    safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in str(marker_id))
    return f"{AUDIT_RESIDUALS}/{safe}"


# -- paper 002's correction cycle (agvviz/viz/log_correction.py) ----------------------------------
#: CNOEM solver iteration (sequence timeline, only on the window's iteration columns).
TIMELINE_CNOEM_ITER = "cnoem_iter"
CORRECTION_WORLD = "world/correction"  # parent of the correction run's 3D entities
#: LineStrips3D: true, raw navigation and corrected navigation trajectories.
CORRECTION_TRAJECTORY_TRUTH = f"{CORRECTION_WORLD}/trajectory/truth"
CORRECTION_TRAJECTORY_NAV = f"{CORRECTION_WORLD}/trajectory/nav"
CORRECTION_TRAJECTORY_CORRECTED = f"{CORRECTION_WORLD}/trajectory/corrected"
#: Transform3D T_world_agv of the current poses, each with a ``body`` box (:func:`correction_body`).
CORRECTION_AGV_TRUTH = f"{CORRECTION_WORLD}/agv/truth"
CORRECTION_AGV_NAV = f"{CORRECTION_WORLD}/agv/nav"
CORRECTION_AGV_CORRECTED = f"{CORRECTION_WORLD}/agv/corrected"
CORRECTION_WINDOW_CAMERAS = f"{CORRECTION_WORLD}/window/cameras"  # Points3D: the last window's cameras
CORRECTION_WINDOW_RAYS = f"{CORRECTION_WORLD}/window/rays"  # LineStrips3D: the closing frame's sight lines
CORRECTION_COST = "correction/cost"  # Scalars per iteration (cnoem_iter)
CORRECTION_REPROJ_RMS_PX = "correction/reproj_rms_px"  # Scalars per iteration (cnoem_iter)
CORRECTION_COST_PER_ITERATION = "correction/cost_per_iteration"  # BarChart of the last cycle
CORRECTION_REPROJ_RMS_PX_PER_ITERATION = "correction/reproj_rms_px_per_iteration"  # BarChart of the last cycle
CORRECTION_CYCLE_REPROJ_RMS_PX = "correction/cycle/reproj_rms_px"  # Scalars per closed cycle
CORRECTION_CYCLE_MAX_REPROJ_PX = "correction/cycle/max_reproj_px"  # Scalars per frame: the gate's limit
CORRECTION_CYCLE_POSITION_SIGMA_MM = "correction/cycle/position_sigma_mm"  # Scalars per closed cycle
CORRECTION_CYCLE_MAX_POSITION_SIGMA_MM = "correction/cycle/max_position_sigma_mm"  # Scalars per frame: the limit
ERROR_NAV_MM = "errors/nav_position_mm"  # Scalars per frame: navigation error vs truth
ERROR_CORRECTED_MM = "errors/corrected_position_mm"  # Scalars per frame: corrected error vs truth
ERROR_CORRECTION_JUMP_MM = "errors/correction_jump_mm"  # Scalars per applied correction
EVENTS_CORRECTIONS = "events/corrections"  # TextLog per closed cycle with the jump


def correction_body(agv_entity: str) -> str:
    """The body box under one of the correction run's vehicle poses."""
    return f"{agv_entity}/body"


def correction_observed(cam_name: str) -> str:
    """Points2D: the last window's measured corners on the image of ``cam_name``."""
    return f"{image(cam_name)}/window_observed"


def correction_theoretical(cam_name: str) -> str:
    """Points2D per CNOEM iteration (``cnoem_iter``): the window's solved corners."""
    return f"{image(cam_name)}/window_theoretical"


def correction_status(cam_name: str) -> str:
    """Points2D with one label at the image centre: which window the panel shows (closed at
    which frame), or why it shows none yet (a corner-only run has no image)."""
    return f"{image(cam_name)}/window_status"


def correction_border(cam_name: str) -> str:
    """Boxes2D (static): the image outline of ``cam_name``."""
    return f"{image(cam_name)}/border"


# -- error budget (agvviz/viz/log_budget.py) --------------------------------------------------------
BUDGET = "budget"
BUDGET_TABLE = f"{BUDGET}/table"  # TextDocument (static): the budget as a markdown table
BUDGET_SHARES = f"{BUDGET}/shares_pct"  # the chart of shares (%), a 2D view (static), below:
BUDGET_SHARE_BARS = f"{BUDGET_SHARES}/bars"  # Boxes2D: one bar per source, then interaction/other, labelled
BUDGET_SHARE_CI = f"{BUDGET_SHARES}/ci"  # LineStrips2D: each bar's bootstrap interval (a whisker)
BUDGET_SHARE_AXIS = f"{BUDGET_SHARES}/axis"  # LineStrips2D: the 0 % line and the grid at every 25 %
BUDGET_SHARE_LABELS = f"{BUDGET_SHARES}/labels"  # Points2D right of the bars: each bar's label
BUDGET_SHARE_TICKS = f"{BUDGET_SHARES}/ticks"  # Points2D: the grid's labels ("0 %", "25 %", …)
#: Series names of the recording's own error (every source on) and of the floor (all off).
BUDGET_ALL_ON = "all_on"
BUDGET_ALL_OFF = "all_off"


def budget_series_relative(source: str, what: str = "position_error_mm") -> str:
    """``<source>/<what>`` below :data:`BUDGET` (``/`` in a source name becomes ``_``)."""
    return f"{source.replace('/', '_')}/{what}"


def budget_series(source: str, what: str = "position_error_mm") -> str:
    """``budget/<source>/<what>``: Scalars per frame, ``what`` is ``position_error_mm`` or ``delta_mm``."""
    return f"{BUDGET}/{budget_series_relative(source, what)}"


# -- studies: p4p Monte-Carlo and CNOEM grid (agvviz/viz/log_studies.py) ------------------------------
#: Trial index within its cell (sequence timeline).
TIMELINE_TRIAL = "trial"
#: The paper cells' SNR (dB) and the CRLB cells' σ in milli-pixels (sequence timelines).
TIMELINE_SNR_DB = "snr_db"
TIMELINE_SIGMA_MPX = "sigma_mpx"
#: The CNOEM grid report's cell index (sequence timeline).
TIMELINE_CELL = "cell"
MC_REPORT = "mc/report"  # TextDocument (static): the Monte-Carlo report
MC_PAPER = "mc/paper"  # mc/paper/h<h>_z<z>_n<N>: the paper cells of one geometry, over snr_db
MC_CRLB = "mc/crlb"  # mc/crlb/tilt<t>_h<h>_z<z>_n<N>: the CRLB cells of one geometry, over sigma_mpx
MC_FIG9_11 = f"{MC_PAPER}/h0.2667_z2_n4"  # the paper cells of figures 9–11
#: Ids of the Monte-Carlo study's paper and CRLB cells (:mod:`agvviz.replay.studies.monte_carlo_cells`).
MC_PAPER_CELL = re.compile(r"paper_h(?P<h>[\d.]+)_z(?P<z>[\d.]+)_snr(?P<snr>\d+)_n(?P<n>\d)")
MC_CRLB_CELL = re.compile(r"crlb_tilt(?P<tilt>[\d.]+)_h(?P<h>[\d.]+)_z(?P<z>[\d.]+)_s(?P<s>[\d.]+)_n(?P<n>\d)")


def mc_trial_errors(cell_id: str) -> str:
    """``mc/trials/<cell>/error_mm``: one Scalars child per solver (and ``crlb``) over ``trial``."""
    return f"mc/trials/{cell_id}/error_mm"


def mc_paper_group(cell_id: str) -> str | None:
    """The group of paper cell ``cell_id`` (``mc/paper/h<h>_z<z>_n<N>``); None: not a paper cell."""
    m = MC_PAPER_CELL.fullmatch(cell_id)
    return f"{MC_PAPER}/h{m['h']}_z{m['z']}_n{m['n']}" if m else None


def mc_crlb_group(cell_id: str) -> str | None:
    """The group of CRLB cell ``cell_id`` (``mc/crlb/tilt<t>_h<h>_z<z>_n<N>``); None: not a CRLB cell."""
    m = MC_CRLB_CELL.fullmatch(cell_id)
    return f"{MC_CRLB}/tilt{m['tilt']}_h{m['h']}_z{m['z']}_n{m['n']}" if m else None


CNOEM_REPORT = "cnoem/report"  # TextDocument (static): the CNOEM study report
CNOEM_MEAN_ERROR_M = "cnoem/mean_error_m"  # Scalars per cell, one child per method
CNOEM_RATIO_TO_IPPE_FIRST = "cnoem/ratio_to_ippe_first"  # Scalars per cell
CNOEM_RMS_OVER_CRLB = "cnoem/rms_over_crlb"  # Scalars per cell, one child per method
CNOEM_CRLB_M = "cnoem/crlb_m"  # Scalars per cell: the CRLB position bound (m)


def cnoem_trial_errors(cell_id: str) -> str:
    """``cnoem/trials/<cell>/error_m``: one Scalars child per method (and ``crlb``) over ``trial``."""
    return f"cnoem/trials/{cell_id}/error_m"


# -- overlay of several runs: agvviz diff / sweep (agvviz/viz/overlay.py) ----------------------------
OVERLAY_IMAGE = "image"  # image/<cam>: the first run's image; image/<cam>/<key>: a run's reprojection
OVERLAY_ERRORS = "errors"  # errors/<quantity>/<key>: Scalars per frame
OVERLAY_DELTA = "delta"  # delta/<quantity>: B − A; delta/<quantity>/zero: the zero line
OVERLAY_ERROR_VECTORS = "world/error"  # world/error/<key>: Arrows3D, the magnified position error
OVERLAY_ERROR_PATHS = "world/error_path"  # world/error_path/<key>: LineStrips3D (static)
COMPARE_REPORT = "compare/report"  # TextDocument (static): the comparison table
#: TextDocument (static): which colour is which run, the one key of every overlay view (3D views
#: and plots carry no per-run labels or legends that could collide or cover the data).
COMPARE_KEY = "compare/key"
AGV = "world/agv"
TRAJECTORY = "world/trajectory"


def overlay_agv(key: str) -> str:
    """``world/agv/<key>``: Transform3D per solved frame of run ``key``."""
    return f"{AGV}/{key}"


def overlay_agv_marker(key: str) -> str:
    """``world/agv/<key>/marker``: the run's position marker."""
    return f"{overlay_agv(key)}/marker"


def overlay_trajectory(key: str) -> str:
    """``world/trajectory/<key>``: LineStrips3D, the whole estimated trajectory of run ``key``."""
    return f"{TRAJECTORY}/{key}"


def overlay_error_vector(key: str) -> str:
    """``world/error/<key>``: Arrows3D per frame, the run's magnified position error (unlabelled on
    screen: the key, :data:`COMPARE_KEY`, names the colours; the view title the magnification)."""
    return f"{OVERLAY_ERROR_VECTORS}/{key}"


def overlay_error_path(key: str) -> str:
    return f"{OVERLAY_ERROR_PATHS}/{key}"


def overlay_image(cam_name: str) -> str:
    """``image/<cam>``: the first run's image of ``cam_name`` (copied)."""
    return f"{OVERLAY_IMAGE}/{cam_name}"


def overlay_detected(cam_name: str) -> str:
    return f"{overlay_image(cam_name)}/detected"


def overlay_reprojected(cam_name: str, key: str) -> str:
    return f"{overlay_image(cam_name)}/{key}"


def overlay_errors(quantity: str) -> str:
    """``errors/<quantity>``: parent of every run's series of ``quantity``."""
    return f"{OVERLAY_ERRORS}/{quantity}"


def overlay_error(quantity: str, key: str) -> str:
    return f"{overlay_errors(quantity)}/{key}"


def overlay_delta(quantity: str) -> str:
    return f"{OVERLAY_DELTA}/{quantity}"


def overlay_delta_zero(quantity: str) -> str:
    return f"{overlay_delta(quantity)}/zero"


# -- the sweep .rrd: agvviz sweep, diff --out (agvviz/viz/overlay.py, issue 27) -------------------
#: A sweep ``.rrd`` holds the overlay above (frames once under ``image/<cam>``, the settings drawn
#: together) and, under ``settings/<key>/``, each setting's layers: every entity of a run
#: ``.rrd`` at its own path below the prefix (``settings/<key>/world/agv/camera``,
#: ``settings/<key>/errors/position_mm``, ``settings/<key>/run/manifest``, ...) except the
#: camera images, which are under ``image/<cam>`` once.
SWEEP_SETTINGS = "settings"
SWEEP_INDEX = "sweep/index"  # TextDocument (static): JSON block, one entry per setting: key, label, rank, settings


def sweep_setting(key: str) -> str:
    """``settings/<key>``: root of one setting's layers in a sweep ``.rrd``."""
    return f"{SWEEP_SETTINGS}/{key}"


def sweep_layer(key: str, entity: str) -> str:
    """``settings/<key>/<entity>``: a run entity (e.g. :data:`ERROR_POSITION_MM`) of setting ``key``."""
    return f"{sweep_setting(key)}/{entity}"


_CAMERA_IMAGE = re.compile(rf"^({re.escape(AGV_CAMERA)}|{re.escape(FIXED_CAMERAS)})/{re.escape(camera_frame(''))}[^/]+/image$")


def camera_images(entity_paths) -> list[str]:
    """The camera image entities (:func:`image`) among ``entity_paths``, sorted (zoom crops are not)."""
    return sorted(p for p in entity_paths if _CAMERA_IMAGE.match(p))
