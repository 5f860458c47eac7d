"""CNOEM (paper 002) window solvers: cost against the paper's own formula, derivatives against
finite differences, solutions against truth, the window CRLB against a Monte-Carlo and the
single-frame bound, and the IPPE baselines."""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.geometry import se3
from agvviz.geometry.euler import matrix_from_hpr
from agvviz.model.studies import GridCell
from agvviz.sim import auv
from agvviz.solvers import cnoem, uncertainty, window_baselines
from agvviz.solvers.bundle import pixel_residuals_and_jacobian, solve_bundle
from agvviz.solvers.cnoem import CornerWindow, Sighting, WindowError
from agvviz.solvers.window_crlb import position_bound_m, window_crlb

# Closed-form identities on products of sines/cosines (magnitude ≤ 1): a few hundred ulps,
# whatever the summation order of the BLAS kernel (see tests/test_geometry.py).
TOL_UNIT = 256 * np.finfo(float).eps

CELL = GridCell(10.0, 0.2, 0.1, 1.0, 1.0)


def _trial(seed: int, sigma_px: float = 0.0, cell: GridCell = CELL):
    geometry = auv.cycle_geometry(cell)
    trial = auv.draw_trial(geometry, sigma_px, np.random.default_rng(seed))
    return trial, CornerWindow.from_sightings(trial.sightings)


def _position_error_m(T_a: np.ndarray, T_b: np.ndarray) -> float:
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))


def test_cost_is_the_papers_equation_13():
    trial, window = _trial(1, sigma_px=1.0)
    T_F_world = se3.inverse(trial.T_world_F_nav)
    E = cnoem.sighting_errors(window, T_F_world)
    # Eq 8 / 13 literally: p = ((u − u0)/k1·f, (v − v0)/k2·f, f) with f = 1, P = T_F^O T_W^F P^W.
    expected = np.zeros(window.n_sightings)
    for j, s in enumerate(trial.sightings):
        K = s.K
        P = se3.transform_points(se3.inverse(s.T_F_cam) @ T_F_world, s.points_world_m)
        for (u, v), (X, Y, Z) in zip(s.pixels_px, P):
            x, y, z = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0
            expected[j] += ((Y * z - Z * y) ** 2 + (X * z - Z * x) ** 2 + (X * y - Y * x) ** 2) / (x * x + y * y + z * z)
    np.testing.assert_allclose(E, expected, rtol=1e-10)


@pytest.mark.parametrize("which", ["ray", "pixel"])
def test_jacobians_match_finite_differences(which):
    trial, window = _trial(2, sigma_px=1.0)
    T = se3.inverse(trial.T_world_F_nav)
    fn = cnoem.ray_residuals_and_jacobian if which == "ray" else pixel_residuals_and_jacobian
    f0, J = fn(window, T)
    h = 1e-6
    J_fd = np.zeros_like(J)
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        J_fd[:, k] = (fn(window, se3.exp(d) @ T)[0] - fn(window, se3.exp(-d) @ T)[0]) / (2 * h)
    # Central differences: truncation O(h²·f''') ≪ 1e-6 of the column scale.
    np.testing.assert_allclose(J, J_fd, atol=1e-6 * np.abs(J).max())


def test_normal_equations_equal_the_jacobian_form():
    trial, window = _trial(3, sigma_px=1.0)
    T = se3.inverse(trial.T_world_F_nav)
    cost, H, g = cnoem.ray_normal_equations(window, T)
    r, J = cnoem.ray_residuals_and_jacobian(window, T)
    assert cost == pytest.approx(0.5 * r @ r, rel=1e-10)
    np.testing.assert_allclose(H, J.T @ J, atol=1e-10 * np.abs(H).max())
    np.testing.assert_allclose(g, J.T @ r, atol=1e-9 * np.abs(g).max())


def test_euler_derivatives_match_eq_18_and_finite_differences():
    n = np.array([0.1, -0.2, 0.7, 1.0, 2.0, 3.0])
    dR = cnoem.euler_derivatives(n)
    sa, sb, sg = np.sin(n[:3])
    ca, cb, cg = np.cos(n[:3])
    # First rows of eq 18 as printed.
    np.testing.assert_allclose(dR[0][0], [-sb * sg * ca, sa * sg, sg * ca * cb], atol=TOL_UNIT)
    np.testing.assert_allclose(dR[1][0], [-sb * cg - sa * sg * cb, 0.0, cb * cg - sa * sb * sg], atol=TOL_UNIT)
    np.testing.assert_allclose(dR[2][0], [-sg * cb - sa * sb * cg, -ca * cg, -sb * sg + sa * cb * cg], atol=TOL_UNIT)
    for k in range(3):
        h = np.zeros(6)
        h[k] = 1e-6
        fd = (cnoem.transform_from_euler_params(n + h) - cnoem.transform_from_euler_params(n - h))[:3, :3] / 2e-6
        np.testing.assert_allclose(dR[k], fd, atol=1e-9)
    np.testing.assert_allclose(cnoem.euler_params_from_transform(cnoem.transform_from_euler_params(n)), n, atol=1e-12)


