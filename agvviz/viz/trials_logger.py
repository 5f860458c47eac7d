"""Sinks of the study stages: log a study run into the run's recording stream.

Monte-Carlo (:mod:`agvviz.replay.studies.monte_carlo`): the entities and the layout are the study's
(:mod:`agvviz.viz.monte_carlo_report`, shared with ``bench/bench_monte_carlo.py``): every
trial's error per cell and solver over timeline ``trial``, the CRLB of each cell, the per-cell
figures and the report.

CNOEM grid (:mod:`agvviz.replay.studies.cnoem`), timeline ``trial`` = the trial's index within
its cell::

    cnoem/report                                TextDocument: the study report (static)
    cnoem/trials/<cell>/error_m/<method>        Scalars over trial: position error of F (m) of
                                                each trial (failed solves left out)
    cnoem/trials/<cell>/error_m/crlb            Scalars at the first and last trial: the cell's
                                                multi-frame CRLB position bound (m), a flat line

Either run's layout opens on the error-against-trial plots, with the report, the run summary
and the manifest beside them.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from agvviz.model.studies import CnoemTrialsOutcome, TrialsOutcome
from agvviz.viz import paths
from agvviz.viz.cnoem_report import COLORS as CNOEM_COLORS
from agvviz.viz.monte_carlo_report import TIMELINE_TRIAL, log_study, study_blueprint

CNOEM_REPORT = "cnoem/report"
#: The multi-frame methods, plotted against the bound apart from the (much worse) IPPE baselines.
CNOEM_WINDOW_METHODS = ("cnoem", "cnoem_multistart", "bundle")
#: Cells whose error-against-trial plots get a tab of their own (the others: change a view's origin).
CNOEM_MAX_FEATURED_CELLS = 8


def log_trials(stream: rr.RecordingStream, outcome: TrialsOutcome) -> None:
    """Log ``outcome``'s error series, per-cell figures and report markdown into ``stream``
    (the :class:`~agvviz.viz.run_logger.RunLogger`'s, beside its manifest and summary)."""
    log_study(stream, outcome.results, outcome.report_markdown)


def trials_blueprint(outcome: TrialsOutcome) -> rrb.Blueprint:
    """The run's layout: error against trial of the featured cells (timeline ``trial``), the
    report, summary and manifest; the paper figures and CRLB cells in tabs of their own."""
    return study_blueprint(
        outcome.results,
        active="trials",
        documents=((paths.RUN_SUMMARY, "summary"), (paths.RUN_MANIFEST, "manifest")),
    )


def cnoem_trial_errors(cell_id: str) -> str:
    """The entity under which cell ``cell_id``'s per-trial errors are logged, one child per method."""
    return f"cnoem/trials/{cell_id}/error_m"


def log_cnoem_trials(stream: rr.RecordingStream, outcome: CnoemTrialsOutcome) -> None:
    """Log ``outcome``'s report and every trial's error series into ``stream`` (the
    :class:`~agvviz.viz.run_logger.RunLogger`'s). Per-trial data go out with ``send_columns``
    (a ``trial`` TimeColumn), so the trial timeline never leaks onto later logs."""
    stream.log(CNOEM_REPORT, rr.TextDocument(outcome.report_markdown, media_type=rr.MediaType.MARKDOWN), static=True)
    for cell_id, r in outcome.results.items():
        base = cnoem_trial_errors(cell_id)
        n_trials = 0
        for method in outcome.methods:
            errors_m = np.asarray(r.errors_m[method], dtype=float)
            n_trials = max(n_trials, len(errors_m))
            ok = np.flatnonzero(np.isfinite(errors_m))
            stream.log(f"{base}/{method}", rr.SeriesPoints(names=method, colors=CNOEM_COLORS[method], marker_sizes=2.0), static=True)
            if len(ok):
                stream.send_columns(
                    f"{base}/{method}",
                    indexes=[rr.TimeColumn(TIMELINE_TRIAL, sequence=ok)],
                    columns=rr.Scalars.columns(scalars=errors_m[ok]),
                )
        if n_trials and np.isfinite(r.crlb_position_m):
            stream.log(f"{base}/crlb", rr.SeriesLines(names="crlb", colors=CNOEM_COLORS["crlb"], widths=2.0), static=True)
            stream.send_columns(
                f"{base}/crlb",
                indexes=[rr.TimeColumn(TIMELINE_TRIAL, sequence=[0, n_trials - 1])],
                columns=rr.Scalars.columns(scalars=np.full(2, r.crlb_position_m)),
            )


def cnoem_trials_blueprint(outcome: CnoemTrialsOutcome) -> rrb.Blueprint:
    """The run's layout: per featured cell (the first :data:`CNOEM_MAX_FEATURED_CELLS`), the
    multi-frame methods' error against trial with the CRLB above all methods' (the IPPE
    baselines' errors are metres, the window methods' decimetres); the report, summary and
    manifest beside them; timeline ``trial``."""
    cell_views = []
    for cell_id in list(outcome.results)[:CNOEM_MAX_FEATURED_CELLS]:
        origin = cnoem_trial_errors(cell_id)
        cell_views.append(
            rrb.Vertical(
                rrb.TimeSeriesView(
                    origin=origin, contents=[f"$origin/{m}" for m in (*CNOEM_WINDOW_METHODS, "crlb")],
                    name=f"{cell_id}: multi-frame methods, position error of F (m) per trial, CRLB (grey)",
                    plot_legend=rrb.PlotLegend(visible=True),
                ),
                rrb.TimeSeriesView(
                    origin=origin, name=f"{cell_id}: every method, position error of F (m) per trial",
                    plot_legend=rrb.PlotLegend(visible=True),
                ),
                name=cell_id,
            )
        )
    texts = [rrb.TextDocumentView(origin=CNOEM_REPORT, name="report")]
    texts += [
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(*cell_views) if cell_views else rrb.Spacer(),
            rrb.Tabs(*texts),
            column_shares=[0.6, 0.4],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE_TRIAL),
        auto_views=False,
    )
