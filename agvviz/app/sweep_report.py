"""The ranking document of a sweep ``.rrd`` (issue 27): the settings ranked, each one's p-value
against the best, and the verdict in words — one function, :func:`ranking_markdown`, so the
document has one author (``agvviz sweep`` writes it as ``compare/report`` in the file).
"""

from __future__ import annotations

from agvviz.app.diff import format_number, format_p

#: A setting whose paired test against the best gives p below this differs from it.
ALPHA = 0.05
#: Columns of the ranking table shown in the document (every column is in ranking.csv / .md).
SHOWN = ("rank", "setting", "solved", "position_rmse_mm", "position_p95_mm", "heading_rmse_deg",
         "reproj_median_px", "p_vs_best", "status")


def verdict_lines(ranked: list, rank_by: str, alpha: float = ALPHA) -> list[str]:
    """The verdict: the best setting by ``rank_by`` and, for each other that ran, whether the
    paired Wilcoxon test tells it from the best at level ``alpha``; the failed ones named."""
    ok = [e for e in ranked if e.ok]
    if not ok:
        return ["No setting ran: nothing to rank."]
    best = ok[0]
    lines = [f"**Best: {best.label}** ({rank_by} = {format_number(best.metrics.get(rank_by))})."]
    same = [e for e in ok[1:] if e.p_vs_best is None or e.p_vs_best >= alpha]
    worse = [e for e in ok[1:] if e.p_vs_best is not None and e.p_vs_best < alpha]
    if worse:
        lines.append("Worse than the best (paired Wilcoxon, p < " + f"{alpha:g}): "
                     + ", ".join(f"{e.label} (p {_p(e.p_vs_best)})" for e in worse) + ".")
    if same:
        lines.append(f"Not told apart from the best at p < {alpha:g}: "
                     + ", ".join(f"{e.label} (p {_p(e.p_vs_best)})" for e in same) + ".")
    failed = [e for e in ranked if not e.ok]
    if failed:
        lines.append("Failed: " + ", ".join(e.label for e in failed) + " (see the status column).")
    return lines


def _p(p: float | None) -> str:
    text = format_p(p)
    return text if text.startswith("<") or text == "—" else f"= {text}"


def ranking_markdown(recording_name: str, ranked: list, rank_by: str, header: list[str], rows: list[list[str]]) -> str:
    """The sweep's ranking document: title, verdict, the table of ``header``/``rows`` (from
    :func:`agvviz.app.sweep.ranking_rows`) reduced to :data:`SHOWN` and ``rank_by``, and how
    the p-values were made."""
    wanted = list(dict.fromkeys([*SHOWN[:2], rank_by, *SHOWN[2:]]))
    columns = [header.index(h) for h in wanted if h in header]
    table = [
        "| " + " | ".join(header[i] for i in columns) + " |",
        "| " + " | ".join("---" for _ in columns) + " |",
        *["| " + " | ".join(row[i].replace("|", "\\|") for i in columns) + " |" for row in rows],
    ]
    direction = "higher" if rank_by in ("solved", "solved_pct") else "lower"
    return "\n".join([
        f"# sweep over {recording_name}", "",
        *verdict_lines(ranked, rank_by), "",
        *table, "",
        f"Ranked by `{rank_by}` ({direction} is better). p_vs_best: Wilcoxon signed-rank test of the per-frame "
        "errors against the best setting, on the frames both solved. Each setting's layers are under "
        "`settings/<key>/` (`sweep/index` lists the keys); `agvviz diff FILE#A FILE#B` compares two.",
    ]) + "\n"
