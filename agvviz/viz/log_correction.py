"""The correction modality of a run ``.rrd``: paper 002's correction cycle (:mod:`agvviz.replay.correct`).

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
``<camera image>/window_status``                        Points2D, one label at the top: the
                                                        window shown (cycle, closed at frame N)
                                                        or why none (corner observations only)
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
``set_time("cnoem_iter")`` + log, which would leak the iteration onto later logs. The entity
paths are in :mod:`agvviz.viz.paths` (``CORRECTION_*``); the layout is
:func:`agvviz.viz.blueprints.correction_blueprint`.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from agvviz.model.correction import CorrectionEvent, CorrectionStep
from agvviz.viz import paths
from agvviz.viz.log_frames import trajectory
from agvviz.viz.style import (
    COLOR_CAMERA,
    COLOR_CORRECTED,
    COLOR_IMAGE_FRAME,
    COLOR_NAV,
    COLOR_OBSERVED,
    COLOR_STALE,
    COLOR_THEORETICAL,
    COLOR_THRESHOLD,
    COLOR_TRUTH,
    LEGEND,
)
from agvviz.viz.timelines import elapsed_s, set_stamp

#: Nominal vehicle body drawn around each pose (half sizes x right, y forward, z up, in m). A
#: visual marker only: the recording does not carry a body size.
BODY_HALF_SIZES_M = (0.35, 0.6, 0.2)
#: The corrected body is drawn this much larger, so its outline shows around the truth's when
#: the two coincide (they do to a few cm).
CORRECTED_BODY_SCALE = 1.08
#: Window corners on the image: the solved (theoretical) ones smaller and on top of the observed.
OBSERVED_RADIUS = rr.Radius.ui_points(3.0)
THEORETICAL_RADIUS = rr.Radius.ui_points(1.5)


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
        #: Whether the run logs camera images (a corner-only recording has none): the camera
        #: panels' status says so. Set by the run's sink before each step.
        self.images = True
        self._window_closed: tuple[int, int] | None = None  # (cycle, frame) of the window drawn
        self._status: dict[str, str] = {}  # camera -> the status label logged last
        #: The largest value of each closed-cycle plot so far (its limit line included): the
        #: layout's y axes run from 0 to it (:meth:`cycle_axes_high`).
        self._cycle_high: dict[str, float] = {}

    def _styles(self) -> None:
        rec = self._rec
        for entity, name, color in (
            (paths.ERROR_NAV_MM, LEGEND[COLOR_NAV] + " [mm]", COLOR_NAV),
            (paths.ERROR_CORRECTED_MM, LEGEND[COLOR_CORRECTED] + " [mm]", COLOR_CORRECTED),
            (paths.CORRECTION_CYCLE_MAX_REPROJ_PX, "max_reproj_px (reject above)", COLOR_THRESHOLD),
            (paths.CORRECTION_CYCLE_MAX_POSITION_SIGMA_MM, "max position σ (reject above)", COLOR_THRESHOLD),
            (paths.CORRECTION_COST, "window cost (sum of squared ray residuals)", COLOR_THEORETICAL),
            (paths.CORRECTION_REPROJ_RMS_PX, "window reprojection RMS [px]", COLOR_OBSERVED),
        ):
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        for entity, name, color in (
            (paths.ERROR_CORRECTION_JUMP_MM, "correction applied: jump [mm]", COLOR_CORRECTED),
            (paths.CORRECTION_CYCLE_REPROJ_RMS_PX, "closed cycle: window RMS [px]", COLOR_OBSERVED),
            (paths.CORRECTION_CYCLE_POSITION_SIGMA_MM, "closed cycle: position σ [mm]", COLOR_OBSERVED),
        ):
            rec.log(entity, rr.SeriesPoints(names=name, colors=color, marker_sizes=4.0), static=True)
        for entity, name, color, scale in (
            (paths.CORRECTION_AGV_TRUTH, LEGEND[COLOR_TRUTH], COLOR_TRUTH, 1.0),
            (paths.CORRECTION_AGV_NAV, LEGEND[COLOR_NAV], COLOR_NAV, 1.0),
            (paths.CORRECTION_AGV_CORRECTED, LEGEND[COLOR_CORRECTED], COLOR_CORRECTED, CORRECTED_BODY_SCALE),
        ):
            rec.log(
                paths.correction_body(entity),
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
        rec.log(paths.CORRECTION_TRAJECTORY_NAV, trajectory(self._nav, COLOR_NAV))
        rec.log(paths.CORRECTION_TRAJECTORY_CORRECTED, trajectory(self._corrected, COLOR_CORRECTED))
        rec.log(paths.CORRECTION_AGV_NAV, _transform(step.T_world_agv_nav))
        rec.log(paths.CORRECTION_AGV_CORRECTED, _transform(step.T_world_agv_corrected))
        if step.T_world_agv_truth is not None:
            truth = step.T_world_agv_truth[:3, 3]
            self._truth.append(truth)
            rec.log(paths.CORRECTION_TRAJECTORY_TRUTH, trajectory(self._truth, COLOR_TRUTH))
            rec.log(paths.CORRECTION_AGV_TRUTH, _transform(step.T_world_agv_truth))
            rec.log(paths.ERROR_NAV_MM, rr.Scalars(1000.0 * float(np.linalg.norm(step.T_world_agv_nav[:3, 3] - truth))))
            rec.log(paths.ERROR_CORRECTED_MM, rr.Scalars(1000.0 * float(np.linalg.norm(step.T_world_agv_corrected[:3, 3] - truth))))
        if self._max_reproj_px is not None:
            rec.log(paths.CORRECTION_CYCLE_MAX_REPROJ_PX, rr.Scalars(float(self._max_reproj_px)))
            self._note_high(paths.CORRECTION_CYCLE_REPROJ_RMS_PX, float(self._max_reproj_px))
        if self._max_position_sigma_m is not None:
            rec.log(paths.CORRECTION_CYCLE_MAX_POSITION_SIGMA_MM, rr.Scalars(1000.0 * float(self._max_position_sigma_m)))
            self._note_high(paths.CORRECTION_CYCLE_POSITION_SIGMA_MM, 1000.0 * float(self._max_position_sigma_m))
        if step.event is not None:
            self._log_event(step.event)
        self._log_status()
        self._index += 1

    def _note_high(self, plot: str, value: float) -> None:
        if np.isfinite(value):
            self._cycle_high[plot] = max(self._cycle_high.get(plot, 0.0), float(value))

    def cycle_axes_high(self) -> dict[str, float]:
        """The closed-cycle plots' largest values (window RMS px, position σ mm; each with its
        limit): their y axes run from 0 to these (auto range left 0 out: "1.5–2")."""
        return dict(self._cycle_high)

    def status_text(self) -> str:
        """What a camera panel shows now, in words (two short lines): the window of which cycle,
        closed at which frame (drawn until the next closes), or why it is empty."""
        no_image = "" if self.images else "\nno image: the recording holds corner observations only"
        if self._window_closed is None:
            if not self.images:
                return "no image at this frame: corner observations only\nno window yet: drawn when a cycle closes"
            return "no window yet: drawn when a cycle closes"
        cycle, frame = self._window_closed
        return f"window of cycle {cycle}, closed at frame {frame}" + no_image

    def _log_status(self) -> None:
        """The status label at the centre of each camera panel, when it changed."""
        text = self.status_text()
        for cam in sorted(self._cameras or {}):
            if self._status.get(cam) == text:
                continue
            camera = self._camera(cam)
            # at the top centre, above the corners
            top = [0.0, 0.0] if camera is None or not camera.width_px else [camera.width_px / 2, 0.08 * camera.height_px]
            self._rec.log(paths.correction_status(cam), rr.Points2D(
                [top], labels=[text], colors=COLOR_STALE, radii=rr.Radius.ui_points(0.5), show_labels=True,
            ))
            self._status[cam] = text

    def _log_event(self, event: CorrectionEvent) -> None:
        rec = self._rec
        level = rr.TextLogLevel.INFO if event.applied else rr.TextLogLevel.WARN
        if event.applied:
            # the key facts on the first line (what the log panel shows), the evidence below
            text = (
                f"cycle {event.cycle_index}: jump {event.jump_m * 1000:.1f} mm\n"
                f"{event.n_sightings} sightings in {event.n_frames} frames; start frame moved "
                f"{np.linalg.norm(event.T_world_F_after[:3, 3] - event.T_world_F_before[:3, 3]) * 1000:.1f} mm"
            )
            rec.log(paths.ERROR_CORRECTION_JUMP_MM, rr.Scalars(1000.0 * event.jump_m))
        else:
            text = f"cycle {event.cycle_index}: not applied\n{event.reason}; {event.n_sightings} sightings in {event.n_frames} frames"
        rec.log(paths.EVENTS_CORRECTIONS, rr.TextLog(text, level=level))
        if event.position_sigma_m is not None and np.isfinite(event.position_sigma_m):
            rec.log(paths.CORRECTION_CYCLE_POSITION_SIGMA_MM, rr.Scalars(1000.0 * event.position_sigma_m))
            self._note_high(paths.CORRECTION_CYCLE_POSITION_SIGMA_MM, 1000.0 * event.position_sigma_m)
        if event.window is None or event.solution is None or not event.solution.iterations:
            return
        window, iterations = event.window, event.solution.iterations
        costs = np.array([it.cost for it in iterations])
        rms_px = np.array([it.reproj_rms_px for it in iterations])
        self._window_closed = (int(event.cycle_index), self._index)
        rec.log(paths.CORRECTION_CYCLE_REPROJ_RMS_PX, rr.Scalars(float(rms_px[-1])))
        self._note_high(paths.CORRECTION_CYCLE_REPROJ_RMS_PX, float(rms_px[-1]))
        rec.log(paths.CORRECTION_COST_PER_ITERATION, rr.BarChart(costs, color=COLOR_THEORETICAL))
        rec.log(paths.CORRECTION_REPROJ_RMS_PX_PER_ITERATION, rr.BarChart(rms_px, color=COLOR_OBSERVED))
        n = len(iterations)
        indexes = [
            rr.TimeColumn(paths.TIMELINE_CNOEM_ITER, sequence=np.arange(n)),
            rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.full(n, self._index)),
            rr.TimeColumn(paths.TIMELINE_TIME, timestamp=np.full(n, int(event.log_time_ns), dtype=np.int64).astype("datetime64[ns]")),
            rr.TimeColumn(paths.TIMELINE_ELAPSED, duration=np.full(n, elapsed_s(event.log_time_ns, self.recording_start_ns))),
        ]
        rec.send_columns(paths.CORRECTION_COST, indexes=indexes, columns=rr.Scalars.columns(scalars=costs))
        rec.send_columns(paths.CORRECTION_REPROJ_RMS_PX, indexes=indexes, columns=rr.Scalars.columns(scalars=rms_px))
        cams = [s.cam_name for s in window.sightings]
        corner_cam = np.array([cams[j] for j in window.sighting_index])
        for cam in sorted(set(cams)):
            mask = corner_cam == cam
            camera = self._camera(cam)
            self._log_border(cam, camera)
            K = window.sightings[cams.index(cam)].K
            rec.log(paths.correction_observed(cam), rr.Points2D(_image_px(window.pixels_px[mask], K, camera), colors=COLOR_OBSERVED, radii=OBSERVED_RADIUS, draw_order=20.0))
            rec.log(paths.correction_theoretical(cam), rr.Points2D.from_fields(colors=COLOR_THEORETICAL, radii=THEORETICAL_RADIUS, draw_order=21.0), static=True)
            projected = np.concatenate([_image_px(window.project(it.T_F_world)[mask], K, camera) for it in iterations])
            columns = rr.Points2D.columns(positions=projected).partition(np.full(n, int(mask.sum())))
            rec.send_columns(paths.correction_theoretical(cam), indexes=indexes, columns=columns)
        if event.T_world_F_after is not None:
            T_world_F = event.T_world_F_after
            last_frame = max(s.frame_index for s in window.sightings)
            centres, rays = [], []
            for s in window.sightings:
                c = (T_world_F @ s.T_F_cam)[:3, 3]
                centres.append(c)
                if s.frame_index == last_frame:  # the closing frame's sight lines only
                    rays.append([c, np.mean(s.points_world_m, axis=0)])
            rec.log(paths.CORRECTION_WINDOW_CAMERAS, rr.Points3D(centres, colors=COLOR_CAMERA, radii=rr.Radius.ui_points(3.0)))
            rec.log(paths.CORRECTION_WINDOW_RAYS, rr.LineStrips3D(rays, colors=(*COLOR_CAMERA, 160), radii=rr.Radius.ui_points(1.0)))

    def _camera(self, cam_name: str):
        state = None if self._cameras is None else self._cameras.get(cam_name)
        return None if state is None else getattr(state, "camera", None)

    def _log_border(self, cam_name: str, camera) -> None:
        if cam_name in self._bordered or camera is None or not camera.width_px or not camera.height_px:
            return
        self._rec.log(
            paths.correction_border(cam_name),
            rr.Boxes2D(mins=[[0.0, 0.0]], sizes=[[camera.width_px, camera.height_px]], colors=COLOR_IMAGE_FRAME,
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