def test_paper_error_propagation_is_the_gradient_of_half_sum_E_squared():
    trial, window = _trial(4, sigma_px=1.0)
    n = cnoem.euler_params_from_transform(se3.inverse(trial.T_world_F_nav))
    grad = np.sum(cnoem.paper_error_propagation(window, n), axis=0)
    fd = np.zeros(6)
    for k in range(6):
        h = np.zeros(6)
        h[k] = 1e-6
        fd[k] = (
            cnoem.paper_cost(window, cnoem.transform_from_euler_params(n + h))
            - cnoem.paper_cost(window, cnoem.transform_from_euler_params(n - h))
        ) / 2e-6
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


def test_translation_first_is_exact_for_the_true_rotation():
    trial, window = _trial(5)
    T_true = se3.inverse(trial.T_world_F_truth)
    T = cnoem.translation_first(window, T_true[:3, :3])
    np.testing.assert_allclose(T[:3, 3], T_true[:3, 3], atol=1e-8)


@pytest.mark.parametrize("seed", range(4))
def test_noise_free_solvers_recover_truth_from_the_papers_start_noise(seed):
    trial, window = _trial(10 + seed)
    assert _position_error_m(trial.T_world_F_nav, trial.T_world_F_truth) > 1.0  # a real 10 m-σ start
    sol = cnoem.solve_cnoem(window, trial.T_world_F_nav)
    assert sol.success and _position_error_m(sol.T_world_F, trial.T_world_F_truth) < 1e-6
    b = solve_bundle(window, trial.T_world_F_nav)
    assert b.success and _position_error_m(b.T_world_F, trial.T_world_F_truth) < 1e-6
    assert sol.iterations[-1].reproj_rms_px < 1e-6


def test_paper_update_lowers_its_cost_monotonically():
    trial, window = _trial(20, cell=GridCell(5.0, 0.2, 0.1, 1.5, 1.0))
    start = cnoem.translation_first(window, se3.inverse(trial.T_world_F_nav)[:3, :3])
    sol = cnoem.solve_cnoem(window, trial.T_world_F_nav, update="paper", max_iterations=300)
    assert sol.success and len(sol.iterations) == 302  # given start, translation first, 300 steps
    np.testing.assert_allclose(sol.iterations[0].T_F_world, se3.inverse(trial.T_world_F_nav), atol=1e-9)
    np.testing.assert_allclose(sol.iterations[1].T_F_world, start, atol=1e-9)
    costs = [it.cost for it in sol.iterations if it.accepted]
    assert all(b < a for a, b in zip(costs, costs[1:]))
    assert costs[-1] < 0.95 * costs[0]
    # The first-order update crawls along this ill-conditioned valley (cond ≈ 1e7): 300 steps
    # do not leave the translation-first start's neighbourhood (bench/bench_cnoem.py reports it).
    assert abs(_position_error_m(sol.T_world_F, trial.T_world_F_truth) - _position_error_m(se3.inverse(start), trial.T_world_F_truth)) < 0.05


def test_window_crlb_of_one_sighting_is_the_single_frame_crlb():
    trial, _ = _trial(6)
    s = trial.sightings[0]
    T_world_marker = se3.make(np.eye(3), [0.0, 0.0, 0.0])
    # One sighting, F = the camera, world = marker frame: T_F_world == T_cam_marker.
    T_cam_marker = se3.make(matrix_from_hpr(0.1, 2.0, 0.05), [0.2, -0.1, 4.0])
    points = auv.marker_corners_marker()
    px = auv.camera().project(se3.transform_points(T_cam_marker, points))
    window = CornerWindow.from_sightings([Sighting("7", "left", 0, points, px, s.K, np.eye(4))])
    np.testing.assert_allclose(
        window_crlb(window, se3.inverse(T_cam_marker) @ T_world_marker, 1.0),
        uncertainty.crlb(T_cam_marker, points, s.K, 1.0),
        rtol=1e-8,
    )


def test_bundle_rms_meets_the_window_crlb():
    cell = GridCell(5.0, 0.2, 0.1, 1.5, 1.0)
    rng = np.random.default_rng(7)
    geometry = auv.cycle_geometry(cell)
    errors = []
    for _ in range(150):
        trial = auv.draw_trial(geometry, cell.sigma_px, rng)
        window = CornerWindow.from_sightings(trial.sightings)
        sol = solve_bundle(window, trial.T_world_F_nav)
        errors.append(_position_error_m(sol.T_world_F, trial.T_world_F_truth))
    bound = position_bound_m(window_crlb(window, trial.T_world_F_truth, cell.sigma_px))
    ratio = np.sqrt(np.mean(np.square(errors))) / bound
    # 150 trials: the RMS of 3-D errors has a relative standard error ≈ 1/sqrt(2·150·3/…) ≈ 5 %;
    # an efficient estimator sits at 1, so [0.85, 1.15] is a 3σ band.
    assert 0.85 < ratio < 1.15


