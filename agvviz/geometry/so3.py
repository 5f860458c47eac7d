"""SO(3): hat/vee, exp/log and the left Jacobian. Numpy only.

Rotation vectors ``phi_rad`` are axis × angle (rad). See :mod:`agvviz.conventions`.
"""

from __future__ import annotations

import math

import numpy as np

_SMALL_ANGLE_RAD = 1e-6
_EYE3 = np.eye(3)
_EYE3.setflags(write=False)


def _one_minus_cos_over_theta_sq(theta: float) -> float:
    """(1 − cos θ)/θ² written as 2 sin²(θ/2)/θ²: no cancellation for small θ (the direct form
    loses ≈ε/θ² relative, ≈1e-10 absolute in J_l just above the small-angle switch)."""
    s = np.sin(0.5 * theta)
    return 2.0 * s * s / (theta * theta)


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix ``w^`` of a 3-vector, so that ``hat(w) @ v == cross(w, v)``."""
    w = np.asarray(w, dtype=float)
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def hat_batch(w: np.ndarray) -> np.ndarray:
    """:func:`hat` of every 3-vector in ``w`` (..., 3) → (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2] = -w[..., 2], w[..., 1]
    W[..., 1, 0], W[..., 1, 2] = w[..., 2], -w[..., 0]
    W[..., 2, 0], W[..., 2, 1] = -w[..., 1], w[..., 0]
    return W


def vee(W: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`: the 3-vector of a skew-symmetric matrix."""
    W = np.asarray(W, dtype=float)
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


def exp(phi_rad: np.ndarray) -> np.ndarray:
    """Rotation matrix of rotation vector ``phi_rad`` (Rodrigues, paper 000 eq 29)."""
    phi = np.asarray(phi_rad, dtype=float)
    theta = math.sqrt(phi.dot(phi))  # np.linalg.norm(phi), written out
    K = hat(phi)
    if theta < _SMALL_ANGLE_RAD:
        # Taylor series to second order; exact to machine precision here.
        return _EYE3 + K + 0.5 * K @ K
    a = np.sin(theta) / theta
    b = _one_minus_cos_over_theta_sq(theta)
    return _EYE3 + a * K + b * K @ K


def log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of rotation matrix ``R``; the angle lies in [0, π].

    Robust near 0 and near π (where the antisymmetric part vanishes).
    """
    R = np.asarray(R, dtype=float)
    # In Python floats (the same double arithmetic as numpy's, without its per-call cost on
    # scalars): this runs for every pose compared, interpolated or turned into an error.
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    cos_theta = min(max((r00 + r11 + r22 - 1.0) / 2.0, -1.0), 1.0)
    w = np.array([r21 - r12, r02 - r20, r10 - r01])  # 2 sin θ · axis
    sin_theta = 0.5 * math.sqrt(w.dot(w))  # np.linalg.norm(w), written out
    # atan2 keeps θ accurate everywhere; arccos alone loses digits near 0 and π, and dividing
    # w by sin(arccos(·)) then turns that into ≈1e-9 rad errors at π − 1e-3.
    theta = float(np.arctan2(sin_theta, cos_theta))
    if theta < _SMALL_ANGLE_RAD:
        return 0.5 * w
    if np.pi - theta < 1e-3:
        # Near π: use the symmetric part, R + I ≈ 2 a aᵀ (sign from the antisymmetric part).
        B = (R + R.T) / 2.0 - cos_theta * np.eye(3)
        B /= 1.0 - cos_theta
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / np.sqrt(max(B[i, i], 1e-300))
        axis /= np.linalg.norm(axis)
        if np.dot(axis, w) < 0.0:
            axis = -axis
        # Refine the angle with the antisymmetric part, which keeps precision near π.
        sin_theta = 0.5 * float(np.dot(axis, w))
        theta = float(np.arctan2(sin_theta, cos_theta))
        return axis * theta
    return w * (theta / (2.0 * sin_theta))


def left_jacobian(phi_rad: np.ndarray) -> np.ndarray:
    """Left Jacobian J_l(φ) of SO(3) (the V matrix of paper 000 eq 30)."""
    phi = np.asarray(phi_rad, dtype=float)
    theta = math.sqrt(phi.dot(phi))  # np.linalg.norm(phi), written out
    K = hat(phi)
    if theta < _SMALL_ANGLE_RAD:
        return _EYE3 + 0.5 * K + K @ K / 6.0
    a = _one_minus_cos_over_theta_sq(theta)
    b = (theta - np.sin(theta)) / theta**3
    return _EYE3 + a * K + b * K @ K


def left_jacobian_inv(phi_rad: np.ndarray) -> np.ndarray:
    """Inverse of :func:`left_jacobian`."""
    phi = np.asarray(phi_rad, dtype=float)
    theta = math.sqrt(phi.dot(phi))  # np.linalg.norm(phi), written out
    K = hat(phi)
    if theta < _SMALL_ANGLE_RAD:
        return _EYE3 - 0.5 * K + K @ K / 12.0
    half = theta / 2.0
    c = (1.0 - half / np.tan(half)) / theta**2
    return _EYE3 - 0.5 * K + c * K @ K


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix to ``M`` in the Frobenius norm (SVD orthonormalisation)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt
