"""Sink of the trials stage (:mod:`agvviz.graph.trials`): log a Monte-Carlo study run into the
run's recording stream.

The entities and the layout are the study's (:mod:`agvviz.viz.monte_carlo_report`, shared with
``bench/bench_monte_carlo.py``): every trial's error per cell and solver over timeline
``trial``, the CRLB of each cell, the per-cell figures and the report. The run's layout opens on
the error-against-trial plots, with the report, the run summary and the manifest beside them.
"""

from __future__ import annotations

import rerun as rr
import rerun.blueprint as rrb

from agvviz.graph.trials import TrialsOutcome
from agvviz.viz import paths
from agvviz.viz.monte_carlo_report import log_study, study_blueprint


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
