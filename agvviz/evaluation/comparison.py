"""Metrics of one run and the paired comparison of two runs. Numpy and scipy only.

A run is given as a :class:`RunSeries` (per-frame arrays, as read back from its ``.rrd`` by
:func:`agvviz.app.run_series.load_run`). Every metric is named ``<quantity>_<statistic>_<unit>`` over the
absolute per-frame values, e.g. ``position_rmse_mm``, ``heading_p95_deg``,
``ape_trans_rmse_mm``, ``rpe_rot_median_deg``; plus the counts ``frames``, ``solved``,
``rejected``, ``solved_pct``, when asked for, ``time_offset_ms`` and, when a run's summary
counts suspect frames (issue 25), ``suspects``, ``suspects_pct``, ``suspect_stretches`` and
``suspects.<cause>`` (each run's own counts, from its summary).

Comparing A with B: frames are matched by time (mutual nearest stamps within half a frame
interval). Error metrics in a comparison are computed on the frames *both* runs solved, so the
two columns describe the same frames; the counts are each run's own. For every error
quantity the paired per-frame absolute values give a Wilcoxon signed-rank p-value and, for
each statistic, a block-bootstrap interval on ``stat(B) − stat(A)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agvviz.evaluation import statistics, trajectory
from agvviz.evaluation.gates import suspect_counts, suspect_metric_names
from agvviz.evaluation.trajectory import EvaluationError


@dataclass(frozen=True)
class Quantity:
    """A per-frame (or per-pair, for RPE) error quantity."""

    key: str
    unit: str
    description: str


#: Per-frame quantities read directly from a run's ``errors/*`` series (already vs truth).
DIRECT = (
    Quantity("position", "mm", "AGV position error ‖p_est − p_truth‖"),
    Quantity("heading", "deg", "heading error (eq 57 angle, wrapped)"),
    Quantity("pitch", "deg", "pitch error (eq 57 angle, wrapped)"),
    Quantity("roll", "deg", "roll error (eq 57 angle, wrapped)"),
    Quantity("reproj", "px", "RMS reprojection error of the solved code"),
)
#: Quantities computed here from the logged poses (evo definitions).
DERIVED = (
    Quantity("ape_trans", "mm", "APE translation part, after alignment"),
    Quantity("ape_rot", "deg", "APE rotation angle, after alignment"),
    Quantity("rpe_trans", "mm", "RPE translation part over rpe_delta frames"),
    Quantity("rpe_rot", "deg", "RPE rotation angle over rpe_delta frames"),
)
QUANTITIES = DIRECT + DERIVED
COUNTS = ("frames", "solved", "rejected", "solved_pct")


def metric_name(quantity: Quantity, statistic: str) -> str:
    return f"{quantity.key}_{statistic}_{quantity.unit}"


def metric_names(time_offset: bool = False) -> list[str]:
    """Every metric name, in table order."""
    names = list(COUNTS)
    names += [metric_name(q, s) for q in QUANTITIES for s in statistics.STATISTICS]
    return names + (["time_offset_ms"] if time_offset else [])


@dataclass
class RunSeries:
    """One run, frame by frame (every array has one entry per frame, in frame order).

    Attributes
    ----------
    name : str
        Recording name of the run, e.g. ``qr_floor-lm``.
    frames : (N,) int64
        Frame indices, increasing.
    time_ns : (N,) int64
        Recording time of each frame.
    solved : (N,) bool
    errors : dict
        Quantity key of :data:`DIRECT` → (N,) float, NaN where the run logged no value; units
        as in :data:`DIRECT` (position in mm).
    T_truth, T_est : (N, 4, 4) float
        ``T_world_agv`` of the truth and of the estimate; NaN where unknown / not solved.
    settings, manifest, summary : dict
        The run's settings, manifest and summary as stored in its ``.rrd``.
    """

    name: str
    frames: np.ndarray
    time_ns: np.ndarray
    solved: np.ndarray
    errors: dict[str, np.ndarray]
    T_truth: np.ndarray
    T_est: np.ndarray
    settings: dict = field(default_factory=dict)
    manifest: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)

    def __post_init__(self):
        n = len(self.frames)
        arrays = {"time_ns": self.time_ns, "solved": self.solved, "T_truth": self.T_truth, "T_est": self.T_est}
        arrays.update({f"errors[{k}]": v for k, v in self.errors.items()})
        for what, array in arrays.items():
            if len(array) != n:
                raise EvaluationError(f"run {self.name}: {what} has {len(array)} entries for {n} frames")
        if n > 1 and np.any(np.diff(self.frames) <= 0):
            raise EvaluationError(f"run {self.name}: frame indices must increase")


def _pose_known(T: np.ndarray) -> np.ndarray:
    return np.all(np.isfinite(T.reshape(len(T), 16)), axis=1)


def quantity_values(
    run: RunSeries, rows: np.ndarray, align: str = "none", rpe_delta: int = 1
) -> dict[str, np.ndarray]:
    """Absolute per-frame values of every quantity on the frames ``rows`` of ``run``.

    Parameters
    ----------
    rows : (M,) int array
        Indices into the run's arrays (not frame numbers) to evaluate; APE is aligned on
        these frames and RPE pairs both ends within them.
    align : str
        APE alignment (:data:`agvviz.evaluation.trajectory.ALIGNMENTS`).
    rpe_delta : int
        RPE pair distance in frames.

    Returns
    -------
    dict
        Quantity key → (N,) float: the absolute value on each row in ``rows`` where it is
        known, NaN elsewhere. RPE values sit on the pair's first frame.
    """
    rows = np.asarray(rows, dtype=np.int64)
    n = len(run.frames)
    values = {q.key: np.full(n, np.nan) for q in QUANTITIES}
    for q in DIRECT:
        values[q.key][rows] = np.abs(run.errors[q.key][rows])
    with_poses = rows[_pose_known(run.T_truth[rows]) & _pose_known(run.T_est[rows])]
    if len(with_poses) >= max(1, trajectory.MIN_POINTS[align]):
        T_ref, T_est = run.T_truth[with_poses], run.T_est[with_poses]
        T_ref_est = trajectory.align(T_est[:, :3, 3], T_ref[:, :3, 3], align)
        trans_m, rot_deg = trajectory.ape(T_ref, trajectory.apply_alignment(T_ref_est, T_est))
        values["ape_trans"][with_poses] = trans_m * 1000.0
        values["ape_rot"][with_poses] = rot_deg
        pairs = trajectory.rpe_pairs(run.frames[with_poses], rpe_delta)
        if len(pairs):
            trans_m, rot_deg = trajectory.rpe(T_ref, T_est, pairs)
            values["rpe_trans"][with_poses[pairs[:, 0]]] = trans_m * 1000.0
            values["rpe_rot"][with_poses[pairs[:, 0]]] = rot_deg
    return values


def _counts(run: RunSeries) -> dict[str, float | None]:
    frames, solved = len(run.frames), int(np.count_nonzero(run.solved))
    return {
        "frames": frames,
        "solved": solved,
        "rejected": frames - solved,
        "solved_pct": 100.0 * solved / frames if frames else None,
    }


def _time_offset_ms(run: RunSeries) -> float | None:
    est = run.solved & _pose_known(run.T_est)
    ref = _pose_known(run.T_truth)
    try:
        dt_s = trajectory.estimate_time_offset_s(
            run.time_ns[est], run.T_est[est, :3, 3], run.time_ns[ref], run.T_truth[ref, :3, 3]
        )
    except EvaluationError:
        return None
    return dt_s * 1000.0


def run_metrics(
    run: RunSeries, align: str = "none", rpe_delta: int = 1, time_offset: bool = False
) -> dict[str, float | None]:
    """Every metric of one run over its own solved frames (``None`` where undefined)."""
    values = quantity_values(run, np.flatnonzero(run.solved), align, rpe_delta)
    metrics = _counts(run)
    for q in QUANTITIES:
        v = values[q.key]
        for stat, value in statistics.describe(v[np.isfinite(v)]).items():
            metrics[metric_name(q, stat)] = value
    if time_offset:
        metrics["time_offset_ms"] = _time_offset_ms(run)
    return metrics


def match_frames(
    t_a_ns: np.ndarray, t_b_ns: np.ndarray, max_dt_ns: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Match frames of two runs by time: mutual nearest stamps within ``max_dt_ns``.

    ``max_dt_ns`` defaults to half the smaller median frame interval (so a frame never
    matches a neighbour of its true partner); 0 when a run has a single frame.

    Returns
    -------
    ia, ib : (M,) int arrays
        Indices into A's and B's arrays of each matched pair, in A's order.
    """
    t_a = np.asarray(t_a_ns, dtype=np.int64)
    t_b = np.asarray(t_b_ns, dtype=np.int64)
    if len(t_a) == 0 or len(t_b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if max_dt_ns is None:
        intervals = [np.median(np.diff(t)) for t in (t_a, t_b) if len(t) > 1]
        max_dt_ns = int(min(intervals) // 2) if intervals else 0

    def nearest(t_from: np.ndarray, t_to: np.ndarray) -> np.ndarray:
        k = np.clip(np.searchsorted(t_to, t_from), 1, max(len(t_to) - 1, 1))
        left = np.clip(k - 1, 0, len(t_to) - 1)
        right = np.clip(k, 0, len(t_to) - 1)
        return np.where(np.abs(t_to[left] - t_from) <= np.abs(t_to[right] - t_from), left, right)

    ab = nearest(t_a, t_b)
    ba = nearest(t_b, t_a)
    ia = np.arange(len(t_a))
    keep = (ba[ab] == ia) & (np.abs(t_b[ab] - t_a) <= max_dt_ns)
    return ia[keep], ab[keep]


@dataclass(frozen=True)
class MetricRow:
    """One line of a comparison: values of A and B, B − A, its interval and the test."""

    name: str
    a: float | None
    b: float | None
    diff: float | None
    ci_low: float | None = None
    ci_high: float | None = None
    p_value: float | None = None
    n: int | None = None  # paired frames (or frame pairs, for RPE) behind the row


@dataclass(frozen=True)
class FrameDifference:
    """A matched frame where the two estimates differ."""

    frame_a: int
    frame_b: int
    time_ns: int
    separation_mm: float  # ‖p_A − p_B‖ of the two estimates
    position_a_mm: float
    position_b_mm: float
    heading_a_deg: float
    heading_b_deg: float


@dataclass
class Comparison:
    """Result of :func:`compare_runs` (B relative to A)."""

    a_name: str
    b_name: str
    rows: list[MetricRow]
    matched: np.ndarray  # (M, 2) int: (A index, B index) of frames matched by time
    common: np.ndarray  # (K, 2) int: matched frames solved by both
    only_a_frames: list[int]  # A frames with no B frame at their time
    only_b_frames: list[int]
    solved_only_by_a: list[int]  # matched A frames solved by A, rejected by B
    solved_only_by_b: list[int]  # matched B frames solved by B, rejected by A
    largest: list[FrameDifference]
    settings_changed: dict[str, tuple]  # setting → (A value, B value)
    notes: list[str]
    align: str
    rpe_delta: int
    confidence: float
    delta_series: dict[str, tuple[np.ndarray, np.ndarray]]  # key → (A indices, B − A values)

    def metrics(self) -> dict[str, dict[str, float | None]]:
        """``{"A": {metric: value}, "B": {...}}`` for :mod:`agvviz.evaluation.expression`."""
        return {
            "A": {row.name: row.a for row in self.rows},
            "B": {row.name: row.b for row in self.rows},
        }

    def row(self, name: str) -> MetricRow:
        for row in self.rows:
            if row.name == name:
                return row
        raise KeyError(f"no metric {name!r}; known: {', '.join(r.name for r in self.rows)}")


def _difference(a, b):
    return None if a is None or b is None else b - a


def _settings_changed(a: dict, b: dict) -> dict[str, tuple]:
    return {k: (a.get(k), b.get(k)) for k in sorted(a.keys() | b.keys()) if a.get(k) != b.get(k)}


def compare_runs(
    a: RunSeries,
    b: RunSeries,
    *,
    align: str = "none",
    rpe_delta: int = 1,
    time_offset: bool = False,
    max_dt_ns: int | None = None,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
    top_k: int = 5,
) -> Comparison:
    """Compare run B with run A frame by frame.

    Parameters
    ----------
    a, b : RunSeries
    align : str
        APE alignment of each run to its truth (computed on the frames both solved).
    rpe_delta : int
        RPE pair distance in frames.
    time_offset : bool
        Also estimate each run's time offset to its truth (``time_offset_ms``).
    max_dt_ns : int, optional
        Largest stamp difference of matched frames (default: half a frame interval).
    confidence, n_resamples, seed
        Bootstrap intervals: coverage, resamples, seed (same inputs ⇒ same numbers).
    top_k : int
        How many of the most different frames to name.
    """
    if align not in trajectory.ALIGNMENTS:
        raise EvaluationError(f"unknown alignment {align!r}; choose one of: {', '.join(trajectory.ALIGNMENTS)}")
    ia, ib = match_frames(a.time_ns, b.time_ns, max_dt_ns)
    both = a.solved[ia] & b.solved[ib]
    ca, cb = ia[both], ib[both]
    va = quantity_values(a, ca, align, rpe_delta)
    vb = quantity_values(b, cb, align, rpe_delta)

    rows = []
    counts_a, counts_b = _counts(a), _counts(b)
    for name in COUNTS:
        rows.append(MetricRow(name, counts_a[name], counts_b[name], _difference(counts_a[name], counts_b[name])))
    if any(isinstance(run.summary.get("suspects"), dict) for run in (a, b)):
        # Suspect counts (issue 25) from each run's summary: a run without them has no value.
        suspects_a, suspects_b = suspect_counts(a.summary), suspect_counts(b.summary)
        for name in suspect_metric_names():
            va_, vb_ = suspects_a[name], suspects_b[name]
            rows.append(MetricRow(name, va_, vb_, _difference(va_, vb_)))
    delta_series = {}
    for q in QUANTITIES:
        x, y = va[q.key][ca], vb[q.key][cb]
        ok = np.isfinite(x) & np.isfinite(y)
        x, y = x[ok], y[ok]
        stats_a, stats_b = statistics.describe(x), statistics.describe(y)
        p_value = statistics.wilcoxon_paired(x, y) if len(x) else None
        cis = (
            statistics.paired_bootstrap_ci(x, y, confidence=confidence, n_resamples=n_resamples, seed=seed)
            if len(x) >= 2 else {}
        )
        for stat in statistics.STATISTICS:
            low, high = cis.get(stat, (None, None))
            rows.append(MetricRow(
                metric_name(q, stat), stats_a[stat], stats_b[stat],
                _difference(stats_a[stat], stats_b[stat]), low, high, p_value, int(len(x)),
            ))
        if q in DIRECT:
            # Signed per-frame Δ of the absolute error (B − A) on A's frames, for the overlay.
            delta_series[q.key] = (ca[ok], y - x)
    notes = []
    if time_offset:
        t_a, t_b = _time_offset_ms(a), _time_offset_ms(b)
        rows.append(MetricRow("time_offset_ms", t_a, t_b, _difference(t_a, t_b)))
        if t_a is None or t_b is None:
            notes.append("a time offset could not be estimated for every run (too few poses or no motion)")

    sha_a, sha_b = a.manifest.get("recording_sha256"), b.manifest.get("recording_sha256")
    if sha_a != sha_b:
        notes.append("the runs replay different recordings (recording_sha256 differs)")
    only_a = sorted(set(range(len(a.frames))) - set(ia.tolist()))
    only_b = sorted(set(range(len(b.frames))) - set(ib.tolist()))
    if only_a or only_b:
        notes.append(f"{len(only_a)} frames of A and {len(only_b)} of B have no partner at their time")

    separation_mm = np.linalg.norm(a.T_est[ca, :3, 3] - b.T_est[cb, :3, 3], axis=1) * 1000.0
    order = [k for k in np.argsort(-separation_mm, kind="stable") if separation_mm[k] > 0][:top_k]
    largest = [
        FrameDifference(
            frame_a=int(a.frames[ca[k]]), frame_b=int(b.frames[cb[k]]), time_ns=int(a.time_ns[ca[k]]),
            separation_mm=float(separation_mm[k]),
            position_a_mm=float(a.errors["position"][ca[k]]), position_b_mm=float(b.errors["position"][cb[k]]),
            heading_a_deg=float(a.errors["heading"][ca[k]]), heading_b_deg=float(b.errors["heading"][cb[k]]),
        )
        for k in order
    ]
    return Comparison(
        a_name=a.name,
        b_name=b.name,
        rows=rows,
        matched=np.stack([ia, ib], axis=1),
        common=np.stack([ca, cb], axis=1),
        only_a_frames=[int(a.frames[i]) for i in only_a],
        only_b_frames=[int(b.frames[i]) for i in only_b],
        solved_only_by_a=[int(a.frames[i]) for i, j in zip(ia, ib) if a.solved[i] and not b.solved[j]],
        solved_only_by_b=[int(b.frames[j]) for i, j in zip(ia, ib) if b.solved[j] and not a.solved[i]],
        largest=largest,
        settings_changed=_settings_changed(a.settings, b.settings),
        notes=notes,
        align=align,
        rpe_delta=rpe_delta,
        confidence=confidence,
        delta_series=delta_series,
    )
