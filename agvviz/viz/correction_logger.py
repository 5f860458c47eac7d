"""Log paper 002's correction cycle (:mod:`agvviz.graph.correct`) into a run ``.rrd``.

Entities (all under ``correction/`` or ``world/correction/``; timelines ``time``, ``frame`` and,
for the solver's iterations only, ``cnoem_iter``):

``world/correction/trajectory/{truth,nav,corrected}``   LineStrips3D: true, raw navigation and
                                                        corrected navigation trajectories
``world/correction/agv/{nav,corrected}``                Points3D: the current positions
``world/correction/window/cameras``                     Points3D: every camera position of the
                                                        last closed window (at the solution)
``world/correction/window/rays``                        LineStrips3D: each sighting's camera →
                                                        marker centre
``correction/image/<cam>/observed``                     Points2D: the window's measured corners
``correction/image/<cam>/theoretical``                  Points2D per solver iteration on the
                                                        ``cnoem_iter`` timeline (paper Fig. 4)
``correction/cost``, ``correction/reproj_rms_px``       Scalars per iteration (``cnoem_iter``)
``correction/cost_per_iteration``                       BarChart of the last cycle's costs
``errors/nav_position_m``, ``errors/corrected_position_m``   Scalars per frame vs truth
``events/corrections``                                  TextLog per closed cycle with the jump

Iteration data go out with ``send_columns`` (an iteration TimeColumn), never with
``set_time("cnoem_iter")`` + log, which would leak the iteration onto later logs.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from agvviz.graph.correct import CorrectionEvent, CorrectionStep
from agvviz.viz import paths
from agvviz.viz.run_logger import _trajectory
from agvviz.viz.style import COLOR_CAMERA, COLOR_CORRECTED, COLOR_NAV, COLOR_OBSERVED, COLOR_THEORETICAL, COLOR_TRUTH

TIMELINE_CNOEM_ITER = "cnoem_iter"
TRAJECTORY_TRUTH = "world/correction/trajectory/truth"
TRAJECTORY_NAV = "world/correction/trajectory/nav"
TRAJECTORY_CORRECTED = "world/correction/trajectory/corrected"
AGV_NAV = "world/correction/agv/nav"
AGV_CORRECTED = "world/correction/agv/corrected"
WINDOW_CAMERAS = "world/correction/window/cameras"
WINDOW_RAYS = "world/correction/window/rays"
COST = "correction/cost"
REPROJ_RMS_PX = "correction/reproj_rms_px"
COST_PER_ITERATION = "correction/cost_per_iteration"
ERROR_NAV_M = "errors/nav_position_m"
ERROR_CORRECTED_M = "errors/corrected_position_m"
EVENTS_CORRECTIONS = "events/corrections"



def image_observed(cam_name: str) -> str:
    return f"correction/image/{cam_name}/observed"


def image_theoretical(cam_name: str) -> str:
    return f"correction/image/{cam_name}/theoretical"


class CorrectionLogger:
    """Logs :class:`CorrectionStep` items into ``stream`` (the run logger's recording stream)."""

    def __init__(self, stream: rr.RecordingStream):
        self._rec = stream
        self._truth: list[np.ndarray] = []
        self._nav: list[np.ndarray] = []
        self._corrected: list[np.ndarray] = []
        self._index = 0
        self._styled = False

    def _styles(self) -> None:
        rec = self._rec
        for entity, name, color in (
            (ERROR_NAV_M, "navigation error [m]", COLOR_NAV),
            (ERROR_CORRECTED_M, "corrected navigation error [m]", COLOR_CORRECTED),
            (COST, "window cost per iteration", COLOR_THEORETICAL),
            (REPROJ_RMS_PX, "window reprojection RMS per iteration [px]", COLOR_CAMERA),
        ):
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        self._styled = True

    def _set_time(self, log_time_ns: int) -> None:
        self._rec.set_time(paths.TIMELINE_FRAME, sequence=self._index)
        self._rec.set_time(paths.TIMELINE_TIME, timestamp=np.datetime64(int(log_time_ns), "ns"))

    def log(self, step: CorrectionStep) -> None:
        """One frame time: positions, trajectories, errors; the window when a cycle closed."""
        if not self._styled:
            self._styles()
        rec = self._rec
        self._set_time(step.log_time_ns)
        self._nav.append(step.T_world_agv_nav[:3, 3])
        self._corrected.append(step.T_world_agv_corrected[:3, 3])
        rec.log(TRAJECTORY_NAV, _trajectory(self._nav, COLOR_NAV))
        rec.log(TRAJECTORY_CORRECTED, _trajectory(self._corrected, COLOR_CORRECTED))
        rec.log(AGV_NAV, rr.Points3D([self._nav[-1]], colors=COLOR_NAV, radii=rr.Radius.ui_points(7.0)))
        rec.log(AGV_CORRECTED, rr.Points3D([self._corrected[-1]], colors=COLOR_CORRECTED, radii=rr.Radius.ui_points(7.0)))
        if step.T_world_agv_truth is not None:
            self._truth.append(step.T_world_agv_truth[:3, 3])
            rec.log(TRAJECTORY_TRUTH, _trajectory(self._truth, COLOR_TRUTH))
            truth = step.T_world_agv_truth[:3, 3]
            rec.log(ERROR_NAV_M, rr.Scalars(float(np.linalg.norm(step.T_world_agv_nav[:3, 3] - truth))))
            rec.log(ERROR_CORRECTED_M, rr.Scalars(float(np.linalg.norm(step.T_world_agv_corrected[:3, 3] - truth))))
        if step.event is not None:
            self._log_event(step.event)
        self._index += 1

    def _log_event(self, event: CorrectionEvent) -> None:
        rec = self._rec
        level = rr.TextLogLevel.INFO if event.applied else rr.TextLogLevel.WARN
        if event.applied:
            text = (
                f"cycle {event.cycle_index}: {event.n_frames} frames, {event.n_sightings} sightings; "
                f"correction jump {event.jump_m:.3f} m; start frame moved "
                f"{np.linalg.norm(event.T_world_F_after[:3, 3] - event.T_world_F_before[:3, 3]):.3f} m"
            )
        else:
            text = f"cycle {event.cycle_index}: {event.n_frames} frames, {event.n_sightings} sightings; no correction: {event.reason}"
        rec.log(EVENTS_CORRECTIONS, rr.TextLog(text, level=level))
        if event.window is None or event.solution is None or not event.solution.iterations:
            return
        window, iterations = event.window, event.solution.iterations
        costs = np.array([it.cost for it in iterations])
        rec.log(COST_PER_ITERATION, rr.BarChart(costs, color=COLOR_THEORETICAL))
        n = len(iterations)
        indexes = [
            rr.TimeColumn(TIMELINE_CNOEM_ITER, sequence=np.arange(n)),
            rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.full(n, self._index)),
            rr.TimeColumn(paths.TIMELINE_TIME, timestamp=np.full(n, int(event.log_time_ns), dtype=np.int64).astype("datetime64[ns]")),
        ]
        rec.send_columns(COST, indexes=indexes, columns=rr.Scalars.columns(scalars=costs))
        rec.send_columns(REPROJ_RMS_PX, indexes=indexes, columns=rr.Scalars.columns(scalars=[it.reproj_rms_px for it in iterations]))
        cams = [s.cam_name for s in window.sightings]
        corner_cam = np.array([cams[j] for j in window.sighting_index])
        for cam in sorted(set(cams)):
            mask = corner_cam == cam
            rec.log(image_observed(cam), rr.Points2D(window.pixels_px[mask], colors=COLOR_OBSERVED, radii=rr.Radius.ui_points(3.0)))
            rec.log(image_theoretical(cam), rr.Points2D.from_fields(colors=COLOR_THEORETICAL, radii=rr.Radius.ui_points(3.0)), static=True)
            projected = np.concatenate([window.project(it.T_F_world)[mask] for it in iterations])
            columns = rr.Points2D.columns(positions=projected).partition(np.full(n, int(mask.sum())))
            rec.send_columns(image_theoretical(cam), indexes=indexes, columns=columns)
        if event.T_world_F_after is not None:
            T_world_F = event.T_world_F_after
            centres, rays = [], []
            for s in window.sightings:
                c = (T_world_F @ s.T_F_cam)[:3, 3]
                centres.append(c)
                rays.append([c, np.mean(s.points_world_m, axis=0)])
            rec.log(WINDOW_CAMERAS, rr.Points3D(centres, colors=COLOR_CAMERA, radii=rr.Radius.ui_points(3.0)))
            rec.log(WINDOW_RAYS, rr.LineStrips3D(rays, colors=(*COLOR_CAMERA, 90), radii=rr.Radius.ui_points(0.5)))