def test_ippe_baselines_are_exact_without_noise_and_nav_choice_uses_attitude():
    trial, _ = _trial(8)
    for T in (
        window_baselines.ippe_first(trial.sightings)[0],
        window_baselines.ippe_first_nav(trial.sightings, trial.T_world_F_nav)[0],
        window_baselines.ippe_mean_nav(trial.sightings, trial.T_world_F_nav)[0],
    ):
        assert _position_error_m(T, trial.T_world_F_truth) < 1e-6
    cands, _ = window_baselines.ippe_candidates(window_baselines.earliest(trial.sightings))
    # Navigation attitude = the second (mirror) candidate's: the nav choice must follow it.
    chosen, _ = window_baselines.ippe_first_nav(trial.sightings, cands[1])
    np.testing.assert_allclose(chosen, cands[1])


def test_multistart_switches_when_another_start_is_clearly_better():
    trial, window = _trial(9, sigma_px=1.0)
    # A start turned 180° in heading converges to a false minimum with a clearly higher cost.
    flipped = trial.T_world_F_nav @ se3.make(matrix_from_hpr(np.pi, 0.0, 0.0), [0.0, 0.0, 0.0])
    wrong = cnoem.solve_cnoem(window, flipped)
    right = cnoem.solve_cnoem(window, trial.T_world_F_nav)
    assert wrong.iterations[-1].cost > 1.2 * right.iterations[-1].cost  # ≫ 9σ² apart over ~380 residuals
    best = cnoem.solve_cnoem_multistart(window, [flipped, trial.T_world_F_nav])
    np.testing.assert_allclose(best.T_F_world, right.T_F_world)


def test_bad_input_is_refused_with_a_clear_error():
    with pytest.raises(WindowError, match="no marker sightings"):
        CornerWindow.from_sightings([])
    trial, window = _trial(1)
    bad = Sighting("7", "left", 0, np.zeros((4, 3)), np.full((4, 2), np.nan), np.eye(3), np.eye(4))
    with pytest.raises(WindowError, match="non-finite"):
        CornerWindow.from_sightings([bad])
    with pytest.raises(ValueError, match="unknown CNOEM update"):
        cnoem.solve_cnoem(window, trial.T_world_F_nav, update="adam")
    with pytest.raises(WindowError, match="rigid"):
        cnoem.solve_cnoem(window, np.full((4, 4), np.nan))


def test_normal_equations_stay_accurate_far_from_the_world_origin():
    # UTM-like coordinates: the quadratic form is built relative to the window centroid.
    trial, _ = _trial(11, sigma_px=1.0)
    shift = se3.make(np.eye(3), [4.0e5, 6.0e6, 0.0])
    sightings = [
        Sighting(s.marker_id, s.cam_name, s.frame_index, se3.transform_points(shift, s.points_world_m), s.pixels_px, s.K, s.T_F_cam)
        for s in trial.sightings
    ]
    window = CornerWindow.from_sightings(sightings)
    T = se3.inverse(shift @ trial.T_world_F_nav)
    cost, H, g = cnoem.ray_normal_equations(window, T)
    r, J = cnoem.ray_residuals_and_jacobian(window, T)
    assert cost == pytest.approx(0.5 * r @ r, rel=1e-6)
    np.testing.assert_allclose(g, J.T @ r, atol=1e-6 * np.abs(J.T @ r).max())
    sol = cnoem.solve_cnoem(window, shift @ trial.T_world_F_nav)
    reference = cnoem.solve_cnoem(CornerWindow.from_sightings(trial.sightings), trial.T_world_F_nav)
    np.testing.assert_allclose(sol.T_world_F[:3, 3] - shift[:3, 3], reference.T_world_F[:3, 3], atol=1e-6)


def test_multistart_keeps_the_navigation_solution_against_a_marginally_better_mirror():
    # Seed chosen where IPPE's mirror branch converges to a LOWER ray cost ≈14 m from the truth.
    cell = GridCell(15.0, 0.4, 0.2, 1.5, 1.5)
    geometry = auv.cycle_geometry(cell)
    rng = np.random.default_rng(0)
    for _ in range(3):
        trial = auv.draw_trial(geometry, cell.sigma_px, rng)
    window = CornerWindow.from_sightings(trial.sightings)
    cands, _ = window_baselines.ippe_candidates(window_baselines.earliest(trial.sightings))
    solutions = [cnoem.solve_cnoem(window, T) for T in (trial.T_world_F_nav, *cands)]
    mirror = min(solutions, key=lambda s: s.iterations[-1].cost)
    assert _position_error_m(mirror.T_world_F, trial.T_world_F_truth) > 5.0  # the mirror fits better...
    for reference in (None, trial.T_world_F_nav):
        chosen = cnoem.solve_cnoem_multistart(window, [trial.T_world_F_nav, *cands], T_reference_world_F=reference)
        assert _position_error_m(chosen.T_world_F, trial.T_world_F_truth) < 2.0  # ...but not by enough
