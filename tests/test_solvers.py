"""Pose solvers (agvviz.solvers) against synthetic truth.

Noise-free pixels are projected with the true pose, so every solver must return that pose up
to round-off. LM is checked against finite differences and on noisy data against P4P.
"""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.geometry import se3, so3
from agvviz.geometry.euler import Rx, Rz
from agvviz.geometry.plane import square_points_marker
from agvviz.solvers import SOLVER_NAMES, SolverOptions, solve
from agvviz.solvers.lm import reprojection_rms_px, residuals_and_jacobian
from agvviz.solvers.p4p import solve_p4p

# --- synthetic scenes --------------------------------------------------------------------

K_AGV = np.array([[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]])  # 1280×1024
K_PAPER = np.array([[1562.5, 0.0, 0.0], [0.0, 1562.5, 0.0], [0.0, 0.0, 1.0]])  # paper 000 §6
R_FACING = np.diag([1.0, -1.0, -1.0])  # marker face toward the camera, marker y up the image


def tilted_view(tilt_deg, distance_m, inplane_deg, tilt_axis_deg=0.0, offset_m=(0.0, 0.0)):
    """T_cam_marker for a code ``distance_m`` ahead, its normal tilted by ``tilt_deg`` from the
    optical axis about an in-plane axis at ``tilt_axis_deg``, then turned by ``inplane_deg``
    about its own normal."""
    R = (
        R_FACING
        @ Rz(np.radians(tilt_axis_deg))
        @ Rx(np.radians(tilt_deg))
        @ Rz(np.radians(inplane_deg))
    )
    return se3.make(R, [offset_m[0], offset_m[1], distance_m])


def agv_view():
    """Floor code 1 m ahead of a camera 1.5 m high that looks at it (AGV body: x right,
    y forward, z up; camera x = body x)."""
    cam_pos = np.array([0.0, 0.0, 1.5])
    target = np.array([0.0, 1.0, 0.0])
    z_cam = (target - cam_pos) / np.linalg.norm(target - cam_pos)
    x_cam = np.array([1.0, 0.0, 0.0])
    T_world_cam = se3.make(np.stack([x_cam, np.cross(z_cam, x_cam), z_cam], axis=1), cam_pos)
    T_world_marker = se3.make(np.eye(3), target)
    return se3.inverse(T_world_cam) @ T_world_marker


# (id, K, T_cam_marker, code side m, check pixels inside the 1280×1024 image)
SCENES = [
    ("paper_s6_t2", K_PAPER, se3.make(np.eye(3), [0.05, 0.05, 2.0]), 2 * 0.1333, False),
    ("paper_s6_t4", K_PAPER, se3.make(np.eye(3), [0.05, 0.05, 4.0]), 2 * 0.2667, False),
    ("agv_floor", K_AGV, agv_view(), 0.5, True),
    ("tilt20_d1", K_AGV, tilted_view(20, 1.0, 0.0), 0.5, True),
    ("tilt45_d2_rot180", K_AGV, tilted_view(45, 2.0, 180.0, 30.0, (0.2, -0.1)), 0.5, True),
    ("tilt70_d1.5_rot90", K_AGV, tilted_view(70, 1.5, 90.0, -60.0), 0.5, True),
    ("tilt60_d4_rot-135", K_AGV, tilted_view(60, 4.0, -135.0, 120.0, (-0.5, 0.4)), 0.5, True),
    ("tilt30_d3_rot180", K_AGV, tilted_view(30, 3.0, 180.0, 90.0), 0.5, True),
    # Seen from behind (marker z away from the camera), off the optical axis: the one kind of
    # tilted view OpenCV's EPnP solves for planar points (see EPNP_WRONG).
    ("tilt45_back_d2", K_AGV, se3.make(Rz(0.3) @ Rx(np.radians(45)), [0.1, -0.05, 2.0]), 0.5, True),
]

#: Scenes where OpenCV 5.0's SOLVEPNP_EPNP returns a wrong pose with success=True on exact
#: planar input: in most views where the marker's z axis points at the camera (the rotation
#: comes back off by twice the tilt; tilt70_d1.5_rot90 happens to survive), and when the
#: points' centroid is on the optical axis (translation off by cm to 1e6 m). Strict xfail:
#: the test fails if OpenCV ever fixes this.
EPNP_WRONG = {
    "agv_floor",
    "tilt20_d1",
    "tilt45_d2_rot180",
    "tilt60_d4_rot-135",
    "tilt30_d3_rot180",
}


