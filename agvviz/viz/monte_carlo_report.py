"""Log the p4p_monte_carlo study (:mod:`agvviz.replay.studies.monte_carlo_cells`) into a Rerun recording.

One implementation for both outputs: :func:`log_study` writes the study's entities into a
recording stream — the run's (:mod:`agvviz.viz.trials_logger`, ``agvviz run`` on a study
recording) or a file of its own (:func:`write_report_rrd`, ``bench/bench_monte_carlo.py``) —
and :func:`study_blueprint` lays them out.

Entity tree (timelines: ``trial`` = trial index within its cell; ``snr_db`` for the paper
cells; ``sigma_mpx`` = σ in milli-pixels for the CRLB cells)::

    mc/report                                      TextDocument: the markdown report (static)
    mc/trials/<cell>/error_mm/<solver>             Scalars over trial: ‖t̂ − t‖ (mm) of each
                                                   trial (failed solves left out)
    mc/trials/<cell>/error_mm/crlb                 Scalars at the first and last trial: the
                                                   cell's CRLB (sqrt trace, mm), a flat line
    mc/paper/h<h>_z<z>_n<N>/t<i>_mean/<solver>     Scalars: mean of t_i (m) over snr_db
    mc/paper/h<h>_z<z>_n<N>/rmse_mm/<solver>|crlb  Scalars: RMSE of t and its CRLB (mm)
    mc/paper/h<h>_z<z>_n<N>/rmse_over_crlb/<solver>   Scalars: RMSE ÷ CRLB over snr_db
    mc/crlb/tilt<t>_h<h>_z<z>_n<N>/rmse_over_crlb/<solver>   Scalars over sigma_mpx

The layout has one tab per timeline (a view shows the active timeline only): the trials (error
against trial of a few cells, the report), the paper's figures 9–11 (t1, t2, t3 of p4p and lm
over SNR, h = 0.2667 m, z = 2 m, 4 points, with the RMSE against the CRLB and their ratio) and
the CRLB cells; switching tab, switch the timeline too (the tab's name says which).
"""

from __future__ import annotations

import os
import re

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from agvviz.model.studies import CellResult
from agvviz.replay.studies.monte_carlo_cells import PAPER_FIGURES, SOLVERS
from agvviz.viz.rrd_file import AtomicRrd

SOLVER_COLORS = {
    "p4p": (60, 120, 255),
    "lm": (230, 40, 40),
    "lm_pixel": (255, 160, 0),
    "lm_amb": (0, 220, 220),
    "ippe": (40, 200, 90),
    "sqpnp": (200, 120, 255),
    "crlb": (230, 230, 230),
}
_PAPER = re.compile(r"paper_h(?P<h>[\d.]+)_z(?P<z>[\d.]+)_snr(?P<snr>\d+)_n(?P<n>\d)")
_CRLB = re.compile(r"crlb_tilt(?P<tilt>[\d.]+)_h(?P<h>[\d.]+)_z(?P<z>[\d.]+)_s(?P<s>[\d.]+)_n(?P<n>\d)")
FIG9_11 = "mc/paper/h0.2667_z2_n4"
REPORT = "mc/report"
TIMELINE_TRIAL = "trial"
TIMELINE_SNR_DB = "snr_db"
TIMELINE_SIGMA_MPX = "sigma_mpx"
#: Cells whose error-against-trial plot gets a tab of its own (the others: change a view's origin).
MAX_FEATURED_CELLS = 8
#: Which tab a layout opens on, and the timeline it needs.
TAB_TIMELINES = {"trials": TIMELINE_TRIAL, "figures": TIMELINE_SNR_DB, "crlb": TIMELINE_SIGMA_MPX}


def trial_errors(cell_id: str) -> str:
    """The entity under which cell ``cell_id``'s per-trial errors are logged, one child per solver."""
    return f"mc/trials/{cell_id}/error_mm"


