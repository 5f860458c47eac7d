"""Library API behind ``agvviz diff`` and ``agvviz sweep``: returns values, prints nothing.

- :func:`load_run` reads a run ``.rrd`` back through Rerun's API into a
  :class:`~agvviz.evaluation.comparison.RunSeries` (the ``.rrd`` alone is enough).
- :func:`diff` compares two runs (table, paired tests, intervals, most different frames),
  optionally writes the overlay ``.rrd`` and evaluates a ``--fail-if`` condition.
- :func:`sweep` replays one or several recordings under the cross product of setting values
  on a Dask cluster (:mod:`agvviz.app.cluster`; each recording detected once per detection
  settings), ranks each recording's runs, and writes one ``.rrd`` per setting, an overlay
  ``.rrd`` and the ranking as CSV and markdown.
"""

from __future__ import annotations

import csv
import io
import itertools
import math
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from agvviz.recording import outputs
from agvviz.errors import InputError
from agvviz.evaluation import expression, statistics
from agvviz.evaluation.comparison import (
    DIRECT,
    QUANTITIES,
    Comparison,
    RunSeries,
    compare_runs,
    match_frames,
    metric_names,
    quantity_values,
    run_metrics,
)
from agvviz.evaluation.trajectory import ALIGNMENTS, EvaluationError
from agvviz.settings import RunSettings, SettingsError, apply_overrides, field_types
from agvviz.viz import paths
from agvviz.viz.overlay import OverlayRun, OverlayTruth, write_overlay
from agvviz.viz.readback import (
    RrdContents,
    RrdReadError,
    document_json,
    frame_times,
    points2d,
    read_rrd,
    scalar_series,
    transforms,
)

#: Per-frame error series of a run: quantity key → (entity, scale to the quantity's unit).
ERROR_ENTITIES = {
    "position": (paths.ERROR_POSITION_MM, 1.0),
    "heading": (paths.ERROR_HEADING_DEG, 1.0),
    "pitch": (paths.ERROR_PITCH_DEG, 1.0),
    "roll": (paths.ERROR_ROLL_DEG, 1.0),
    "reproj": (paths.ERROR_REPROJ_RMS_PX, 1.0),
}
#: Spellings of run settings accepted by ``sweep --set`` besides the setting names themselves.
SETTING_ALIASES = {"lm.max_iters": "lm_max_iterations", "lm.max_iterations": "lm_max_iterations"}
#: Metrics for which a larger value ranks higher.
HIGHER_IS_BETTER = {"solved", "solved_pct"}

#: Detected-corner entity of a camera on the AGV and of one fixed in the world (uwb_room's
#: wall cameras, ``world/cameras/cam_<name>``): every camera logs one row per frame there.
_CAMERA_DETECTED = {
    fixed: re.compile("^" + re.escape(paths.detected("\0", fixed)).replace("\x00", "(?P<cam>[^/]+)") + "$")
    for fixed in (False, True)
}


class CompareError(InputError):
    """A comparison or sweep that cannot be done as asked (bad grid, unknown metric, ...)."""


# -- reading runs --------------------------------------------------------------------------
def cameras_of(contents: RrdContents) -> list[str]:
    """Names of the cameras whose corners a run ``.rrd`` holds, sorted: those on the AGV and
    those fixed in the world (:func:`fixed_cameras_of` tells which)."""
    return sorted({
        m["cam"] for p in contents.entity_paths for pattern in _CAMERA_DETECTED.values() if (m := pattern.match(p))
    })


def fixed_cameras_of(contents: RrdContents) -> set[str]:
    """Names of the cameras fixed in the world (``world/cameras/cam_<name>``) whose corners a
    run ``.rrd`` holds: their images and corners are under :func:`paths.image` ``(cam, fixed=True)``."""
    return {m["cam"] for p in contents.entity_paths if (m := _CAMERA_DETECTED[True].match(p))}