def project(K, T_cam_marker, points_marker_m):
    w = se3.transform_points(T_cam_marker, points_marker_m)
    assert np.all(w[:, 2] > 0)
    p = w @ K.T
    return p[:, :2] / p[:, 2:3]


def pose_errors(T_est, T_true):
    """(rotation error rad, translation error m)."""
    rot = float(np.linalg.norm(so3.log(T_est[:3, :3].T @ T_true[:3, :3])))
    return rot, float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


def noisy_agv_problem(rng, n_points, sigma_px=0.5):
    T_true = agv_view()
    pts = square_points_marker(0.5, with_midpoints=n_points == 8)
    px = project(K_AGV, T_true, pts) + rng.normal(0.0, sigma_px, (n_points, 2))
    return T_true, pts, px


# --- exactness on noise-free data ------------------------------------------------------

CASES = [
    pytest.param(
        name,
        scene,
        n,
        id=f"{name}-{scene[0]}-{n}pts",
        marks=[pytest.mark.xfail(strict=True, reason="OpenCV EPnP wrong on planar points")]
        if name == "epnp" and scene[0] in EPNP_WRONG
        else [],
    )
    for name in SOLVER_NAMES
    for scene in SCENES
    for n in (4, 8)
    if not (name == "ippe_square" and n == 8) and name != "planar"  # planar: test_planar.py
]


@pytest.mark.parametrize("name, scene, n_points", CASES)
def test_every_solver_is_exact_on_noise_free_pixels(name, scene, n_points):
    _, K, T_true, side_m, in_image = scene
    pts = square_points_marker(side_m, with_midpoints=n_points == 8)
    px = project(K, T_true, pts)
    if in_image:  # the scene is a view a real 1280×1024 camera could have
        assert np.all((px > -0.5) & (px < [1279.5, 1023.5]))
    result = solve(name, pts, px, K)
    assert result.success, result.reason
    rot_err, trans_err = pose_errors(result.T_cam_marker, T_true)
    # Every solver is exact in exact arithmetic; 1e-6 rad / 1e-6 m leaves room for OpenCV's
    # iterative solvers (SOLVEPNP_ITERATIVE stops at ≈1e-8). P4P is closed form and LM starts
    # from it, so they must stay at round-off level (pixels ~1e3, depths ~1: ≈1e-12).
    tol = 1e-10 if name in ("p4p", "lm") else 1e-6
    assert rot_err < tol and trans_err < tol, (rot_err, trans_err)
    assert result.reproj_rms_px < 1e-4  # ITERATIVE reaches ≈5e-7 px
    assert (len(result.iterations) > 0) == (name == "lm")


def test_ippe_square_uses_the_first_four_points_and_refuses_other_squares():
    T_true = tilted_view(40, 2.0, 30.0)
    pts = square_points_marker(0.5, with_midpoints=True)
    px = project(K_AGV, T_true, pts)
    result = solve("ippe_square", pts, px, K_AGV)
    assert result.success and pose_errors(result.T_cam_marker, T_true)[1] < 1e-6
    skewed = pts.copy()
    skewed[2, 0] += 0.01  # BR moved 1 cm: no longer the canonical square
    result = solve("ippe_square", skewed, project(K_AGV, T_true, skewed), K_AGV)
    assert not result.success and result.reason.startswith("not a canonical square")
    shifted = pts + [0.1, 0.0, 0.0]  # a square, but not centred on the origin
    result = solve("ippe_square", shifted, project(K_AGV, T_true, shifted), K_AGV)
    assert not result.success and result.reason.startswith("not a canonical square")


def test_p4p_step_by_step_against_the_paper_eqs():
    """Rebuild eqs 7–21 literally for the paper's §6 case and compare with solve_p4p."""
    T_true = se3.make(np.eye(3), [0.05, 0.05, 2.0])
    pts = square_points_marker(0.2666)
    px = project(K_PAPER, T_true, pts)
    q = np.c_[pts[:, :2], np.ones(4)].T
    p = np.c_[px, np.ones(4)].T
    v = np.linalg.inv(p[:, :3]) @ p[:, 3]
    r = np.linalg.inv(q[:, :3]) @ q[:, 3]
    W = np.diag([r[2] / r[0] * v[0] / v[2], r[2] / r[1] * v[1] / v[2], 1.0])
    g = np.linalg.inv(K_PAPER) @ p[:, :3] @ W @ np.linalg.inv(q[:, :3])
    n1, n2 = np.linalg.norm(g[:, 0]), np.linalg.norm(g[:, 1])
    s = (n1 + n2) / (n1**2 + n2**2)
    # s is the depth of point 3 (eq 15: H = z'_3 T, the paper prints 1/z'_3).
    assert s == pytest.approx(se3.transform_points(T_true, pts)[2, 2], rel=1e-12)
    T, reason = solve_p4p(pts, px, K_PAPER)
    assert reason == ""
    np.testing.assert_allclose(T[:3, 3], s * g[:, 2], atol=1e-12)
    np.testing.assert_allclose(T[:3, :2], s * g[:, :2], atol=1e-12)


