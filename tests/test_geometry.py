"""agvviz.geometry against independent references: scipy's Rotation and expm, OpenCV's
projectPoints, and central finite differences. Angles sweep the awkward cases: 0, 1e-9,
the small-angle switch (1e-6), π/2, π − 1e-3 (near-π switch), π − 1e-7, π."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from agvviz.geometry import euler, se3, so3
from agvviz.geometry.camera import PinholeCamera
from agvviz.geometry.plane import (
    DegenerateGeometryError,
    marker_frame_from_corners,
    square_points_marker,
)

# Identities on entries of magnitude ≲ 1 (rotation matrices, unit quaternions, sines and
# cosines) are compared to ULPS ulps × the magnitude: a handful of roundings per entry, in an
# order that depends on the BLAS kernel (OPENBLAS_CORETYPE) and on numpy/scipy's own
# summation order. The expressions are well conditioned (no cancellation beyond a few terms),
# so "a few hundred ulps" bounds them on every machine while still catching any wrong term
# (which is ≥ 1e-9 for the angles swept here).
EPS = np.finfo(float).eps
ULPS = 256
TOL_UNIT = ULPS * EPS  # ≈ 5.7e-14

ANGLES_RAD = [0.0, 1e-9, 1e-7, 0.9e-6, 1.1e-6, 1e-3, 0.5, np.pi / 2, 3.0,
              np.pi - 1e-3, np.pi - 1.1e-3, np.pi - 1e-7, np.pi]


def random_axes(seed, n=20):
    a = np.random.default_rng(seed).normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def rot_vectors(seed=0):
    """Rotation vectors at every sweep angle along random axes and the coordinate axes."""
    axes = np.vstack([np.eye(3), random_axes(seed)])
    return [angle * axis for angle in ANGLES_RAD for axis in axes]


def random_poses(seed, n=20):
    rng = np.random.default_rng(seed)
    return [se3.make(Rotation.random(random_state=rng).as_matrix(), rng.normal(0, 2, 3))
            for _ in range(n)]


# --- SO(3) --------------------------------------------------------------------------------


def test_hat_vee():
    rng = np.random.default_rng(1)
    for _ in range(20):
        w, v = rng.normal(size=3), rng.normal(size=3)
        W = so3.hat(w)
        np.testing.assert_allclose(W @ v, np.cross(w, v), atol=TOL_UNIT * np.linalg.norm(w) * np.linalg.norm(v))
        np.testing.assert_array_equal(W, -W.T)
        np.testing.assert_array_equal(so3.vee(W), w)
        xi = rng.normal(size=6)
        np.testing.assert_array_equal(se3.vee(se3.hat(xi)), xi)


def test_so3_exp_matches_scipy_and_expm():
    for phi in rot_vectors(2):
        R = so3.exp(phi)
        # Both references are accurate to a few ulp of entries of size ≤ 1 (expm: Padé with
        # scaling and squaring through BLAS, a few tens of ulps).
        np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=TOL_UNIT)
        np.testing.assert_allclose(R, expm(so3.hat(phi)), atol=TOL_UNIT)


@pytest.mark.parametrize("source", ["scipy", "so3.exp"])
def test_so3_log_inverts_exp(source):
    for phi in rot_vectors(3):
        R = Rotation.from_rotvec(phi).as_matrix() if source == "scipy" else so3.exp(phi)
        log_R = so3.log(R)
        # exp(log(R)) reproduces R. Near π − 1e-3 the axis comes from R − Rᵀ = 2 sin θ·a,
        # whose 1e-16 round-off is amplified by 1/sin θ = 1e3: hence 1e-12, not 1e-15.
        np.testing.assert_allclose(so3.exp(log_R), R, atol=1e-12)
        theta = np.linalg.norm(phi)
        if theta > np.pi - 1e-9:  # at π, φ and −φ are the same rotation
            assert min(np.linalg.norm(log_R - phi), np.linalg.norm(log_R + phi)) < 1e-12
        else:
            np.testing.assert_allclose(log_R, phi, atol=1e-12)
            np.testing.assert_allclose(log_R, Rotation.from_matrix(R).as_rotvec(), atol=1e-12)
        assert np.linalg.norm(log_R) <= np.pi * (1 + TOL_UNIT)


def test_left_jacobian_against_finite_differences():
    eps = 1e-6
    for phi in rot_vectors(4)[::3]:
        J_l = so3.left_jacobian(phi)
        # Exp(φ + ε) ≈ Exp(J_l ε)·Exp(φ): column k is d/dε_k Log(Exp(φ + ε e_k)·Exp(φ)ᵀ).
        J_fd = np.empty((3, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = eps
            plus = so3.log(so3.exp(phi + e) @ so3.exp(phi).T)
            minus = so3.log(so3.exp(phi - e) @ so3.exp(phi).T)
            J_fd[:, k] = (plus - minus) / (2 * eps)
        # Central differences: O(eps²) truncation, ≈1e-16/eps round-off → 1e-8 is generous.
        np.testing.assert_allclose(J_l, J_fd, atol=1e-8)
        np.testing.assert_allclose(so3.left_jacobian_inv(phi) @ J_l, np.eye(3), atol=1e-12)


# --- SE(3) --------------------------------------------------------------------------------


def tangent_vectors(seed=5):
    rng = np.random.default_rng(seed)
    return [np.concatenate([rng.normal(0, 2, 3), phi]) for phi in rot_vectors(seed)[::2]]


def test_se3_exp_matches_expm_and_log_inverts_it():
    for xi in tangent_vectors():
        T = se3.exp(xi)
        np.testing.assert_allclose(T, expm(se3.hat(xi)), atol=1e-13)
        assert se3.is_rigid(T)
        np.testing.assert_allclose(se3.exp(se3.log(T)), T, atol=1e-11)  # 1e-12 near π × |ρ|
        if np.linalg.norm(xi[3:]) < np.pi - 1e-9:
            np.testing.assert_allclose(se3.log(T), xi, atol=1e-11)


def test_se3_exp_is_so3_exp_and_left_jacobian():
    """se3.exp writes so3.exp and so3.left_jacobian out in scalar arithmetic: the same
    formulas, so the same numbers up to the order of a few roundings per entry."""
    for xi in tangent_vectors():
        T = se3.exp(xi)
        np.testing.assert_allclose(T[:3, :3], so3.exp(xi[3:]), atol=TOL_UNIT)
        np.testing.assert_allclose(T[:3, 3], so3.left_jacobian(xi[3:]) @ xi[:3], atol=TOL_UNIT * np.abs(xi[:3]).max())


def test_batched_forms_equal_the_single_ones():
    """so3.hat_batch, se3.exp_batch, se3.transform_points_batch and the stacked
    J_point_wrt_left_perturbation: per row the single function's arithmetic, so equal to it up
    to a few roundings (np.sin against math.sin may differ by an ulp)."""
    xis = np.array(tangent_vectors())
    W = so3.hat_batch(xis[:, 3:])
    T = se3.exp_batch(xis)
    assert W.shape == (len(xis), 3, 3) and T.shape == (len(xis), 4, 4)
    for k, xi in enumerate(xis):
        np.testing.assert_array_equal(W[k], so3.hat(xi[3:]))
        np.testing.assert_allclose(T[k], se3.exp(xi), atol=TOL_UNIT * max(1.0, np.abs(xi[:3]).max()))
    np.testing.assert_array_equal(so3.hat_batch(xis[:6, 3:].reshape(2, 3, 3))[1, 2], so3.hat(xis[5, 3:]))
    rng = np.random.default_rng(11)
    poses = np.array(random_poses(11, n=4))
    points = rng.normal(size=(4, 5, 3))
    moved = se3.transform_points_batch(poses, points)
    shared = se3.transform_points_batch(poses, points[0])
    J = se3.J_point_wrt_left_perturbation(moved)
    assert J.shape == (4, 5, 3, 6)
    for k in range(4):
        scale = TOL_UNIT * max(1.0, np.abs(poses[k]).max()) * max(1.0, np.abs(points).max())
        np.testing.assert_allclose(moved[k], se3.transform_points(poses[k], points[k]), atol=scale)
        np.testing.assert_allclose(shared[k], se3.transform_points(poses[k], points[0]), atol=scale)
        np.testing.assert_array_equal(J[k], se3.J_point_wrt_left_perturbation(moved[k]))
    assert se3.J_point_wrt_left_perturbation(np.array([1.0, 2.0, 3.0])).shape == (1, 3, 6)
    assert np.all(np.isnan(se3.exp(np.array([np.inf, 0, 0, 0, 0, 0]))))


def test_inverse_and_transform_points():
    rng = np.random.default_rng(6)
    for T in random_poses(6):
        scale = max(1.0, np.abs(T).max())  # translation entries are metres, not ≤ 1
        np.testing.assert_allclose(se3.inverse(T) @ T, np.eye(4), atol=TOL_UNIT * scale)
        p = rng.normal(size=(5, 3))
        np.testing.assert_allclose(se3.transform_points(T, p), (T @ np.c_[p, np.ones(5)].T).T[:, :3],
                                   atol=TOL_UNIT * scale * max(1.0, np.abs(p).max()))


def test_adjoint_identity():
    rng = np.random.default_rng(7)
    for T in random_poses(7):
        xi = rng.normal(0, 0.7, 6)
        np.testing.assert_allclose(T @ se3.exp(xi) @ se3.inverse(T),
                                   se3.exp(se3.adjoint(T) @ xi), atol=1e-12)


def test_point_jacobian_wrt_left_perturbation():
    rng = np.random.default_rng(8)
    eps = 1e-6
    for T in random_poses(8, n=5):
        p = se3.transform_points(T, rng.normal(size=(4, 3)))
        J = se3.J_point_wrt_left_perturbation(p)
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            fd = (se3.transform_points(se3.exp(d), p) - se3.transform_points(se3.exp(-d), p)) / (2 * eps)
            np.testing.assert_allclose(J[:, :, k], fd, atol=1e-8)


def test_is_rigid_rejects_non_rigid():
    T = se3.make(so3.exp([0.1, 0.2, 0.3]), [1, 2, 3])
    assert se3.is_rigid(T)
    assert not se3.is_rigid(T @ np.diag([1, 1, -1, 1]))  # reflection
    assert not se3.is_rigid(T * 1.01)
    bad = T.copy()
    bad[0, 3] = np.nan
    assert not se3.is_rigid(bad)


def test_quaternion_round_trip_against_scipy():
    rng = np.random.default_rng(9)
    rotations = [Rotation.from_rotvec(phi) for phi in rot_vectors(9)[::2]]
    rotations += list(Rotation.random(50, random_state=rng))
    # Half-turns about each axis and a diagonal: exercise every branch of Shepperd's method.
    half_turn_axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1]], float)
    rotations += [Rotation.from_rotvec(np.pi * a / np.linalg.norm(a)) for a in half_turn_axes]
    for rot in rotations:
        R = rot.as_matrix()
        q = se3.to_quaternion_xyzw(R)
        q_ref = rot.as_quat()  # scipy: scalar last (x, y, z, w)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < TOL_UNIT
        assert min(np.linalg.norm(q - q_ref), np.linalg.norm(q + q_ref)) < TOL_UNIT
        t = rng.normal(size=3)
        T = se3.from_quaternion_xyzw(q, t)
        np.testing.assert_allclose(T[:3, :3], R, atol=TOL_UNIT)
        np.testing.assert_array_equal(T[:3, 3], t)


# --- Euler Z-X-Y --------------------------------------------------------------------------


def test_matrix_from_hpr_is_intrinsic_zxy():
    rng = np.random.default_rng(10)
    for h, p, r in rng.uniform(-np.pi, np.pi, (50, 3)):
        np.testing.assert_allclose(euler.matrix_from_hpr(h, p, r),
                                   Rotation.from_euler("ZXY", [h, p, r]).as_matrix(), atol=TOL_UNIT)
    # Paper 000 eq 38, element by element.
    h, p, r = 0.3, -0.4, 1.1
    ch, sh, cp, sp, cr, sr = np.cos(h), np.sin(h), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    eq38 = [[ch * cr - sh * sp * sr, -sh * cp, ch * sr + sh * cr * sp],
            [sh * cr + ch * sp * sr, ch * cp, sh * sr - ch * sp * cr],
            [-cp * sr, sp, cp * cr]]
    np.testing.assert_allclose(euler.matrix_from_hpr(h, p, r), eq38, atol=TOL_UNIT)


def test_hpr_round_trip_away_from_gimbal():
    rng = np.random.default_rng(11)
    # |pitch| ≤ π/2 − 0.01 keeps |r32| ≤ 0.99995 < the default threshold 0.999999.
    hpr = np.c_[rng.uniform(-np.pi, np.pi, 200), rng.uniform(-np.pi / 2 + 0.01, np.pi / 2 - 0.01, 200),
                rng.uniform(-np.pi, np.pi, 200)]
    hpr = np.vstack([hpr, [[0, 0, 0], [np.pi, 0, 0], [0, 0, np.pi], [1e-9, -1e-9, 1e-9]]])
    for h, p, r in hpr:
        out = euler.hpr_from_matrix(euler.matrix_from_hpr(h, p, r))
        # Compare as angles; cos θ ≥ 0.01 amplifies entry round-off by ≤ 100.
        assert np.max(np.abs(euler.wrap_angle_rad(np.subtract(out, [h, p, r])))) < 1e-12
        assert all(-np.pi < a <= np.pi for a in (out[0], out[2]))


def test_hpr_angles_stay_in_the_documented_range():
    # atan2(-0.0, -1) = -π: the heading/roll of a half turn must still come out as +π.
    assert euler.hpr_from_matrix(np.diag([-1.0, -1.0, 1.0])) == (np.pi, 0.0, 0.0)
    assert euler.hpr_from_matrix(np.diag([-1.0, 1.0, -1.0])) == (0.0, 0.0, np.pi)


@pytest.mark.parametrize("pitch_sign", [1.0, -1.0])
def test_gimbal_rule_of_eq_57(pitch_sign):
    rng = np.random.default_rng(12)
    for h, r in rng.uniform(-np.pi, np.pi, (50, 2)):
        R = euler.matrix_from_hpr(h, pitch_sign * np.pi / 2, r)
        out = euler.hpr_from_matrix(R)
        # Heading is set to 0 and the roll carries ψ + γ at +π/2 (eq 48), γ − ψ at −π/2 (eq 53).
        expected_roll = r + h if pitch_sign > 0 else r - h
        assert out[0] == 0.0 and out[1] == pitch_sign * np.pi / 2
        assert abs(euler.wrap_angle_rad(out[2] - expected_roll)) < 1e-12
        np.testing.assert_allclose(euler.matrix_from_hpr(*out), R, atol=1e-12)


def test_gimbal_threshold_is_a_parameter():
    threshold = 0.99
    h, r = 0.7, -0.4
    below = euler.matrix_from_hpr(h, np.arcsin(threshold - 1e-9), r)
    out = euler.hpr_from_matrix(below, gimbal_threshold=threshold)
    np.testing.assert_allclose(out, [h, np.arcsin(threshold - 1e-9), r], atol=1e-12)
    above = euler.matrix_from_hpr(h, -np.arcsin(threshold + 1e-9), r)
    out = euler.hpr_from_matrix(above, gimbal_threshold=threshold)
    assert out[:2] == (0.0, -np.pi / 2)
    # The default threshold treats the same matrix normally.
    assert euler.hpr_from_matrix(above)[0] == pytest.approx(h, abs=1e-12)
    for bad in (0.0, 1.0, 1.5):
        with pytest.raises(ValueError, match="gimbal_threshold"):
            euler.hpr_from_matrix(above, gimbal_threshold=bad)


def test_wrap_angle():
    assert euler.wrap_angle_rad(-np.pi) == np.pi
    assert euler.wrap_angle_rad(3 * np.pi) == pytest.approx(np.pi)
    np.testing.assert_allclose(euler.wrap_angle_rad(np.array([0.0, 2 * np.pi + 0.1, -0.1])),
                               [0.0, 0.1, -0.1], atol=TOL_UNIT * 2 * np.pi)  # 2π + 0.1 − 2π: ulps of 2π


# --- camera -------------------------------------------------------------------------------

K_CAM = np.array([[1000.0, 0.0, 639.5], [0.0, 1010.0, 511.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.28, 0.07, 1e-3, -5e-4, -0.008])


def points_in_view(seed, n=200):
    """Camera-frame points within a ±35° × ±30° field of view, 0.5–5 m deep."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.5, 5.0, n)
    return np.c_[rng.uniform(-0.7, 0.7, n) * z, rng.uniform(-0.58, 0.58, n) * z, z]


