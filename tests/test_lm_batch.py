"""Vectorised P4P/LM (agvviz.solvers.lm_batch) equal the single-frame solvers."""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.geometry import se3
from agvviz.geometry.euler import Rx, Rz
from agvviz.geometry.plane import square_points_marker
from agvviz.solvers import SolverOptions, solve
from agvviz.solvers.lm import refine_lm, reprojection_rms_px, residuals_and_jacobian
from agvviz.solvers.lm_batch import p4p_batch, refine_lm_batch, solve_lm_batch

K = np.array([[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]])


def problems(n_frames: int, n_points: int, seed: int):
    rng = np.random.default_rng(seed)
    pts = square_points_marker(0.5, with_midpoints=n_points == 8)
    P, X, truth = [], [], []
    for _ in range(n_frames):
        T = se3.make(
            np.diag([1.0, -1.0, -1.0]) @ Rz(rng.uniform(0, 6.28)) @ Rx(np.radians(rng.uniform(5, 60))) @ Rz(rng.uniform(0, 6.28)),
            [rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(1.0, 3.0)],
        )
        w = se3.transform_points(T, pts)
        P.append(pts)
        X.append((w @ K.T)[:, :2] / w[:, 2:3] + rng.normal(0.0, 0.5, (n_points, 2)))
        truth.append(T)
    return np.array(P), np.array(X), truth


EPS = np.finfo(float).eps
OPTIONS = SolverOptions()  # the defaults both solvers use: step_tol 1e-12, cost_rel_tol 1e-14


def cost_floor(T, points, pixels, objective):
    """(cost, JᵀJ, δc): the cost ½‖f‖², its Gauss–Newton Hessian, and the round-off δc with
    which the cost can be evaluated at all.

    Every residual is a difference of large terms (depth: k·w − z·u with |k·w| ≈ 10³·|w|;
    pixel: π(Kw) − p with |p| ≈ 10³ px) that cancel to ≈ 1. Each f_i therefore carries an
    absolute error ≈ ε·m_i (m_i the magnitude of its terms), and ½‖f‖² an error
    δc ≈ Σ|f_i|·ε·m_i — for these frames 50–20 000 × cost_rel_tol·cost. Below that no
    step, accepted or rejected, can be told apart from round-off."""
    w = se3.transform_points(T, points)
    f, J = residuals_and_jacobian(T, points, pixels, K, objective)
    if objective == "depth":
        mag = (np.abs(w) @ np.abs(K[:2]).T + np.abs(w[:, 2:3]) * np.abs(pixels)).reshape(-1)
    else:
        mag = (np.abs(pixels) + np.abs(f.reshape(-1, 2) + pixels)).reshape(-1)
    return 0.5 * float(f @ f), J.T @ J, EPS * float(np.abs(f) @ mag)


@pytest.mark.parametrize("objective, n_points", [("depth", 4), ("pixel", 4), ("depth", 8), ("pixel", 8)])
def test_batch_lm_equals_single_frame_lm(objective, n_points):
    """Both LMs converge to the same minimum, to the accuracy their stopping rule guarantees.

    Stopping rule (lm.refine_lm, lm_batch.refine_lm_batch, identical): stop when ‖δ‖ < step_tol
    or a trial step, accepted or not, changes the cost by ≤ τ·cost (τ = cost_rel_tol).
    Near the minimum x* the cost is quadratic, c(x) = c* + ½ eᵀHe with e = Log(T·T*⁻¹) and
    H = JᵀJ. A step changes the cost by at least a fixed fraction of the excess c − c* (for
    the tiny λ reached by then, essentially all of it), so a solver stops with c − c* ≤ τ·c
    — unless the cost itself cannot be evaluated to better than δc (see cost_floor), in which
    case it stops anywhere with c − c* ≲ δc (that is where the rejected-step chains come
    from). So each result satisfies ½‖e‖²_H ≤ τ·c + δc, and by the triangle inequality in the
    H-norm the two results differ by d = Log(T_batch·T_single⁻¹) with

        ½ dᵀHd ≤ (2·√(τ·c + δc))² = 4·(τ·c + δc).

    Measured (300 frames per case): the left side is ≤ 0.09 × (τ·c + δc) with OpenBLAS
    Prescott kernels, ≤ 1e-4 × with Haswell/Zen (bit-identical for the pixel objective).
    That bound is ~1e-9 m / rad in the worst-conditioned direction — it is not vacuous:
    asserted below to be < 1 µm.

    Iteration counts are not compared: once both are at the round-off floor, whether a step
    is rejected and how many ×10 damping increases it takes before a step changes the cost
    by ≤ τ·c depends on the last bits of the Jacobian (measured: equal with Haswell, up to
    16 apart with Prescott). What the method guarantees is that both stop on the criterion,
    not on the iteration budget.
    """
    P, X, _ = problems(60, n_points, seed=n_points)
    batch = solve_lm_batch(P, X, K, objective=objective)
    tau = OPTIONS.cost_rel_tol
    for k in range(len(P)):
        single = solve("lm", P[k], X[k], K, SolverOptions(objective=objective))
        assert single.success and batch.ok[k]
        cost, H, floor = cost_floor(single.T_cam_marker, P[k], X[k], objective)
        bound = 4.0 * (tau * cost + floor)
        d = se3.log(batch.T_cam_marker[k] @ se3.inverse(single.T_cam_marker))
        assert 0.5 * d @ H @ d <= bound, (k, 0.5 * d @ H @ d, bound)
        assert np.sqrt(2.0 * bound / np.linalg.eigvalsh(H)[0]) < 1e-6  # the bound means something
        # Both stopped on the convergence rule, not on the iteration budget.
        assert batch.iterations[k] < OPTIONS.max_iterations
        assert len(single.iterations) - 1 < OPTIONS.max_iterations
        # The batch RMS is the RMS of the batch pose: the same sum in another order, whose
        # error is a few ε relative to the cancelling terms |p| ≈ 10³ px, not to the RMS.
        rms = reprojection_rms_px(batch.T_cam_marker[k], P[k], X[k], K)
        assert abs(batch.reproj_rms_px[k] - rms) <= 64 * EPS * np.abs(X[k]).max()


