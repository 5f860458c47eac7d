"""Pose uncertainty: covariance at the solution, the Cramér–Rao lower bound, NEES. Numpy only.

Noise model
    Every measured ideal (undistorted) pixel coordinate carries independent zero-mean Gaussian
    noise of standard deviation σ (px), the same for u and v and for every point.

Tangent space
    Every 6×6 covariance here is the covariance of the pose named in the function, ``T``, under
    the LEFT perturbation ``T = Exp(δ)·T̂`` with δ = (ρ, φ) — translation part first, rotation
    part second (:mod:`agvviz.conventions`). ρ is in metres, φ in radians. A 3×3 *position*
    covariance is the covariance of the origin of the child frame expressed in the parent frame
    (for ``T_cam_marker``: the marker centre in the camera frame, the paper's t; for
    ``T_world_agv``: the AGV origin in the world frame); see :func:`position_covariance`.

Estimators
    ``pixel`` objective (paper 000 eq 22) is the maximum-likelihood estimator under this noise
    model; its first-order covariance is ``σ²(JᵀJ)⁻¹`` with J the pixel-residual Jacobian at
    the solution. ``depth`` objective (eq 23) minimises ``Σ z_i²‖p'_i − p_i‖²``: a weighted
    least-squares estimator with weights W = diag(z_i²) that are NOT the inverse noise variance,
    so ``σ²(JᵀJ)⁻¹`` is wrong for it. Its first-order covariance is the sandwich
    ``σ² (JᵀWJ)⁻¹ (JᵀW²J) (JᵀWJ)⁻¹`` (J the pixel Jacobian; the residual-times-∂z term of the
    depth Jacobian vanishes to first order at small residuals). It is never smaller than the
    ML covariance (Gauss–Markov) and equals it when all depths are equal.

The Cramér–Rao lower bound for any unbiased estimator at the TRUE pose is the inverse Fisher
information ``σ²(JᵀJ)⁻¹`` with J evaluated at the true pose.
"""

from __future__ import annotations

from agvviz.errors import RunError

import numpy as np

from agvviz.geometry import se3, so3
from agvviz.geometry.camera import PinholeCamera

#: Covariance-producing objectives (see the module docstring).
OBJECTIVES = ("depth", "pixel")


class UncertaintyError(RunError):
    """The geometry does not determine the pose (singular information matrix) or bad input."""


