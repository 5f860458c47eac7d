"""The studies in an ``.rrd``: a study run's trials (``agvviz run`` on a p4p Monte-Carlo or CNOEM
grid recording, into the :class:`~agvviz.viz.run_logger.RunLogger`'s stream) and the studies' own
report files (``bench/bench_monte_carlo.py``, ``bench/bench_cnoem.py``).

p4p Monte-Carlo (:mod:`agvviz.replay.studies.monte_carlo`, :mod:`agvviz.replay.studies.monte_carlo_cells`):
one implementation for both outputs, :func:`log_study` (timelines: ``trial`` = trial index within
its cell; ``sigma_mpx`` = the cell's σ in milli-pixels, for every cell; ``snr_db`` for the paper cells too)::

    mc/report                                      TextDocument: the markdown report (static)
    mc/trials/<cell>/error_mm/<solver>             Scalars over trial: ‖t̂ − t‖ (mm) of each
                                                   trial (failed solves left out); no tab shows it
    mc/trials/<cell>/error_mm/crlb                 Scalars at the first and last trial: the
                                                   cell's CRLB (sqrt trace, mm), a flat line
    <group> = mc/paper/h<h>_z<z>_n<N> (paper cells) or mc/crlb/tilt<t>_h<h>_z<z>_n<N> (CRLB cells);
    every figure below is at the cell's σ on ``sigma_mpx``, paper cells also at ``snr_db``:
    <group>/rmse_mm/<solver>                       Scalars ×3: RMSE of t (mm), its 95 % interval
                                                   low and high (statistics.rmse_ci), one colour
                                                   and one legend name
    <group>/rmse_mm/crlb                           Scalars: the cell's CRLB (mm)
    <group>/rmse_over_crlb/<solver>                Scalars: RMSE ÷ CRLB
    mc/paper/h<h>_z<z>_n<N>/t<i>_mean/<solver>     Scalars: mean of t_i (m)

CNOEM grid run (:mod:`agvviz.replay.studies.cnoem`), timeline ``trial`` = the trial's index within
its cell::

    cnoem/report                                TextDocument: the study report (static)
    cnoem/trials/<cell>/error_m/<method>        Scalars over trial: position error of F (m) of
                                                each trial (failed solves left out)
    cnoem/trials/<cell>/error_m/crlb            Scalars at the first and last trial: the cell's
                                                multi-frame CRLB position bound (m), a flat line

CNOEM grid report file (:mod:`agvviz.replay.studies.cnoem_cells`), timeline ``cell`` = the cell's index
in :func:`agvviz.sim.auv.grid_cells` (distance slowest, σ fastest)::

    cnoem/report                          TextDocument: the markdown report (static)
    cnoem/mean_error_m/<method>           Scalars: mean position error of F per cell (m)
    cnoem/ratio_to_ippe_first             Scalars: cnoem mean ÷ ippe_first mean per cell
    cnoem/rms_over_crlb/<method>          Scalars: RMS ÷ multi-frame CRLB per cell
    cnoem/crlb_m                          Scalars: the cell's CRLB position bound (m)

The layouts are :func:`agvviz.viz.blueprints.study_blueprint`, ``trials_blueprint``,
``cnoem_trials_blueprint`` and ``cnoem_report_blueprint``.
"""

from __future__ import annotations

import os

import numpy as np
import rerun as rr

from agvviz.model.studies import CellResult, CnoemCellResult, CnoemTrialsOutcome, TrialsOutcome
from agvviz.replay.studies.cnoem_cells import METHODS as CNOEM_METHODS
from agvviz.replay.studies.monte_carlo_cells import SOLVERS
from agvviz.evaluation.statistics import rmse_ci
from agvviz.viz import paths
from agvviz.viz.blueprints import cnoem_report_blueprint, mc_default_tab, study_blueprint
from agvviz.viz.rrd_file import AtomicRrd
from agvviz.viz.style import CNOEM_COLORS, SOLVER_COLORS, solver_color



