"""Write the CNOEM grid study (:mod:`agvviz.replay.studies.cnoem_cells`) as a Rerun ``.rrd``.

Entity tree (timeline ``cell`` = the cell's index in :func:`agvviz.sim.auv.grid_cells`, distance
slowest, σ fastest)::

    cnoem/report                          TextDocument: the markdown report (static)
    cnoem/mean_error_m/<method>           Scalars: mean position error of F per cell (m)
    cnoem/ratio_to_ippe_first             Scalars: cnoem mean ÷ ippe_first mean per cell
    cnoem/rms_over_crlb/<method>          Scalars: RMS ÷ multi-frame CRLB per cell
    cnoem/crlb_m                          Scalars: the cell's CRLB position bound (m)
"""

from __future__ import annotations

import os

import rerun as rr
import rerun.blueprint as rrb

from agvviz.model.studies import CnoemCellResult
from agvviz.replay.studies.cnoem_cells import METHODS
from agvviz.viz.rrd_file import AtomicRrd

COLORS = {
    "cnoem": (230, 40, 40),
    "cnoem_multistart": (255, 120, 120),
    "bundle": (255, 160, 0),
    "ippe_first": (40, 200, 90),
    "ippe_first_nav": (60, 120, 255),
    "ippe_mean_nav": (200, 120, 255),
    "crlb": (230, 230, 230),
}


def write_report_rrd(out_path: str | os.PathLike, results: list[CnoemCellResult], report_md: str) -> None:
    """Log the study into ``out_path`` (temporary file beside it, renamed when complete)."""
    with AtomicRrd(out_path, recording_id="agvviz-cnoem-study", recording_name="cnoem grid study") as rrd:
        rec = rrd.rec
        rec.log("cnoem/report", rr.TextDocument(report_md, media_type=rr.MediaType.MARKDOWN), static=True)
        for m in METHODS:
            rec.log(f"cnoem/mean_error_m/{m}", rr.SeriesLines(names=m, colors=COLORS[m], widths=1.5), static=True)
        for m in ("cnoem", "bundle"):
            rec.log(f"cnoem/rms_over_crlb/{m}", rr.SeriesLines(names=m, colors=COLORS[m], widths=1.5), static=True)
        rec.log("cnoem/ratio_to_ippe_first", rr.SeriesLines(names="cnoem ÷ ippe_first", colors=COLORS["cnoem"]), static=True)
        rec.log("cnoem/crlb_m", rr.SeriesLines(names="CRLB position bound [m]", colors=COLORS["crlb"]), static=True)
        for index, r in enumerate(results):
            rec.set_time("cell", sequence=index)
            for m in METHODS:
                rec.log(f"cnoem/mean_error_m/{m}", rr.Scalars(r.mean_m(m)))
            for m in ("cnoem", "bundle"):
                rec.log(f"cnoem/rms_over_crlb/{m}", rr.Scalars(r.rms_m(m) / r.crlb_position_m))
            rec.log("cnoem/ratio_to_ippe_first", rr.Scalars(r.mean_m("cnoem") / r.mean_m("ippe_first")))
            rec.log("cnoem/crlb_m", rr.Scalars(r.crlb_position_m))
        rrd.commit(
            rrb.Blueprint(
                rrb.Horizontal(
                    rrb.Vertical(
                        rrb.TimeSeriesView(origin="/cnoem/mean_error_m", name="mean position error of F [m] per cell"),
                        rrb.TimeSeriesView(origin="/cnoem/ratio_to_ippe_first", name="CNOEM ÷ IPPE per cell (paper: 0.217 overall)"),
                        rrb.TimeSeriesView(origin="/cnoem/rms_over_crlb", name="RMS ÷ multi-frame CRLB per cell"),
                    ),
                    rrb.TextDocumentView(origin="/cnoem/report", name="report"),
                    column_shares=[0.55, 0.45],
                ),
                rrb.TimePanel(state="collapsed", timeline="cell"),
                auto_views=False,
            )
        )
