"""SE(3) with tangent order ξ = (ρ, φ) and left perturbation ``T ← Exp(δ)·T``. Numpy only.

See :mod:`agvviz.conventions`. Homogeneous transforms are 4×4 arrays named ``T_a_b``.
"""

from __future__ import annotations

import numpy as np

from agvviz.geometry import so3


def make(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4×4 transform from rotation ``R`` (3×3) and translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: ``inverse(T_a_b) == T_b_a``."""
    R = T[:3, :3]
    t = T[:3, 3]
    return make(R.T, -R.T @ t)


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map points (N, 3) from frame b into frame a."""
    points_b = np.asarray(points_b, dtype=float).reshape(-1, 3)
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def hat(xi: np.ndarray) -> np.ndarray:
    """4×4 Lie-algebra matrix of ξ = (ρ, φ)."""
    xi = np.asarray(xi, dtype=float)
    X = np.zeros((4, 4))
    X[:3, :3] = so3.hat(xi[3:])
    X[:3, 3] = xi[:3]
    return X


def vee(X: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`: ξ = (ρ, φ)."""
    return np.concatenate([X[:3, 3], so3.vee(X[:3, :3])])


def exp(xi: np.ndarray) -> np.ndarray:
    """Exp(ξ) for ξ = (ρ, φ): rotation Exp(φ), translation J_l(φ)·ρ (paper 000 eqs 28–30)."""
    xi = np.asarray(xi, dtype=float)
    rho, phi = xi[:3], xi[3:]
    return make(so3.exp(phi), so3.left_jacobian(phi) @ rho)


def log(T: np.ndarray) -> np.ndarray:
    """Log(T) = ξ = (ρ, φ), the inverse of :func:`exp`."""
    phi = so3.log(T[:3, :3])
    rho = so3.left_jacobian_inv(phi) @ T[:3, 3]
    return np.concatenate([rho, phi])


def adjoint(T: np.ndarray) -> np.ndarray:
    """6×6 adjoint for ξ = (ρ, φ): ``T·Exp(ξ)·T⁻¹ = Exp(Ad(T)·ξ)``."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[:3, 3:] = so3.hat(t) @ R
    Ad[3:, 3:] = R
    return Ad


def J_point_wrt_left_perturbation(points_a: np.ndarray) -> np.ndarray:
    """Jacobian of ``Exp(δ)·p`` w.r.t. δ = (ρ, φ) at δ = 0, for points ``p = T·s`` already
    transformed (N, 3). Returns (N, 3, 6) = [I, -p^] (paper 000 eq 27)."""
    p = np.asarray(points_a, dtype=float).reshape(-1, 3)
    J = np.zeros((p.shape[0], 3, 6))
    J[:, 0, 0] = J[:, 1, 1] = J[:, 2, 2] = 1.0
    # -p^ = [[0, z, -y], [-z, 0, x], [y, -x, 0]]
    J[:, 0, 4] = p[:, 2]
    J[:, 0, 5] = -p[:, 1]
    J[:, 1, 3] = -p[:, 2]
    J[:, 1, 5] = p[:, 0]
    J[:, 2, 3] = p[:, 1]
    J[:, 2, 4] = -p[:, 0]
    return J


def is_rigid(T: np.ndarray, atol: float = 1e-6) -> bool:
    """True when ``T`` is a finite 4×4 rigid transform (orthonormal, det +1, last row 0001)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (
        np.allclose(R.T @ R, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) < atol
        and np.allclose(T[3], [0, 0, 0, 1], atol=atol)
    )


def from_quaternion_xyzw(q_xyzw: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Transform from a unit quaternion (x, y, z, w) and a translation."""
    x, y, z, w = np.asarray(q_xyzw, dtype=float) / np.linalg.norm(q_xyzw)
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    return make(R, t)


def to_quaternion_xyzw(T_or_R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w ≥ 0, of a rotation matrix or transform."""
    R = np.asarray(T_or_R, dtype=float)[:3, :3]
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q
