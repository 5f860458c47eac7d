"""The one Levenberg–Marquardt core (agvviz.solvers.lm_core): a known optimum, batched equal to
single, the damping schedule, the iteration budget, and refusal of bad numbers."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from agvviz.geometry import so3
from agvviz.solvers import lm_core
from agvviz.solvers.lm_core import LmOptions, minimize, minimize_batch

EPS = np.finfo(float).eps
OPTIONS = LmOptions()  # step_tol 1e-12, cost_rel_tol 1e-14: the defaults every solver uses


def stopping_bound(cost: float, residuals: np.ndarray, magnitudes: np.ndarray) -> float:
    """4·(τ·c + δc): how far (in ½‖e‖²_H) two points the stopping rule accepts can be apart.

    Near the minimum x* the cost is c* + ½eᵀHe (H = JᵀJ). A damped Gauss–Newton step with the
    tiny λ reached by then removes essentially all of the excess c − c*, so the rule
    "|Δc| ≤ τ·c" stops with ½‖e‖²_H ≤ τ·c — unless the cost cannot be evaluated to better than
    δc = ε·Σ|r_i|·m_i (each residual is a difference of terms of magnitude m_i), in which case it
    stops anywhere with c − c* ≲ δc. Two such points (or one and the exact optimum) are within
    ½dᵀHd ≤ (2·√(τ·c + δc))² = 4·(τ·c + δc) by the triangle inequality in the H-norm (as
    tests/test_lm_batch.py)."""
    return 4.0 * (OPTIONS.cost_rel_tol * cost + EPS * float(np.abs(residuals) @ magnitudes))


# -- a rotation alignment with a closed-form optimum --------------------------------------------


def test_rotation_alignment_reaches_the_closed_form_optimum():
    """Wahba's problem min_R Σ|R a_i − b_i|² on SO(3) (retraction R ← Exp(φ)·R) from a start 1 rad
    off: LM ends within the stopping rule's guarantee of the SVD (Kabsch) solution."""
    rng = np.random.default_rng(1)
    a = rng.normal(size=(12, 3))
    R_true = so3.exp(rng.normal(size=3))
    b = a @ R_true.T + rng.normal(0.0, 0.05, a.shape)

    def residuals_and_jacobian(R):
        Ra = a @ R.T
        return (Ra - b).ravel(), -so3.hat_batch(Ra).reshape(-1, 3)  # ∂(Exp(φ)·R·a)/∂φ = −(R a)^

    U, _, Vt = np.linalg.svd(b.T @ a)
    R_star = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    start = so3.exp(rng.normal(size=3) * (1.0 / np.sqrt(3.0))) @ R_true
    result = minimize(start, lambda R, phi: so3.exp(phi) @ R, residuals_and_jacobian=residuals_and_jacobian)
    assert result.converged and result.stop_reason in lm_core.CONVERGED and not result.failed
    assert len(result.iterations) - 1 < OPTIONS.max_iterations
    r, J = residuals_and_jacobian(result.x)
    H = J.T @ J
    d = so3.log(result.x @ R_star.T)
    bound = stopping_bound(result.cost, r, (np.abs(a @ result.x.T) + np.abs(b)).ravel())
    assert 0.5 * d @ H @ d <= bound, (0.5 * d @ H @ d, bound)
    assert np.sqrt(2.0 * bound / np.linalg.eigvalsh(H)[0]) < 1e-6  # the bound is not vacuous
    assert result.cost == 0.5 * float(r @ r)  # the reported cost is c(x)
    costs = [it.cost for it in result.iterations]
    assert all(c1 <= c0 for c0, c1 in zip(costs, costs[1:]))  # the kept cost never rises


# -- batched and single ------------------------------------------------------------------------

T_S = np.linspace(0.0, 4.0, 15)


def curve_fits(n: int, seed: int):
    """n fits of y = a·exp(−b t) + c with noise; starts 30 % off. Returns starts, data, truth."""
    rng = np.random.default_rng(seed)
    truth = np.column_stack([rng.uniform(1, 3, n), rng.uniform(0.3, 1.5, n), rng.uniform(-1, 1, n)])
    y = truth[:, :1] * np.exp(-truth[:, 1:2] * T_S) + truth[:, 2:] + rng.normal(0.0, 0.02, (n, T_S.size))
    return truth * rng.uniform(0.7, 1.3, truth.shape), y, truth


def fit_residuals_and_jacobian(x: np.ndarray, y: np.ndarray):
    """r (…, m) and J (…, m, 3) of the curve fit for params x (…, 3) and data y (…, m)."""
    e = np.exp(-x[..., 1:2] * T_S)
    r = x[..., 0:1] * e + x[..., 2:3] - y
    J = np.stack([e, -x[..., 0:1] * T_S * e, np.ones_like(e)], axis=-1)
    return r, J


