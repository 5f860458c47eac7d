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

Both chain with ``∂w/∂δ = [I, −w^]`` (eq 27). :func:`residuals_and_jacobian` and
:func:`reprojection_rms_px` also take stacks of frames (used by :mod:`.lm_batch`).

The iteration is :func:`agvviz.solvers.lm_core.minimize`: its damping schedule (λ relative to
mean(diag(JᵀJ)), ÷10 on an accepted step, ×10 on a refused one), acceptance (lower cost, every
point still in front of the camera) and stopping rule (‖δ‖ < ``step_tol``, or a step changes the
cost by at most ``cost_rel_tol``·cost, or the cost is 0). Running out of ``max_iterations``
returns the best pose so far, like OpenCV's iteration criteria: it is still an estimate, and the
caller's reprojection check decides whether it is usable (the iteration list shows it stopped
early).
"""

from __future__ import annotations

import numpy as np

from agvviz.geometry import se3
from agvviz.solvers.types import LmIteration
from agvviz.solvers import lm_core

OBJECTIVES = ("depth", "pixel")

#: What refine_lm / refine_lm_batch report for each failure of the core.
FAILURE_REASONS = {
    lm_core.START_INFEASIBLE: "point behind camera",
    lm_core.START_NOT_FINITE: "non-finite residuals at the start pose",
    lm_core.SINGULAR: "singular normal equations",
}


def reprojection_rms_px(
    T_cam_marker: np.ndarray, points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray
) -> float | np.ndarray:
    """RMS over points of the Euclidean pixel distance between projection and measurement.

    One frame: (4, 4), (N, 3), (N, 2), (3, 3) → float. A stack of B frames: (B, 4, 4),
    (B, N, 3), (B, N, 2), (B, 3, 3) → (B,).
    """
    w = se3.transform_points_batch(T_cam_marker, points_marker_m)
    projected = w @ np.swapaxes(np.asarray(K, dtype=float), -1, -2)
    error = projected[..., :2] / projected[..., 2:3] - pixels_px
    # np.mean written out (its sum divided by the count), without its per-call cost
    rms = np.sqrt(np.add.reduce(np.sum(error**2, axis=-1), axis=-1) / error.shape[-2])
    return float(rms) if rms.ndim == 0 else rms


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

    A stack of B frames — (B, 4, 4), (B, N, 3), (B, N, 2), (B, 3, 3) — gives f (B, 2N) and
    J (B, 2N, 6): per frame the same formulas as alone.
    """
    w = se3.transform_points_batch(T_cam_marker, points_marker_m)  # (..., N, 3)
    J_w_wrt_delta = se3.J_point_wrt_left_perturbation(w)  # (..., N, 3, 6)
    K_rows = K[..., None, :2, :]  # (..., 1, 2, 3): the first two rows of K, for every point
    z = w[..., 2]
    if objective == "depth":
        f = w @ np.swapaxes(K[..., :2, :], -1, -2) - z[..., None] * pixels_px  # (k1·w − z u, k2·w − z v)
        J_f_wrt_w = np.broadcast_to(K_rows, w.shape[:-1] + (2, 3)).copy()
        J_f_wrt_w[..., 2] -= pixels_px
    elif objective == "pixel":
        # Pinhole projection (ideal image, no distortion): normalise, then apply K.
        x, y = w[..., 0] / z, w[..., 1] / z
        K_ = K[..., None, :, :]
        u = K_[..., 0, 0] * x + K_[..., 0, 1] * y + K_[..., 0, 2]
        v = K_[..., 1, 1] * y + K_[..., 1, 2]
        f = np.stack([u, v], axis=-1) - pixels_px
        # ∂(u, v)/∂w = K[:2, :2] · [[1/z, 0, −x/z], [0, 1/z, −y/z]], x, y normalised
        J_xy_wrt_w = np.zeros(w.shape[:-1] + (2, 3))
        J_xy_wrt_w[..., 0, 0] = J_xy_wrt_w[..., 1, 1] = 1.0 / z
        J_xy_wrt_w[..., 0, 2] = -x / z
        J_xy_wrt_w[..., 1, 2] = -y / z
        J_f_wrt_w = K_rows[..., :2] @ J_xy_wrt_w
    else:
        raise ValueError(f"unknown objective {objective!r}; valid: {OBJECTIVES}")
    J = J_f_wrt_w @ J_w_wrt_delta  # (..., N, 2, 6)
    n = w.shape[-2]
    return f.reshape(f.shape[:-2] + (2 * n,)), J.reshape(J.shape[:-3] + (2 * n, 6))


def retract_left(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The left perturbation ``Exp(δ)·T`` of one pose, δ = (ρ, φ)."""
    return se3.exp(delta) @ T


def retract_left_batch(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``Exp(δ_k)·T_k`` for a stack: T (B, 4, 4), δ (B, 6)."""
    return se3.exp_batch(delta) @ T


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
    path_out: list | None = None,
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
    ``path_out``, when given, receives the pose kept after each record (``path_out[k]`` after
    ``iterations[k]``): what the viewer draws as each iteration's reprojected corners.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; valid: {OBJECTIVES}")
    points_marker_m = np.asarray(points_marker_m, dtype=float).reshape(-1, 3)
    pixels_px = np.asarray(pixels_px, dtype=float)
    K = np.asarray(K, dtype=float)
    result = lm_core.minimize(
        np.array(T_start_cam_marker, dtype=float),
        retract_left,
        residuals_and_jacobian=lambda T: residuals_and_jacobian(T, points_marker_m, pixels_px, K, objective),
        feasible=lambda T: bool((se3.transform_points_batch(T, points_marker_m)[:, 2] > 0.0).all()),
        reproj_rms_px=lambda T: reprojection_rms_px(T, points_marker_m, pixels_px, K),
        options=lm_core.LmOptions(max_iterations, initial_damping, step_tol, cost_rel_tol),
    )
    if path_out is not None:
        path_out.extend(result.path)
    if result.failed:
        return None, FAILURE_REASONS[result.stop_reason], result.iterations
    return result.x, "", result.iterations