# -- p4p Monte-Carlo ---------------------------------------------------------------------------
def log_study(rec: rr.RecordingStream, results: dict[str, CellResult], report_md: str) -> None:
    """Log the report, every trial's error and the per-cell figures into ``rec``.

    Per-trial data go out with ``send_columns`` (a ``trial`` TimeColumn), so the trial
    timeline never leaks onto later logs; the per-cell figures are logged at ``snr_db`` /
    ``sigma_mpx`` with the stream's time reset before and after.
    """
    rec.log(paths.MC_REPORT, rr.TextDocument(report_md, media_type=rr.MediaType.MARKDOWN), static=True)
    for cid, r in results.items():
        base = paths.mc_trial_errors(cid)
        n_trials = 0
        for name, errors_m in r.errors_t_m.items():
            errors_mm = np.asarray(errors_m, dtype=float) * 1000.0
            n_trials = max(n_trials, len(errors_mm))
            ok = np.flatnonzero(np.isfinite(errors_mm))
            rec.log(
                f"{base}/{name}",
                rr.SeriesPoints(names=name, colors=solver_color(name), marker_sizes=2.0),
                static=True,
            )
            if len(ok):
                rec.send_columns(
                    f"{base}/{name}",
                    indexes=[rr.TimeColumn(paths.TIMELINE_TRIAL, sequence=ok)],
                    columns=rr.Scalars.columns(scalars=errors_mm[ok]),
                )
        if n_trials:
            rec.log(f"{base}/crlb", rr.SeriesLines(names="crlb", colors=SOLVER_COLORS["crlb"], widths=2.0), static=True)
            rec.send_columns(
                f"{base}/crlb",
                indexes=[rr.TimeColumn(paths.TIMELINE_TRIAL, sequence=[0, n_trials - 1])],
                columns=rr.Scalars.columns(scalars=np.full(2, r.crlb_t_m * 1000.0)),
            )

    styled: set[str] = set()

    def style(entity: str, series: str | list[str], colors, widths) -> None:
        if entity not in styled:
            rec.log(entity, rr.SeriesLines(names=series, colors=colors, widths=widths), static=True)
            styled.add(entity)

    def scalar(entity: str, value: float, series: str) -> None:
        style(entity, series, solver_color(series), 2.0)
        rec.log(entity, rr.Scalars(float(value)))

    def rmse_with_band(entity: str, errors_m: np.ndarray, series: str) -> None:
        """RMSE (mm) and its 95 % interval over the cell's trials: a line and a thin band
        above and below it, one colour, one legend name."""
        rmse, lo, hi = rmse_ci(errors_m)
        color = solver_color(series)
        # the band's lines carry the solver's name: the legend shows one entry per name
        style(entity, [series, series, series], [color, color, color], [2.0, 0.5, 0.5])
        rec.log(entity, rr.Scalars(np.array([rmse, lo, hi]) * 1000.0))

    # Every per-cell figure is placed at its σ (milli-pixels, the ``sigma_mpx`` timeline the
    # layout opens on, so every tab has data); paper cells at their SNR (``snr_db``) too.
    for cid, r in results.items():
        rec.reset_time()
        group = paths.mc_paper_group(cid) or paths.mc_crlb_group(cid)
        if group is None:
            continue
        rec.set_time(paths.TIMELINE_SIGMA_MPX, sequence=sigma_mpx(r.sigma_px))
        paper = paths.MC_PAPER_CELL.fullmatch(cid)
        if paper is not None:
            rec.set_time(paths.TIMELINE_SNR_DB, sequence=int(paper["snr"]))
            for name in SOLVERS:
                for i in range(3):
                    scalar(f"{group}/t{i + 1}_mean/{name}", r.stats[name].mean_t_m[i], name)
        for name in SOLVERS:
            rmse_with_band(f"{group}/rmse_mm/{name}", r.errors_t_m.get(name, np.array([r.stats[name].rmse_t_m])), name)
            scalar(f"{group}/rmse_over_crlb/{name}", r.stats[name].rmse_t_m / r.crlb_t_m, name)
        scalar(f"{group}/rmse_mm/crlb", r.crlb_t_m * 1000.0, "crlb")
    rec.reset_time()


def sigma_mpx(sigma_px: float) -> int:
    """σ in milli-pixels, the ``sigma_mpx`` timeline's sequence value."""
    return int(round(float(sigma_px) * 1000))


def write_monte_carlo_report_rrd(out_path: str | os.PathLike, results: dict[str, CellResult], report_md: str) -> None:
    """Write the study as an ``.rrd`` of its own (temporary file beside it, renamed when
    complete), opening on the paper's figures (:func:`~agvviz.viz.blueprints.mc_default_tab`)."""
    with AtomicRrd(out_path, recording_id="agvviz-p4p-monte-carlo", recording_name="p4p_monte_carlo report") as rrd:
        log_study(rrd.rec, results, report_md)
        rrd.commit(study_blueprint(results, active=mc_default_tab(results)))