def correction_blueprint(cam_names: list[str]) -> rrb.Blueprint:
    """Layout of a run with ``correction``::

        ┌──────────────────────────────┬──────────────────────────────────────┐
        │ 3D world: markers, truth /   │ last window per camera: observed     │
        │ navigation / corrected       │ corners (white), theoretical corners │
        │ trajectories, window cameras │ of the iteration (orange, cnoem_iter)│
        ├──────────────┬───────────────┼───────────────────┬──────────────────┤
        │ position     │ window cost & │ corrections       │ summary /        │
        │ errors       │ reprojection  │ (TextLog, jumps)  │ manifest         │
        └──────────────┴───────────────┴───────────────────┴──────────────────┘
    """

    images = [
        rrb.Tabs(
            rrb.Spatial2DView(origin=f"correction/image/{c}", name=f"window corners {c}: observed (white), iteration (orange)"),
            rrb.Spatial2DView(origin=paths.image(c), name=f"camera {c} (image runs)"),
        )
        for c in cam_names
    ]
    world = rrb.Spatial3DView(
        origin=paths.WORLD,
        name="world: truth (green), navigation (red), corrected (teal), window cameras",
        contents=["+ /world/markers/**", "+ /world/correction/**"],
    )
    errors = rrb.TimeSeriesView(
        origin="/", contents=[f"/{ERROR_NAV_M}", f"/{ERROR_CORRECTED_M}"], name="position error [m]",
        plot_legend=rrb.PlotLegend(visible=True),
    )
    solver = rrb.Tabs(
        rrb.BarChartView(origin=COST_PER_ITERATION, name="cost per iteration (last cycle)"),
        rrb.TimeSeriesView(origin="/", contents=[f"/{COST}", f"/{REPROJ_RMS_PX}"], name="iterations (cnoem_iter)"),
    )
    documents = rrb.Tabs(
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
    )
    top = rrb.Horizontal(world, rrb.Vertical(*images) if images else rrb.Spacer(), column_shares=[0.55, 0.45])
    bottom = rrb.Horizontal(
        errors, solver, rrb.TextLogView(origin=EVENTS_CORRECTIONS, name="corrections"), documents,
        column_shares=[0.3, 0.25, 0.25, 0.2],
    )
    return rrb.Blueprint(
        rrb.Vertical(top, bottom, row_shares=[0.6, 0.4]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_FRAME),
        auto_views=False,
    )