def fit_magnitudes(x, y):
    return np.abs(x[0] * np.exp(-x[1] * T_S)) + abs(x[2]) + np.abs(y)


def add(x, delta):
    return x + delta


def test_batched_equals_single_within_the_stopping_rule():
    starts, y, _ = curve_fits(40, seed=2)
    batch = minimize_batch(starts, add, lambda x, k: fit_residuals_and_jacobian(x, y[k]))
    assert batch.converged.all() and not batch.failed.any()
    for k in range(len(starts)):
        single = minimize(starts[k], add, residuals_and_jacobian=lambda x: fit_residuals_and_jacobian(x, y[k]))
        assert single.converged and single.stop_reason in lm_core.CONVERGED
        assert batch.stop_reason[k] in lm_core.CONVERGED
        assert batch.iterations[k] < OPTIONS.max_iterations and len(single.iterations) - 1 < OPTIONS.max_iterations
        r, J = fit_residuals_and_jacobian(single.x, y[k])
        H = J.T @ J
        d = batch.x[k] - single.x
        bound = stopping_bound(single.cost, r, fit_magnitudes(single.x, y[k]))
        assert 0.5 * d @ H @ d <= bound, (k, 0.5 * d @ H @ d, bound)
        assert np.sqrt(2.0 * bound / np.linalg.eigvalsh(H)[0]) < 1e-6
        r_batch, _ = fit_residuals_and_jacobian(batch.x[k], y[k])
        assert batch.cost[k] == pytest.approx(0.5 * r_batch @ r_batch, rel=64 * EPS)


def test_noise_free_curve_fit_recovers_the_generating_parameters():
    starts, _, truth = curve_fits(5, seed=3)
    y = truth[:, :1] * np.exp(-truth[:, 1:2] * T_S) + truth[:, 2:]
    for k in range(len(starts)):
        result = minimize(starts[k], add, residuals_and_jacobian=lambda x: fit_residuals_and_jacobian(x, y[k]))
        assert result.converged
        # c* = 0 at the truth; the rule leaves at most the round-off floor of the cost.
        _, J = fit_residuals_and_jacobian(truth[k], y[k])
        H = J.T @ J
        floor = 4.0 * EPS**2 * float(fit_magnitudes(truth[k], y[k]) @ fit_magnitudes(truth[k], y[k]))
        e = result.x - truth[k]
        assert 0.5 * e @ H @ e <= 4.0 * (OPTIONS.cost_rel_tol * result.cost + floor), (k, e)
        assert np.abs(e).max() < 1e-9


# -- the damping schedule and the iteration budget ---------------------------------------------


def test_a_refused_step_multiplies_the_damping_and_keeps_the_point():
    """r(x) = atan(x) from x = 3 with λ₀ = 1e-8: the Gauss–Newton step overshoots to x ≈ −9.5
    (|atan| larger), so steps are refused and λ grows ×10 until λ > 1.08 (the first step that
    lowers the cost); every accepted step divides it by 10."""

    def residuals_and_jacobian(x):
        return np.array([math.atan(x[0])]), np.array([[1.0 / (1.0 + x[0] ** 2)]])

    result = minimize(np.array([3.0]), add, residuals_and_jacobian=residuals_and_jacobian,
                      options=LmOptions(initial_damping=1e-8))
    its = result.iterations
    assert result.converged and abs(result.x[0]) < 1e-6
    # The first step is scale-free damped Gauss–Newton: δ = −r/J / (1 + λ) (μ = λ·JᵀJ here).
    assert its[1].step_norm == pytest.approx(math.atan(3.0) * 10.0 / (1.0 + 1e-8), rel=1e-12)
    assert [it.accepted for it in its[1:11]] == [False] * 9 + [True]
    for k in range(1, len(its) - 1):
        expected = its[k].damping / 10.0 if its[k].accepted else its[k].damping * 10.0
        assert its[k + 1].damping == expected
        if not its[k].accepted:
            assert its[k].cost == its[k - 1].cost and result.path[k] is result.path[k - 1]
        else:
            assert its[k].cost < its[k - 1].cost


def rosenbrock(x):
    return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]]), np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])


def rosenbrock_batch(x, k):
    r = np.column_stack([10.0 * (x[:, 1] - x[:, 0] ** 2), 1.0 - x[:, 0]])
    J = np.zeros((len(x), 2, 2))
    J[:, 0, 0], J[:, 0, 1], J[:, 1, 0] = -20.0 * x[:, 0], 10.0, -1.0
    return r, J


