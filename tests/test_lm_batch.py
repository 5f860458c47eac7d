"""Vectorised P4P/LM (agvviz.solvers.lm_batch) equal the single-frame solvers."""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.geometry import se3
from agvviz.geometry.euler import Rx, Rz
from agvviz.geometry.plane import square_points_marker
from agvviz.solvers import SolverOptions, solve
from agvviz.solvers.lm_batch import p4p_batch, solve_lm_batch

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


@pytest.mark.parametrize("objective, n_points", [("depth", 4), ("pixel", 4), ("depth", 8), ("pixel", 8)])
def test_batch_lm_equals_single_frame_lm(objective, n_points):
    P, X, _ = problems(60, n_points, seed=n_points)
    batch = solve_lm_batch(P, X, K, objective=objective)
    for k in range(len(P)):
        single = solve("lm", P[k], X[k], K, SolverOptions(objective=objective))
        assert single.success and batch.ok[k]
        # Same arithmetic per frame: equal to round-off (measured: depth bit-identical,
        # pixel ≤ 2e-10 over 1000 frames; 1e-9 m / rad-entry leaves margin).
        np.testing.assert_allclose(batch.T_cam_marker[k], single.T_cam_marker, atol=1e-9, rtol=0)
        assert batch.iterations[k] == len(single.iterations) - 1
        assert batch.reproj_rms_px[k] == pytest.approx(single.reproj_rms_px, rel=1e-9)


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
            np.testing.assert_allclose(batch.T_cam_marker[k], single.T_cam_marker, atol=1e-12, rtol=0)


def test_batch_lm_keeps_best_pose_when_out_of_iterations():
    P, X, _ = problems(5, 8, seed=1)
    batch = solve_lm_batch(P, X, K, max_iterations=1)
    assert batch.ok.all()
    for k in range(len(P)):
        single = solve("lm", P[k], X[k], K, SolverOptions(max_iterations=1))
        np.testing.assert_allclose(batch.T_cam_marker[k], single.T_cam_marker, atol=1e-9, rtol=0)
