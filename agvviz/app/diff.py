"""Library API behind ``agvviz diff``: returns values, prints nothing.

:func:`diff` compares run B with run A (both ``.rrd``, read back by
:func:`agvviz.app.run_series.load_run`): the metrics table, paired tests, intervals and the
most different frames; optionally writes the overlay ``.rrd`` (both runs on A's clock) and
evaluates a ``--fail-if`` condition. :func:`diff_verdict`, :func:`diff_table` and
:func:`comparison_markdown` say it in words; :func:`format_number` and :func:`format_p` are the
number formats of every comparison table (the sweep's ranking too).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agvviz.recording import outputs
from agvviz.errors import InputError
from agvviz.evaluation import expression, gates as gate_rules
from agvviz.evaluation.gates import Gate
from agvviz.evaluation.comparison import DIRECT, Comparison, RunSeries, compare_runs, metric_names
from agvviz.evaluation.trajectory import ALIGNMENTS
from agvviz.app import run_series
from agvviz.viz.overlay import OverlayRun, write_overlay
from agvviz.viz.readback import read_rrd, split_setting


class CompareError(InputError):
    """A comparison or sweep that cannot be done as asked (bad grid, unknown metric, ...)."""


def _fusion_note(a: RunSeries, b: RunSeries) -> str | None:
    """For camera–UWB runs: what the position errors compared are, and each run's fused error
    as its summary gives it (the fused estimate has no per-frame pairing to test)."""
    fused = [run.summary.get("fusion") for run in (a, b)]
    if not all(isinstance(fusion, dict) for fusion in fused):
        return None
    parts = []
    for label, fusion in zip("AB", fused):
        stats = fusion.get("fused_xy_error_mm") or {}
        rmse = stats.get("rmse")
        text = f"{label} {fusion.get('fusion', '?')}: " + (
            f"RMSE {rmse:.3g} mm over {stats.get('n', 0)} outputs" if isinstance(rmse, (int, float)) else "no error"
        )
        parts.append(text)
    return (
        "camera–UWB runs: the position errors compared are the camera estimate's per frame (each run "
        "summary's position_error_mm); the fused camera+UWB estimate is not compared frame by frame "
        "(its outputs follow the UWB fixes too); its 2-D error from each run's summary: " + "; ".join(parts)
    )


# -- formatting ------------------------------------------------------------------------------
def format_number(value, digits: int = 4) -> str:
    if value is None:
        return "—"
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    if not math.isfinite(value):
        return str(value)
    return f"{value:.{digits}g}"


def format_p(p: float | None) -> str:
    """A p-value as a reader wants it: ``"<0.001"``, ``"0.004"``, ``"0.03"``, ``"0.4"``, ``"1"``;
    ``"—"`` when there is none."""
    if p is None or not math.isfinite(p):
        return "—"
    if p < 0.001:
        return "<0.001"
    if p < 0.01:
        return f"{p:.3f}"
    return f"{p:.2f}".rstrip("0").rstrip(".")


def _p_phrase(p: float) -> str:
    text = format_p(p)
    return f"p {text[0]} {text[1:]}" if text.startswith("<") else f"p = {text}"


def _decimals(*values: float | None) -> int:
    """Decimals that show two significant digits of the largest magnitude in ``values``."""
    magnitude = max((abs(v) for v in values if v is not None and math.isfinite(v)), default=0.0)
    if magnitude == 0.0:
        return 2
    return max(0, 1 - math.floor(math.log10(magnitude)))


#: Metric the verdict of ``diff`` decides by, in order of preference, with why. The first one
#: both runs have values of decides (a recording without truth has no position error).
HEADLINE_METRICS = (
    ("position_rmse_mm", "position RMSE", "mm", "the estimated AGV position against truth"),
    ("reproj_rmse_px", "reprojection RMS", "px",
     "the recording has no truth: the fit of the solved pose to the detected corners"),
)
#: Rows of the compact ``diff`` table (``diff_table(..., all_metrics=True)`` gives every row).
COMPACT_METRICS = (
    "solved", "suspects", "position_rmse_mm", "position_median_mm", "position_p95_mm", "heading_rmse_deg",
    "reproj_median_px", "rpe_trans_rmse_mm",
)


@dataclass(frozen=True)
class Verdict:
    """What ``diff`` says first: the headline metric's difference, in words.

    ``outcome`` is ``"worse"``, ``"better"`` (B relative to A), ``"no significant difference"``,
    ``"identical"`` or ``"not comparable"``; ``metric`` the metric that decides (None when none
    can); ``lines`` the text, headline first.
    """

    outcome: str
    metric: str | None
    lines: list[str]

    @property
    def headline(self) -> str:
        return self.lines[0]


def diff_verdict(comparison: Comparison, alpha: float | None = None) -> Verdict:
    """The verdict of a comparison, e.g. ``B worse in position RMSE by 0.39 mm [0.30, 0.47]
    (A 0.33 → B 0.72 mm), p < 0.001``.

    B is called worse (better) when the headline metric grew (shrank), the Wilcoxon p is below
    ``alpha`` (default ``1 − confidence`` of the comparison) *and* the bootstrap interval of
    B − A excludes zero; otherwise there is no significant difference. A second line names the
    metric that decides and why; a third, when the runs solved different numbers of frames,
    says so (the error metrics only cover the frames both solved).
    """
    c = comparison
    alpha = 1.0 - c.confidence if alpha is None else alpha
    k = len(c.common)
    chosen = next(
        ((row, label, unit, why) for name, label, unit, why in HEADLINE_METRICS
         if (row := c.row(name)).a is not None and row.b is not None),
        None,
    )
    extra = []
    suspects = next((r for r in c.rows if r.name == "suspects"), None)
    if suspects is not None and suspects.a != suspects.b:
        by_cause = ", ".join(
            f"{r.name.split('.', 1)[1]} {format_number(r.a)} → {format_number(r.b)}"
            for r in c.rows if r.name.startswith("suspects.") and r.a != r.b
        )
        extra.append(f"suspect frames (checks without truth): A {format_number(suspects.a)}, "
                     f"B {format_number(suspects.b)}" + (f" ({by_cause})" if by_cause else ""))
    solved = c.row("solved")
    if solved.a != solved.b:
        fewer = "fewer" if solved.b < solved.a else "more"
        extra.append(
            f"B solved {abs(solved.b - solved.a)} {fewer} frames than A ({solved.b} vs {solved.a} of "
            f"{c.row('frames').b} vs {c.row('frames').a}); the errors above cover only the {k} frames both solved."
        )
    if chosen is None:
        return Verdict("not comparable", None, [
            f"no verdict: the runs have no frame both solved with an error to compare ({k} frames both solved)",
            *extra,
        ])
    row, label, unit, why = chosen
    level = round(c.confidence * 100)
    reason = (
        f"{label} decides ({why}, over the {row.n} frames both runs solved); [ ] is the {level} % "
        "block-bootstrap interval, p the Wilcoxon signed-rank test of the paired per-frame errors."
    )
    d = _decimals(row.diff, row.ci_low, row.ci_high)
    values = f"(A {row.a:.{d}f} → B {row.b:.{d}f} {unit})"
    if row.diff == 0 and (row.p_value is None or row.p_value == 1.0) and row.ci_low in (None, 0.0) \
            and row.ci_high in (None, 0.0):
        return Verdict("identical", row.name, [
            f"no difference in {label}: the two runs' errors are identical on the {row.n} frames both solved "
            f"(both {row.a:.{d}f} {unit})", f"{label} decides ({why}).", *extra,
        ])
    interval = "" if row.ci_low is None else f" [{row.ci_low:.{d}f}, {row.ci_high:.{d}f}]"
    # "better by x [lo, hi]" reads as a size: the interval of A − B, positive like x.
    better_interval = "" if row.ci_low is None else f" [{-row.ci_high:.{d}f}, {-row.ci_low:.{d}f}]"
    p_text = _p_phrase(row.p_value) if row.p_value is not None else "no test"
    significant = (
        row.p_value is not None and row.p_value < alpha and row.ci_low is not None
        and (row.ci_low > 0 or row.ci_high < 0)
    )
    if significant and row.diff > 0:
        outcome, head = "worse", f"B worse in {label} by {row.diff:.{d}f} {unit}{interval} {values}, {p_text}"
    elif significant and row.diff < 0:
        outcome, head = "better", f"B better in {label} by {-row.diff:.{d}f} {unit}{better_interval} {values}, {p_text}"
    else:
        outcome = "no significant difference"
        head = (f"no significant difference in {label}: B − A = {row.diff:+.{d}f} {unit}{interval} {values}, "
                f"{p_text}")
    return Verdict(outcome, row.name, [head, reason, *extra])


def diff_table(comparison: Comparison, all_metrics: bool = False) -> tuple[list[str], list[list[str]]]:
    """Header and rows (strings) of the ``diff`` table: metric, A, B, B − A, its interval, p.

    The compact table (:data:`COMPACT_METRICS`, the ones present) unless ``all_metrics``; p as
    :func:`format_p` gives it. The number of paired frames is in :func:`diff_table_title`.
    """
    rows = comparison.rows if all_metrics else [r for r in comparison.rows if r.name in COMPACT_METRICS]
    header = ["metric", "A", "B", "B − A", f"{round(comparison.confidence * 100)} % CI of B − A", "p"]
    table = []
    for r in rows:
        ci = "—" if r.ci_low is None else f"[{format_number(r.ci_low, 3)}, {format_number(r.ci_high, 3)}]"
        diff = "—" if r.diff is None else (format_number(r.diff) if r.diff <= 0 else "+" + format_number(r.diff))
        table.append([r.name, format_number(r.a), format_number(r.b), diff, ci, format_p(r.p_value)])
    return header, table


def diff_table_title(comparison: Comparison, all_metrics: bool = False) -> str:
    """One line above the table: what the columns mean and which frames they cover."""
    c = comparison
    rest = "" if all_metrics else f"; {len(c.rows) - len(diff_table(c)[1])} more metrics with --all"
    return (
        f"A = {c.a_name}, B = {c.b_name}: {len(c.matched)} frames matched by time, errors over the "
        f"{len(c.common)} both solved; B − A positive = B larger (worse for errors); "
        f"CI: block bootstrap; p: Wilcoxon signed-rank{rest}"
    )


def comparison_markdown(comparison: Comparison) -> str:
    """The comparison as markdown: the verdict, the compact table, every metric, the most
    different frames and notes (the overlay's report panel)."""
    c = comparison
    verdict = diff_verdict(c)

    def table(all_metrics: bool) -> list[str]:
        header, rows = diff_table(c, all_metrics)
        return [
            "| " + " | ".join(header) + " |",
            "| --- |" + " ---: |" * (len(header) - 1),
            *["| " + " | ".join(row) + " |" for row in rows],
        ]

    lines = [
        f"# {c.a_name} (A) vs {c.b_name} (B)",
        "",
        f"**{verdict.headline}**",
        "",
        *[f"{line}  " for line in verdict.lines[1:]],
        "",
        f"{len(c.matched)} frames matched by time; error metrics over the {len(c.common)} frames both runs "
        f"solved (absolute values; APE alignment `{c.align}`, RPE over {c.rpe_delta} frame(s)). "
        "B − A positive = B larger (worse, for errors).",
        "",
        *table(False),
    ]
    if c.settings_changed:
        lines += ["", "Settings that differ: " + ", ".join(
            f"`{name}` {a!r} → {b!r}" for name, (a, b) in c.settings_changed.items()
        )]
    if c.largest:
        lines += ["", "## Frames where the estimates differ most", "",
                  "| frame A | frame B | ‖p_A − p_B‖ mm | error A mm | error B mm |",
                  "| ---: | ---: | ---: | ---: | ---: |"]
        lines += [
            f"| {d.frame_a} | {d.frame_b} | {d.separation_mm:.3f} | {d.position_a_mm:.3f} | {d.position_b_mm:.3f} |"
            for d in c.largest
        ]
    if c.solved_only_by_a or c.solved_only_by_b:
        lines += ["", f"Solved only by A: frames {c.solved_only_by_a[:20]}; only by B: frames {c.solved_only_by_b[:20]}"]
    lines += [f"\nNote: {note}" for note in c.notes]
    lines += ["", "## All metrics", "", *table(True)]
    return "\n".join(lines) + "\n"


# -- diff ------------------------------------------------------------------------------------
@dataclass
class DiffOutcome:
    """What :func:`diff` found and wrote."""

    comparison: Comparison
    overlay_path: Path | None
    fail_if: list[str]  # the --fail-if conditions
    failed: bool  # a --fail-if condition holds (False when there is none)
    seconds: dict[str, float]  # wall time of each step: load, compare, overlay
    gates: list[Gate] = field(default_factory=list)  # the verdict of each condition
    junit_path: Path | None = None  # where the verdicts were written as JUnit XML


def diff(
    a_path: str | os.PathLike,
    b_path: str | os.PathLike,
    *,
    overlay_path: str | os.PathLike | None = None,
    fail_if: str | list[str] | tuple[str, ...] | None = None,
    junit_path: str | os.PathLike | None = None,
    align: str = "none",
    rpe_delta: int = 1,
    time_offset: bool = False,
    images: bool = True,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
    top_k: int = 5,
) -> DiffOutcome:
    """Compare run B with run A (both ``.rrd``), read back through Rerun's API.

    A and B are run ``.rrd`` files or settings inside a sweep ``.rrd`` (``sweep.rrd#ippe``,
    ``sweep.rrd#solver=ippe``: :func:`agvviz.viz.readback.read_rrd`); a setting the file does not
    hold is one line naming the ones it does. The overlay (``overlay_path``) is the two-run case
    of the sweep ``.rrd``: both runs' layers under ``settings/a`` and ``settings/b``, so
    ``diff OUT#A OUT#B`` reads them back.

    ``fail_if`` (one condition or several) is parsed before any file is read, so a typo in a
    metric name fails at once (:class:`~agvviz.evaluation.expression.ExpressionError`, listing
    the known metrics); ``failed`` is True when any holds. Besides the comparison's metrics a
    condition can read each run's suspect counts (``B.suspects``, ``B.suspects.map_entry``,
    :func:`agvviz.evaluation.gates.suspect_metric_names`). ``junit_path``: the verdicts as
    JUnit XML (one testcase per condition), written also when a condition cannot be evaluated
    (then ExpressionError is raised after it, and no overlay is written).
    The overlay (``overlay_path``) holds both runs on A's clock; ``images=False`` leaves the
    camera images out of it.
    """
    if align not in ALIGNMENTS:
        raise CompareError(f"unknown alignment {align!r}; choose one of: {', '.join(ALIGNMENTS)}")
    if rpe_delta < 1:
        raise CompareError(f"rpe_delta must be ≥ 1 frame, got {rpe_delta}")
    conditions = [fail_if] if isinstance(fail_if, str) else list(fail_if or [])
    parsed = gate_rules.parse_conditions(conditions, metric_names(time_offset) + gate_rules.suspect_metric_names())
    if overlay_path is not None and Path(overlay_path).suffix != ".rrd":
        raise CompareError(f"--out must be a .rrd file, got {overlay_path}")
    if overlay_path is not None:  # before any work: never over A or B (also through links)
        outputs.prepare_output(overlay_path, inputs=(split_setting(a_path)[0], split_setting(b_path)[0]))
    if junit_path is not None:
        if not conditions:
            raise CompareError("--junit-xml writes the verdict of --fail-if conditions; give at least one --fail-if")
        outputs.prepare_output(junit_path, inputs=(split_setting(a_path)[0], split_setting(b_path)[0]),
                               option="--junit-xml")
    seconds = {}
    t0 = time.perf_counter()
    a, b = run_series.load_run(a_path), run_series.load_run(b_path)
    seconds["load"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    comparison = compare_runs(
        a, b, align=align, rpe_delta=rpe_delta, time_offset=time_offset,
        confidence=confidence, n_resamples=n_resamples, seed=seed, top_k=top_k,
    )
    note = _fusion_note(a, b)
    if note is not None:
        comparison.notes.append(note)
    seconds["compare"] = time.perf_counter() - t0
    runs = {"A": a, "B": b}
    verdicts = gate_rules.evaluate(
        parsed, comparison.metrics(),
        lambda run, name: gate_rules.missing_reason(name, runs[run].summary)
        if name in gate_rules.suspect_metric_names() else None,
    )
    junit = None

    def write_junit(overlay: Path | None) -> Path:
        from agvviz.app.run import write_junit as write

        properties = {"A": str(a_path), "B": str(b_path), **({"overlay": str(overlay)} if overlay else {})}
        return write(Path(junit_path), "diff", f"agvviz diff {a.name} vs {b.name}", verdicts,
                     properties=properties, details=diff_verdict(comparison).headline,
                     inputs=(split_setting(a_path)[0], split_setting(b_path)[0]))

    errors = [g for g in verdicts if g.holds is None]
    if errors:
        if junit_path is not None:
            write_junit(None)
        raise expression.ExpressionError("; ".join(g.message for g in errors))
    failed = any(g.holds for g in verdicts)
    written = None
    if overlay_path is not None:
        t0 = time.perf_counter()
        written = _write_diff_overlay(Path(overlay_path), Path(a_path), Path(b_path), a, b, comparison, images)
        seconds["overlay"] = time.perf_counter() - t0
    if junit_path is not None:
        junit = write_junit(written)
    return DiffOutcome(comparison=comparison, overlay_path=written, fail_if=conditions, failed=failed,
                       seconds=seconds, gates=verdicts, junit_path=junit)



def _write_diff_overlay(
    out: Path, a_path: Path, b_path: Path, a: RunSeries, b: RunSeries, c: Comparison, images: bool
) -> Path:
    ia, ib = c.matched[:, 0], c.matched[:, 1]
    a_contents = read_rrd(a_path)
    a_file, a_setting = split_setting(a_path)
    cams = run_series.cameras_of(a_contents) if images else []
    reproj_a = run_series.reprojected_corners(a_path, cams) if images else {}
    reproj_b_own = run_series.reprojected_corners(b_path, cams) if images else {}
    # B's corners go onto A's frame numbers through the time matching.
    b_to_a = {int(b.frames[j]): int(a.frames[i]) for i, j in zip(ia, ib)}
    reproj_b = {cam: {b_to_a[f]: pts for f, pts in per.items() if f in b_to_a} for cam, per in reproj_b_own.items()}
    runs = [
        OverlayRun("a", f"A {a.name}", a.frames, a.time_ns, a.T_est, run_series.overlay_errors(a), reproj_a,
                   T_truth=a.T_truth, short_label="A"),
        OverlayRun("b", f"B {b.name}", a.frames[ia], a.time_ns[ia], b.T_est[ib], run_series.overlay_errors(b, ib), reproj_b,
                   T_truth=b.T_truth[ib], short_label="B"),
    ]
    deltas = {
        f"{q.key}_{q.unit}": (a.frames[c.delta_series[q.key][0]], a.time_ns[c.delta_series[q.key][0]],
                              c.delta_series[q.key][1])
        for q in DIRECT
    }
    return write_overlay(
        out,
        recording_name=f"diff {a.name} vs {b.name}",
        runs=runs,
        truth=run_series.overlay_truth(a),
        source=a_path,
        cam_names=cams,
        fixed_cams=run_series.fixed_cameras_of(a_contents) & set(cams),
        report_markdown=comparison_markdown(c),
        deltas=deltas,
        inputs=(split_setting(a_path)[0], split_setting(b_path)[0]),
        # The two-run case of the sweep .rrd: both runs' layers, `diff OUT#A OUT#B` reads them back.
        layers={"a": a_path, "b": b_path},
        index=[{"key": "a", "label": "A", "rank": None, "settings": a.settings, "run": str(a_path)},
               {"key": "b", "label": "B", "rank": None, "settings": b.settings, "run": str(b_path)}],
        # A setting of a sweep .rrd has no images of its own: the sweep's frames.
        frames_from=a_file if a_setting is not None and cams else None,
    )