def test_out_of_iterations_returns_the_best_point_so_far():
    start = np.array([-1.2, 1.0])
    result = minimize(start, add, residuals_and_jacobian=rosenbrock, options=LmOptions(max_iterations=3))
    assert not result.converged and not result.failed and result.stop_reason == lm_core.MAX_ITERATIONS
    assert len(result.iterations) == 4 and len(result.path) == 4
    best = min(range(4), key=lambda k: result.iterations[k].cost)
    assert result.cost == result.iterations[best].cost < result.iterations[0].cost
    np.testing.assert_array_equal(result.x, result.path[best])
    np.testing.assert_array_equal(rosenbrock(result.x)[0], rosenbrock(result.path[best])[0])
    full = minimize(start, add, residuals_and_jacobian=rosenbrock)
    assert full.converged and np.abs(full.x - 1.0).max() < 1e-6  # the budget, not the problem, stopped it
    batch = minimize_batch(np.array([start, start]), add, rosenbrock_batch,
                           options=LmOptions(max_iterations=3))
    assert list(batch.stop_reason) == [lm_core.MAX_ITERATIONS] * 2 and list(batch.iterations) == [3, 3]
    # Same schedule step by step (two refusals among the three steps here): three damped 2×2
    # solves (κ ≲ 10³) apart only by summation order, so equal to ≲ κ·ε relative, not to 1e-10.
    assert [it.accepted for it in result.iterations[1:]].count(False) >= 1
    assert not batch.converged.any()
    np.testing.assert_allclose(batch.x, [result.x, result.x], rtol=1e-10)


# -- bad numbers --------------------------------------------------------------------------------


def sqrt_fit(x):
    """r = √x − 1 (minimum at x = 1); NaN left of 0, where the square root does not exist."""
    if x[0] < 0.0:
        return np.array([np.nan]), np.array([[np.nan]])
    return np.array([math.sqrt(x[0]) - 1.0]), np.array([[0.5 / math.sqrt(x[0])]])


def test_non_finite_residuals_are_refused_cleanly():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning either
        # A step into the NaN region (from 9 the Gauss–Newton step lands at −3) is refused.
        result = minimize(np.array([9.0]), add, residuals_and_jacobian=sqrt_fit)
        assert not result.iterations[1].accepted and result.iterations[2].damping == 10.0 * result.iterations[1].damping
        assert result.converged and abs(result.x[0] - 1.0) < 1e-6
        # A NaN start is a failed result with a reason, not an exception or a NaN point.
        nan_start = minimize(np.array([-1.0]), add, residuals_and_jacobian=sqrt_fit)
        assert nan_start.failed and nan_start.x is None and nan_start.stop_reason == lm_core.START_NOT_FINITE
        assert nan_start.iterations == [] and nan_start.cost == np.inf
        infeasible = minimize(np.array([9.0]), add, residuals_and_jacobian=sqrt_fit, feasible=lambda x: x[0] < 5.0)
        assert infeasible.failed and infeasible.x is None and infeasible.stop_reason == lm_core.START_INFEASIBLE
        # A zero Jacobian: singular normal equations, the start kept as the best point.
        flat = minimize(np.array([2.0]), add, residuals_and_jacobian=lambda x: (np.array([1.0]), np.zeros((1, 1))))
        assert flat.failed and flat.stop_reason == lm_core.SINGULAR and flat.x[0] == 2.0


def test_batch_refuses_bad_problems_one_by_one():
    """A NaN start and a singular problem in a batch fail alone; the others are solved."""
    starts, y, _ = curve_fits(6, seed=4)
    starts[2] = np.nan

    def residuals_and_jacobian(x, k):
        r, J = fit_residuals_and_jacobian(x, y[k])
        J[k == 4] = 0.0  # problem 4 does not depend on its parameters
        return r, J

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        batch = minimize_batch(starts, add, residuals_and_jacobian)
    assert batch.stop_reason[2] == lm_core.START_NOT_FINITE and batch.cost[2] == np.inf
    assert batch.stop_reason[4] == lm_core.SINGULAR and np.all(batch.x[4] == starts[4])
    assert list(batch.failed) == [False, False, True, False, True, False]
    for k in (0, 1, 3, 5):
        single = minimize(starts[k], add, residuals_and_jacobian=lambda x: fit_residuals_and_jacobian(x, y[k]))
        assert batch.converged[k] and single.converged
        r, J = fit_residuals_and_jacobian(single.x, y[k])
        d = batch.x[k] - single.x
        assert 0.5 * d @ (J.T @ J) @ d <= stopping_bound(single.cost, r, fit_magnitudes(single.x, y[k]))


def test_options_and_callbacks_are_checked():
    with pytest.raises(ValueError, match="initial_damping"):
        LmOptions(initial_damping=0.0)
    with pytest.raises(ValueError, match="exactly one"):
        minimize(np.zeros(1), add)
    with pytest.raises(ValueError, match="exactly one"):
        minimize(np.zeros(1), add, residuals_and_jacobian=sqrt_fit, normal_equations=lambda x: (0.0, None, None))
