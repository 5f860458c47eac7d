"""Write the p4p_monte_carlo study (:mod:`agvviz.evaluation.monte_carlo`) as a Rerun ``.rrd``.

Entity tree (timeline ``snr_db`` for the paper cells, ``sigma_mpx`` = σ in milli-pixels for
the CRLB cells)::

    mc/report                                      TextDocument: the markdown report (static)
    mc/paper/h<h>_z<z>_n<N>/t<i>_mean/<solver>     Scalars: mean of t_i (m) over snr_db
    mc/paper/h<h>_z<z>_n<N>/rmse_mm/<solver>|crlb  Scalars: RMSE of t and its CRLB (mm)
    mc/paper/h<h>_z<z>_n<N>/rmse_over_crlb/<solver>   Scalars: RMSE ÷ CRLB over snr_db
    mc/crlb/tilt<t>_h<h>_z<z>_n<N>/rmse_over_crlb/<solver>   Scalars over sigma_mpx

The default blueprint shows the paper's figures 9–11 (t1, t2, t3 of p4p and lm over SNR,
h = 0.2667 m, z = 2 m, 4 points), the RMSE against the CRLB of that sweep and their ratio, and
the report; the CRLB cells are on timeline ``sigma_mpx`` (switch the timeline to see them).
"""

from __future__ import annotations

import os
import re

import rerun as rr
import rerun.blueprint as rrb

from agvviz.evaluation.monte_carlo import SOLVERS, CellResult
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


def write_report_rrd(out_path: str | os.PathLike, results: dict[str, CellResult], report_md: str) -> None:
    """Log the study into ``out_path`` (temporary file beside it, renamed when complete)."""
    with AtomicRrd(out_path, recording_id="agvviz-p4p-monte-carlo", recording_name="p4p_monte_carlo report") as rrd:
        rec = rrd.rec
        rec.log("mc/report", rr.TextDocument(report_md, media_type=rr.MediaType.MARKDOWN), static=True)
        styled: set[str] = set()

        def scalar(entity: str, value: float, series: str) -> None:
            if entity not in styled:
                rec.log(entity, rr.SeriesLines(names=series, colors=SOLVER_COLORS[series], widths=2.0), static=True)
                styled.add(entity)
            rec.log(entity, rr.Scalars(float(value)))

        for cid, r in results.items():
            rec.reset_time()
            m = _PAPER.fullmatch(cid)
            if m:
                group = f"mc/paper/h{m['h']}_z{m['z']}_n{m['n']}"
                rec.set_time("snr_db", sequence=int(m["snr"]))
                for name in SOLVERS:
                    s = r.stats[name]
                    for i in range(3):
                        scalar(f"{group}/t{i + 1}_mean/{name}", s.mean_t_m[i], name)
                    scalar(f"{group}/rmse_mm/{name}", s.rmse_t_m * 1000.0, name)
                    scalar(f"{group}/rmse_over_crlb/{name}", s.rmse_t_m / r.crlb_t_m, name)
                scalar(f"{group}/rmse_mm/crlb", r.crlb_t_m * 1000.0, "crlb")
                continue
            m = _CRLB.fullmatch(cid)
            if m:
                group = f"mc/crlb/tilt{m['tilt']}_h{m['h']}_z{m['z']}_n{m['n']}"
                rec.set_time("sigma_mpx", sequence=int(round(float(m["s"]) * 1000)))
                for name in SOLVERS:
                    scalar(f"{group}/rmse_over_crlb/{name}", r.stats[name].rmse_t_m / r.crlb_t_m, name)
        blueprint = rrb.Blueprint(
            rrb.Vertical(
                rrb.Horizontal(
                    *[
                        rrb.TimeSeriesView(origin=f"{FIG9_11}/t{i}_mean", name=f"fig {8 + i}: mean t{i} (m) vs SNR dB, h 0.2667 z 2 N 4")
                        for i in (1, 2, 3)
                    ]
                ),
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin=f"{FIG9_11}/rmse_mm", name="RMSE of t (mm) vs SNR dB, and the CRLB"),
                    rrb.TimeSeriesView(origin=f"{FIG9_11}/rmse_over_crlb", name="RMSE ÷ CRLB vs SNR dB, h 0.2667 z 2 N 4"),
                    rrb.TextDocumentView(origin="mc/report", name="report"),
                ),
            ),
            rrb.BlueprintPanel(state="collapsed"),
            rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(state="collapsed"),
            auto_views=False,
        )
        rrd.commit(blueprint)