def test_batch_p4p_equals_single_frame_p4p_and_reports_failures():
    P, X, _ = problems(30, 4, seed=9)
    X[3, 3] = 0.5 * (X[3, 0] + X[3, 2])  # collinear triple in frame 3
    batch = p4p_batch(P, X, K)
    for k in range(len(P)):
        single = solve("p4p", P[k], X[k], K)
        if k == 3:
            assert not batch.ok[k] and batch.reason[k] == single.reason == "degenerate: pixels collinear"
            assert np.all(np.isnan(batch.T_cam_marker[k]))
        else:
            # Same arithmetic, different summation order: a few hundred ulps of the entries,
            # amplified by the conditioning of the pixel matrix P (κ ≈ 10³–10⁵ here) that
            # P4P solves with (measured ≤ 6 ulp with any kernel).
            p = np.column_stack([X[k, :3], np.ones(3)]).T
            atol = 256 * EPS * np.linalg.cond(p) * np.abs(single.T_cam_marker).max()
            np.testing.assert_allclose(batch.T_cam_marker[k], single.T_cam_marker, atol=atol, rtol=0)


def test_batch_lm_keeps_best_pose_when_out_of_iterations():
    P, X, _ = problems(5, 8, seed=1)
    batch = solve_lm_batch(P, X, K, max_iterations=1)
    assert batch.ok.all()
    for k in range(len(P)):
        single = solve("lm", P[k], X[k], K, SolverOptions(max_iterations=1))
        # One step from the same P4P start: δ solves (JᵀJ + μI)δ = −Jᵀf, so its round-off is
        # ≈ κ(JᵀJ + μI)·ε relative (κ ≈ 10³ here); a few hundred ulps × κ × the entries'
        # magnitude (measured ≤ 8 ulp with any kernel).
        start = solve("p4p", P[k], X[k], K).T_cam_marker
        _, H, _ = cost_floor(start, P[k], X[k], "depth")
        kappa = np.linalg.cond(H + 1e-3 * np.mean(np.diag(H)) * np.eye(6))
        atol = 256 * EPS * kappa * np.abs(single.T_cam_marker).max()
        np.testing.assert_allclose(batch.T_cam_marker[k], single.T_cam_marker, atol=atol, rtol=0)



def test_batch_lm_refuses_bad_frames_one_by_one():
    """A frame without a start pose and one whose start puts a point behind the camera fail
    alone, with refine_lm's reasons; the others are solved."""
    P, X, truth = problems(5, 4, seed=5)
    T0 = np.array(truth)
    T0[1] = np.nan
    T0[3] = se3.make(np.eye(3), [0.0, 0.0, -4.0]) @ T0[3]  # the marker behind the camera
    batch = refine_lm_batch(T0, P, X, K)
    assert list(batch.ok) == [True, False, True, False, True]
    assert batch.reason[1] == "no start pose" and batch.reason[3] == "point behind camera"
    assert np.all(np.isnan(batch.T_cam_marker[[1, 3]])) and np.all(np.isnan(batch.reproj_rms_px[[1, 3]]))
    options = dict(objective="depth", max_iterations=50, initial_damping=1e-3, step_tol=1e-12, cost_rel_tol=1e-14)
    for k in (1, 3):  # a NaN start has no point in front of the camera either
        assert refine_lm(T0[k], P[k], X[k], K, **options)[:2] == (None, "point behind camera")
    assert np.all(batch.reproj_rms_px[[0, 2, 4]] < 3.0)  # σ = 0.5 px noise on 4 points