def test_project_matches_opencv_with_distortion():
    cam = PinholeCamera(K_CAM, DIST, 1280, 1024)
    pts = points_in_view(13)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K_CAM, DIST)
    np.testing.assert_allclose(cam.project(pts), ref.reshape(-1, 2), atol=1e-9)
    assert cam.has_distortion and not cam.without_distortion().has_distortion


def test_project_with_jacobian_against_finite_differences():
    skewed = K_CAM.copy()
    skewed[0, 1] = 2.0
    for cam in (PinholeCamera(K_CAM, DIST), PinholeCamera(skewed, DIST), PinholeCamera(K_CAM)):
        pts = points_in_view(14, n=30)
        px, J = cam.project_with_jacobian(pts)
        np.testing.assert_array_equal(px, cam.project(pts))
        eps = 1e-6
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            fd = (cam.project(pts + d) - cam.project(pts - d)) / (2 * eps)
            # J ~ 1e3 px/m; central-difference error ≈ 1e-16·1e3/eps + O(eps²) ≈ 1e-7 px/m.
            np.testing.assert_allclose(J[:, :, k], fd, atol=1e-5)


def test_undistort_pixels_inverts_project():
    cam = PinholeCamera(K_CAM, DIST, 1280, 1024)
    pts = points_in_view(15)
    ideal = cam.without_distortion().project(pts)
    np.testing.assert_allclose(cam.undistort_pixels(cam.project(pts)), ideal, atol=1e-9)
    rays = cam.rays(cam.project(pts))
    np.testing.assert_allclose(rays, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-12)
    # OpenCV agrees once iterated to convergence (its default 5 iterations are ≈0.5 px off
    # at this image's corners, k1 = -0.28).
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPoints(cam.project(pts).reshape(-1, 1, 2), K_CAM, DIST, None, K_CAM,
                              criteria=criteria)
    np.testing.assert_allclose(cam.undistort_pixels(cam.project(pts)), ref.reshape(-1, 2), atol=1e-8)