def _paper_group(cell_id: str) -> str | None:
    m = _PAPER.fullmatch(cell_id)
    return f"mc/paper/h{m['h']}_z{m['z']}_n{m['n']}" if m else None


def _crlb_group(cell_id: str) -> str | None:
    m = _CRLB.fullmatch(cell_id)
    return f"mc/crlb/tilt{m['tilt']}_h{m['h']}_z{m['z']}_n{m['n']}" if m else None


def log_study(rec: rr.RecordingStream, results: dict[str, CellResult], report_md: str) -> None:
    """Log the report, every trial's error and the per-cell figures into ``rec``.

    Per-trial data go out with ``send_columns`` (a ``trial`` TimeColumn), so the trial
    timeline never leaks onto later logs; the per-cell figures are logged at ``snr_db`` /
    ``sigma_mpx`` with the stream's time reset before and after.
    """
    rec.log(REPORT, rr.TextDocument(report_md, media_type=rr.MediaType.MARKDOWN), static=True)
    for cid, r in results.items():
        base = trial_errors(cid)
        n_trials = 0
        for name, errors_m in r.errors_t_m.items():
            errors_mm = np.asarray(errors_m, dtype=float) * 1000.0
            n_trials = max(n_trials, len(errors_mm))
            ok = np.flatnonzero(np.isfinite(errors_mm))
            rec.log(
                f"{base}/{name}",
                rr.SeriesPoints(names=name, colors=SOLVER_COLORS.get(name, (200, 200, 200)), marker_sizes=2.0),
                static=True,
            )
            if len(ok):
                rec.send_columns(
                    f"{base}/{name}",
                    indexes=[rr.TimeColumn(TIMELINE_TRIAL, sequence=ok)],
                    columns=rr.Scalars.columns(scalars=errors_mm[ok]),
                )
        if n_trials:
            rec.log(f"{base}/crlb", rr.SeriesLines(names="crlb", colors=SOLVER_COLORS["crlb"], widths=2.0), static=True)
            rec.send_columns(
                f"{base}/crlb",
                indexes=[rr.TimeColumn(TIMELINE_TRIAL, sequence=[0, n_trials - 1])],
                columns=rr.Scalars.columns(scalars=np.full(2, r.crlb_t_m * 1000.0)),
            )

    styled: set[str] = set()

    def scalar(entity: str, value: float, series: str) -> None:
        if entity not in styled:
            rec.log(entity, rr.SeriesLines(names=series, colors=SOLVER_COLORS[series], widths=2.0), static=True)
            styled.add(entity)
        rec.log(entity, rr.Scalars(float(value)))

    for cid, r in results.items():
        rec.reset_time()
        group = _paper_group(cid)
        if group is not None:
            rec.set_time(TIMELINE_SNR_DB, sequence=int(_PAPER.fullmatch(cid)["snr"]))
            for name in SOLVERS:
                s = r.stats[name]
                for i in range(3):
                    scalar(f"{group}/t{i + 1}_mean/{name}", s.mean_t_m[i], name)
                scalar(f"{group}/rmse_mm/{name}", s.rmse_t_m * 1000.0, name)
                scalar(f"{group}/rmse_over_crlb/{name}", s.rmse_t_m / r.crlb_t_m, name)
            scalar(f"{group}/rmse_mm/crlb", r.crlb_t_m * 1000.0, "crlb")
            continue
        group = _crlb_group(cid)
        if group is not None:
            rec.set_time(TIMELINE_SIGMA_MPX, sequence=int(round(float(_CRLB.fullmatch(cid)["s"]) * 1000)))
            for name in SOLVERS:
                scalar(f"{group}/rmse_over_crlb/{name}", r.stats[name].rmse_t_m / r.crlb_t_m, name)
    rec.reset_time()


def featured_cells(results: dict[str, CellResult]) -> list[str]:
    """The cells whose error-against-trial plot the layout shows: the cells of the paper's
    figures present in ``results``, then the others in recording order, at most
    :data:`MAX_FEATURED_CELLS`."""
    figure_cells = [cid for cid, *_ in PAPER_FIGURES.values() if cid in results]
    ordered = list(dict.fromkeys(figure_cells + list(results)))
    return ordered[:MAX_FEATURED_CELLS]


