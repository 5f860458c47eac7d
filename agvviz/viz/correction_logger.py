"""Log paper 002's correction cycle (:mod:`agvviz.replay.correct`) into a run ``.rrd``.

Entities (timelines ``frame``, ``time`` and ``elapsed``; the solver's iterations also on
``cnoem_iter``):

``world/correction/trajectory/{truth,nav,corrected}``   LineStrips3D: true, raw navigation and
                                                        corrected navigation trajectories
``world/correction/agv/{truth,nav,corrected}``          Transform3D T_world_agv of the current
                                                        poses, each with a ``body`` box (the 3D
                                                        view follows ``corrected``)
``world/correction/window/cameras``                     Points3D: every camera position of the
                                                        last closed window (at the solution)
``world/correction/window/rays``                        LineStrips3D: the closing frame's
                                                        sight lines, camera → marker centre
``<camera image>/window_observed``                      Points2D: the last window's measured
                                                        corners, in the recorded image's pixels
``<camera image>/window_theoretical``                   Points2D per solver iteration on
                                                        ``cnoem_iter`` (paper Fig. 4); on the
                                                        frame timeline the solution's
``<camera image>/border``                               Boxes2D: the image outline (static), so
                                                        a corner-only run shows the frame
``correction/cost``, ``correction/reproj_rms_px``       Scalars per iteration (``cnoem_iter``)
``correction/cost_per_iteration``,
``correction/reproj_rms_px_per_iteration``              BarCharts of the last cycle
``correction/cycle/reproj_rms_px|position_sigma_mm``    Scalars per closed cycle (points)
``correction/cycle/max_reproj_px|max_position_sigma_mm``  Scalars per frame: the gates' limits
``errors/nav_position_mm``, ``errors/corrected_position_mm``   Scalars per frame vs truth
``errors/correction_jump_mm``                           Scalars per applied correction (points)
``events/corrections``                                  TextLog per closed cycle with the jump

``<camera image>`` is :func:`agvviz.viz.paths.image` (the recorded image when the recording has
images; with corners only the same 2D space holds the corners alone). Window corners are the
solver's ideal pixels, drawn through the camera's distortion so they sit on the image.

Iteration data go out with ``send_columns`` (an iteration TimeColumn), never with
``set_time("cnoem_iter")`` + log, which would leak the iteration onto later logs.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from agvviz.model.correction import CorrectionEvent, CorrectionStep
from agvviz.viz import paths
from agvviz.viz.run_logger import _trajectory
from agvviz.viz.style import (
    COLOR_CAMERA,
    COLOR_CORRECTED,
    COLOR_NAV,
    COLOR_OBSERVED,
    COLOR_THEORETICAL,
    COLOR_THRESHOLD,
    COLOR_TRUTH,
    LEGEND,
)
from agvviz.viz.timelines import elapsed_s, set_stamp

TIMELINE_CNOEM_ITER = "cnoem_iter"
TRAJECTORY_TRUTH = "world/correction/trajectory/truth"
TRAJECTORY_NAV = "world/correction/trajectory/nav"
TRAJECTORY_CORRECTED = "world/correction/trajectory/corrected"
AGV_TRUTH = "world/correction/agv/truth"
AGV_NAV = "world/correction/agv/nav"
AGV_CORRECTED = "world/correction/agv/corrected"
WINDOW_CAMERAS = "world/correction/window/cameras"
WINDOW_RAYS = "world/correction/window/rays"
COST = "correction/cost"
REPROJ_RMS_PX = "correction/reproj_rms_px"
COST_PER_ITERATION = "correction/cost_per_iteration"
REPROJ_RMS_PX_PER_ITERATION = "correction/reproj_rms_px_per_iteration"
CYCLE_REPROJ_RMS_PX = "correction/cycle/reproj_rms_px"
CYCLE_MAX_REPROJ_PX = "correction/cycle/max_reproj_px"
CYCLE_POSITION_SIGMA_MM = "correction/cycle/position_sigma_mm"
CYCLE_MAX_POSITION_SIGMA_MM = "correction/cycle/max_position_sigma_mm"
ERROR_NAV_MM = "errors/nav_position_mm"
ERROR_CORRECTED_MM = "errors/corrected_position_mm"
ERROR_JUMP_MM = "errors/correction_jump_mm"
EVENTS_CORRECTIONS = "events/corrections"

#: Nominal vehicle body drawn around each pose (half sizes x right, y forward, z up, in m). A
#: visual marker only: the recording does not carry a body size.
BODY_HALF_SIZES_M = (0.35, 0.6, 0.2)
#: The corrected body is drawn this much larger, so its outline shows around the truth's when
#: the two coincide (they do to a few cm).
CORRECTED_BODY_SCALE = 1.08
#: Window corners on the image: the solved (theoretical) ones smaller and on top of the observed.
OBSERVED_RADIUS = rr.Radius.ui_points(3.0)
THEORETICAL_RADIUS = rr.Radius.ui_points(1.5)
#: The 3D view's eye in the corrected vehicle's frame (beside, behind and above it) and the point
#: it looks at (ahead of it), m: the view rides along with the vehicle.
EYE_POSITION_AGV_M = (3.0, -7.0, 3.0)
EYE_TARGET_AGV_M = (0.0, 3.0, 0.0)


def image_observed(cam_name: str) -> str:
    return f"{paths.image(cam_name)}/window_observed"


def image_theoretical(cam_name: str) -> str:
    return f"{paths.image(cam_name)}/window_theoretical"


def image_border(cam_name: str) -> str:
    return f"{paths.image(cam_name)}/border"


def body(agv_entity: str) -> str:
    return f"{agv_entity}/body"


class CorrectionLogger:
    """Logs :class:`CorrectionStep` items into ``stream`` (the run logger's recording stream).

    recording_start_ns : the recording's first stamp (``elapsed`` counts from it); None: the
        first step's stamp.
    cameras : camera name → object with ``camera`` (PinholeCamera), read when a window is logged:
        its distortion places the window corners on the image and its size draws the border.
        None: corners drawn at the solver's ideal pixels, no border.
    max_reproj_px, max_position_sigma_m : the cycle gates (threshold lines); None: not drawn.
    """

    def __init__(
        self,
        stream: rr.RecordingStream,
        recording_start_ns: int | None = None,
        cameras: dict | None = None,
        max_reproj_px: float | None = None,
        max_position_sigma_m: float | None = None,
    ):
        self._rec = stream
        self.recording_start_ns = None if recording_start_ns is None else int(recording_start_ns)
        self._cameras = cameras
        self._max_reproj_px = max_reproj_px
        self._max_position_sigma_m = max_position_sigma_m
        self._truth: list[np.ndarray] = []
        self._nav: list[np.ndarray] = []
        self._corrected: list[np.ndarray] = []
        self._index = 0
        self._styled = False
        self._bordered: set[str] = set()

    def _styles(self) -> None:
        rec = self._rec
        for entity, name, color in (
            (ERROR_NAV_MM, LEGEND[COLOR_NAV] + " [mm]", COLOR_NAV),
            (ERROR_CORRECTED_MM, LEGEND[COLOR_CORRECTED] + " [mm]", COLOR_CORRECTED),
            (CYCLE_MAX_REPROJ_PX, "max_reproj_px (reject above)", COLOR_THRESHOLD),
            (CYCLE_MAX_POSITION_SIGMA_MM, "max position σ (reject above)", COLOR_THRESHOLD),
            (COST, "window cost (sum of squared ray residuals)", COLOR_THEORETICAL),
            (REPROJ_RMS_PX, "window reprojection RMS [px]", COLOR_OBSERVED),
        ):
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        for entity, name, color in (
            (ERROR_JUMP_MM, "correction applied: jump [mm]", COLOR_CORRECTED),
            (CYCLE_REPROJ_RMS_PX, "closed cycle: window RMS [px]", COLOR_OBSERVED),
            (CYCLE_POSITION_SIGMA_MM, "closed cycle: position σ [mm]", COLOR_OBSERVED),
        ):
            rec.log(entity, rr.SeriesPoints(names=name, colors=color, marker_sizes=4.0), static=True)
        for entity, name, color, scale in (
            (AGV_TRUTH, LEGEND[COLOR_TRUTH], COLOR_TRUTH, 1.0),
            (AGV_NAV, LEGEND[COLOR_NAV], COLOR_NAV, 1.0),
            (AGV_CORRECTED, LEGEND[COLOR_CORRECTED], COLOR_CORRECTED, CORRECTED_BODY_SCALE),
        ):
            rec.log(
                body(entity),
                rr.Boxes3D(half_sizes=[np.multiply(BODY_HALF_SIZES_M, scale)], colors=color, labels=name, show_labels=False,
                           fill_mode=rr.components.FillMode.MajorWireframe, radii=rr.Radius.ui_points(1.5)),
                static=True,
            )
        self._styled = True

    def _set_time(self, log_time_ns: int) -> None:
        if self.recording_start_ns is None:
            self.recording_start_ns = int(log_time_ns)
        set_stamp(self._rec, self._index, log_time_ns, self.recording_start_ns)

    def log(self, step: CorrectionStep) -> None:
        """One frame time: poses, trajectories, errors, gate limits; the window when a cycle
        closed."""
        if not self._styled:
            self._styles()
        rec = self._rec
        self._set_time(step.log_time_ns)
        self._nav.append(step.T_world_agv_nav[:3, 3])
        self._corrected.append(step.T_world_agv_corrected[:3, 3])
        rec.log(TRAJECTORY_NAV, _trajectory(self._nav, COLOR_NAV))
        rec.log(TRAJECTORY_CORRECTED, _trajectory(self._corrected, COLOR_CORRECTED))
        rec.log(AGV_NAV, _transform(step.T_world_agv_nav))
        rec.log(AGV_CORRECTED, _transform(step.T_world_agv_corrected))
        if step.T_world_agv_truth is not None:
            truth = step.T_world_agv_truth[:3, 3]
            self._truth.append(truth)
            rec.log(TRAJECTORY_TRUTH, _trajectory(self._truth, COLOR_TRUTH))
            rec.log(AGV_TRUTH, _transform(step.T_world_agv_truth))
            rec.log(ERROR_NAV_MM, rr.Scalars(1000.0 * float(np.linalg.norm(step.T_world_agv_nav[:3, 3] - truth))))
            rec.log(ERROR_CORRECTED_MM, rr.Scalars(1000.0 * float(np.linalg.norm(step.T_world_agv_corrected[:3, 3] - truth))))
        if self._max_reproj_px is not None:
            rec.log(CYCLE_MAX_REPROJ_PX, rr.Scalars(float(self._max_reproj_px)))
        if self._max_position_sigma_m is not None:
            rec.log(CYCLE_MAX_POSITION_SIGMA_MM, rr.Scalars(1000.0 * float(self._max_position_sigma_m)))
        if step.event is not None:
            self._log_event(step.event)
        self._index += 1

    def _log_event(self, event: CorrectionEvent) -> None:
        rec = self._rec
        level = rr.TextLogLevel.INFO if event.applied else rr.TextLogLevel.WARN
        if event.applied:
            text = (
                f"cycle {event.cycle_index}: correction jump {event.jump_m * 1000:.1f} mm "
                f"({event.n_sightings} sightings in {event.n_frames} frames; start frame moved "
                f"{np.linalg.norm(event.T_world_F_after[:3, 3] - event.T_world_F_before[:3, 3]) * 1000:.1f} mm)"
            )
            rec.log(ERROR_JUMP_MM, rr.Scalars(1000.0 * event.jump_m))
        else:
            text = f"cycle {event.cycle_index}: no correction: {event.reason} ({event.n_sightings} sightings in {event.n_frames} frames)"
        rec.log(EVENTS_CORRECTIONS, rr.TextLog(text, level=level))
        if event.position_sigma_m is not None and np.isfinite(event.position_sigma_m):
            rec.log(CYCLE_POSITION_SIGMA_MM, rr.Scalars(1000.0 * event.position_sigma_m))
        if event.window is None or event.solution is None or not event.solution.iterations:
            return
        window, iterations = event.window, event.solution.iterations
        costs = np.array([it.cost for it in iterations])
        rms_px = np.array([it.reproj_rms_px for it in iterations])
        rec.log(CYCLE_REPROJ_RMS_PX, rr.Scalars(float(rms_px[-1])))
        rec.log(COST_PER_ITERATION, rr.BarChart(costs, color=COLOR_THEORETICAL))
        rec.log(REPROJ_RMS_PX_PER_ITERATION, rr.BarChart(rms_px, color=COLOR_OBSERVED))
        n = len(iterations)
        indexes = [
            rr.TimeColumn(TIMELINE_CNOEM_ITER, sequence=np.arange(n)),
            rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.full(n, self._index)),
            rr.TimeColumn(paths.TIMELINE_TIME, timestamp=np.full(n, int(event.log_time_ns), dtype=np.int64).astype("datetime64[ns]")),
            rr.TimeColumn(paths.TIMELINE_ELAPSED, duration=np.full(n, elapsed_s(event.log_time_ns, self.recording_start_ns))),
        ]
        rec.send_columns(COST, indexes=indexes, columns=rr.Scalars.columns(scalars=costs))
        rec.send_columns(REPROJ_RMS_PX, indexes=indexes, columns=rr.Scalars.columns(scalars=rms_px))
        cams = [s.cam_name for s in window.sightings]
        corner_cam = np.array([cams[j] for j in window.sighting_index])
        for cam in sorted(set(cams)):
            mask = corner_cam == cam
            camera = self._camera(cam)
            self._log_border(cam, camera)
            K = window.sightings[cams.index(cam)].K
            rec.log(image_observed(cam), rr.Points2D(_image_px(window.pixels_px[mask], K, camera), colors=COLOR_OBSERVED, radii=OBSERVED_RADIUS, draw_order=20.0))
            rec.log(image_theoretical(cam), rr.Points2D.from_fields(colors=COLOR_THEORETICAL, radii=THEORETICAL_RADIUS, draw_order=21.0), static=True)
            projected = np.concatenate([_image_px(window.project(it.T_F_world)[mask], K, camera) for it in iterations])
            columns = rr.Points2D.columns(positions=projected).partition(np.full(n, int(mask.sum())))
            rec.send_columns(image_theoretical(cam), indexes=indexes, columns=columns)
        if event.T_world_F_after is not None:
            T_world_F = event.T_world_F_after
            last_frame = max(s.frame_index for s in window.sightings)
            centres, rays = [], []
            for s in window.sightings:
                c = (T_world_F @ s.T_F_cam)[:3, 3]
                centres.append(c)
                if s.frame_index == last_frame:  # the closing frame's sight lines only
                    rays.append([c, np.mean(s.points_world_m, axis=0)])
            rec.log(WINDOW_CAMERAS, rr.Points3D(centres, colors=COLOR_CAMERA, radii=rr.Radius.ui_points(3.0)))
            rec.log(WINDOW_RAYS, rr.LineStrips3D(rays, colors=(*COLOR_CAMERA, 160), radii=rr.Radius.ui_points(1.0)))

    def _camera(self, cam_name: str):
        state = None if self._cameras is None else self._cameras.get(cam_name)
        return None if state is None else getattr(state, "camera", None)

    def _log_border(self, cam_name: str, camera) -> None:
        if cam_name in self._bordered or camera is None or not camera.width_px or not camera.height_px:
            return
        self._rec.log(
            image_border(cam_name),
            rr.Boxes2D(mins=[[0.0, 0.0]], sizes=[[camera.width_px, camera.height_px]], colors=(110, 110, 110),
                       radii=rr.Radius.ui_points(1.0)),
            static=True,
        )
        self._bordered.add(cam_name)


def _transform(T_world_agv: np.ndarray) -> rr.Transform3D:
    return rr.Transform3D(translation=T_world_agv[:3, 3], mat3x3=T_world_agv[:3, :3])


def _image_px(ideal_px: np.ndarray, K: np.ndarray, camera) -> np.ndarray:
    """Pixels of the recorded image for the solver's ideal pixels (matrix ``K``): through the
    camera's distortion when it is known, else unchanged."""
    if camera is None or not camera.has_distortion:
        return ideal_px
    rays = np.linalg.solve(K, np.column_stack([ideal_px, np.ones(len(ideal_px))]).T).T
    return camera.project(rays)


def correction_blueprint(cam_names: list[str]) -> rrb.Blueprint:
    """Layout of a run with ``correction`` (time panel on ``elapsed``)::

        tab "correction run"
        ┌────────────────────────────────────┬─────────────────────────────────┐
        │ 3D: markers, truth / navigation /  │ per camera: the image (when     │
        │ corrected vehicles + trajectories, │ recorded), this frame's corners │
        │ last window's cameras and rays;    │ and the last window's observed  │
        │ the eye follows the corrected AUV  │ / solved corners                │
        ├──────────────┬──────────────┬──────┴───────────┬─────────────────────┤
        │ error vs     │ corrected    │ closed cycles:   │ corrections log /   │
        │ truth [mm]   │ error [mm]   │ RMS, σ vs limits │ summary / manifest  │
        └──────────────┴──────────────┴──────────────────┴─────────────────────┘
        tab "solver iterations (cnoem_iter)": the window's corners per camera and the last
        cycle's cost and RMS per iteration; scrub the ``cnoem_iter`` timeline to watch the
        theoretical corners converge.

    The 3D view's origin is the corrected vehicle, so its eye (behind, beside and above it,
    :data:`EYE_POSITION_AGV_M`) rides along: the vehicle stays in frame at every time.
    """
    world = rrb.Spatial3DView(
        origin=AGV_CORRECTED,
        name=f"3D: {LEGEND[COLOR_TRUTH]} (green), {LEGEND[COLOR_NAV]} (red), {LEGEND[COLOR_CORRECTED]} (magenta); "
        "last window's camera positions and closing sight lines (orange)",
        contents=["+ /world/markers/**", "+ /world/correction/**"],
        eye_controls=rrb.EyeControls3D(
            position=EYE_POSITION_AGV_M, look_target=EYE_TARGET_AGV_M, eye_up=[0.0, 0.0, 1.0]
        ),
    )
    cameras = [
        rrb.Spatial2DView(
            origin=paths.image(c),
            name=f"camera {c}: window corners observed (white), solved (orange); detected (cyan)",
            contents=["+ $origin/**", f"- {paths.image(c)}/lm_iteration", f"- {paths.image(c)}/lm_path"],
        )
        for c in cam_names
    ]
    errors = rrb.TimeSeriesView(
        origin="/", contents=[f"/{ERROR_NAV_MM}", f"/{ERROR_CORRECTED_MM}", f"/{ERROR_JUMP_MM}"],
        name="position error vs truth [mm]", plot_legend=rrb.PlotLegend(visible=True),
    )
    corrected = rrb.TimeSeriesView(
        origin="/", contents=[f"/{ERROR_CORRECTED_MM}", f"/{ERROR_JUMP_MM}"],
        name="corrected error [mm] (zoomed in)", plot_legend=rrb.PlotLegend(visible=True),
    )
    cycles = rrb.Tabs(
        rrb.TimeSeriesView(
            origin="/", contents=[f"/{CYCLE_REPROJ_RMS_PX}", f"/{CYCLE_MAX_REPROJ_PX}"],
            name="closed cycles: window RMS [px]", plot_legend=rrb.PlotLegend(visible=True),
        ),
        rrb.TimeSeriesView(
            origin="/", contents=[f"/{CYCLE_POSITION_SIGMA_MM}", f"/{CYCLE_MAX_POSITION_SIGMA_MM}"],
            name="closed cycles: position σ [mm]", plot_legend=rrb.PlotLegend(visible=True),
        ),
        active_tab=0,
    )
    documents = rrb.Tabs(
        rrb.TextLogView(
            origin=EVENTS_CORRECTIONS, name="corrections (one line per cycle)",
            columns=rrb.TextLogColumns(timeline_columns=[paths.TIMELINE_ELAPSED], text_log_columns=["body"]),
        ),
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        active_tab=0,
    )
    top = rrb.Horizontal(world, rrb.Vertical(*cameras) if cameras else rrb.Spacer(), column_shares=[0.58, 0.42])
    bottom = rrb.Horizontal(errors, corrected, cycles, documents, column_shares=[0.25, 0.22, 0.22, 0.31])
    run_tab = rrb.Vertical(top, bottom, row_shares=[0.6, 0.4], name="correction run")
    iteration_cameras = [
        rrb.Spatial2DView(
            origin=paths.image(c),
            name=f"camera {c}, last window: observed (white), theoretical at the iteration (orange)",
            contents=[f"+ {image_observed(c)}", f"+ {image_theoretical(c)}", f"+ {image_border(c)}"],
        )
        for c in cam_names
    ]
    solver = rrb.Vertical(
        rrb.BarChartView(origin=COST_PER_ITERATION, name="last cycle: window cost per iteration",
                         plot_legend=rrb.PlotLegend(visible=False)),
        rrb.BarChartView(origin=REPROJ_RMS_PX_PER_ITERATION, name="last cycle: reprojection RMS [px] per iteration",
                         plot_legend=rrb.PlotLegend(visible=False)),
    )
    iterations_tab = rrb.Horizontal(
        rrb.Vertical(*iteration_cameras) if iteration_cameras else rrb.Spacer(), solver,
        column_shares=[0.6, 0.4], name=f"solver iterations (timeline {TIMELINE_CNOEM_ITER})",
    )
    return rrb.Blueprint(
        rrb.Tabs(run_tab, iterations_tab, active_tab=0),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_ELAPSED),
        auto_views=False,
    )
