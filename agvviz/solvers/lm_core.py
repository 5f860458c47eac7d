"""One Levenberg–Marquardt core for every solver that iterates. Numpy only; no I/O.

Problem
    Minimise the cost ``c(x) = ½‖r(x)‖²`` over a point x of a manifold. The caller gives

    * ``retract(x, δ) -> x'``, the update by a tangent step δ (n,): the left perturbation
      ``Exp(δ)·T`` on SE(3) (:mod:`agvviz.conventions`), a body-frame (x, y, heading) step for a
      planar pose, plain addition on ℝⁿ, …;
    * ``residuals_and_jacobian(x) -> (r (m,), J (m, n))`` with ``J = ∂r(retract(x, δ))/∂δ`` at
      δ = 0 — or, for a problem that forms the Gauss–Newton normal equations faster than its
      residual vector (CNOEM's 13×13 quadratic form), ``normal_equations(x) -> (c, JᵀJ, Jᵀr)``;
    * optionally ``feasible(x) -> bool`` (a point where it is False — a marker point behind the
      camera — is never accepted) and ``reproj_rms_px(x) -> float`` for the iteration record
      (NaN when not given).

Damping schedule (Levenberg, fixed factors; the same for every solver)
    A trial step solves ``(JᵀJ + μ I) δ = −Jᵀr`` with ``μ = λ · mean(diag(JᵀJ))``, so λ is
    scale-free. λ starts at ``initial_damping``. The trial point ``x' = retract(x, δ)`` is
    accepted when it is feasible, its cost and normal equations are finite and
    ``c(x') < c(x)``: then ``x ← x'`` and ``λ ← λ / 10``. Otherwise x stays and ``λ ← 10 λ``.

Stopping rule (after every trial step, accepted or not)
    Converged when ``‖δ‖ < step_tol``, or ``|c(x) − c(x')| ≤ cost_rel_tol · c(x)`` (a step that
    changes the cost that little cannot be told from round-off), or ``c(x) = 0``. After
    ``max_iterations`` trial steps without convergence the best point so far is returned with
    ``converged = False``: still an estimate, as with OpenCV's iteration criteria; the caller
    decides whether to use it.

Failures (``failed``)
    The start is infeasible or its cost or normal equations are not finite (``x`` is then
    ``None``); or the damped normal equations are singular (``x`` is the best point so far).
    A trial point with non-finite residuals is not a failure: the step is refused like an
    uphill one and the damping grows.

Records
    ``iterations[0]`` is the start (its cost, λ₀, step 0, accepted); then one
    :class:`~agvviz.solvers.types.LmIteration` per trial step: the cost and RMS of the point kept
    after it, the λ the step was solved with, ‖δ‖, whether it was accepted. ``path[k]`` is the
    point kept after record k (the same object while steps are refused).

Batched form
    :func:`minimize_batch` solves B independent problems of equal size at once (stacked
    (B, m) residuals and (B, m, n) Jacobians, batched n×n solves) with a λ per problem and, per
    problem, the acceptance, schedule and stopping rule of :func:`minimize`; a problem that
    stops is no longer evaluated. It keeps a count of trial steps per problem, not records.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from agvviz.solvers.types import LmIteration

#: λ is divided by this after an accepted step and multiplied by it after a refused one.
DAMPING_FACTOR = 10.0

# Why a solve stopped (``stop_reason``).
CONVERGED_STEP = "step below step_tol"
CONVERGED_COST = "cost change below cost_rel_tol"
CONVERGED_ZERO = "zero cost"
MAX_ITERATIONS = "iteration budget exhausted"
START_INFEASIBLE = "start point infeasible"
START_NOT_FINITE = "non-finite residuals or Jacobian at the start point"
SINGULAR = "singular normal equations"

CONVERGED = (CONVERGED_STEP, CONVERGED_COST, CONVERGED_ZERO)
FAILURES = (START_INFEASIBLE, START_NOT_FINITE, SINGULAR)


@dataclass(frozen=True)
class LmOptions:
    """max_iterations : trial steps at most; initial_damping : λ₀ (relative to mean(diag(JᵀJ)));
    step_tol, cost_rel_tol : the stopping rule (module docstring)."""

    max_iterations: int = 50
    initial_damping: float = 1e-3
    step_tol: float = 1e-12
    cost_rel_tol: float = 1e-14

    def __post_init__(self):
        if not (self.max_iterations >= 0 and self.initial_damping > 0.0):
            raise ValueError(
                f"LM options: need max_iterations ≥ 0 and initial_damping > 0, got "
                f"{self.max_iterations} and {self.initial_damping}"
            )
        if not (self.step_tol >= 0.0 and self.cost_rel_tol >= 0.0):
            raise ValueError(f"LM options: tolerances must be ≥ 0, got {self.step_tol}, {self.cost_rel_tol}")


@dataclass
class LmResult:
    """Result of :func:`minimize`.

    x : the best point (the start when no step was accepted); ``None`` when the start was refused.
    cost : ½‖r‖² at x (+inf when x is None).
    iterations, path : the records (module docstring); empty when the start was refused.
    converged : True when the stopping rule was met; stop_reason : one of the module constants.
    """

    x: Any
    cost: float
    iterations: list[LmIteration] = field(default_factory=list)
    path: list = field(default_factory=list)
    converged: bool = False
    stop_reason: str = ""

    @property
    def failed(self) -> bool:
        return self.stop_reason in FAILURES


@dataclass
class LmBatchResult:
    """Result of :func:`minimize_batch`, per problem (first axis B).

    x : (B, ...) the best points; a problem refused at the start keeps its start.
    cost : (B,) ½‖r‖² at x (+inf where refused at the start).
    iterations : (B,) trial steps taken; converged : (B,) bool; stop_reason : (B,) str.
    """

    x: np.ndarray
    cost: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    stop_reason: np.ndarray

    @property
    def failed(self) -> np.ndarray:
        return np.isin(self.stop_reason, FAILURES)


def minimize(
    x0: Any,
    retract: Callable[[Any, np.ndarray], Any],
    *,
    residuals_and_jacobian: Callable[[Any], tuple[np.ndarray, np.ndarray]] | None = None,
    normal_equations: Callable[[Any], tuple[float, np.ndarray, np.ndarray]] | None = None,
    feasible: Callable[[Any], bool] | None = None,
    reproj_rms_px: Callable[[Any], float] | None = None,
    options: LmOptions = LmOptions(),
) -> LmResult:
    """Levenberg–Marquardt from ``x0``; give exactly one of ``residuals_and_jacobian`` and
    ``normal_equations`` (module docstring). Never raises on bad numbers: they give a failed
    result with its ``stop_reason``."""
    if (residuals_and_jacobian is None) == (normal_equations is None):
        raise ValueError("give exactly one of residuals_and_jacobian and normal_equations")

    def evaluate(x) -> tuple[float, np.ndarray | None, np.ndarray | None, str]:
        """(cost, JᵀJ, Jᵀr, "") or (inf, None, None, why the point is refused)."""
        if feasible is not None and not feasible(x):
            return float("inf"), None, None, START_INFEASIBLE
        if normal_equations is not None:
            cost, H, g = normal_equations(x)
            cost = float(cost)
        else:
            r, J = residuals_and_jacobian(x)
            cost, H, g = 0.5 * float(r @ r), J.T @ J, J.T @ r
        if not (np.isfinite(cost) and np.isfinite(H).all() and np.isfinite(g).all()):
            return float("inf"), None, None, START_NOT_FINITE
        return cost, H, g, ""

    def rms(x) -> float:
        return float("nan") if reproj_rms_px is None else float(reproj_rms_px(x))

    x = x0
    cost, H, g, refused = evaluate(x)
    if refused:
        return LmResult(None, float("inf"), [], [], False, refused)
    damping = float(options.initial_damping)
    rms_x = rms(x)
    iterations = [LmIteration(cost, rms_x, damping, 0.0, True)]
    path = [x]
    if cost == 0.0:
        return LmResult(x, cost, iterations, path, True, CONVERGED_ZERO)
    n = H.shape[0]
    diagonal = np.diag_indices(n)
    for _ in range(options.max_iterations):
        A = H.copy()
        A[diagonal] += damping * (float(np.trace(H)) / n)  # μ = λ·mean(diag(JᵀJ))
        try:
            delta = np.linalg.solve(A, -g)
        except np.linalg.LinAlgError:
            return LmResult(x, cost, iterations, path, False, SINGULAR)
        if not np.isfinite(delta).all():
            return LmResult(x, cost, iterations, path, False, SINGULAR)
        step_norm = float(np.sqrt(delta @ delta))
        x_trial = retract(x, delta)
        cost_trial, H_trial, g_trial, refused = evaluate(x_trial)
        accepted = not refused and cost_trial < cost
        small_change = abs(cost - cost_trial) <= options.cost_rel_tol * cost
        damping_used = damping
        if accepted:
            x, cost, H, g = x_trial, cost_trial, H_trial, g_trial
            damping /= DAMPING_FACTOR
            rms_x = rms(x)
        else:
            damping *= DAMPING_FACTOR
        iterations.append(LmIteration(cost, rms_x, damping_used, step_norm, accepted))
        path.append(x)
        if step_norm < options.step_tol:
            return LmResult(x, cost, iterations, path, True, CONVERGED_STEP)
        if small_change:
            return LmResult(x, cost, iterations, path, True, CONVERGED_COST)
        if cost == 0.0:
            return LmResult(x, cost, iterations, path, True, CONVERGED_ZERO)
    return LmResult(x, cost, iterations, path, False, MAX_ITERATIONS)


def minimize_batch(
    x0: np.ndarray,
    retract: Callable[[np.ndarray, np.ndarray], np.ndarray],
    residuals_and_jacobian: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    *,
    feasible: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    options: LmOptions = LmOptions(),
) -> LmBatchResult:
    """:func:`minimize` of B independent problems at once, per problem the same rules.

    Parameters
    ----------
    x0 : (B, ...) start points, one per problem (an array).
    retract : ``(x (M, ...), δ (M, n)) -> x' (M, ...)``.
    residuals_and_jacobian : ``(x (M, ...), idx (M,)) -> (r (M, m), J (M, m, n))`` for the
        problems ``idx`` (indices into the batch) at points x.
    feasible : optional ``(x (M, ...), idx (M,)) -> (M,) bool``.
    options : as :func:`minimize`.
    """
    x = np.array(x0, dtype=float)
    b = x.shape[0]
    cost = np.full(b, np.inf)
    iterations = np.zeros(b, dtype=int)
    converged = np.zeros(b, dtype=bool)
    stop_reason = np.full(b, "", dtype=object)
    H = g = None  # (B, n, n), (B, n), allocated at the first evaluation

    def evaluate(x_sub: np.ndarray, idx: np.ndarray):
        """(cost (M,), JᵀJ, Jᵀr for the accepted rows, why each row is refused ("" if not))."""
        c = np.full(idx.size, np.inf)
        why = np.full(idx.size, "", dtype=object)
        ok = np.ones(idx.size, dtype=bool) if feasible is None else np.asarray(feasible(x_sub, idx), dtype=bool)
        why[~ok] = START_INFEASIBLE
        rows = np.flatnonzero(ok)
        Hs = gs = None
        if rows.size:
            r, J = residuals_and_jacobian(x_sub[rows], idx[rows])
            Jt = np.swapaxes(J, 1, 2)
            Hs, gs = Jt @ J, (Jt @ r[:, :, None])[:, :, 0]
            c_rows = 0.5 * np.einsum("bi,bi->b", r, r)
            finite = np.isfinite(c_rows) & np.all(np.isfinite(Hs), axis=(1, 2)) & np.all(np.isfinite(gs), axis=1)
            why[rows[~finite]] = START_NOT_FINITE
            c[rows[finite]] = c_rows[finite]
        return c, Hs, gs, rows, why

    everyone = np.arange(b)
    c0, Hs, gs, rows, why = evaluate(x, everyone)
    refused = why != ""
    stop_reason[refused] = why[refused]
    if rows.size:
        n = Hs.shape[-1]
        H, g = np.zeros((b, n, n)), np.zeros((b, n))
        H[rows], g[rows] = Hs, gs
    cost[~refused] = c0[~refused]
    zero = ~refused & (cost == 0.0)
    converged[zero], stop_reason[zero] = True, CONVERGED_ZERO
    active = ~refused & ~zero
    damping = np.full(b, float(options.initial_damping))
    for _ in range(options.max_iterations):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        Ha = H[idx]
        n = Ha.shape[-1]
        mean_diag = np.trace(Ha, axis1=1, axis2=2) / n
        A = Ha + (damping[idx] * mean_diag)[:, None, None] * np.eye(n)  # μ = λ·mean(diag(JᵀJ))
        delta, singular = _solve_each(A, -g[idx])
        if np.any(singular):
            stop_reason[idx[singular]] = SINGULAR
            active[idx[singular]] = False
            idx, delta = idx[~singular], delta[~singular]
            if idx.size == 0:
                break
        step_norm = np.sqrt(np.einsum("bi,bi->b", delta, delta))
        x_trial = retract(x[idx], delta)
        cost_trial, Hs, gs, rows, _ = evaluate(x_trial, idx)
        accepted = cost_trial < cost[idx]  # a refused trial point has cost +inf
        small_change = np.abs(cost[idx] - cost_trial) <= options.cost_rel_tol * cost[idx]
        iterations[idx] += 1
        acc = idx[accepted]
        x[acc] = x_trial[accepted]
        cost[acc] = cost_trial[accepted]
        if rows.size:
            accepted_rows = accepted[rows]  # rows of (Hs, gs) that belong to accepted problems
            H[idx[rows[accepted_rows]]] = Hs[accepted_rows]
            g[idx[rows[accepted_rows]]] = gs[accepted_rows]
        damping[acc] /= DAMPING_FACTOR
        damping[idx[~accepted]] *= DAMPING_FACTOR
        for done, reason in (
            (step_norm < options.step_tol, CONVERGED_STEP),
            (small_change, CONVERGED_COST),
            (cost[idx] == 0.0, CONVERGED_ZERO),
        ):
            stop = idx[done & active[idx]]
            converged[stop], stop_reason[stop], active[stop] = True, reason, False
    stop_reason[active] = MAX_ITERATIONS
    return LmBatchResult(x, cost, iterations, converged, stop_reason)


def _solve_each(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve the stacked systems A (M, n, n) δ = b (M, n); (δ, singular (M,) bool). One batched
    solve, and one by one only when a system is singular (numpy refuses the whole stack)."""
    try:
        delta = np.linalg.solve(A, b[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        delta = np.zeros_like(b)
        for k in range(A.shape[0]):
            try:
                delta[k] = np.linalg.solve(A[k], b[k])
            except np.linalg.LinAlgError:
                delta[k] = np.nan
    return delta, ~np.all(np.isfinite(delta), axis=1)