def log_trials(stream: rr.RecordingStream, outcome: TrialsOutcome) -> None:
    """Log ``outcome``'s error series, per-cell figures and report markdown into ``stream``
    (the :class:`~agvviz.viz.run_logger.RunLogger`'s, beside its manifest and summary)."""
    log_study(stream, outcome.results, outcome.report_markdown)


# -- CNOEM grid ----------------------------------------------------------------------------------
def log_cnoem_trials(stream: rr.RecordingStream, outcome: CnoemTrialsOutcome) -> None:
    """Log ``outcome``'s report and every trial's error series into ``stream`` (the
    :class:`~agvviz.viz.run_logger.RunLogger`'s). Per-trial data go out with ``send_columns``
    (a ``trial`` TimeColumn), so the trial timeline never leaks onto later logs."""
    stream.log(paths.CNOEM_REPORT, rr.TextDocument(outcome.report_markdown, media_type=rr.MediaType.MARKDOWN), static=True)
    for cell_id, r in outcome.results.items():
        base = paths.cnoem_trial_errors(cell_id)
        n_trials = 0
        for method in outcome.methods:
            errors_m = np.asarray(r.errors_m[method], dtype=float)
            n_trials = max(n_trials, len(errors_m))
            ok = np.flatnonzero(np.isfinite(errors_m))
            stream.log(f"{base}/{method}", rr.SeriesPoints(names=method, colors=CNOEM_COLORS[method], marker_sizes=2.0), static=True)
            if len(ok):
                stream.send_columns(
                    f"{base}/{method}",
                    indexes=[rr.TimeColumn(paths.TIMELINE_TRIAL, sequence=ok)],
                    columns=rr.Scalars.columns(scalars=errors_m[ok]),
                )
        if n_trials and np.isfinite(r.crlb_position_m):
            stream.log(f"{base}/crlb", rr.SeriesLines(names="crlb", colors=CNOEM_COLORS["crlb"], widths=2.0), static=True)
            stream.send_columns(
                f"{base}/crlb",
                indexes=[rr.TimeColumn(paths.TIMELINE_TRIAL, sequence=[0, n_trials - 1])],
                columns=rr.Scalars.columns(scalars=np.full(2, r.crlb_position_m)),
            )


def write_cnoem_report_rrd(out_path: str | os.PathLike, results: list[CnoemCellResult], report_md: str) -> None:
    """Log the study into ``out_path`` (temporary file beside it, renamed when complete)."""
    with AtomicRrd(out_path, recording_id="agvviz-cnoem-study", recording_name="cnoem grid study") as rrd:
        rec = rrd.rec
        rec.log(paths.CNOEM_REPORT, rr.TextDocument(report_md, media_type=rr.MediaType.MARKDOWN), static=True)
        for m in CNOEM_METHODS:
            rec.log(f"{paths.CNOEM_MEAN_ERROR_M}/{m}", rr.SeriesLines(names=m, colors=CNOEM_COLORS[m], widths=1.5), static=True)
        for m in ("cnoem", "bundle"):
            rec.log(f"{paths.CNOEM_RMS_OVER_CRLB}/{m}", rr.SeriesLines(names=m, colors=CNOEM_COLORS[m], widths=1.5), static=True)
        rec.log(paths.CNOEM_RATIO_TO_IPPE_FIRST, rr.SeriesLines(names="cnoem ÷ ippe_first", colors=CNOEM_COLORS["cnoem"]), static=True)
        rec.log(paths.CNOEM_CRLB_M, rr.SeriesLines(names="CRLB position bound [m]", colors=CNOEM_COLORS["crlb"]), static=True)
        for index, r in enumerate(results):
            rec.set_time(paths.TIMELINE_CELL, sequence=index)
            for m in CNOEM_METHODS:
                rec.log(f"{paths.CNOEM_MEAN_ERROR_M}/{m}", rr.Scalars(r.mean_m(m)))
            for m in ("cnoem", "bundle"):
                rec.log(f"{paths.CNOEM_RMS_OVER_CRLB}/{m}", rr.Scalars(r.rms_m(m) / r.crlb_position_m))
            rec.log(paths.CNOEM_RATIO_TO_IPPE_FIRST, rr.Scalars(r.mean_m("cnoem") / r.mean_m("ippe_first")))
            rec.log(paths.CNOEM_CRLB_M, rr.Scalars(r.crlb_position_m))
        rrd.commit(cnoem_report_blueprint())
