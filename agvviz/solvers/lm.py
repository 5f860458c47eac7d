"""Levenberg–Marquardt pose refinement on SE(3), paper 000 eqs 22–30. Numpy only.

The pose ``T_cam_marker`` is updated with the left perturbation ``T ← Exp(δ)·T``,
δ = (ρ, φ) (see :mod:`agvviz.conventions`). For each marker point ``s_i`` the camera-frame
point is ``w_i = R s_i + t = (x, y, z)`` and the measured ideal pixel is ``(u_i, v_i)``.

Objectives (cost = ½‖f‖², residuals stacked per point as (u, v)):

* ``"depth"`` — paper 000 eq 23: ``f_i = z·(p'_i − p_i) = (k1·w − z u, k2·w − z v)`` with
  ``k1, k2`` the first two rows of K. It is linear in w, so
  ``∂f_i/∂w = [[k11, k12, k13 − u], [k21, k22, k23 − v]]`` (eq 26). It weights each point's
  pixel error by its depth, so it is not the maximum-likelihood objective for pixel noise.
* ``"pixel"`` — paper 000 eq 22: ``f_i = π(K w) − p_i``, the pixel reprojection error;
  ``∂f_i/∂w`` is the pinhole projection Jacobian.

Both chain with ``∂w/∂δ = [I, −w^]`` (eq 27).

Damping scheme (Levenberg): the normal equations are ``(JᵀJ + μ I) δ = −Jᵀf`` with
``μ = λ · mean(diag(JᵀJ))``, so λ is scale-free. λ starts at ``initial_damping``; an accepted
step (lower cost, every point still in front of the camera) divides λ by 10, a rejected step
multiplies it by 10 and leaves the pose unchanged.

Convergence: the step norm ‖δ‖ < ``step_tol``, or the cost changes by at most
``cost_rel_tol``·cost (accepted or not: a rejected step that changes the cost that little
is round-off), or the cost is exactly 0. Running out of ``max_iterations`` returns the best
pose so far, like OpenCV's iteration criteria: it is still an estimate, and the caller's
reprojection check decides whether it is usable (the iteration list shows it stopped early).
"""

from __future__ import annotations

import numpy as np

from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.results import LmIteration

OBJECTIVES = ("depth", "pixel")

_DAMPING_FACTOR = 10.0


def reprojection_rms_px(
    T_cam_marker: np.ndarray, points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray
) -> float:
    """RMS over points of the Euclidean pixel distance between projection and measurement."""
    w = se3.transform_points(T_cam_marker, points_marker_m)
    projected = w @ np.asarray(K, dtype=float).T
    projected = projected[:, :2] / projected[:, 2:3]
    return float(np.sqrt(np.mean(np.sum((projected - pixels_px) ** 2, axis=1))))


