"""The mathematics of the error budget behind ``agvviz budget``: shares, the remainder, the
per-frame differences and the budget's table. Computes on values; the counterfactual runs that
produce them (re-recording with one error source off, replaying, loading the runs) are
:func:`agvviz.app.budget.error_budget`'s.

For an agvviz recording made under a non-ideal realism profile (:mod:`agvviz.sim.realism`),
each error source that is on is switched off in turn: the scenario is recorded again with the
same seed and options plus ``realism_off=<existing>,<source>``, replayed with the same run
settings and compared with the replay of the recording itself. Every source draws from its own
random stream, so that counterfactual world differs from the original only by the source
switched off: the budget is exact, not a Monte-Carlo estimate.

The share of the position error a source causes is a share of the *mean squared* error::

    share(source) = (rmse_all² − rmse_off²) / rmse_all²

Variances, not RMSEs, because independent error sources add in the mean square (the RMSE of
the sum of independent errors is the root of the sum of their squares): with independent,
additive sources the shares are fractions of one total that sum to 1 less the floor's part.
Sources interact, however — a bump that tilts the camera changes how much a calibration error
costs, a dropped frame removes a frame from the RMSE, a solver is not linear — so the shares
need not sum to 1, and one may even be negative (switching that source off made the error
larger). :attr:`ErrorBudget.interaction` is the remainder ``1 − Σ shares`` ("interaction /
other"): what the sources cause only together, plus the floor. The floor itself,
:attr:`ErrorBudget.floor_rmse_mm`, is the RMSE of the ideal world (every source off: only the
solver, the detector and the ideal profile's own blur and noise remain).

The per-frame differences (:attr:`SourceBudget.delta_mm` = error with every source on − error
with this one off, mm, on the frames both runs solved, matched by their time stamp) show *when*
a source costs what it costs (:func:`matched_difference`). Returns values, prints nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agvviz.settings import RunSettings, as_dict

#: Name of the remainder ``1 − Σ shares`` in tables and the ``.rrd``.
INTERACTION = "interaction/other"


@dataclass
class SourceBudget:
    """One error source: the run with it switched off and its share of the position error."""

    source: str
    rmse_off_mm: float | None  # position RMSE with this source off (None: no frame solved)
    share: float  # (rmse_all² − rmse_off²) / rmse_all² (NaN when rmse_all is 0 or rmse_off None)
    solved_off: int  # frames solved with the source off
    time_ns: np.ndarray  # per frame of the run with the source off (its time stamps)
    position_error_off_mm: np.ndarray  # per frame, NaN where not solved
    delta_mm: np.ndarray  # per frame of time_ns: error all on − error this off (NaN: either unsolved)


@dataclass
class ErrorBudget:
    """The error budget of one recording under one set of run settings."""

    recording: Path
    scenario: str
    seed: int
    profile: str  # the realism profile the recording was made under
    realism_off: str  # what the recording itself already had switched off
    settings: dict
    rmse_all_mm: float  # position RMSE of the recording as it is
    solved_all: int
    floor_rmse_mm: float | None  # every source off: the ideal world's RMSE
    time_ns: np.ndarray  # per frame of the recording's run
    frames: np.ndarray  # frame index per entry of time_ns
    position_error_all_mm: np.ndarray  # per frame, NaN where not solved
    sources: list[SourceBudget] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def interaction(self) -> float:
        """``1 − Σ shares``: what the sources cause only together (and the floor's part)."""
        return 1.0 - float(sum(s.share for s in self.sources if math.isfinite(s.share)))

    def summary(self) -> dict:
        """Plain data for a run summary (``summary["error_budget"]``): the profile, the RMSE
        with every source on and off, and per source its RMSE when off and its share."""
        return {
            "profile": self.profile,
            "realism_off": self.realism_off,
            "rmse_all_mm": self.rmse_all_mm,
            "floor_rmse_mm": self.floor_rmse_mm,
            "sources": [
                {"source": s.source, "rmse_off_mm": s.rmse_off_mm, "share": _finite_or_none(s.share)}
                for s in self.sources
            ],
            "interaction": _finite_or_none(self.interaction),
            "warnings": list(self.warnings),
        }

    def rows(self) -> list[tuple[str, str, str]]:
        """(source, RMSE with it off, share %) rows, then the remainder, all on and the floor."""
        rows = [(s.source, _mm(s.rmse_off_mm), _pct(s.share)) for s in self.sources]
        rows.append((INTERACTION, "", _pct(self.interaction)))
        rows.append(("all on (the recording)", _mm(self.rmse_all_mm), "100.0"))
        rows.append(("floor (all off, ideal)", _mm(self.floor_rmse_mm), _pct(share(self.rmse_all_mm, self.floor_rmse_mm, floor=True))))
        return rows

    def markdown(self) -> str:
        """The budget as a markdown table with a few lines of explanation."""
        lines = [
            f"# Error budget of {self.recording.name}",
            "",
            f"Scenario `{self.scenario}`, seed {self.seed}, realism `{self.profile}`"
            + (f" (already off: `{self.realism_off}`)" if self.realism_off else "")
            + f"; run settings `{_settings_text(self.settings)}`.",
            "",
            f"| source | position RMSE with it off (mm) | share of the error (%) | {100 * SHARE_CONFIDENCE:g} % CI over frames (%) |",
            "|---|---:|---:|---:|",
        ]
        intervals = {i.name: i for i in share_intervals(self)}
        for a, b, c in self.rows():
            i = intervals.get(a)
            ci = f"[{_pct(i.low)}, {_pct(i.high)}]" if i is not None and math.isfinite(i.low) else ""
            lines.append(f"| {a} | {b} | {c} | {ci} |")
        lines += [
            "",
            "share = (RMSE_all² − RMSE_off²) / RMSE_all² — a share of the mean squared error. "
            f"Sources interact, so the shares need not sum to 100 %; `{INTERACTION}` is the remainder "
            "(1 − Σ shares). The floor's share is RMSE_floor² / RMSE_all²: what remains with every source off.",
            "",
            NEGATIVE_SHARE_NOTE,
            "",
            f"CI: block bootstrap over the recording's {len(self.time_ns)} frames ({SHARE_RESAMPLES} resamples, seed "
            f"{SHARE_SEED}); few frames give wide intervals.",
        ]
        lines += [f"\n*warning:* {w}" for w in self.warnings]
        return "\n".join(lines) + "\n"


#: The bootstrap of the shares' intervals: confidence, resamples and the seed of its draws.
SHARE_CONFIDENCE = 0.95
SHARE_RESAMPLES = 2000
SHARE_SEED = 0

#: One line under the chart and the table: what a negative share means.
NEGATIVE_SHARE_NOTE = (
    "A negative share: with that source off the error grew — sources interact (one error can "
    "cancel part of another), so the shares need not add up; interaction/other is the rest."
)


@dataclass(frozen=True)
class ShareInterval:
    """A share and its bootstrap interval over frames (fractions, not %)."""

    name: str  # the source, or INTERACTION
    share: float
    low: float
    high: float


def share_intervals(budget: ErrorBudget, confidence: float = SHARE_CONFIDENCE,
                    n_resamples: int = SHARE_RESAMPLES, seed: int = SHARE_SEED) -> list[ShareInterval]:
    """Each source's share, then interaction/other, with a bootstrap interval over the frames.

    The frames of the recording's run (``budget.time_ns``) are resampled with a circular block
    bootstrap (:func:`agvviz.evaluation.statistics.block_bootstrap_indices`: neighbouring frames
    see the same code, so blocks of ⌈n^(1/3)⌉ keep that correlation); in each resample every
    share is recomputed from the mean squared errors of the resampled frames — all on, and the
    same stamps with the source off (a frame one of the two runs did not solve is left out of
    that run's mean) — and interaction/other as 1 − Σ shares. The interval is the percentile
    interval of those; the share itself is the budget's (every frame each run solved). Seeded:
    the same budget gives the same intervals. NaN bounds when fewer than 2 frames were solved."""
    from agvviz.evaluation.statistics import block_bootstrap_indices, default_block_length

    n = len(budget.time_ns)
    shares = [(s.source, s.share) for s in budget.sources] + [(INTERACTION, budget.interaction)]
    all_on = np.asarray(budget.position_error_all_mm, dtype=float)
    if n < 2 or np.sum(np.isfinite(all_on)) < 2:
        return [ShareInterval(name, value, math.nan, math.nan) for name, value in shares]
    rng = np.random.default_rng(seed)
    idx = block_bootstrap_indices(n, n_resamples, default_block_length(n), rng)  # (R, n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mse_all = np.nanmean(all_on[idx] ** 2, axis=1)  # (R,)
        resampled = []
        for s in budget.sources:
            where = {int(t): k for k, t in enumerate(s.time_ns)}
            off = np.array([s.position_error_off_mm[where[int(t)]] if int(t) in where else np.nan
                            for t in budget.time_ns], dtype=float)
            mse_off = np.nanmean(off[idx] ** 2, axis=1)
            resampled.append((mse_all - mse_off) / mse_all)
        resampled.append(1.0 - np.sum(resampled, axis=0) if resampled else np.ones(n_resamples))
    tail = 100.0 * (1.0 - confidence) / 2.0
    out = []
    for (name, value), draws in zip(shares, resampled):
        draws = draws[np.isfinite(draws)]
        low, high = (np.percentile(draws, [tail, 100.0 - tail]) if draws.size else (math.nan, math.nan))
        out.append(ShareInterval(name, value, float(low), float(high)))
    return out


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _mm(value: float | None) -> str:
    return "—" if value is None else f"{value:.3f}"


def _pct(value: float) -> str:
    return "—" if not math.isfinite(value) else f"{100.0 * value:.1f}"


def share(rmse_all: float, rmse_off: float | None, floor: bool = False) -> float:
    """(rmse_all² − rmse_off²) / rmse_all², or with ``floor`` rmse_off² / rmse_all² (the part
    that remains with every source off); NaN when rmse_all is 0 or rmse_off None."""
    if rmse_off is None or not rmse_all > 0.0:
        return float("nan")
    if floor:
        return rmse_off**2 / rmse_all**2
    return (rmse_all**2 - rmse_off**2) / rmse_all**2


def _settings_text(settings: dict) -> str:
    default = as_dict(RunSettings())
    changed = {k: v for k, v in settings.items() if default.get(k) != v}
    return ", ".join(f"{k}={v}" for k, v in changed.items()) or "defaults"


def matched_difference(time_a: np.ndarray, err_a: np.ndarray, time_b: np.ndarray, err_b: np.ndarray) -> np.ndarray:
    """err_a − err_b at each time of ``time_a`` (NaN where b has no such frame or either is NaN)."""
    where = {int(t): k for k, t in enumerate(time_b)}
    out = np.full(len(time_a), np.nan)
    for k, t in enumerate(time_a):
        j = where.get(int(t))
        if j is not None:
            out[k] = err_a[k] - err_b[j]
    return out


__all__ = ["INTERACTION", "ErrorBudget", "ShareInterval", "SourceBudget", "matched_difference", "share", "share_intervals"]
