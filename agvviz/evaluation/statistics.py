"""Summary statistics, bootstrap confidence intervals and the paired signed-rank test.

Numpy only (the normal quantile from :mod:`agvviz.solvers.chi2`; no scipy.stats, whose import
costs ≈0.8 s of CPU). Every random draw comes from ``np.random.default_rng(seed)``.

Per-frame errors of a run are serially correlated (neighbouring frames see the same code
from nearly the same place), so confidence intervals resample *blocks* of consecutive frames
(circular block bootstrap, Politis & Romano 1992) of length ``⌈n^(1/3)⌉`` by default, which
keeps that correlation inside each resample. The Wilcoxon signed-rank test assumes
independent pairs; on strongly correlated errors its p-value is optimistic — read it with
the block-bootstrap interval next to it.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from agvviz.solvers.chi2 import normal_isf

#: Statistics of absolute errors reported for every per-frame quantity.
STATISTICS = ("rmse", "median", "p95", "max")
#: Statistics that get a bootstrap interval (a bootstrap interval of a maximum is meaningless).
BOOTSTRAPPED = ("rmse", "median", "p95")


def _rmse(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(v**2, axis=-1))


#: Each statistic as a function of an array reduced along its last axis.
STATISTIC_FUNCTIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "rmse": _rmse,
    "median": lambda v: np.median(v, axis=-1),
    "p95": lambda v: np.percentile(v, 95, axis=-1),
    "max": lambda v: np.max(v, axis=-1),
}


def describe(values: np.ndarray) -> dict[str, float | None]:
    """:data:`STATISTICS` of ``values`` (N,) (already absolute), ``None`` each when empty."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {name: None for name in STATISTICS}
    return {name: float(STATISTIC_FUNCTIONS[name](v)) for name in STATISTICS}


def default_block_length(n: int) -> int:
    """⌈n^(1/3)⌉: the usual order of block length for a block bootstrap of n samples."""
    return max(1, math.ceil(n ** (1.0 / 3.0)))


def block_bootstrap_indices(
    n: int, n_resamples: int, block_length: int, rng: np.random.Generator
) -> np.ndarray:
    """Indices of ``n_resamples`` circular block-bootstrap resamples of ``n`` samples.

    Returns
    -------
    indices : (n_resamples, n) int array
        Each row concatenates blocks of ``block_length`` consecutive indices (wrapping
        around) with uniformly drawn starts, cut to ``n``. ``block_length`` 1 is the plain
        i.i.d. bootstrap.
    """
    if n < 1:
        raise ValueError("cannot bootstrap an empty sample")
    block_length = max(1, min(int(block_length), n))
    n_blocks = math.ceil(n / block_length)
    starts = rng.integers(0, n, size=(n_resamples, n_blocks))
    offsets = np.arange(block_length)
    indices = (starts[:, :, None] + offsets[None, None, :]) % n
    return indices.reshape(n_resamples, n_blocks * block_length)[:, :n]