def load_run(path: str | os.PathLike) -> RunSeries:
    """Read a run ``.rrd`` back into per-frame arrays (clock, solved, errors, poses).

    The frame clock comes from the detected-corner entities (logged on every frame) of the
    cameras on the AGV and of those fixed in the world (a camera–UWB run's wall cameras log
    every time stamp's views under one frame index), the solved frames from the estimated pose
    ``world/agv/camera``, the errors from ``errors/*`` and the settings from ``run/manifest``.

    In a camera–UWB run too, ``world/agv/camera`` and ``errors/position_mm`` are the camera
    pipeline's estimate of each frame (the chosen camera's fix), what the run summary's
    ``position_error_mm`` is computed from; the fused estimate (``errors/fused_position_mm``,
    2-D, per UWB fix and frame) is not part of the series (:func:`diff` notes its summary).

    Raises
    ------
    RrdReadError
        The file is not a run ``.rrd`` (no manifest, no camera frames).
    """
    contents = read_rrd(path)
    if paths.RUN_MANIFEST not in contents.entity_paths:
        raise RrdReadError(f"{path} is not an agvviz run: it has no {paths.RUN_MANIFEST}")
    manifest = document_json(contents, paths.RUN_MANIFEST)
    clock: dict[int, int] = {}
    fixed = fixed_cameras_of(contents)
    for cam in cameras_of(contents):
        clock.update(frame_times(contents, paths.detected(cam, cam in fixed), "Points2D:positions"))
    if not clock:
        raise RrdReadError(f"{path} holds no camera frames")
    frames = np.array(sorted(clock), dtype=np.int64)
    time_ns = np.array([clock[f] for f in frames], dtype=np.int64)
    where = {int(f): k for k, f in enumerate(frames)}

    def poses(entity: str) -> np.ndarray:
        T = np.full((len(frames), 4, 4), np.nan)
        if _has_temporal(contents, entity, "Transform3D:translation"):
            entity_frames, _, entity_T = transforms(contents, entity)
            for f, pose in zip(entity_frames, entity_T):
                if int(f) in where:
                    T[where[int(f)]] = pose
        return T

    T_est = poses(paths.AGV_CAMERA)
    errors = {}
    for key, (entity, scale) in ERROR_ENTITIES.items():
        values = np.full(len(frames), np.nan)
        if _has_temporal(contents, entity, "Scalars:scalars"):
            idx, series = scalar_series(contents, entity)
            for f, v in zip(idx, series):
                if int(f) in where:
                    values[where[int(f)]] = v * scale
        errors[key] = values
    return RunSeries(
        name=str(manifest.get("recording_name", Path(path).stem)),
        frames=frames,
        time_ns=time_ns,
        solved=np.all(np.isfinite(T_est.reshape(len(frames), 16)), axis=1),
        errors=errors,
        T_truth=poses(paths.AGV_TRUTH),
        T_est=T_est,
        settings=dict(manifest.get("settings", {})),
        manifest=manifest,
        summary=(document_json(contents, paths.RUN_SUMMARY) or {}) if paths.RUN_SUMMARY in contents.entity_paths else {},
    )


def _has_temporal(contents: RrdContents, entity: str, component: str) -> bool:
    """Whether ``entity`` has per-frame ``component`` data (run entities also carry static
    styles or axes, so their mere presence says nothing; a run may have solved no frame)."""
    if entity not in contents.entity_paths:
        return False
    chunks = contents.store.stream().filter(content=f"/{entity}", is_static=False, components=component)
    return any(chunk.num_rows > 0 for chunk in chunks)


def _reprojected(path: Path, cams: list[str]) -> dict[str, dict[int, np.ndarray]]:
    """Each camera's reprojected corners per frame of a run, the camera on the AGV or fixed in
    the world (as that run logged it)."""
    contents = read_rrd(path)
    fixed = fixed_cameras_of(contents)
    return {
        cam: points2d(contents, paths.reprojected(cam, cam in fixed))
        for cam in cams
        if paths.reprojected(cam, cam in fixed) in contents.entity_paths
    }


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
def _fmt(value, digits: int = 4) -> str:
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
    "solved", "position_rmse_mm", "position_median_mm", "position_p95_mm", "heading_rmse_deg",
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
        ci = "—" if r.ci_low is None else f"[{_fmt(r.ci_low, 3)}, {_fmt(r.ci_high, 3)}]"
        diff = "—" if r.diff is None else (_fmt(r.diff) if r.diff <= 0 else "+" + _fmt(r.diff))
        table.append([r.name, _fmt(r.a), _fmt(r.b), diff, ci, format_p(r.p_value)])
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
    fail_if: str | None
    failed: bool  # the --fail-if condition holds (False when there is none)
    seconds: dict[str, float]  # wall time of each step: load, compare, overlay


