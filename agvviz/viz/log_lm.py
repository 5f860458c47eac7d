"""The solver of each frame in a run's ``.rrd``: its LM iterations as bar charts (log10) and as
``lm_iter`` columns, the reprojected points of every iteration and each point's path over them,
and a line of text on what the solver did (or "closed-form"); a suspect frame's text says
"suspect: <finding>" where a clean one says "solved", with the check, the likely cause and the
next step below.

:class:`LmLogger` is one of the modality loggers a :class:`agvviz.viz.run_logger.RunLogger` holds;
its per-frame values go through the run's :class:`agvviz.viz.columns.Columns`.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from agvviz.evaluation.suspect_report import cause_words
from agvviz.model.frames import FrameResult, LmIteration
from agvviz.viz import paths
from agvviz.viz.columns import Columns, Stamp
from agvviz.viz.style import COLOR_CAMERA, COLOR_OBSERVED, COLOR_REPROJECTED

#: LM series per frame and per iteration (``lm_iter`` columns): (entity, legend name, colour).
LM_SERIES = (
    (paths.LM_ITERATIONS, "LM trial steps per frame", COLOR_CAMERA),
    (paths.LM_COST, "LM cost", COLOR_CAMERA),
    (paths.LM_LOG10_COST, "log10 LM cost", COLOR_CAMERA),
    (paths.LM_REPROJ_RMS_PX, "LM reprojection RMS [px]", COLOR_REPROJECTED),
    (paths.LM_DAMPING, "LM damping λ", COLOR_OBSERVED),
    (paths.LM_STEP_NORM, "LM step norm", COLOR_OBSERVED),
)


class LmLogger:
    """Logs each frame's solve into ``rec`` (per-frame values into ``columns``)."""

    def __init__(self, rec: rr.RecordingStream, columns: Columns):
        self._rec = rec
        self._columns = columns
        # What the previous frame left drawn, so a state is logged only when it changes.
        self._bars_drawn = False
        self._points_drawn: set[str] = set()  # cameras whose LM points/path show now
        #: The solver iterated on some frame (the layout then shows the iterations).
        self.iterated = False

    def log_styles(self) -> None:
        """The static styles of the LM series and bar charts."""
        rec = self._rec
        for entity, name, color in LM_SERIES:
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        for entity, color in (
            (paths.LM_LOG10_COST_PER_ITERATION, COLOR_CAMERA),
            (paths.LM_LOG10_DAMPING_PER_ITERATION, COLOR_OBSERVED),
            (paths.LM_LOG10_STEP_NORM_PER_ITERATION, COLOR_OBSERVED),
        ):  # a colour per BarChart call would cost more than its values
            rec.log(entity, [rr.components.ColorBatch([color]).described(rr.BarChart.descriptor_color())], static=True)

    def log(self, frame: FrameResult, stamp: Stamp, fixed: bool) -> None:
        """The frame's solve: LM iterations as bar charts (log10) and lm_iter columns, the
        reprojected points of each iteration, and a line of text; or "closed-form"."""
        rec = self._rec
        iterations: tuple[LmIteration, ...] = tuple(frame.lm_iterations)
        self._columns.row(paths.LM_THIS_FRAME, "markdown", stamp, _lm_text(frame))
        if not iterations:
            self._log_points(frame, stamp, fixed, ())
            if self.iterated:  # no steps on this frame (rejected, or solved without LM): the line breaks here
                self._columns.gap(paths.LM_ITERATIONS, stamp)
            if self._bars_drawn:
                for entity in (
                    paths.LM_LOG10_COST_PER_ITERATION,
                    paths.LM_LOG10_DAMPING_PER_ITERATION,
                    paths.LM_LOG10_STEP_NORM_PER_ITERATION,
                ):
                    rec.log(entity, rr.Clear(recursive=False))
                self._bars_drawn = False
            return
        self.iterated = True
        self._bars_drawn = True
        cost = np.array([it.cost for it in iterations], dtype=float)
        damping = np.array([it.damping for it in iterations], dtype=float)
        step = np.array([it.step_norm for it in iterations], dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            log10_cost = np.log10(cost)
        for entity, values in (
            (paths.LM_LOG10_COST_PER_ITERATION, log10_cost),
            (paths.LM_LOG10_DAMPING_PER_ITERATION, damping),
            (paths.LM_LOG10_STEP_NORM_PER_ITERATION, step),
        ):
            with np.errstate(divide="ignore", invalid="ignore"):
                logged = values if entity == paths.LM_LOG10_COST_PER_ITERATION else np.log10(values)
            # Bar i is record i (the step norm: trial step i + 1; record 0, the start, has no
            # step). No abscissa: it would triple the logging cost of a bar chart.
            logged = logged[1:] if entity == paths.LM_LOG10_STEP_NORM_PER_ITERATION else logged
            self._columns.row(entity, "bar_chart", stamp, np.where(np.isfinite(logged), logged, np.nan))
        columns = self._columns
        if frame.solved:  # a rejected frame has no value in the per-frame series (the text says its steps)
            columns.scalar(paths.LM_ITERATIONS, stamp, len(iterations) - 1)
        else:
            columns.gap(paths.LM_ITERATIONS, stamp)
        for entity, values in (
            (paths.LM_COST, cost),
            (paths.LM_LOG10_COST, np.where(np.isfinite(log10_cost), log10_cost, np.nan)),
            (paths.LM_REPROJ_RMS_PX, [it.reproj_rms_px for it in iterations]),
            (paths.LM_DAMPING, damping),
            (paths.LM_STEP_NORM, step),
        ):
            columns.iterations(entity, stamp, values)
        # One (N, 2) array in image pixels per LM record (the solve stage's lm_iteration_px).
        self._log_points(frame, stamp, fixed, frame.lm_iteration_px)

    def _log_points(self, frame: FrameResult, stamp: Stamp, fixed: bool, per_iteration_px) -> None:
        """Each LM iteration's reprojected points (``lm_iter`` columns) and each point's path
        start → final (this frame); both cleared on a frame without them."""
        points_entity, path_entity = paths.lm_iteration(frame.cam_name, fixed), paths.lm_path(frame.cam_name, fixed)
        if len(per_iteration_px) and len(per_iteration_px) == len(frame.lm_iterations):
            arrays = [np.asarray(p, dtype=float).reshape(-1, 2) for p in per_iteration_px]
            self._columns.iteration_points(points_entity, stamp, arrays)
            tracks = np.stack(arrays, axis=1)  # (N points, iterations, 2): each point's path
            self._columns.row(path_entity, "strips2d", stamp, tracks)
            self._points_drawn.add(frame.cam_name)
        elif frame.cam_name in self._points_drawn:
            self._columns.gap(points_entity, stamp)  # frame/time/elapsed only: lm_iter untouched
            self._columns.gap(path_entity, stamp)
            self._points_drawn.discard(frame.cam_name)


def _lm_text(frame: FrameResult) -> str:
    """One line on what the solver did in ``frame`` (and which markers made the pose)."""
    text = _solve_text(frame)
    markers = ""
    if len(frame.used_marker_ids) > 1:
        markers = f"markers {', '.join(frame.used_marker_ids)} jointly"
    if frame.excluded_marker_ids:
        markers += f"{'; ' if markers else ''}**left out {', '.join(frame.excluded_marker_ids)}**"
    if markers:
        text = f"{markers} — {text}"
    if frame.marker_note:
        text += f"  \n{frame.marker_note}"
    if frame.solved and frame.suspect is not None:  # first, so a short panel shows it
        s = frame.suspect
        text = (f"**suspect: {s.message}**  \n{s.check} check {s.sigma:.1f}σ, likely cause: {cause_words(s.cause)}"
                + (f"; next: {s.next_step}" if s.next_step else "") + " (every suspect frame: the suspects log)  \n"
                + text)
    return text


def _solve_text(frame: FrameResult) -> str:
    iterations = frame.lm_iterations
    if not frame.solved:
        outcome = f"rejected: {frame.rejected}"
    elif frame.suspect is not None:  # solved, but the pose disagrees with what else the log knows
        outcome = "suspect"
    else:
        outcome = "solved"
    if not iterations:
        if frame.solved:
            rms = "" if frame.reproj_rms_px is None else f"; reprojection RMS {frame.reproj_rms_px:.3g} px"
            return f"**closed-form solver: no iterations** (frame {frame.index}, {outcome}{rms})"
        return f"**no solve** (frame {frame.index}, {outcome})"
    first, last = iterations[0], iterations[-1]
    steps = len(iterations) - 1
    accepted = sum(it.accepted for it in iterations[1:])
    return (
        f"**LM, frame {frame.index}** ({outcome}): {steps} trial steps, {accepted} accepted; "
        f"cost (½ sum of squared residuals) {first.cost:.3g} → {last.cost:.3g}; reprojection RMS "
        f"{first.reproj_rms_px:.3g} → {last.reproj_rms_px:.3g} px"
    )