def test_camera_refuses_bad_intrinsics():
    with pytest.raises(ValueError, match="NaN"):
        PinholeCamera(np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="invalid camera matrix"):
        PinholeCamera(np.diag([1000.0, -1000.0, 1.0]))
    with pytest.raises(ValueError, match=r"at most 5 \(plumb_bob\) or exactly 8 \(rational_polynomial\)"):
        PinholeCamera(K_CAM, np.zeros(6))
    # 8 coefficients are the rational model; with k4..k6 = 0 it is stored as plumb_bob
    assert PinholeCamera(K_CAM, np.zeros(8)).dist.size == 5
    assert PinholeCamera(K_CAM, [0, 0, 0, 0, 0, 0.1, 0, 0]).is_rational


# --- marker plane -------------------------------------------------------------------------


@pytest.mark.parametrize("with_midpoints", [False, True])
def test_marker_frame_from_corners_recovers_the_square(with_midpoints):
    pts_marker = square_points_marker(0.53, with_midpoints)
    for T_world_marker in random_poses(16, n=10) + [se3.make(np.eye(3), [1.0, 2.0, 0.0])]:
        corners_world = se3.transform_points(T_world_marker, pts_marker)
        T, pts = marker_frame_from_corners(corners_world)
        np.testing.assert_allclose(T, T_world_marker, atol=1e-12)
        np.testing.assert_allclose(pts, pts_marker, atol=1e-12)
        assert np.all(pts[:, 2] == 0.0)


def test_marker_frame_from_corners_refuses_degenerate_input():
    square = se3.transform_points(se3.make(so3.exp([0.3, -0.2, 1.0]), [1, 2, 0]),
                                  square_points_marker(0.5, with_midpoints=True))
    # TL, TR, BR, BL on one line with non-zero summed edges (x: +2, y: −4 along the line).
    collinear = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    nan = square.copy()
    nan[1, 0] = np.nan
    lifted = square.copy()
    lifted[2, 2] += 0.01  # one corner 1 cm off the plane of the others
    cases = {
        "collinear": (collinear, "collinear"),
        "coincident": (np.ones((4, 3)), "coincide"),
        "nan": (nan, "NaN"),
        "non-planar": (lifted, "not coplanar"),
        "too few": (square[:3], "at least 4"),
        "wrong shape": (square[:, :2], "at least 4"),
    }
    for name, (points, message) in cases.items():
        with pytest.raises(DegenerateGeometryError, match=message):
            marker_frame_from_corners(points)