def test_p4p_refuses_a_plane_through_the_camera():
    # Two corners in front of the camera, two behind: no plane in front explains the pixels.
    T = se3.make(so3.exp([0.0, np.pi / 2 - 0.2, 0.0]), [0.0, 0.0, 0.05])
    pts = square_points_marker(0.5)
    w = se3.transform_points(T, pts)
    assert np.sum(w[:, 2] > 0) == 2
    px = (w @ K_AGV.T)[:, :2] / w[:, 2:3]
    T_p4p, reason = solve_p4p(pts, px, K_AGV)
    assert T_p4p is None and reason == "point behind camera"
    assert solve("p4p", pts, px, K_AGV).reason == "point behind camera"


# --- LM -----------------------------------------------------------------------------------


@pytest.mark.parametrize("objective", ["depth", "pixel"])
def test_lm_jacobian_matches_central_differences(objective):
    rng = np.random.default_rng(7)
    T_true, pts, px = noisy_agv_problem(rng, 8, sigma_px=2.0)
    T = se3.exp(rng.normal(0.0, 0.02, 6)) @ T_true  # away from the optimum: f ≠ 0
    _, J = residuals_and_jacobian(T, pts, px, K_AGV, objective)
    eps = 1e-6
    J_fd = np.empty_like(J)
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        f_plus, _ = residuals_and_jacobian(se3.exp(d) @ T, pts, px, K_AGV, objective)
        f_minus, _ = residuals_and_jacobian(se3.exp(-d) @ T, pts, px, K_AGV, objective)
        J_fd[:, k] = (f_plus - f_minus) / (2 * eps)
    # Central differences: truncation O(eps²) ≈ 1e-12 relative, round-off ≈ 1e-16·|f|/eps.
    np.testing.assert_allclose(J, J_fd, rtol=0, atol=1e-6 * np.max(np.abs(J)))