def diff(
    a_path: str | os.PathLike,
    b_path: str | os.PathLike,
    *,
    overlay_path: str | os.PathLike | None = None,
    fail_if: str | None = None,
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

    ``fail_if`` is parsed before any file is read, so a typo in a metric name fails at once
    (:class:`~agvviz.evaluation.expression.ExpressionError`, listing the known metrics).
    The overlay (``overlay_path``) holds both runs on A's clock; ``images=False`` leaves the
    camera images out of it.
    """
    if align not in ALIGNMENTS:
        raise CompareError(f"unknown alignment {align!r}; choose one of: {', '.join(ALIGNMENTS)}")
    if rpe_delta < 1:
        raise CompareError(f"rpe_delta must be ≥ 1 frame, got {rpe_delta}")
    condition = expression.parse(fail_if, metric_names(time_offset)) if fail_if is not None else None
    if overlay_path is not None and Path(overlay_path).suffix != ".rrd":
        raise CompareError(f"--out must be a .rrd file, got {overlay_path}")
    if overlay_path is not None:  # before any work: never over A or B (also through links)
        outputs.prepare_output(overlay_path, inputs=(a_path, b_path))
    seconds = {}
    t0 = time.perf_counter()
    a, b = load_run(a_path), load_run(b_path)
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
    failed = bool(expression.evaluate(condition, comparison.metrics())) if condition is not None else False
    written = None
    if overlay_path is not None:
        t0 = time.perf_counter()
        written = _write_diff_overlay(Path(overlay_path), Path(a_path), Path(b_path), a, b, comparison, images)
        seconds["overlay"] = time.perf_counter() - t0
    return DiffOutcome(comparison=comparison, overlay_path=written, fail_if=fail_if, failed=failed, seconds=seconds)


def _overlay_errors(run: RunSeries, rows: np.ndarray | None = None) -> dict[str, np.ndarray]:
    rows = np.arange(len(run.frames)) if rows is None else rows
    return {f"{q.key}_{q.unit}": run.errors[q.key][rows] for q in DIRECT}


def _write_diff_overlay(
    out: Path, a_path: Path, b_path: Path, a: RunSeries, b: RunSeries, c: Comparison, images: bool
) -> Path:
    ia, ib = c.matched[:, 0], c.matched[:, 1]
    a_contents = read_rrd(a_path)
    cams = cameras_of(a_contents) if images else []
    reproj_a = _reprojected(a_path, cams) if images else {}
    reproj_b_own = _reprojected(b_path, cams) if images else {}
    # B's corners go onto A's frame numbers through the time matching.
    b_to_a = {int(b.frames[j]): int(a.frames[i]) for i, j in zip(ia, ib)}
    reproj_b = {cam: {b_to_a[f]: pts for f, pts in per.items() if f in b_to_a} for cam, per in reproj_b_own.items()}
    runs = [
        OverlayRun("a", f"A {a.name}", a.frames, a.time_ns, a.T_est, _overlay_errors(a), reproj_a,
                   T_truth=a.T_truth, short_label="A"),
        OverlayRun("b", f"B {b.name}", a.frames[ia], a.time_ns[ia], b.T_est[ib], _overlay_errors(b, ib), reproj_b,
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
        truth=_truth(a),
        source=a_path,
        cam_names=cams,
        fixed_cams=fixed_cameras_of(a_contents) & set(cams),
        report_markdown=comparison_markdown(c),
        deltas=deltas,
        inputs=(a_path, b_path),
    )


def _truth(run: RunSeries) -> OverlayTruth | None:
    known = np.all(np.isfinite(run.T_truth.reshape(len(run.frames), 16)), axis=1)
    if not np.any(known):
        return None
    return OverlayTruth(run.frames[known], run.time_ns[known], run.T_truth[known])


# -- sweep -----------------------------------------------------------------------------------
def parse_grid(pairs: list[str] | tuple[str, ...]) -> dict[str, list[str]]:
    """``["solver=p4p,lm", "lm_max_iterations=3,10"]`` → ``{"solver": ["p4p", "lm"], ...}``.

    Names are run settings (``agvviz run --help``); :data:`SETTING_ALIASES` are accepted too.
    Values are split at commas, duplicates dropped (order kept).
    """
    names = field_types(RunSettings)
    grid: dict[str, list[str]] = {}
    for pair in pairs:
        key, sep, values = pair.partition("=")
        key = SETTING_ALIASES.get(key.strip(), key.strip())
        if not sep or not key:
            raise CompareError(f"--set {pair!r}: expected key=value1,value2,...")
        if key not in names:
            raise CompareError(f"unknown setting {key!r}; valid settings: {', '.join(sorted(names))}")
        if key in grid:
            raise CompareError(f"setting {key!r} given twice; list all its values once: {key}=a,b,c")
        items = [v.strip() for v in values.split(",")]
        if any(not v for v in items):
            raise CompareError(f"--set {pair!r}: empty value in the list")
        grid[key] = list(dict.fromkeys(items))
    return grid


def grid_settings(grid: dict[str, list[str]], base: RunSettings = RunSettings()) -> list[RunSettings]:
    """Every combination of ``grid`` applied to ``base``, validated, in grid order.

    Raises
    ------
    CompareError
        A value is not valid for its setting, or two combinations give the same settings.
    """
    combos = itertools.product(*[[f"{k}={v}" for v in values] for k, values in grid.items()])
    result = []
    for combo in combos:
        try:
            result.append(apply_overrides(base, list(combo)))
        except SettingsError as exc:
            raise CompareError(f"sweep setting {' '.join(combo)}: {exc}") from None
    labels = [s.label() for s in result]
    duplicates = sorted({label for label in labels if labels.count(label) > 1})
    if duplicates:
        raise CompareError(f"the grid gives the same settings more than once: {', '.join(duplicates)}")
    return result


@dataclass
class SweepEntry:
    """One setting of a sweep over one recording, and how it went."""

    label: str
    settings: RunSettings
    out_path: Path
    error: str | None = None  # why the setting failed, None when it ran
    metrics: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)  # wall-clock figures (not in the .rrd)
    p_vs_best: float | None = None  # Wilcoxon p of the ranking quantity vs the best setting
    rank: int | None = None  # 1 = best among its recording's settings; None when failed
    recording: Path | None = None  # the recording replayed

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class RecordingSweep:
    """One recording of a sweep: its ranked entries (best first, failed last) and its files."""

    recording: Path
    out_dir: Path
    entries: list[SweepEntry]
    overlay_path: Path | None
    csv_path: Path
    markdown_path: Path


@dataclass
class SweepOutcome:
    """Ranked entries and the files written.

    ``entries`` holds every recording's entries, each recording's ranked (best first, failed
    last), recordings in the order given; ``overlay_path``, ``csv_path`` and ``markdown_path``
    are the first recording's (the only one's in a sweep of one recording); ``recordings`` has
    each recording's own.
    """

    entries: list[SweepEntry]
    rank_by: str
    overlay_path: Path | None
    csv_path: Path
    markdown_path: Path
    wall_time_s: float
    recordings: list[RecordingSweep] = field(default_factory=list)


def _rank_quantity(rank_by: str) -> str:
    """The per-frame quantity behind a metric (position for the counts)."""
    matches = [q.key for q in QUANTITIES if rank_by.startswith(f"{q.key}_") and rank_by.endswith(f"_{q.unit}")]
    return matches[0] if matches else "position"


def sweep_out_dirs(recordings: Sequence[Path], out_dir: str | os.PathLike | None) -> list[Path]:
    """Where each recording's runs go: ``out_dir`` (default ``runs/sweep-<stem>``) for one
    recording; ``<out_dir>/<stem>`` (default ``runs/sweep/<stem>``) for several.

    Raises
    ------
    CompareError
        A recording is given twice, or two recordings have the same file stem.
    """
    if len(recordings) == 1:
        return [Path(out_dir) if out_dir is not None else Path("runs") / f"sweep-{recordings[0].stem}"]
    seen: dict[str, Path] = {}
    for recording in recordings:
        if recording.stem in seen:
            same = outputs.same_file(recording, seen[recording.stem])
            raise CompareError(
                f"recording {recording} is given twice" if same else
                f"recordings {seen[recording.stem]} and {recording} have the same name "
                f"{recording.stem!r}; their runs would share the folder {recording.stem}/: rename one"
            )
        seen[recording.stem] = recording
    root = Path(out_dir) if out_dir is not None else Path("runs") / "sweep"
    return [root / recording.stem for recording in recordings]


def _count_frames(recording: Path) -> int:
    """Frames of ``recording`` for the progress bar; 0 when it cannot be counted (a bag folder,
    a file that is no recording: its runs report why)."""
    from agvviz.errors import AgvvizError
    from agvviz.recording.reader import count_image_times

    if not recording.is_file():
        return 0
    try:
        return count_image_times(recording)
    except (AgvvizError, OSError, ValueError):
        return 0


def sweep(
    recording: str | os.PathLike | Sequence[str | os.PathLike],
    grid: dict[str, list[str]],
    *,
    base: RunSettings = RunSettings(),
    out_dir: str | os.PathLike | None = None,
    jobs: int | None = None,
    rank_by: str = "position_rmse_mm",
    align: str = "none",
    rpe_delta: int = 1,
    images: bool = True,
    progress: Callable[[int, int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    scheduler: str | None = None,
    cache_dir: str | os.PathLike | None = None,
) -> SweepOutcome:
    """Replay every recording under every combination of ``grid`` on a Dask cluster.

    Parameters
    ----------
    recording : path or sequence of paths
        One recording (an ``.mcap`` or a rosbag2 folder) or several.
    grid : dict
        Setting name → values (strings, as on the command line); see :func:`parse_grid`.
    base : RunSettings
        Settings the grid values are applied to.
    out_dir : path, optional
        See :func:`sweep_out_dirs`. Each recording's folder gets ``<stem>-<label>.rrd`` per
        setting, ``overlay.rrd``, ``ranking.csv`` and ``ranking.md``.
    jobs : int, optional
        Worker processes of the local cluster (default: one per CPU, at most one per run).
    rank_by : str
        Metric to rank by (lower is better, except ``solved``/``solved_pct``).
    progress : callable, optional
        ``progress(frames_done, runs_finished)`` summed over all runs; the frames of each
        recording's detections count too (``on_total(frames)`` is called first with the total).
    scheduler : str, optional
        Address of an existing Dask cluster's scheduler; None starts a local cluster.
    cache_dir : path, optional
        Detection cache folder (default: :func:`agvviz.replay.detect.cache.default_cache_dir`).

    Each recording is detected once per distinct detection settings of the grid
    (:mod:`agvviz.app.cluster`), then every setting only solves. A run that fails is reported in its
    entry (``error``) and ranked last; the others go on. Needs Dask (``agvviz[distributed]``).
    """
    single = isinstance(recording, (str, os.PathLike))
    recordings = [Path(recording)] if single else [Path(r) for r in recording]
    if not recordings:
        raise CompareError("nothing to sweep: give at least one recording")
    for path in recordings:
        if not path.exists():  # an .mcap file or a rosbag2 directory
            raise CompareError(f"recording not found: {path}")
    if rank_by not in metric_names():
        raise CompareError(f"unknown metric {rank_by!r} to rank by; known: {', '.join(metric_names())}")
    if align not in ALIGNMENTS:
        raise CompareError(f"unknown alignment {align!r}; choose one of: {', '.join(ALIGNMENTS)}")
    if not grid:
        raise CompareError("nothing to sweep: give at least one --set key=value1,value2,...")
    if jobs is not None and (isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1):
        raise CompareError(f"--jobs must be a whole number ≥ 1 (or left out for one per CPU), got {jobs}")
    if jobs is not None and scheduler is not None:
        raise CompareError("--jobs sets the processes of the local cluster; with --scheduler the cluster's own "
                           "workers run the sweep: give one or the other")
    settings_list = grid_settings(grid, base)
    out_dirs = sweep_out_dirs(recordings, out_dir)
    from agvviz.app import cluster

    cluster.import_distributed()  # without Dask: one line, before anything is written
    per_recording = []
    for path, folder in zip(recordings, out_dirs):
        entries = [
            SweepEntry(s.label(), s, folder / f"{path.stem}-{s.label()}.rrd", recording=path) for s in settings_list
        ]
        for target in [e.out_path for e in entries] + [folder / n for n in ("overlay.rrd", "ranking.csv", "ranking.md")]:
            outputs.check_not_input(target, recordings, option="the sweep output")
        per_recording.append(entries)
    t_start = time.perf_counter()
    all_entries = [e for entries in per_recording for e in entries]
    tasks = [cluster.RunTask(e.recording, e.settings, e.out_path) for e in all_entries]
    workers = min(jobs or os.cpu_count() or 1, len(tasks))
    cache = Path(cache_dir) if cache_dir is not None else None
    # On a local cluster the detections start at once, here, while the cluster starts
    # (cluster.LocalDetections); on an existing cluster they are its tasks.
    local = cluster.LocalDetections(tasks, cache, workers).start() if scheduler is None else None
    # Frames for the progress bar are counted while the cluster starts (a read of each file).
    frames: dict[Path, int] = {}
    counter = None
    if progress is not None or on_total is not None:
        counter = threading.Thread(
            target=lambda: frames.update({path: _count_frames(path) for path in recordings}),
            name="agvviz count frames", daemon=True,
        )
        counter.start()
    try:
        # The cluster first: an unreachable scheduler leaves nothing behind.
        with cluster.open_client(scheduler, workers, [folder.resolve() for folder in out_dirs]) as client:
            for folder in out_dirs:
                outputs.prepare_dir(folder, option="--out-dir")
            if counter is not None:
                counter.join()
                if on_total is not None:
                    on_total(cluster.progress_total(tasks, frames))
            results = cluster.run_sweep_tasks(
                client, tasks, cache_dir=cache, frames=frames, progress=progress, local=local,
            )
    finally:
        if local is not None:
            local.close()
    for entry, result in zip(all_entries, results):
        entry.timing, entry.error = result.timing, result.error

    done = [
        _finish_recording(path, folder, entries, rank_by, align, rpe_delta, images)
        for path, folder, entries in zip(recordings, out_dirs, per_recording)
    ]
    return SweepOutcome(
        entries=[e for r in done for e in r.entries], rank_by=rank_by, overlay_path=done[0].overlay_path,
        csv_path=done[0].csv_path, markdown_path=done[0].markdown_path,
        wall_time_s=time.perf_counter() - t_start, recordings=done,
    )


def _finish_recording(
    recording: Path, out_dir: Path, entries: list[SweepEntry], rank_by: str, align: str, rpe_delta: int,
    images: bool,
) -> RecordingSweep:
    """Read back one recording's runs, rank them, write its tables and overlay."""
    series: dict[int, RunSeries] = {}
    for index, entry in enumerate(entries):
        if entry.ok:
            try:
                series[index] = load_run(entry.out_path)
                entry.metrics = run_metrics(series[index], align=align, rpe_delta=rpe_delta)
            except (RrdReadError, EvaluationError) as exc:
                entry.error = f"{type(exc).__name__}: {exc}"
    _rank(entries, series, rank_by, align, rpe_delta)
    ranked = sorted(entries, key=lambda e: (e.rank is None, e.rank or 0))
    csv_path, markdown_path = _write_tables(out_dir, ranked, rank_by)
    overlay_path = None
    ok = [e for e in ranked if e.ok]
    if ok:
        overlay_path = _write_sweep_overlay(out_dir / "overlay.rrd", recording, ok, series, entries, rank_by, images)
    return RecordingSweep(recording, out_dir, ranked, overlay_path, csv_path, markdown_path)


