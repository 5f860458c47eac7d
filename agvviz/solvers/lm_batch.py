"""Vectorised P4P and Levenberg–Marquardt: many frames at once in numpy. Numpy only.

Frame k has its own marker points ``points_marker_m[k]`` (P, 3), pixels ``pixels_px[k]`` (P, 2)
and camera matrix ``K[k]`` (3, 3); every frame has the same number of points P. Each frame
follows exactly the arithmetic of the single-frame code — :func:`agvviz.solvers.p4p.solve_p4p`
and :func:`agvviz.solvers.lm.refine_lm` (same damping schedule, acceptance and convergence
rules, per frame) — so results agree with it to round-off; only the loop over frames is
replaced by array operations (batched 6×6 normal equations with ``np.linalg.solve`` on
(N, 6, 6)). Frames that converge stop changing; the loop ends when all have converged or
``max_iterations`` is reached.

Not included: the single-frame LM's fallback to an IPPE start when P4P fails, and the input
checks of :func:`agvviz.solvers.solve`; frames whose P4P fails come back with
``ok = False`` and a reason, for the caller to solve one by one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.solvers.lm import OBJECTIVES
from agvviz.solvers.p4p import COLLINEAR_REL_TOL

_DAMPING_FACTOR = 10.0
_SMALL_ANGLE_RAD = 1e-6
_TRIPLES = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))


@dataclass
class BatchResult:
    """T_cam_marker (N, 4, 4), NaN where not ok; ok (N,) bool; reason (N,) str ("" when ok);
    iterations (N,) trial steps taken; reproj_rms_px (N,) (NaN where not ok)."""

    T_cam_marker: np.ndarray
    ok: np.ndarray
    reason: np.ndarray
    iterations: np.ndarray
    reproj_rms_px: np.ndarray


# -- batched SE(3) -----------------------------------------------------------------------------


def _hat(v: np.ndarray) -> np.ndarray:
    """(N, 3) → (N, 3, 3) skew matrices."""
    H = np.zeros(v.shape[:-1] + (3, 3))
    H[..., 0, 1], H[..., 0, 2] = -v[..., 2], v[..., 1]
    H[..., 1, 0], H[..., 1, 2] = v[..., 2], -v[..., 0]
    H[..., 2, 0], H[..., 2, 1] = -v[..., 1], v[..., 0]
    return H


def se3_exp_batch(xi: np.ndarray) -> np.ndarray:
    """Exp of (N, 6) tangent vectors (ρ, φ) → (N, 4, 4); same formulas as :func:`se3.exp`."""
    rho, phi = xi[:, :3], xi[:, 3:]
    theta = np.linalg.norm(phi, axis=1)
    small = theta < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, theta)
    half_sin = np.sin(0.5 * safe)
    a_rot = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, 2.0 * half_sin * half_sin / (safe * safe))  # (1 − cos θ)/θ²
    c = np.where(small, 1.0 / 6.0, (safe - np.sin(safe)) / safe**3)
    Kx = _hat(phi)
    KK = Kx @ Kx
    eye = np.eye(3)
    R = eye + a_rot[:, None, None] * Kx + b[:, None, None] * KK
    V = eye + b[:, None, None] * Kx + c[:, None, None] * KK
    # Small angles: the single-frame code uses the second-order series, identical to these
    # coefficients at θ → 0 (a_rot = 1, b = 1/2, c = 1/6) — as in so3.exp / left_jacobian.
    T = np.zeros((xi.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = (V @ rho[:, :, None])[:, :, 0]
    T[:, 3, 3] = 1.0
    return T


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 4, 4) × (N, P, 3) → (N, P, 3), as ``se3.transform_points`` per frame."""
    return points @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]


# -- batched P4P --------------------------------------------------------------------------------


def _collinear_any(xy: np.ndarray) -> np.ndarray:
    """(N, 4, 2) → (N,) True where any three of the four points are collinear (p4p's test)."""
    bad = np.zeros(xy.shape[0], dtype=bool)
    for i, j, k in _TRIPLES:
        ab, ac, bc = xy[:, j] - xy[:, i], xy[:, k] - xy[:, i], xy[:, k] - xy[:, j]
        longest = np.maximum.reduce([np.sum(ab * ab, 1), np.sum(ac * ac, 1), np.sum(bc * bc, 1)])
        cross = np.abs(ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0])
        bad |= (longest == 0.0) | (cross <= COLLINEAR_REL_TOL * longest)
    return bad


