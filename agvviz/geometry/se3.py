"""SE(3) with tangent order ξ = (ρ, φ) and left perturbation ``T ← Exp(δ)·T``. Numpy only.

See :mod:`agvviz.conventions`. Homogeneous transforms are 4×4 arrays named ``T_a_b``.
"""

from __future__ import annotations

import math

import numpy as np

from agvviz.geometry import so3


def make(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4×4 transform from rotation ``R`` (3×3) and translation ``t`` (3,)."""
    T = _EYE4.copy()
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


_EYE4 = np.eye(4)
_EYE4.setflags(write=False)  # shared: make() copies it


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: ``inverse(T_a_b) == T_b_a``."""
    R = T[:3, :3]
    t = T[:3, 3]
    return make(R.T, -R.T @ t)


def inverse_batch(T: np.ndarray) -> np.ndarray:
    """:func:`inverse` of a stack of rigid transforms (N, 4, 4)."""
    R = np.swapaxes(T[:, :3, :3], 1, 2)
    out = np.zeros_like(T)
    out[:, :3, :3] = R
    out[:, :3, 3] = -np.einsum("nij,nj->ni", R, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map points (N, 3) from frame b into frame a."""
    points_b = np.asarray(points_b, dtype=float).reshape(-1, 3)
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def transform_points_batch(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """:func:`transform_points` for a stack of transforms: ``T_a_b`` (B, 4, 4) and points
    (B, P, 3), or (P, 3) shared by every transform → (B, P, 3). Any leading shape broadcasts
    the same way (one (4, 4) with (P, 3) gives (P, 3))."""
    T_a_b = np.asarray(T_a_b, dtype=float)
    return np.asarray(points_b, dtype=float) @ np.swapaxes(T_a_b[..., :3, :3], -1, -2) + T_a_b[..., None, :3, 3]


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
    """Exp(ξ) for ξ = (ρ, φ): rotation Exp(φ), translation J_l(φ)·ρ (paper 000 eqs 28–30).

    The formulas of :func:`so3.exp` and :func:`so3.left_jacobian` written out in scalar
    arithmetic (every LM step calls this once, so its overhead counts): with K = φ^ and
    K² = φφᵀ − θ²I, ``R = I + a K + b K²`` and ``J_l = I + b K + c K²``, a = sin θ/θ,
    b = (1 − cos θ)/θ² = 2 sin²(θ/2)/θ², c = (θ − sin θ)/θ³; below the small-angle switch
    the second-order series (a, b, c) = (1, ½, ⅙), as in :mod:`so3`. :func:`exp_batch` is
    the same arithmetic over many ξ.
    """
    r1, r2, r3, x, y, z = np.asarray(xi, dtype=float).reshape(6).tolist()
    tt = x * x + y * y + z * z
    if not math.isfinite(tt + r1 + r2 + r3):
        return np.full((4, 4), np.nan)  # as the array formulas give (math.sin(inf) would raise)
    theta = math.sqrt(tt)
    if theta < so3._SMALL_ANGLE_RAD:
        a, b, c = 1.0, 0.5, 1.0 / 6.0
    else:
        s, half = math.sin(theta), math.sin(0.5 * theta)
        a, b, c = s / theta, 2.0 * half * half / tt, (theta - s) / (tt * theta)
    xy, xz, yz = x * y, x * z, y * z
    v00, v11, v22 = 1.0 + c * (x * x - tt), 1.0 + c * (y * y - tt), 1.0 + c * (z * z - tt)
    v01, v02, v12 = c * xy - b * z, c * xz + b * y, c * yz - b * x
    v10, v20, v21 = c * xy + b * z, c * xz - b * y, c * yz + b * x
    return np.array(
        [
            [1.0 + b * (x * x - tt), b * xy - a * z, b * xz + a * y, v00 * r1 + v01 * r2 + v02 * r3],
            [b * xy + a * z, 1.0 + b * (y * y - tt), b * yz - a * x, v10 * r1 + v11 * r2 + v12 * r3],
            [b * xz - a * y, b * yz + a * x, 1.0 + b * (z * z - tt), v20 * r1 + v21 * r2 + v22 * r3],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def exp_batch(xi: np.ndarray) -> np.ndarray:
    """:func:`exp` of every row of ``xi`` (B, 6) → (B, 4, 4), the same arithmetic vectorised."""
    xi = np.asarray(xi, dtype=float).reshape(-1, 6)
    r1, r2, r3, x, y, z = xi.T
    tt = x * x + y * y + z * z
    theta = np.sqrt(tt)
    small = theta < so3._SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, theta)  # keeps the unused branch free of 0/0
    safe_tt = np.where(small, 1.0, tt)
    s, half = np.sin(safe), np.sin(0.5 * safe)
    a = np.where(small, 1.0, s / safe)
    b = np.where(small, 0.5, 2.0 * half * half / safe_tt)
    c = np.where(small, 1.0 / 6.0, (safe - s) / (safe_tt * safe))
    xy, xz, yz = x * y, x * z, y * z
    T = np.zeros((xi.shape[0], 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = 1.0 + b * (x * x - tt), b * xy - a * z, b * xz + a * y
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = b * xy + a * z, 1.0 + b * (y * y - tt), b * yz - a * x
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = b * xz - a * y, b * yz + a * x, 1.0 + b * (z * z - tt)
    v00, v11, v22 = 1.0 + c * (x * x - tt), 1.0 + c * (y * y - tt), 1.0 + c * (z * z - tt)
    v01, v02, v12 = c * xy - b * z, c * xz + b * y, c * yz - b * x
    v10, v20, v21 = c * xy + b * z, c * xz - b * y, c * yz + b * x
    T[:, 0, 3] = v00 * r1 + v01 * r2 + v02 * r3
    T[:, 1, 3] = v10 * r1 + v11 * r2 + v12 * r3
    T[:, 2, 3] = v20 * r1 + v21 * r2 + v22 * r3
    T[:, 3, 3] = 1.0
    return T


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
    transformed (N, 3), or any stack (..., N, 3). Returns (N, 3, 6) (resp. (..., N, 3, 6))
    = [I, -p^] (paper 000 eq 27); a single point (3,) gives (1, 3, 6)."""
    p = np.asarray(points_a, dtype=float)
    if p.ndim == 1:
        p = p.reshape(1, 3)
    J = np.zeros(p.shape[:-1] + (3, 6))
    J[..., 0, 0] = J[..., 1, 1] = J[..., 2, 2] = 1.0
    # -p^ = [[0, z, -y], [-z, 0, x], [y, -x, 0]]
    J[..., 0, 4] = p[..., 2]
    J[..., 0, 5] = -p[..., 1]
    J[..., 1, 3] = -p[..., 2]
    J[..., 1, 5] = p[..., 0]
    J[..., 2, 3] = p[..., 1]
    J[..., 2, 4] = -p[..., 0]
    return J


_EYE3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_EYE3.setflags(write=False)
_LAST_ROW.setflags(write=False)


def is_rigid(T: np.ndarray, atol: float = 1e-6) -> bool:
    """True when ``T`` is a finite 4×4 rigid transform (orthonormal, det +1, last row 0001).

    The tests are ``np.allclose``'s (|a − b| ≤ atol + 1e-5·|b|), written out: this runs for every
    pose a solver returns, and ``allclose``'s own overhead was most of its cost."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        return False
    R = T[:3, :3]
    return bool(
        (np.abs(R.T @ R - _EYE3) <= atol + 1e-5 * _EYE3).all()
        and abs(np.linalg.det(R) - 1.0) < atol
        and (np.abs(T[3] - _LAST_ROW) <= atol + 1e-5 * _LAST_ROW).all()
    )


def from_quaternion_xyzw(q_xyzw: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Transform from a unit quaternion (x, y, z, w) and a translation."""
    # (as Python floats: the same double arithmetic without numpy's per-scalar cost; the norm is
    # np.linalg.norm's own, sqrt of the dot product, without its per-call cost)
    q = np.asarray(q_xyzw, dtype=float)
    x, y, z, w = (q / math.sqrt(q.dot(q))).tolist()
    tx, ty, tz = np.asarray(t, dtype=float).reshape(3).tolist()
    return np.array(  # make(R, t) in one go
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w), tx],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w), ty],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y), tz],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


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