def residuals_and_jacobian(
    T_cam_marker: np.ndarray,
    points_marker_m: np.ndarray,
    pixels_px: np.ndarray,
    K: np.ndarray,
    objective: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Residual vector f (2N,) and ``J_f_wrt_left_perturbation`` (2N, 6), δ = (ρ, φ).

    Parameters
    ----------
    T_cam_marker : (4, 4) current pose.
    points_marker_m : (N, 3) marker-frame points.
    pixels_px : (N, 2) measured ideal pixels.
    K : (3, 3) upper-triangular camera matrix with last row (0, 0, 1).
    objective : "depth" (eq 23) or "pixel" (eq 22).
    """
    w = se3.transform_points(T_cam_marker, points_marker_m)  # (N, 3)
    J_w_wrt_delta = se3.J_point_wrt_left_perturbation(w)  # (N, 3, 6)
    n = w.shape[0]
    if objective == "depth":
        z = w[:, 2:3]
        f = (w @ K[:2].T) - z * pixels_px  # (k1·w − z u, k2·w − z v)
        J_f_wrt_w = np.broadcast_to(K[:2], (n, 2, 3)).copy()
        J_f_wrt_w[:, :, 2] -= pixels_px
    elif objective == "pixel":
        projected, J_f_wrt_w = PinholeCamera(K).project_with_jacobian(w)
        f = projected - pixels_px
    else:
        raise ValueError(f"unknown objective {objective!r}; valid: {OBJECTIVES}")
    J = J_f_wrt_w @ J_w_wrt_delta  # (N, 2, 6)
    return f.reshape(2 * n), J.reshape(2 * n, 6)


def _cost(
    T_cam_marker: np.ndarray,
    points_marker_m: np.ndarray,
    pixels_px: np.ndarray,
    K: np.ndarray,
    objective: str,
) -> float:
    """½‖f‖², or +inf when a point is not in front of the camera (the step is then refused)."""
    w = se3.transform_points(T_cam_marker, points_marker_m)
    if not np.all(w[:, 2] > 0.0):
        return float("inf")
    f, _ = residuals_and_jacobian(T_cam_marker, points_marker_m, pixels_px, K, objective)
    return 0.5 * float(f @ f)


def refine_lm(
    T_start_cam_marker: np.ndarray,
    points_marker_m: np.ndarray,
    pixels_px: np.ndarray,
    K: np.ndarray,
    *,
    objective: str,
    max_iterations: int,
    initial_damping: float,
    step_tol: float,
    cost_rel_tol: float,
) -> tuple[np.ndarray | None, str, list[LmIteration]]:
    """Refine a pose by Levenberg–Marquardt on SE(3) with the left perturbation.

    Parameters
    ----------
    T_start_cam_marker : (4, 4) starting pose (e.g. from P4P), every point in front.
    points_marker_m : (N, 3) marker-frame points; pixels_px : (N, 2) ideal pixels.
    K : (3, 3) camera matrix.
    objective, max_iterations, initial_damping, step_tol, cost_rel_tol :
        see :class:`agvviz.solvers.SolverOptions`.

    Returns
    -------
    (T_cam_marker, reason, iterations): the refined pose (the best so far when the iteration
    budget runs out) and "", else ``None`` and why the start was unusable. ``iterations[0]`` is the start
    (its cost, ``step_norm`` 0, accepted); then one entry per trial step, accepted or not,
    with the cost and RMS of the pose kept after it and the λ the step was solved with.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; valid: {OBJECTIVES}")
    T = np.array(T_start_cam_marker, dtype=float)
    cost = _cost(T, points_marker_m, pixels_px, K, objective)
    if not np.isfinite(cost):
        return None, "point behind camera", []
    damping = float(initial_damping)
    iterations = [
        LmIteration(cost, reprojection_rms_px(T, points_marker_m, pixels_px, K), damping, 0.0, True)
    ]
    if cost == 0.0:
        return T, "", iterations
    f, J = residuals_and_jacobian(T, points_marker_m, pixels_px, K, objective)
    for _ in range(max_iterations):
        JtJ = J.T @ J
        mu = damping * float(np.mean(np.diag(JtJ)))
        try:
            delta = np.linalg.solve(JtJ + mu * np.eye(6), -(J.T @ f))
        except np.linalg.LinAlgError:
            return None, "singular normal equations", iterations
        step_norm = float(np.linalg.norm(delta))
        T_trial = se3.exp(delta) @ T
        cost_trial = _cost(T_trial, points_marker_m, pixels_px, K, objective)
        accepted = cost_trial < cost
        small_change = abs(cost - cost_trial) <= cost_rel_tol * cost
        damping_used = damping
        if accepted:
            T, cost = T_trial, cost_trial
            damping /= _DAMPING_FACTOR
            f, J = residuals_and_jacobian(T, points_marker_m, pixels_px, K, objective)
        else:
            damping *= _DAMPING_FACTOR
        iterations.append(
            LmIteration(
                cost,
                reprojection_rms_px(T, points_marker_m, pixels_px, K),
                damping_used,
                step_norm,
                accepted,
            )
        )
        if step_norm < step_tol or small_change or cost == 0.0:
            return T, "", iterations
    return T, "", iterations