def _rank(entries: list[SweepEntry], series: dict[int, RunSeries], rank_by: str, align: str, rpe_delta: int) -> None:
    sign = -1.0 if rank_by in HIGHER_IS_BETTER else 1.0
    ok = [i for i, e in enumerate(entries) if e.ok]

    def key(i: int):
        value = entries[i].metrics.get(rank_by)
        return (value is None, sign * value if value is not None else 0.0, entries[i].label)

    order = sorted(ok, key=key)
    for rank, i in enumerate(order, start=1):
        entries[i].rank = rank
    if not order:
        return
    best = order[0]
    quantity = _rank_quantity(rank_by)
    for i in order[1:]:
        ia, ib = match_frames(series[best].time_ns, series[i].time_ns)
        both = series[best].solved[ia] & series[i].solved[ib]
        x = quantity_values(series[best], ia[both], align, rpe_delta)[quantity][ia[both]]
        y = quantity_values(series[i], ib[both], align, rpe_delta)[quantity][ib[both]]
        finite = np.isfinite(x) & np.isfinite(y)
        entries[i].p_vs_best = statistics.wilcoxon_paired(x[finite], y[finite]) if np.any(finite) else None


#: Columns of the ranking tables: (header, metric or attribute).
TABLE_METRICS = (
    "solved", "frames", "position_rmse_mm", "position_median_mm", "position_p95_mm",
    "heading_rmse_deg", "pitch_rmse_deg", "roll_rmse_deg", "reproj_median_px",
    "ape_trans_rmse_mm", "rpe_trans_rmse_mm", "rpe_rot_rmse_deg",
)