def test_depth_residual_is_depth_times_pixel_error():
    rng = np.random.default_rng(3)
    T_true, pts, px = noisy_agv_problem(rng, 8, sigma_px=1.0)
    f_depth, _ = residuals_and_jacobian(T_true, pts, px, K_AGV, "depth")
    f_pixel, _ = residuals_and_jacobian(T_true, pts, px, K_AGV, "pixel")
    z = se3.transform_points(T_true, pts)[:, 2]
    np.testing.assert_allclose(f_depth, np.repeat(z, 2) * f_pixel, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("objective", ["depth", "pixel"])
def test_lm_iterations_start_at_p4p_and_never_increase_cost(objective):
    rng = np.random.default_rng(11)
    options = SolverOptions(objective=objective)
    for _ in range(20):
        _, pts, px = noisy_agv_problem(rng, 8, sigma_px=1.0)
        result = solve("lm", pts, px, K_AGV, options)
        assert result.success, result.reason
        its = result.iterations
        T_p4p = solve("p4p", pts, px, K_AGV).T_cam_marker
        f0, _ = residuals_and_jacobian(T_p4p, pts, px, K_AGV, objective)
        assert its[0].cost == pytest.approx(0.5 * f0 @ f0, rel=1e-12)
        assert its[0].reproj_rms_px == pytest.approx(reprojection_rms_px(T_p4p, pts, px, K_AGV))
        costs = [it.cost for it in its]
        assert all(b <= a for a, b in zip(costs, costs[1:]))
        assert any(it.accepted for it in its[1:])
        assert its[-1].reproj_rms_px == pytest.approx(result.reproj_rms_px, rel=1e-12)
        assert len(its) <= options.max_iterations + 1


def test_lm_pixel_objective_is_a_local_minimum_of_reprojection():
    rng = np.random.default_rng(5)
    _, pts, px = noisy_agv_problem(rng, 8, sigma_px=1.0)
    result = solve("lm", pts, px, K_AGV, SolverOptions(objective="pixel"))
    f, J = residuals_and_jacobian(result.T_cam_marker, pts, px, K_AGV, "pixel")
    # Gradient Jᵀf vanishes at the optimum (relative to ‖J‖·‖f‖).
    assert np.linalg.norm(J.T @ f) < 1e-9 * np.linalg.norm(J) * np.linalg.norm(f)


@pytest.mark.parametrize("n_points", [4, 8])
def test_lm_is_at_least_as_accurate_as_p4p_on_noisy_pixels(n_points):
    rng = np.random.default_rng(2024 + n_points)
    errors = {"p4p": [], "lm": []}
    for _ in range(200):
        T_true, pts, px = noisy_agv_problem(rng, n_points, sigma_px=0.5)
        cam_in_marker_true = se3.inverse(T_true)[:3, 3]
        for name in errors:
            result = solve(name, pts, px, K_AGV)
            assert result.success, result.reason
            cam_in_marker = se3.inverse(result.T_cam_marker)[:3, 3]
            errors[name].append(np.linalg.norm(cam_in_marker - cam_in_marker_true))
    assert np.mean(errors["lm"]) <= np.mean(errors["p4p"])


def test_lm_returns_its_best_pose_when_out_of_iterations():
    rng = np.random.default_rng(1)
    _, pts, px = noisy_agv_problem(rng, 8, sigma_px=1.0)
    start = solve("p4p", pts, px, K_AGV)
    result = solve("lm", pts, px, K_AGV, SolverOptions(max_iterations=1))
    assert result.success and len(result.iterations) == 2
    # One step from the P4P start: no worse than the start, not yet the optimum.
    assert result.iterations[1].cost <= result.iterations[0].cost
    converged = solve("lm", pts, px, K_AGV)
    assert converged.reproj_rms_px <= result.reproj_rms_px <= start.reproj_rms_px


# --- bad input ----------------------------------------------------------------------------


def _good_input():
    pts = square_points_marker(0.5, with_midpoints=True)
    return pts, project(K_AGV, agv_view(), pts)


@pytest.mark.parametrize("name", SOLVER_NAMES)
def test_bad_input_fails_with_a_reason(name):
    pts, px = _good_input()
    nan_px = px.copy()
    nan_px[2, 1] = np.nan
    cases = [
        ((pts, nan_px, K_AGV), "non-finite input"),
        ((pts[:3], px[:3], K_AGV), "fewer than 4 points"),
        ((pts, np.c_[np.linspace(0, 500, 8), np.linspace(10, 300, 8)], K_AGV),
         "degenerate: pixels collinear"),
        ((pts, np.tile(px[:1], (8, 1)), K_AGV), "degenerate: pixels collinear"),
        ((pts, px[:7], K_AGV), "shape mismatch"),
        ((pts[:, :2], px, K_AGV), "shape mismatch"),
        ((pts, px, K_AGV[:2]), "shape mismatch"),
        ((pts, px, np.diag([1000.0, 1000.0, 0.0])), "invalid camera matrix"),
        ((pts + [0.0, 0.0, 0.01], px, K_AGV), "marker points are not on the z = 0 plane"),
        ((pts * [1.0, 0.0, 0.0], px, K_AGV), "degenerate: marker points collinear"),
    ]
    for args, reason in cases:
        result = solve(name, *args)
        assert not result.success and result.T_cam_marker is None, reason
        assert result.reason.startswith(reason), (result.reason, reason)
        assert result.reproj_rms_px is None


def test_p4p_needs_its_first_four_pixels_in_general_position():
    pts, px = _good_input()
    px = px.copy()
    px[3] = 0.5 * (px[0] + px[2])  # BL on the TL–BR diagonal: a collinear triple
    assert solve("p4p", pts, px, K_AGV).reason == "degenerate: pixels collinear"


def test_unknown_names_raise_with_the_valid_ones():
    pts, px = _good_input()
    with pytest.raises(ValueError, match="valid solvers: p4p, lm, ippe"):
        solve("dlt", pts, px, K_AGV)
    with pytest.raises(ValueError, match="depth, pixel"):
        solve("lm", pts, px, K_AGV, SolverOptions(objective="mahalanobis"))


def test_lm_starts_from_ippe_when_p4p_cannot():
    # The first three points lie on the top edge: P4P refuses, LM starts from IPPE instead.
    T_true = tilted_view(35, 2.0, 60.0, 20.0, (0.1, 0.1))
    square = square_points_marker(0.5, with_midpoints=True)
    pts = square[[0, 4, 1, 2, 3, 5, 6, 7]]  # TL, top-mid, TR, BR, BL, right, bottom, left
    px = project(K_AGV, T_true, pts)
    assert solve("p4p", pts, px, K_AGV).reason == "degenerate: pixels collinear"
    result = solve("lm", pts, px, K_AGV)
    assert result.success, result.reason
    assert max(pose_errors(result.T_cam_marker, T_true)) < 1e-9