def pixel_jacobian(T_cam_marker: np.ndarray, points_marker_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``J_pixels_wrt_left_perturbation`` (2N, 6) of the ideal pixels of ``points_marker_m``
    (N, 3) at pose ``T_cam_marker``; rows stacked per point as (u, v), δ = (ρ, φ)."""
    w = se3.transform_points(T_cam_marker, points_marker_m)
    if not np.all(w[:, 2] > 0.0):
        raise UncertaintyError("a point is not in front of the camera: no pixel Jacobian")
    _, J_px_wrt_w = PinholeCamera(np.asarray(K, dtype=float)).project_with_jacobian(w)
    return (J_px_wrt_w @ se3.J_point_wrt_left_perturbation(w)).reshape(-1, 6)


def _inverse_information(information: np.ndarray, what: str) -> np.ndarray:
    """Inverse of a symmetric positive-definite information matrix, or UncertaintyError."""
    eigenvalues = np.linalg.eigvalsh(information)
    if not eigenvalues[0] > 1e-12 * eigenvalues[-1]:
        raise UncertaintyError(
            f"{what}: the points do not determine the pose (information matrix singular, "
            f"eigenvalue ratio {eigenvalues[0] / eigenvalues[-1]:.1e})"
        )
    inverse = np.linalg.inv(information)
    return 0.5 * (inverse + inverse.T)


def crlb(T_true_cam_marker: np.ndarray, points_marker_m: np.ndarray, K: np.ndarray, sigma_px: float) -> np.ndarray:
    """Cramér–Rao lower bound (6, 6) on ``T_cam_marker`` in the left tangent space (ρ, φ) at the
    true pose, for isotropic pixel noise ``sigma_px``: ``σ²(JᵀJ)⁻¹``."""
    J = pixel_jacobian(T_true_cam_marker, points_marker_m, K)
    return sigma_px**2 * _inverse_information(J.T @ J, "CRLB")


def covariance(
    T_cam_marker: np.ndarray,
    points_marker_m: np.ndarray,
    K: np.ndarray,
    sigma_px: float,
    objective: str = "pixel",
) -> np.ndarray:
    """First-order covariance (6, 6) of an estimate of ``T_cam_marker`` (left, (ρ, φ)).

    Parameters
    ----------
    T_cam_marker : (4, 4) the estimate.
    points_marker_m : (N, 3) the marker points the estimator used.
    K : (3, 3) camera matrix.
    sigma_px : pixel noise σ (from :func:`residual_sigma_px` or a setting).
    objective : "pixel" — ML covariance σ²(JᵀJ)⁻¹ (also the right first-order value for any
        estimator that converges to the reprojection minimum); "depth" — the sandwich covariance
        of paper 000 eq 23 (module docstring).
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; valid: {', '.join(OBJECTIVES)}")
    J = pixel_jacobian(T_cam_marker, points_marker_m, K)
    if objective == "pixel":
        return sigma_px**2 * _inverse_information(J.T @ J, "covariance")
    z = se3.transform_points(T_cam_marker, points_marker_m)[:, 2]
    w = np.repeat(z**2, 2)  # weight of each residual row (u and v of a point share its depth)
    bread = _inverse_information(J.T @ (w[:, None] * J), "covariance")
    meat = J.T @ ((w**2)[:, None] * J)
    cov = sigma_px**2 * bread @ meat @ bread
    return 0.5 * (cov + cov.T)


def residual_sum_sq_px2(
    T_cam_marker: np.ndarray, points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray
) -> tuple[float, int]:
    """(Σ squared pixel residuals in px², degrees of freedom 2N − 6) at a 6-DoF solution."""
    w = se3.transform_points(T_cam_marker, points_marker_m)
    projected = w @ np.asarray(K, dtype=float).T
    residual = projected[:, :2] / projected[:, 2:3] - pixels_px
    return float(np.sum(residual**2)), 2 * len(points_marker_m) - 6


def residual_sigma_px(sum_sq_px2: float, dof: int) -> float | None:
    """σ estimate sqrt(Σr²/dof) (unbiased for σ² at an ML solution), ``None`` when dof ≤ 0."""
    return float(np.sqrt(sum_sq_px2 / dof)) if dof > 0 else None


def position_covariance(cov_left: np.ndarray, T_parent_child: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of the child origin in the parent frame, from the pose covariance
    ``cov_left`` (6, 6) of ``T_parent_child`` in the left tangent space.

    Under ``T = Exp(δ)·T̂`` the origin p moves by ``ρ + φ × p`` to first order, so
    ``J = [I, −p^]`` and the result is ``J Σ Jᵀ``.
    """
    p = np.asarray(T_parent_child, dtype=float)[:3, 3]
    J = np.hstack([np.eye(3), -so3.hat(p)])
    cov = J @ cov_left @ J.T
    return 0.5 * (cov + cov.T)


def position_bound_m(cov_position_m2: np.ndarray) -> float:
    """sqrt(trace) of a (3, 3) position covariance: the RMS position error it implies (m)."""
    return float(np.sqrt(max(np.trace(cov_position_m2), 0.0)))


def covariance_world_agv(cov_cam_marker: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """Covariance (6, 6) of ``T_world_agv = T_world_marker·T_cam_marker⁻¹·T_agv_cam⁻¹`` in its
    left tangent space (world frame, (ρ, φ)), from the covariance of ``T_cam_marker``.

    A left perturbation δ of ``T_cam_marker`` becomes ``−Ad(T_world_cam)·δ`` on ``T_world_agv``
    (the marker map and the extrinsic are taken as exact), so Σ_world = Ad Σ Adᵀ.
    """
    Ad = se3.adjoint(T_world_cam)
    cov = Ad @ cov_cam_marker @ Ad.T
    return 0.5 * (cov + cov.T)


def left_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """δ (6,) with ``T_est = Exp(δ)·T_true``: the estimation error in the left tangent space."""
    return se3.log(T_est @ se3.inverse(T_true))


def nees(T_est: np.ndarray, T_true: np.ndarray, cov_left: np.ndarray) -> float:
    """Normalised estimation error squared ``δᵀ Σ⁻¹ δ`` (δ = :func:`left_error`).

    For a consistent estimator (errors Gaussian with covariance Σ) its mean over frames is the
    number of degrees of freedom, 6; much larger means the covariance is over-confident.
    """
    delta = left_error(T_est, T_true)
    return float(delta @ np.linalg.solve(cov_left, delta))