def default_tab(results: dict[str, CellResult]) -> str:
    """The tab a study file opens on: the paper's figures when it has paper cells, else the CRLB
    cells, else the trials."""
    if any(_paper_group(cid) for cid in results):
        return "figures"
    if any(_crlb_group(cid) for cid in results):
        return "crlb"
    return "trials"


def study_blueprint(
    results: dict[str, CellResult], *, active: str = "trials", documents: tuple[tuple[str, str], ...] = ()
) -> rrb.Blueprint:
    """The study's layout; ``active`` is the tab it opens on (trials, figures or crlb; its
    timeline is selected), ``documents`` extra (origin, name) text documents beside the report
    (a run's summary and manifest)."""
    if active not in TAB_TIMELINES:
        raise ValueError(f"unknown tab {active!r}; valid: {', '.join(TAB_TIMELINES)}")
    trial_views = [
        rrb.TimeSeriesView(
            origin=trial_errors(cid), name=f"{cid}: ‖t̂ − t‖ (mm) per trial, CRLB (grey)",
            plot_legend=rrb.PlotLegend(visible=True),
        )
        for cid in featured_cells(results)
    ]
    texts = [rrb.TextDocumentView(origin=REPORT, name="report")]
    texts += [rrb.TextDocumentView(origin=origin, name=name) for origin, name in documents]
    tabs = {
        "trials": rrb.Horizontal(
            rrb.Tabs(*trial_views) if trial_views else rrb.Spacer(),
            rrb.Tabs(*texts),
            column_shares=[0.6, 0.4],
            name="trials (timeline trial)",
        )
    }
    if any(_paper_group(cid) for cid in results):
        tabs["figures"] = rrb.Vertical(
            rrb.Horizontal(
                *[
                    rrb.TimeSeriesView(origin=f"{FIG9_11}/t{i}_mean", name=f"fig {8 + i}: mean t{i} (m) vs SNR dB, h 0.2667 z 2 N 4")
                    for i in (1, 2, 3)
                ]
            ),
            rrb.Horizontal(
                rrb.TimeSeriesView(origin=f"{FIG9_11}/rmse_mm", name="RMSE of t (mm) vs SNR dB, and the CRLB"),
                rrb.TimeSeriesView(origin=f"{FIG9_11}/rmse_over_crlb", name="RMSE ÷ CRLB vs SNR dB, h 0.2667 z 2 N 4"),
                rrb.TextDocumentView(origin=REPORT, name="report"),
            ),
            name="paper figures 9–11 (timeline snr_db)",
        )
    crlb_groups = list(dict.fromkeys(g for cid in results if (g := _crlb_group(cid))))
    if crlb_groups:
        tabs["crlb"] = rrb.Grid(
            *[
                rrb.TimeSeriesView(origin=f"{g}/rmse_over_crlb", name=f"{g.split('/')[-1]}: RMSE ÷ CRLB vs σ (mpx)")
                for g in crlb_groups
            ],
            name="CRLB cells (timeline sigma_mpx)",
        )
    if active not in tabs:
        active = "trials"
    names = list(tabs)
    return rrb.Blueprint(
        rrb.Tabs(*tabs.values(), active_tab=names.index(active)),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TAB_TIMELINES[active]),
        auto_views=False,
    )


def write_report_rrd(out_path: str | os.PathLike, results: dict[str, CellResult], report_md: str) -> None:
    """Write the study as an ``.rrd`` of its own (temporary file beside it, renamed when
    complete), opening on the paper's figures (:func:`default_tab`)."""
    with AtomicRrd(out_path, recording_id="agvviz-p4p-monte-carlo", recording_name="p4p_monte_carlo report") as rrd:
        log_study(rrd.rec, results, report_md)
        rrd.commit(study_blueprint(results, active=default_tab(results)))
