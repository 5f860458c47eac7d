"""Log an error budget (:mod:`agvviz.evaluation.error_budget`) into an ``.rrd``; its layout is
:func:`agvviz.viz.blueprints.budget_blueprint`.

Written into a budget ``.rrd`` of its own (``agvviz budget``) or into the run's ``.rrd``
(``agvviz run --budget``, :meth:`agvviz.viz.run_logger.RunLogger.log_error_budget`).

Entity tree (timelines: ``frame`` = the run's frame index; ``time`` = the frame's stamp;
``elapsed`` = seconds since the run's start, or the budget's first frame)::

    budget/table                           TextDocument: the budget as a markdown table (static)
    budget/shares_pct                      BarChart: share of the position error (%), one bar
                                           per source in table order, then interaction/other
                                           (static; abscissa 0, 1, …; the table names them)
    budget/all_on/position_error_mm        Scalars per frame: the recording's position error
    budget/all_off/position_error_mm       Scalars: the floor (every source off) — its RMSE,
                                           a flat line over the recording's frames
    budget/<source>/position_error_mm      Scalars per frame: position error with <source> off
    budget/<source>/delta_mm               Scalars per frame: error all on − error <source> off

Written atomically with an explicit recording stream (:class:`agvviz.viz.rrd_file.AtomicRrd`).
"""

from __future__ import annotations

import hashlib
import os
import uuid
from pathlib import Path

import numpy as np
import rerun as rr

from agvviz.evaluation.error_budget import ErrorBudget
from agvviz.viz import paths
from agvviz.viz.blueprints import budget_blueprint
from agvviz.viz.rrd_file import AtomicRrd
from agvviz.viz.timelines import elapsed_s

def _send(rec: rr.RecordingStream, entity: str, time_ns: np.ndarray, values: np.ndarray,
          frame_of: dict[int, int], start_ns: int) -> None:
    ok = [k for k, v in enumerate(values) if np.isfinite(v) and int(time_ns[k]) in frame_of]
    if not ok:
        return
    stamps = [int(time_ns[k]) for k in ok]
    rec.send_columns(
        entity,
        indexes=[
            rr.TimeColumn(paths.TIMELINE_FRAME, sequence=[frame_of[t] for t in stamps]),
            rr.TimeColumn(paths.TIMELINE_TIME, timestamp=np.asarray(stamps, dtype="datetime64[ns]")),
            rr.TimeColumn(paths.TIMELINE_ELAPSED, duration=[elapsed_s(t, start_ns) for t in stamps]),
        ],
        columns=rr.Scalars.columns(scalars=np.asarray([values[k] for k in ok], dtype=float)),
    )


def log_budget(rec: rr.RecordingStream, budget: ErrorBudget, recording_start_ns: int | None = None) -> None:
    """Log the table, the bar chart of shares and the per-frame series into ``rec``; the
    ``elapsed`` timeline counts from ``recording_start_ns`` (a run's own start; None: the
    budget's first frame)."""
    start_ns = int(recording_start_ns) if recording_start_ns is not None else int(min(budget.time_ns, default=0))
    rec.log(paths.BUDGET_TABLE, rr.TextDocument(budget.markdown(), media_type=rr.MediaType.MARKDOWN), static=True)
    shares = [s.share for s in budget.sources] + [budget.interaction]
    values = np.array([100.0 * v if np.isfinite(v) else 0.0 for v in shares], dtype=float)
    rec.log(paths.BUDGET_SHARES, rr.BarChart(values, abscissa=np.arange(len(values), dtype=float)), static=True)
    # frames are numbered by the recording's run; a counterfactual frame is placed at the
    # recording's frame with the same stamp (a dropped frame has none and is left out).
    frame_of = {int(t): int(f) for t, f in zip(budget.time_ns, budget.frames)}
    _send(rec, paths.budget_series(paths.BUDGET_ALL_ON), budget.time_ns, budget.position_error_all_mm, frame_of, start_ns)
    if budget.floor_rmse_mm is not None and len(budget.time_ns):
        ends = np.array([budget.time_ns[0], budget.time_ns[-1]])
        _send(rec, paths.budget_series(paths.BUDGET_ALL_OFF), ends, np.full(2, budget.floor_rmse_mm), frame_of, start_ns)
    for s in budget.sources:
        _send(rec, paths.budget_series(s.source), s.time_ns, s.position_error_off_mm, frame_of, start_ns)
        _send(rec, paths.budget_series(s.source, "delta_mm"), budget.time_ns, s.delta_mm, frame_of, start_ns)


def write_budget_rrd(out_path: str | os.PathLike, budget: ErrorBudget) -> Path:
    """Write ``budget`` to ``out_path`` (temporary file beside it, renamed when complete)."""
    key = hashlib.sha256(f"{budget.recording.name}:{budget.seed}:{sorted(budget.settings.items())}".encode()).hexdigest()
    with AtomicRrd(
        out_path,
        recording_id=str(uuid.uuid5(uuid.NAMESPACE_URL, f"agvviz-budget:{key}")),
        recording_name=f"{budget.scenario} error budget",
        inputs=[budget.recording],
    ) as rrd:
        log_budget(rrd.rec, budget)
        return rrd.commit(budget_blueprint(budget))