def ranking_rows(entries: list[SweepEntry], rank_by: str) -> tuple[list[str], list[list[str]]]:
    """Header and rows (strings) of the ranking table, as written to CSV and markdown."""
    metrics = list(dict.fromkeys([rank_by, *TABLE_METRICS]))
    header = ["rank", "setting", *metrics, "p_vs_best", "time_per_frame_ms", "status", "file"]
    rows = []
    for e in entries:
        rows.append([
            str(e.rank) if e.rank else "—",
            e.label,
            *[_fmt(e.metrics.get(m)) for m in metrics],
            format_p(e.p_vs_best),
            _fmt(e.timing.get("time_per_frame_ms")),
            "ok" if e.ok else f"failed: {e.error}",
            e.out_path.name if e.ok else "",
        ])
    return header, rows


def _atomic_write(path: Path, text: str) -> None:
    outputs.atomic_write_text(path, text)


def _write_tables(out_dir: Path, entries: list[SweepEntry], rank_by: str) -> tuple[Path, Path]:
    header, rows = ranking_rows(entries, rank_by)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    csv_path = out_dir / "ranking.csv"
    _atomic_write(csv_path, buffer.getvalue())
    direction = "higher" if rank_by in HIGHER_IS_BETTER else "lower"
    lines = [
        f"Ranked by `{rank_by}` ({direction} is better); p_vs_best: Wilcoxon signed-rank of the "
        "per-frame errors against the best setting, on the frames both solved.",
        "",
        "| " + " | ".join(header) + " |",
        "| " + " | ".join("---" for _ in header) + " |",
    ]
    lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in rows]
    markdown_path = out_dir / "ranking.md"
    _atomic_write(markdown_path, "\n".join(lines) + "\n")
    return csv_path, markdown_path


