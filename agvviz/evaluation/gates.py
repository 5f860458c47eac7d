"""CI gates on runs: the metrics a ``--fail-if`` condition can name, read from run summaries, and
the verdict of each condition. Pure: reads no files, prints nothing.

``agvviz run --fail-if`` names one run's metrics bare (:func:`run_metric_names`,
:func:`run_metrics`): the frame counts, the error statistics when the recording has truth, and
the suspect counts of issue 25 (``suspects``, ``suspects_pct``, ``suspect_stretches``,
``suspects.<cause>``). ``agvviz diff --fail-if`` names A's and B's (``A.suspects``,
``B.suspects.map_entry``): the comparison's metrics plus each run's suspect counts
(:func:`suspect_counts`, from the summary stored in its ``.rrd``).

A summary without a ``suspects`` section (a run written before the checks existed, or a study)
has no value for the suspect metrics: a condition on them is an error saying so, never a silent 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from agvviz.evaluation import expression
from agvviz.evaluation.expression import ExpressionError, Node
from agvviz.evaluation.statistics import STATISTICS
from agvviz.model.suspects import CAUSES

#: Frame counts of a run (the names the comparison of two runs uses too).
RUN_COUNTS = ("frames", "solved", "rejected", "solved_pct")
#: Suspect counts: frames, their share of the solved frames (%), stretches; then one per cause.
SUSPECT_COUNTS = ("suspects", "suspects_pct", "suspect_stretches")
#: Error statistics of a run summary: metric prefix and unit → the summary key.
SUMMARY_QUANTITIES = (
    ("position", "mm", "position_error_mm"),
    ("heading", "deg", "heading_error_deg"),
    ("pitch", "deg", "pitch_error_deg"),
    ("roll", "deg", "roll_error_deg"),
    ("reproj", "px", "reproj_rms_px"),
)


def suspect_metric_names() -> list[str]:
    """``suspects``, ``suspects_pct``, ``suspect_stretches`` and ``suspects.<cause>`` per cause."""
    return list(SUSPECT_COUNTS) + [f"suspects.{cause}" for cause in CAUSES]


def run_metric_names() -> list[str]:
    """Every metric ``agvviz run --fail-if`` knows, in table order."""
    names = list(RUN_COUNTS) + suspect_metric_names()
    return names + [f"{q}_{stat}_{unit}" for q, unit, _ in SUMMARY_QUANTITIES for stat in STATISTICS]


def suspect_counts(summary: dict) -> dict[str, float | None]:
    """The suspect metrics of a run summary (``summary["suspects"]``, written by the check stage);
    every value None when the summary has no ``suspects`` section."""
    section = summary.get("suspects")
    names = suspect_metric_names()
    if not isinstance(section, dict):
        return dict.fromkeys(names)
    n = int(section.get("frames", 0))
    by_cause = section.get("by_cause") or {}
    solved = summary.get("solved")
    values: dict[str, float | None] = {
        "suspects": n,
        "suspects_pct": 100.0 * n / solved if isinstance(solved, (int, float)) and solved > 0 else None,
        "suspect_stretches": len(section.get("stretches") or []),
    }
    values.update({f"suspects.{cause}": int(by_cause.get(cause, 0)) for cause in CAUSES})
    return values


def run_metrics(summary: dict) -> dict[str, float | None]:
    """Every :func:`run_metric_names` metric of one run summary (None where it has no value:
    no truth, no solved frame, no suspect counts)."""
    frames = summary.get("frames")
    solved = summary.get("solved")
    values: dict[str, float | None] = dict.fromkeys(run_metric_names())
    if isinstance(frames, int):
        values["frames"] = frames
        values["solved"] = solved
        values["rejected"] = frames - solved if isinstance(solved, int) else None
        values["solved_pct"] = 100.0 * solved / frames if frames and isinstance(solved, int) else None
    values.update(suspect_counts(summary))
    for q, unit, key in SUMMARY_QUANTITIES:
        stats = summary.get(key) or {}
        for stat in STATISTICS:
            values[f"{q}_{stat}_{unit}"] = stats.get(stat)
    return values


def missing_reason(name: str, summary: dict) -> str:
    """Why metric ``name`` of a run has no value, in words."""
    if name in suspect_metric_names():
        if not isinstance(summary.get("suspects"), dict):
            return "the run's summary holds no suspect counts (the checks did not run on it)"
        return "the run solved no frame"
    if any(name.startswith(f"{q}_") for q, unit, _ in SUMMARY_QUANTITIES[:4]):
        return "the recording has no truth (or no frame was scored against it)"
    return "the run has no frame it could score"


@dataclass(frozen=True)
class Gate:
    """One ``--fail-if`` condition and its verdict: ``holds`` True (the command exits 1), False,
    or None when it could not be evaluated (``error`` says why; the command exits 2);
    ``values`` the metrics it read, as written (``B.suspects``: 7)."""

    condition: str
    holds: bool | None
    values: dict[str, float | None] = field(default_factory=dict)
    error: str | None = None

    @property
    def shown(self) -> str:
        """The condition with the values it read: ``suspects > 0 (suspects = 7)``."""
        values = ", ".join(f"{name} = {_number(value)}" for name, value in self.values.items())
        return self.condition + (f" ({values})" if values else "")

    @property
    def message(self) -> str:
        """One line: the verdict with the values it rests on."""
        if self.error is not None:
            return f"cannot evaluate '{self.condition}': {self.error}"
        values = self.shown[len(self.condition):]
        return f"'{self.condition}' {'holds' if self.holds else 'does not hold'}{values}"


def _number(value) -> str:
    if value is None:
        return "no value"
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        return str(int(value))
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def parse_conditions(conditions, known: list[str], runs: tuple[str, ...] = expression.RUNS) -> list[tuple[str, Node]]:
    """Parse every condition (before any work, so a typo fails at once)."""
    return [(text, expression.parse(text, known, runs)) for text in conditions]


def evaluate(parsed: list[tuple[str, Node]], metrics: dict, explain=None) -> list[Gate]:
    """The verdict of each parsed condition on ``metrics`` (``{"A": {...}, "B": {...}}``, or a
    single run's under ``""``). ``explain(run, name)`` says why a metric has no value (None:
    the grammar's own message stands)."""
    gates = []
    for text, node in parsed:
        read = {m.qualified: metrics.get(m.run, {}).get(m.name) for m in expression.metrics_of(node)}
        try:
            holds = bool(expression.evaluate(node, metrics))
        except ExpressionError as exc:
            error = str(exc)
            for m in expression.metrics_of(node):
                why = explain(m.run, m.name) if read[m.qualified] is None and explain is not None else None
                if why:
                    error = f"{m.qualified} has no value: {why}"
                    break
            gates.append(Gate(text, None, read, error))
            continue
        gates.append(Gate(text, holds, read))
    return gates


def run_gates(conditions, summary: dict) -> list[Gate]:
    """``agvviz run --fail-if``: each condition over one run's summary."""
    parsed = parse_conditions(conditions, run_metric_names(), runs=())
    return evaluate(parsed, {"": run_metrics(summary)}, lambda run, name: missing_reason(name, summary))
