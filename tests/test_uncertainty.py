"""Pose covariance, Cramér–Rao bound and NEES (agvviz.solvers.uncertainty) against Monte-Carlo
scatter of the LM and finite differences. Tangent space: left perturbation, δ = (ρ, φ)."""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.geometry import se3
from agvviz.geometry.euler import Rx, Rz
from agvviz.geometry.plane import square_points_marker
from agvviz.solvers import uncertainty as unc
from agvviz.solvers.lm_batch import solve_lm_batch

K = np.array([[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]])
#: A 0.5 m code 2 m away, tilted 40° (well-conditioned: ~250 px, no near-ambiguity).
T_TRUE = se3.make(np.diag([1.0, -1.0, -1.0]) @ Rx(np.radians(40.0)) @ Rz(0.3), [0.1, -0.05, 2.0])
POINTS = square_points_marker(0.5, with_midpoints=True)
SIGMA_PX = 0.5
TRIALS = 1000


def _project(T, points):
    w = se3.transform_points(T, points)
    return (w @ K.T)[:, :2] / w[:, 2:3]


@pytest.fixture(scope="module")
def trials():
    """TRIALS noisy views of T_TRUE and the batch LM estimates for both objectives."""
    rng = np.random.default_rng(42)
    px = _project(T_TRUE, POINTS)[None] + rng.normal(0.0, SIGMA_PX, (TRIALS, len(POINTS), 2))
    pts = np.broadcast_to(POINTS, (TRIALS,) + POINTS.shape)
    out = {}
    for objective in ("pixel", "depth"):
        result = solve_lm_batch(pts, px, K, objective=objective)
        assert result.ok.all()
        out[objective] = result.T_cam_marker
    return px, out


def test_crlb_matches_finite_difference_fisher_information():
    eps = 1e-6
    J_fd = np.empty((2 * len(POINTS), 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        J_fd[:, k] = (_project(se3.exp(d) @ T_TRUE, POINTS) - _project(se3.exp(-d) @ T_TRUE, POINTS)).ravel() / (2 * eps)
    fisher = J_fd.T @ J_fd / SIGMA_PX**2
    # Central differences are accurate to ~1e-8 relative here; the inverse amplifies by the
    # condition number (~1e4), so 1e-4 relative is a safe bound that still catches any
    # wrong column, sign or σ power.
    np.testing.assert_allclose(unc.crlb(T_TRUE, POINTS, K, SIGMA_PX), np.linalg.inv(fisher), rtol=1e-4, atol=1e-14)


@pytest.mark.parametrize("objective", ["pixel", "depth"])
def test_covariance_matches_monte_carlo_scatter(trials, objective):
    _, estimates = trials
    errors = np.array([unc.left_error(T, T_TRUE) for T in estimates[objective]])
    sample = np.cov(errors.T)
    predicted = unc.covariance(T_TRUE, POINTS, K, SIGMA_PX, objective)
    ratio = np.diag(sample) / np.diag(predicted)
    # Sample variances from 1000 Gaussian draws have relative std sqrt(2/999) ≈ 0.045; a ±15 %
    # band is > 3σ and leaves room for the small second-order (nonlinearity) bias.
    assert np.all(np.abs(ratio - 1.0) < 0.15), ratio


def test_depth_objective_sandwich_is_never_below_the_ml_covariance():
    ml = unc.covariance(T_TRUE, POINTS, K, SIGMA_PX, "pixel")
    sandwich = unc.covariance(T_TRUE, POINTS, K, SIGMA_PX, "depth")
    # Gauss–Markov: the weighted estimator's covariance minus the ML one is positive semidefinite.
    assert np.min(np.linalg.eigvalsh(sandwich - ml)) > -1e-12 * np.max(np.linalg.eigvalsh(ml))
    assert np.trace(sandwich) > np.trace(ml)  # the depths differ (tilted code): strictly worse


def test_nees_mean_is_six_for_the_ml_estimator(trials):
    _, estimates = trials
    values = [
        unc.nees(T, T_TRUE, unc.covariance(T, POINTS, K, SIGMA_PX, "pixel")) for T in estimates["pixel"]
    ]
    # NEES ~ χ²(6): mean 6, std of the mean sqrt(12/1000) ≈ 0.11; ±0.5 is > 4σ.
    assert abs(np.mean(values) - 6.0) < 0.5, np.mean(values)


def test_residual_sigma_estimate_is_unbiased_on_average(trials):
    px, estimates = trials
    sums = [unc.residual_sum_sq_px2(T, POINTS, px[k], K) for k, T in enumerate(estimates["pixel"][:300])]
    pooled = unc.residual_sigma_px(sum(s for s, _ in sums), sum(d for _, d in sums))
    # 300 frames × 10 dof: the pooled σ² has relative std sqrt(2/3000) ≈ 0.026.
    assert pooled == pytest.approx(SIGMA_PX, rel=0.05)


def test_world_agv_covariance_propagation_matches_the_chain():
    """δ on T_cam_marker maps to −Ad(T_world_cam)·δ on T_world_agv (first order)."""
    rng = np.random.default_rng(1)
    T_world_marker = se3.make(Rz(0.7), [3.0, -2.0, 0.0])
    T_agv_cam = se3.make(Rx(np.radians(-120.0)), [0.0, 0.1, 1.5])
    T_world_cam = T_world_marker @ se3.inverse(T_TRUE)
    T_world_agv = T_world_cam @ se3.inverse(T_agv_cam)
    Ad = se3.adjoint(T_world_cam)
    for _ in range(5):
        delta = rng.normal(0.0, 1e-6, 6)
        T_agv = T_world_marker @ se3.inverse(se3.exp(delta) @ T_TRUE) @ se3.inverse(T_agv_cam)
        np.testing.assert_allclose(unc.left_error(T_agv, T_world_agv), -Ad @ delta, atol=1e-11)
    cov = unc.covariance(T_TRUE, POINTS, K, SIGMA_PX)
    np.testing.assert_allclose(unc.covariance_world_agv(cov, T_world_cam), Ad @ cov @ Ad.T, rtol=1e-12)


def test_position_covariance_matches_sampled_origins():
    rng = np.random.default_rng(5)
    cov = unc.covariance(T_TRUE, POINTS, K, SIGMA_PX)
    deltas = rng.multivariate_normal(np.zeros(6), cov, size=20000)
    origins = np.array([(se3.exp(d) @ T_TRUE)[:3, 3] for d in deltas])
    predicted = unc.position_covariance(cov, T_TRUE)
    # 20000 samples: sample variances within ~2 %; the first-order map adds < 1e-3 relative here.
    np.testing.assert_allclose(np.diag(np.cov(origins.T)), np.diag(predicted), rtol=0.06)


def test_singular_geometry_is_a_clear_error():
    collinear = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0], [0.3, 0.0, 0.0]])
    with pytest.raises(unc.UncertaintyError, match="do not determine the pose"):
        unc.crlb(se3.make(np.eye(3), [0, 0, 2.0]), collinear, K, 1.0)