def _entity_key(index: int, label: str) -> str:
    return f"s{index + 1}_" + re.sub(r"[^A-Za-z0-9_-]+", "_", label)


def _write_sweep_overlay(
    out: Path, recording: Path, ok: list[SweepEntry], series: dict[int, RunSeries],
    entries: list[SweepEntry], rank_by: str, images: bool,
) -> Path:
    index_of = {id(e): i for i, e in enumerate(entries)}
    first = series[index_of[id(ok[0])]]
    first_contents = read_rrd(ok[0].out_path)
    cams = cameras_of(first_contents) if images else []
    runs = []
    for rank, entry in enumerate(ok):
        s = series[index_of[id(entry)]]
        ia, ib = match_frames(first.time_ns, s.time_ns)
        to_first = {int(s.frames[j]): int(first.frames[i]) for i, j in zip(ia, ib)}
        reprojected = {
            cam: {to_first[f]: pts for f, pts in per.items() if f in to_first}
            for cam, per in (_reprojected(entry.out_path, cams) if images else {}).items()
        }
        runs.append(OverlayRun(
            _entity_key(rank, entry.label), f"#{entry.rank} {entry.label}",
            first.frames[ia], first.time_ns[ia], s.T_est[ib], _overlay_errors(s, ib), reprojected,
            T_truth=None if s.T_truth is None else s.T_truth[ib], short_label=f"#{entry.rank}",
        ))
    header, rows = ranking_rows(ok, rank_by)
    report = "\n".join([
        f"# sweep over {recording.name}", "",
        "| " + " | ".join(header[:6]) + " |", "| " + " | ".join("---" for _ in header[:6]) + " |",
        *["| " + " | ".join(row[:6]) + " |" for row in rows],
    ]) + "\n"
    return write_overlay(
        out,
        recording_name=f"sweep {recording.stem}",
        runs=runs,
        truth=_truth(first),
        source=ok[0].out_path,
        cam_names=cams,
        fixed_cams=fixed_cameras_of(first_contents) & set(cams),
        report_markdown=report,
        inputs=(recording, *[e.out_path for e in ok]),
    )
