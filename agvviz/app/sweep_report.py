"""The ranking document of a sweep ``.rrd`` (issue 27; issue 26: the ranking in the viewer): the
settings ranked, each one's colour in the overlay, p against the best and the verdict in words —
one function, :func:`ranking_markdown`, so the document has one author (``agvviz sweep`` writes it
as ``compare/report`` in the file; ``ranking.md``/``ranking.csv`` hold every column).
"""

from __future__ import annotations

import math

from agvviz.app.diff import format_number, format_p
from agvviz.viz.style import color_name

#: p below which a setting is called worse than the best (paired Wilcoxon, two-sided).
SWEEP_ALPHA = 0.05
#: The ranking's columns the viewer's report shows besides the ranking metric.
REPORT_METRICS = ("solved", "position_p95_mm", "heading_rmse_deg")
#: Metrics for which a larger value ranks higher.
HIGHER_IS_BETTER = {"solved", "solved_pct"}


def sweep_verdict(entry, best, alpha: float = SWEEP_ALPHA) -> str:
    """One setting against the best: ``best``, ``worse than #1 (p < 0.001)``, ``not told apart
    from #1 (p 0.4)``, or ``no paired test`` when no frame was solved by both."""
    if entry is best:
        return "best"
    if entry.p_vs_best is None or not math.isfinite(entry.p_vs_best):
        return f"no paired test with #{best.rank} (no frame both solved)"
    p = format_p(entry.p_vs_best)
    shown = f"p {p}" if p.startswith("<") else f"p = {p}"
    if entry.p_vs_best < alpha:
        return f"worse than #{best.rank} ({shown})"
    return f"not told apart from #{best.rank} ({shown} ≥ {alpha:g})"


def ranking_markdown(recording_name: str, entries: list, rank_by: str) -> str:
    """The sweep's ranking as the viewer shows it: rank, the colour of the setting in the overlay,
    the setting, the ranking metric and a few others, p vs the best and the verdict it gives;
    failed settings below. ``entries`` (:class:`~agvviz.app.sweep.SweepEntry`) in rank order."""
    ok = [e for e in entries if e.ok]
    direction = "higher" if rank_by in HIGHER_IS_BETTER else "lower"
    metrics = list(dict.fromkeys([rank_by, *REPORT_METRICS]))
    header = ["rank", "colour", "setting", *metrics, "p vs best", "verdict"]
    lines = [
        f"### Sweep over {recording_name}: ranked by `{rank_by}` ({direction} is better)", "",
        "| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |",
    ]
    for index, e in enumerate(ok):
        cells = [f"#{e.rank}", color_name(index), e.label, *[format_number(e.metrics.get(m)) for m in metrics],
                 format_p(e.p_vs_best) if e is not ok[0] else "—", sweep_verdict(e, ok[0])]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    if not ok:
        lines.append("No setting ran: nothing to rank.")
    lines += ["", f"p vs best: Wilcoxon signed-rank of the per-frame errors against #1, on the frames both "
              f"solved; worse when p < {SWEEP_ALPHA:g}. Every column: ranking.md / ranking.csv. Each setting's "
              "layers are under `settings/<key>/` (`sweep/index` lists the keys); `agvviz diff FILE#A FILE#B` "
              "compares two."]
    failed = [e for e in entries if not e.ok]
    if failed:
        lines += ["", "Failed settings:", *[f"- {e.label}: {e.error}" for e in failed]]
    return "\n".join(lines) + "\n"
