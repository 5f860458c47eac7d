"""Log an error budget (:mod:`agvviz.evaluation.error_budget`) into an ``.rrd``; its layout is
:func:`agvviz.viz.blueprints.budget_blueprint`.

Written into a budget ``.rrd`` of its own (``agvviz budget``) or into the run's ``.rrd``
(``agvviz run --budget``, :meth:`agvviz.viz.run_logger.RunLogger.log_error_budget`).

Entity tree (timelines: ``frame`` = the run's frame index; ``time`` = the frame's stamp;
``elapsed`` = seconds since the run's start, or the budget's first frame)::

    budget/table                           TextDocument: the budget as a markdown table (static)
    budget/shares_pct/bars                 Boxes2D: share of the position error, one bar per
                                           source in table order, then interaction/other, each
                                           labelled "<source> 61.3 % [48.0, 72.1]" (static;
                                           x = share, CHART_WIDTH units across the grid, y = row;
                                           orange ≥ 0, blue < 0, grey rest)
    budget/shares_pct/ci                   LineStrips2D: each share's 95 % bootstrap interval
                                           over frames (evaluation.error_budget.share_intervals)
    budget/shares_pct/labels               Points2D above each bar: its label
    budget/shares_pct/axis|ticks           the 0 % line, a grid at a round step (≤ 7 lines), its labels
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

from agvviz.evaluation.error_budget import INTERACTION, ErrorBudget, ShareInterval, share_intervals
from agvviz.viz import paths
from agvviz.viz.style import (
    COLOR_BUDGET_ALL_ON,
    COLOR_BUDGET_FLOOR,
    COLOR_BUDGET_INTERACTION,
    COLOR_BUDGET_NEGATIVE,
    COLOR_BUDGET_SOURCE,
    COLOR_ZERO,
    budget_source_color,
)
from agvviz.viz.blueprints import BUDGET_CHART_WIDTH as CHART_WIDTH
from agvviz.viz.blueprints import BUDGET_CHART_BAR_HALF_HEIGHT as BAR_HALF_HEIGHT
from agvviz.viz.blueprints import BUDGET_CHART_LABEL_ABOVE as LABEL_ABOVE
from agvviz.viz.blueprints import BUDGET_CHART_ROW as ROW
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
    log_share_chart(rec, share_intervals(budget))
    rec.log(paths.budget_series(paths.BUDGET_ALL_ON), rr.SeriesLines(names="all on (the recording)", colors=COLOR_BUDGET_ALL_ON, widths=2.0), static=True)
    rec.log(paths.budget_series(paths.BUDGET_ALL_OFF), rr.SeriesLines(names="floor: all off (RMSE)", colors=COLOR_BUDGET_FLOOR, widths=1.5), static=True)
    for s in budget.sources:
        color = budget_source_color(s.source)
        rec.log(paths.budget_series(s.source), rr.SeriesLines(names=f"{s.source} off", colors=color, widths=1.0), static=True)
        rec.log(paths.budget_series(s.source, "delta_mm"), rr.SeriesLines(names=s.source, colors=color, widths=1.0), static=True)
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


#: The grid's steps (%): the smallest giving at most MAX_GRID_LINES lines (more overlapped their labels).
GRID_STEPS_PCT = (10.0, 20.0, 25.0, 50.0, 100.0, 200.0, 500.0)
MAX_GRID_LINES = 7


def share_chart_rows(intervals: list[ShareInterval]) -> list[tuple[str, float, float, float, tuple]]:
    """(label, share %, low %, high %, colour) per bar, in table order: a source's bar is orange
    when its share is ≥ 0, blue when negative; interaction/other grey. NaN shares are drawn at 0."""
    rows = []
    for i in intervals:
        share, low, high = (100.0 * v for v in (i.share, i.low, i.high))
        ci = f" [{low:.1f}, {high:.1f}]" if np.isfinite(low) and np.isfinite(high) else ""
        value = f"{share:.1f} %" if np.isfinite(share) else "—"
        color = COLOR_BUDGET_INTERACTION if i.name == INTERACTION else (
            COLOR_BUDGET_NEGATIVE if np.isfinite(share) and share < 0 else COLOR_BUDGET_SOURCE)
        rows.append((f"{i.name} {value}{ci}", share if np.isfinite(share) else 0.0, low, high, color))
    return rows


def share_grid(values: np.ndarray) -> np.ndarray:
    """The grid lines (%) of a chart holding ``values`` and 0: a round step, at most MAX_GRID_LINES lines."""
    lo, hi = min(0.0, float(values.min())), max(0.0, float(values.max()))
    for step in GRID_STEPS_PCT:
        low, high = step * np.floor(lo / step), step * np.ceil(hi / step)
        if high == low:
            high = low + step
        if (high - low) / step + 1 <= MAX_GRID_LINES:
            break
    return np.arange(low, high + 1e-9, step)


def log_share_chart(rec: rr.RecordingStream, intervals: list[ShareInterval]) -> None:
    """The shares as horizontal bars with their intervals, each row's label above its bar (x:
    share, the grid labelled in %; the view, :func:`agvviz.viz.blueprints.budget_shares_view`,
    is a 2D view)."""
    rows = share_chart_rows(intervals)
    if not rows:
        return
    shares = np.array([r[1] for r in rows])
    values = np.concatenate([shares, [r[2] for r in rows if np.isfinite(r[2])], [r[3] for r in rows if np.isfinite(r[3])]])
    grid = share_grid(values)
    scale = CHART_WIDTH / (grid[-1] - grid[0])

    def x(pct):
        return (np.asarray(pct, dtype=float) - grid[0]) * scale

    y = np.arange(len(rows)) * ROW + LABEL_ABOVE
    left = x(np.minimum(shares, 0.0))
    mins = np.stack([left, y - BAR_HALF_HEIGHT], axis=1)
    sizes = np.stack([np.abs(shares) * scale, np.full(len(rows), 2 * BAR_HALF_HEIGHT)], axis=1)
    rec.log(paths.BUDGET_SHARE_BARS, rr.Boxes2D(mins=mins, sizes=sizes, colors=[r[4] for r in rows],
                                                radii=rr.Radius.ui_points(2.0), labels=[r[0] for r in rows],
                                                show_labels=False), static=True)
    whiskers = [[[x(r[2]), yk], [x(r[3]), yk]] for r, yk in zip(rows, y) if np.isfinite(r[2]) and np.isfinite(r[3])]
    whiskers += [[[x(v), yk - 1.5], [x(v), yk + 1.5]] for r, yk in zip(rows, y) if np.isfinite(r[2]) and np.isfinite(r[3])
                 for v in (r[2], r[3])]
    if whiskers:
        rec.log(paths.BUDGET_SHARE_CI, rr.LineStrips2D(whiskers, colors=COLOR_BUDGET_ALL_ON, radii=rr.Radius.ui_points(1.0)), static=True)
    top, bottom = 0.0, y[-1] + ROW / 2
    rec.log(paths.BUDGET_SHARE_AXIS, rr.LineStrips2D([[[x(g), top], [x(g), bottom]] for g in grid],
                                                     colors=COLOR_ZERO, radii=[rr.Radius.ui_points(1.5 if g == 0 else 0.5) for g in grid]), static=True)
    # each bar's label above it, centred on the chart (the chart's width holds the longest)
    rec.log(paths.BUDGET_SHARE_LABELS, rr.Points2D([[CHART_WIDTH / 2, yk - LABEL_ABOVE] for yk in y], colors=[r[4] for r in rows],
                                                   radii=0.1, labels=[r[0] for r in rows], show_labels=True), static=True)
    # the grid's labels under it (the view's bounds, blueprints.budget_share_bounds, hold them)
    ticks = [[x(g), bottom + 2.0] for g in grid]
    rec.log(paths.BUDGET_SHARE_TICKS, rr.Points2D(ticks, colors=COLOR_ZERO, radii=0.1,
                                                  labels=[f"{g:.0f} %" for g in grid], show_labels=True), static=True)


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