def p4p_batch(points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray) -> BatchResult:
    """Paper 000 eqs 7–21 on the first four points of every frame (see :mod:`.p4p`)."""
    n = points_marker_m.shape[0]
    K = np.broadcast_to(np.asarray(K, dtype=float), (n, 3, 3))
    xy = points_marker_m[:, :4, :2]
    uv = pixels_px[:, :4]
    reason = np.full(n, "", dtype=object)
    reason[_collinear_any(xy)] = "degenerate: marker points collinear"
    reason[_collinear_any(uv)] = "degenerate: pixels collinear"
    ok = reason == ""
    q = np.concatenate([xy, np.ones((n, 4, 1))], axis=2).transpose(0, 2, 1)  # (N, 3, 4)
    p = np.concatenate([uv, np.ones((n, 4, 1))], axis=2).transpose(0, 2, 1)
    P, Q = p[:, :, :3].copy(), q[:, :, :3].copy()
    P[~ok], Q[~ok] = np.eye(3), np.eye(3)  # keep degenerate frames from raising
    v = np.linalg.solve(P, p[:, :, 3:])[..., 0]
    r = np.linalg.solve(Q, q[:, :, 3:])[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        w1 = r[:, 2] * v[:, 0] / (r[:, 0] * v[:, 2])
        w2 = r[:, 2] * v[:, 1] / (r[:, 1] * v[:, 2])
        w4 = r[:, 2] / v[:, 2]
    behind = ok & ~((w1 > 0) & (w2 > 0) & (w4 > 0))
    reason[behind] = "point behind camera"
    ok &= ~behind
    W = np.zeros((n, 3, 3))
    W[:, 0, 0], W[:, 1, 1], W[:, 2, 2] = np.where(ok, w1, 1.0), np.where(ok, w2, 1.0), 1.0
    T_h = P @ W @ np.linalg.inv(Q)
    g = np.linalg.solve(K, T_h)
    n1, n2 = np.linalg.norm(g[:, :, 0], axis=1), np.linalg.norm(g[:, :, 1], axis=1)
    s = (n1 + n2) / (n1 * n1 + n2 * n2)
    r1, r2, t = s[:, None] * g[:, :, 0], s[:, None] * g[:, :, 1], s[:, None] * g[:, :, 2]
    c1 = r1 / np.linalg.norm(r1, axis=1, keepdims=True)
    c2 = r2 - np.sum(c1 * r2, axis=1, keepdims=True) * c1
    c2 = c2 / np.linalg.norm(c2, axis=1, keepdims=True)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = np.stack([c1, c2, np.cross(c1, c2)], axis=2)
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    finite = np.all(np.isfinite(T), axis=(1, 2))
    reason[ok & ~finite] = "non-finite result"
    ok &= finite
    T[~ok] = np.nan
    return BatchResult(T, ok, reason, np.zeros(n, dtype=int), _rms(T, points_marker_m, pixels_px, K, ok))


# -- batched LM ---------------------------------------------------------------------------------


def _rms(T, points, pixels, K, ok) -> np.ndarray:
    rms = np.full(T.shape[0], np.nan)
    if np.any(ok):
        w = _transform(T[ok], points[ok])
        proj = w @ K[ok].transpose(0, 2, 1)
        err = proj[..., :2] / proj[..., 2:3] - pixels[ok]
        rms[ok] = np.sqrt(np.mean(np.sum(err**2, axis=2), axis=1))
    return rms


def _residuals_and_jacobian(T, points, pixels, K, objective):
    """f (M, 2P) and J (M, 2P, 6) for each frame (:func:`lm.residuals_and_jacobian`)."""
    w = _transform(T, points)  # (M, P, 3)
    m, npts = w.shape[:2]
    J_w = np.zeros((m, npts, 3, 6))
    J_w[..., 0, 0] = J_w[..., 1, 1] = J_w[..., 2, 2] = 1.0
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    J_w[..., 0, 4], J_w[..., 0, 5] = z, -y
    J_w[..., 1, 3], J_w[..., 1, 5] = -z, x
    J_w[..., 2, 3], J_w[..., 2, 4] = y, -x
    K2 = K[:, None, :2, :]  # (M, 1, 2, 3)
    if objective == "depth":
        f = w @ K[:, :2, :].transpose(0, 2, 1) - z[..., None] * pixels
        J_f_w = np.broadcast_to(K2, (m, npts, 2, 3)).copy()
        J_f_w[..., 2] -= pixels
    else:
        # As PinholeCamera.project (no distortion): normalise, then apply K.
        xn, yn = x / z, y / z
        Kc = K[:, None, :, :]
        f = np.stack(
            [Kc[..., 0, 0] * xn + Kc[..., 0, 1] * yn + Kc[..., 0, 2], Kc[..., 1, 1] * yn + Kc[..., 1, 2]],
            axis=-1,
        ) - pixels
        # Pinhole Jacobian: d(u, v)/d(x, y, z) = K2[:, :, :2] · [[1/z, 0, −x/z²], [0, 1/z, −y/z²]]
        J_xy = np.zeros((m, npts, 2, 3))
        J_xy[..., 0, 0] = J_xy[..., 1, 1] = 1.0 / z
        J_xy[..., 0, 2] = -x / z**2
        J_xy[..., 1, 2] = -y / z**2
        J_f_w = K2[..., :2] @ J_xy
    J = (J_f_w @ J_w).reshape(m, 2 * npts, 6)
    return f.reshape(m, 2 * npts), J


def _costs(T, points, pixels, K, objective) -> np.ndarray:
    w = _transform(T, points)
    f, _ = _residuals_and_jacobian(T, points, pixels, K, objective)
    cost = 0.5 * (f[:, None, :] @ f[:, :, None])[:, 0, 0]
    return np.where(np.all(w[..., 2] > 0.0, axis=1), cost, np.inf)


def refine_lm_batch(
    T_start_cam_marker: np.ndarray,
    points_marker_m: np.ndarray,
    pixels_px: np.ndarray,
    K: np.ndarray,
    *,
    objective: str = "depth",
    max_iterations: int = 50,
    initial_damping: float = 1e-3,
    step_tol: float = 1e-12,
    cost_rel_tol: float = 1e-14,
) -> BatchResult:
    """LM refinement of N poses at once; per frame identical to :func:`lm.refine_lm`.

    Parameters
    ----------
    T_start_cam_marker : (N, 4, 4) start poses (NaN rows are skipped, reason "no start pose").
    points_marker_m : (N, P, 3); pixels_px : (N, P, 2); K : (N, 3, 3) or (3, 3).
    objective, max_iterations, initial_damping, step_tol, cost_rel_tol : as
        :class:`agvviz.solvers.SolverOptions`.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; valid: {OBJECTIVES}")
    T = np.array(T_start_cam_marker, dtype=float)
    n = T.shape[0]
    K = np.broadcast_to(np.asarray(K, dtype=float), (n, 3, 3))
    reason = np.full(n, "", dtype=object)
    started = np.all(np.isfinite(T), axis=(1, 2))
    reason[~started] = "no start pose"
    T[~started] = np.eye(4)
    cost = _costs(T, points_marker_m, pixels_px, K, objective)
    behind = started & ~np.isfinite(cost)
    reason[behind] = "point behind camera"
    active = started & ~behind & (cost != 0.0)
    done = started & ~behind & (cost == 0.0)
    damping = np.full(n, float(initial_damping))
    iterations = np.zeros(n, dtype=int)
    f = np.zeros((n, 2 * points_marker_m.shape[1]))
    J = np.zeros((n, 2 * points_marker_m.shape[1], 6))
    if np.any(active):
        f[active], J[active] = _residuals_and_jacobian(
            T[active], points_marker_m[active], pixels_px[active], K[active], objective
        )
    for _ in range(max_iterations):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        Ja, fa = J[idx], f[idx]
        JtJ = Ja.transpose(0, 2, 1) @ Ja
        mu = damping[idx] * np.mean(np.diagonal(JtJ, axis1=1, axis2=2), axis=1)
        A = JtJ + mu[:, None, None] * np.eye(6)
        delta = np.linalg.solve(A, -(Ja.transpose(0, 2, 1) @ fa[:, :, None]))[..., 0]
        step_norm = np.linalg.norm(delta, axis=1)
        T_trial = se3_exp_batch(delta) @ T[idx]
        cost_trial = _costs(T_trial, points_marker_m[idx], pixels_px[idx], K[idx], objective)
        accepted = cost_trial < cost[idx]
        small_change = np.abs(cost[idx] - cost_trial) <= cost_rel_tol * cost[idx]
        iterations[idx] += 1
        acc = idx[accepted]
        T[acc] = T_trial[accepted]
        cost[acc] = cost_trial[accepted]
        damping[acc] /= _DAMPING_FACTOR
        damping[idx[~accepted]] *= _DAMPING_FACTOR
        if acc.size:
            f[acc], J[acc] = _residuals_and_jacobian(
                T[acc], points_marker_m[acc], pixels_px[acc], K[acc], objective
            )
        converged = (step_norm < step_tol) | small_change | (cost[idx] == 0.0)
        done[idx[converged]] = True
        active[idx[converged]] = False
    # Frames still iterating when the budget runs out keep their best pose (as refine_lm).
    ok = reason == ""
    T[~ok] = np.nan
    return BatchResult(T, ok, reason, iterations, _rms(T, points_marker_m, pixels_px, K, ok))


def solve_lm_batch(
    points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray, **lm_options
) -> BatchResult:
    """P4P start (:func:`p4p_batch`) then :func:`refine_lm_batch`, for (N, P, 3) points and
    (N, P, 2) pixels with (3, 3) or (N, 3, 3) K. Frames whose P4P fails keep its reason."""
    points_marker_m = np.asarray(points_marker_m, dtype=float)
    pixels_px = np.asarray(pixels_px, dtype=float)
    K = np.broadcast_to(np.asarray(K, dtype=float), (points_marker_m.shape[0], 3, 3))
    start = p4p_batch(points_marker_m, pixels_px, K)
    result = refine_lm_batch(start.T_cam_marker, points_marker_m, pixels_px, K, **lm_options)
    result.reason[~start.ok] = start.reason[~start.ok]
    return result
