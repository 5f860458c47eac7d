"""Analytic P4P from a homography, paper 000 eqs 4–21. Numpy only.

Four coplanar marker points ``q_i = (x_i, y_i, 1)`` (z = 0 in the marker frame) and their
ideal pixels ``p_i = (u_i, v_i, 1)`` give the homography ``H = K (r1 r2 t)`` up to the
depth of point 3:

* ``P = (p1 p2 p3)``, ``Q = (q1 q2 q3)``, ``v = P⁻¹ p4`` (eq 7), ``r = Q⁻¹ q4`` (eq 8);
* ``W = diag(r3 v1 / (r1 v3), r3 v2 / (r2 v3), 1)`` — the depths z'_1, z'_2, z'_3 relative
  to z'_3 (eqs 13–14);
* ``T = P W Q⁻¹`` (eq 15), ``g = K⁻¹ T`` (eq 16);
* ``s = (|g1| + |g2|) / (|g1|² + |g2|²)`` (eq 18, least-squares unit length of s·g1, s·g2);
* ``r1 = s g1``, ``r2 = s g2``, ``t = s g3`` (eqs 19–20), ``r3 = r1 × r2`` (eq 21).

Positive depth (paper 000 §3: "setting the constant factor s to be positive eliminates the
solution with negative depth"): s > 0 by construction and ``T q_i`` has third component
``W11, W22, 1, r3/v3`` for points 1–4, so all four depths are positive exactly when those
ratios are; otherwise the pixels cannot come from a plane in front of the camera and the
solve fails with "point behind camera".

Orthonormalisation: Gram–Schmidt on (r1, r2), as the paper says (§3, end): r1 keeps its
direction, r2 loses its r1 component, r3 = r1 × r2. The translation keeps the scale s.
On noise-free input R is already a rotation and this changes nothing.
"""

from __future__ import annotations

import numpy as np

#: |cross| / (longest edge)² below which three points count as collinear.
COLLINEAR_REL_TOL = 1e-9

_TRIPLES = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))


def any_three_collinear(points_2d: np.ndarray, rel_tol: float = COLLINEAR_REL_TOL) -> bool:
    """True when any three of four 2-D points (4, 2) are collinear or coincide.

    The test is scale-free: twice the triangle area over the squared longest edge.
    """
    for i, j, k in _TRIPLES:
        a, b, c = points_2d[i], points_2d[j], points_2d[k]
        ab, ac, bc = b - a, c - a, c - b
        longest_sq = max(ab @ ab, ac @ ac, bc @ bc)
        cross = abs(ab[0] * ac[1] - ab[1] * ac[0])
        if longest_sq == 0.0 or cross <= rel_tol * longest_sq:
            return True
    return False


def gram_schmidt_rotation(r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """Rotation (3×3) with first column along ``r1`` and second in the (r1, r2) plane."""
    c1 = r1 / np.linalg.norm(r1)
    c2 = r2 - (c1 @ r2) * c1
    c2 = c2 / np.linalg.norm(c2)
    return np.stack([c1, c2, np.cross(c1, c2)], axis=1)


def solve_p4p(
    points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray | None, str]:
    """Pose of the marker in the camera frame from the first four points (paper 000 eqs 7–21).

    Parameters
    ----------
    points_marker_m : (N, 3) marker-frame points with z = 0, N ≥ 4; only the first 4 are used.
    pixels_px : (N, 2) ideal (undistorted) pixels of those points.
    K : (3, 3) camera matrix.

    Returns
    -------
    (T_cam_marker, reason): the (4, 4) pose and "" on success, else ``None`` and why.
    Inputs are assumed finite and well-shaped (checked by :func:`agvviz.solvers.solve`).
    """
    xy = np.asarray(points_marker_m, dtype=float)[:4, :2]
    uv = np.asarray(pixels_px, dtype=float)[:4]
    if any_three_collinear(uv):
        return None, "degenerate: pixels collinear"
    if any_three_collinear(xy):
        return None, "degenerate: marker points collinear"
    q = np.concatenate([xy, np.ones((4, 1))], axis=1).T  # columns q1..q4
    p = np.concatenate([uv, np.ones((4, 1))], axis=1).T  # columns p1..p4
    P, Q = p[:, :3], q[:, :3]
    v = np.linalg.solve(P, p[:, 3])  # eq 7
    r = np.linalg.solve(Q, q[:, 3])  # eq 8
    # No three points are collinear, so every component of v and r is non-zero (Cramer's rule:
    # each is a ratio of triangle areas).
    W = np.diag([r[2] * v[0] / (r[0] * v[2]), r[2] * v[1] / (r[1] * v[2]), 1.0])
    depth_ratios = np.array([W[0, 0], W[1, 1], 1.0, r[2] / v[2]])  # z'_i / z'_3, i = 1..4
    if not (depth_ratios > 0.0).all():
        return None, "point behind camera"
    T = P @ W @ np.linalg.inv(Q)  # eq 15
    g = np.linalg.solve(K, T)  # eq 16
    n1, n2 = np.linalg.norm(g[:, 0]), np.linalg.norm(g[:, 1])
    s = (n1 + n2) / (n1 * n1 + n2 * n2)  # eq 18
    r1, r2, t = s * g[:, 0], s * g[:, 1], s * g[:, 2]  # eqs 19–20
    R = gram_schmidt_rotation(r1, r2)  # eq 21 plus orthonormalisation
    T_cam_marker = np.eye(4)
    T_cam_marker[:3, :3] = R
    T_cam_marker[:3, 3] = t
    if not np.isfinite(T_cam_marker).all():
        return None, "non-finite result"
    return T_cam_marker, ""