def paired_bootstrap_ci(
    a: np.ndarray,
    b: np.ndarray,
    statistics: tuple[str, ...] = BOOTSTRAPPED,
    *,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    block_length: int | None = None,
    seed: int = 0,
) -> dict[str, tuple[float, float]]:
    """Percentile bootstrap interval of ``stat(b) − stat(a)`` for paired samples.

    Parameters
    ----------
    a, b : (N,) arrays
        Paired values (e.g. absolute errors of the same frames under runs A and B), in time
        order; both are resampled with the *same* indices, so the pairing is kept.
    statistics : names from :data:`STATISTIC_FUNCTIONS`
    confidence : float
        Two-sided coverage, e.g. 0.95.
    block_length : int, optional
        Default :func:`default_block_length` of N.
    seed : int
        Seed of the resampling (same inputs and seed ⇒ same interval).

    Returns
    -------
    dict
        statistic name → (low, high).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"paired samples must be 1-D of equal length, got {a.shape} and {b.shape}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    rng = np.random.default_rng(seed)
    idx = block_bootstrap_indices(
        len(a), n_resamples, default_block_length(len(a)) if block_length is None else block_length, rng
    )
    a_star, b_star = a[idx], b[idx]
    tail = 100.0 * (1.0 - confidence) / 2.0
    result = {}
    for name in statistics:
        f = STATISTIC_FUNCTIONS[name]
        differences = f(b_star) - f(a_star)
        low, high = np.percentile(differences, [tail, 100.0 - tail])
        result[name] = (float(low), float(high))
    return result


def wilcoxon_paired(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sided p-value of the Wilcoxon signed-rank test of ``b − a`` against zero median.

    The p-value of ``scipy.stats.wilcoxon(b − a, zero_method="wilcox",
    alternative="two-sided")`` with its default ``method="auto"`` and ``correction=False``
    (scipy 1.17), computed here without importing scipy.stats (≈0.8 s of CPU). Zero
    differences are dropped (Wilcoxon's treatment); the statistic is the sum of the average
    ranks of |d| over the positive differences. Like scipy's ``auto``, with ``N = len(a)``
    (zeros included):

    * N ≤ 50, no zero and no tie — the exact null distribution of the rank sum;
    * N ≤ 13 with a zero or a tie — scipy's permutation test, which then enumerates all 2^N
      sign flips (no random draw): the same exact sum over the average ranks, here by
      :func:`_rank_sum_counts` (zeros flip to themselves and only double every count; scipy's
      comparison tolerance, 100 ulp of t, is far below the ½ between distinct rank sums);
    * otherwise the normal approximation with scipy's tie correction, no continuity correction.

    Both exact forms give ``min(1, 2·min(P(T ≤ t), P(T ≥ t)))`` as a ratio of integers, equal
    to scipy's bit for bit; the normal form differs from scipy's only by erfc against
    ``scipy.special.ndtr`` (≈1e-15 relative). When every difference is zero (or there is none)
    the runs are identical on these values and the p-value is 1 (scipy: 1 for N ≤ 13, NaN above).
    A NaN difference is refused (scipy would give NaN).
    """
    d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
    if d.ndim != 1:
        raise ValueError(f"paired samples must be 1-D, got shape {d.shape}")
    if np.any(np.isnan(d)):
        raise ValueError("paired differences must not be NaN")
    nonzero = d[d != 0.0]
    if nonzero.size == 0:
        return 1.0
    ranks_x2, tie_sizes = _doubled_average_ranks(np.abs(nonzero))
    t_x2 = int(ranks_x2[nonzero > 0.0].sum())  # twice the statistic: an integer
    has_zeros, has_ties = nonzero.size < d.size, bool(np.any(tie_sizes > 1))
    if d.size <= 50 and (d.size <= 13 or not (has_zeros or has_ties)):
        counts = _rank_sum_counts(ranks_x2)
        at_most, at_least = int(counts[: t_x2 + 1].sum()), int(counts[t_x2:].sum())
        return min(1.0, 2 * min(at_most, at_least) / 2**nonzero.size)
    n = float(nonzero.size)
    mean = n * (n + 1.0) * 0.25
    tie_correction = float(np.sum(tie_sizes.astype(float) ** 3 - tie_sizes))
    sd = math.sqrt((n * (n + 1.0) * (2.0 * n + 1.0) - tie_correction / 2.0) / 24.0)
    z = (0.5 * t_x2 - mean) / sd
    return math.erfc(abs(z) / math.sqrt(2.0))  # 2·P(N(0,1) > |z|)


def _doubled_average_ranks(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(2 × the average rank of each of ``values`` (ties share the mean of their ranks), as
    int64; the size of each group of equal values, in ascending order of value).

    A group of k equal values at ordinal ranks i … i+k−1 has average rank i + (k−1)/2, twice
    that is the integer 2i + k − 1."""
    order = np.argsort(values, kind="stable")
    sorted_values = values[order]
    starts = np.flatnonzero(np.concatenate(([True], sorted_values[1:] != sorted_values[:-1])))
    sizes = np.diff(np.append(starts, len(values)))
    group_ranks_x2 = 2 * (starts + 1) + sizes - 1
    ranks_x2 = np.empty(len(values), dtype=np.int64)
    ranks_x2[order] = np.repeat(group_ranks_x2, sizes)
    return ranks_x2, sizes


def _rank_sum_counts(weights: np.ndarray) -> np.ndarray:
    """counts[s] = the number of subsets of ``weights`` (positive integers) whose sum is s, for
    s = 0 … sum(weights): the null distribution of the signed-rank sum times 2^n, each rank
    counted as positive or not with probability ½. Dynamic programming, integers, exact up to
    n = 62 (every count is at most 2^n; used for n ≤ 50)."""
    if len(weights) > 62:
        raise ValueError(f"exact counts need at most 62 weights, got {len(weights)}")
    counts = np.zeros(int(np.sum(weights)) + 1, dtype=np.int64)
    counts[0] = 1
    for w in (int(w) for w in weights):
        counts[w:] = counts[w:] + counts[:-w]  # right side first: the subsets without w
    return counts


def rmse_ci(errors: np.ndarray, confidence: float = 0.95) -> tuple[float, float, float]:
    """RMSE of independent ``errors`` (NaN left out) and its ``confidence`` interval: the
    normal interval of the mean of the squared errors (central limit theorem; independent
    trials, so no blocks), its ends' square roots — (nan, nan, nan) without a finite error; the
    interval is (rmse, rmse) for one error. Used by the Monte-Carlo study's lines per solver."""
    e2 = np.asarray(errors, dtype=float) ** 2
    e2 = e2[np.isfinite(e2)]
    if e2.size == 0:
        return math.nan, math.nan, math.nan
    mean = float(np.mean(e2))
    z = normal_isf((1.0 - confidence) / 2.0)  # scipy.stats.norm.ppf(0.5 + confidence / 2)
    half = 0.0 if e2.size < 2 else float(z * np.std(e2, ddof=1) / math.sqrt(e2.size))
    return math.sqrt(mean), math.sqrt(max(mean - half, 0.0)), math.sqrt(mean + half)
