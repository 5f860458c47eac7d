"""Cramér–Rao lower bound for the pose of a correction cycle's start frame F from a whole window
of sightings (paper 002's multi-frame set-up). Numpy only.

Noise model: every measured ideal pixel coordinate of every corner in every frame and camera
carries independent zero-mean Gaussian noise σ (px); the navigation's relative poses
``T_F_cam`` and the marker map are exact. The Fisher information of the left perturbation δ of
``T_F_world`` (``T_F_world = Exp(δ)·T̂``, δ = (ρ, φ)) is ``JᵀJ / σ²`` with J the pixel Jacobian of
:func:`agvviz.solvers.bundle.pixel_residuals_and_jacobian` at the TRUE pose.

Position: ``T_world_F = T_F_world⁻¹`` moves by ``T_world_F·Exp(−δ)``, so F's origin moves by
``−R_world_F·ρ`` to first order; its covariance is ``R Σ_ρρ Rᵀ`` and the RMS position bound is
``sqrt(trace Σ_ρρ)`` whatever R is.
"""

from __future__ import annotations

import numpy as np

from agvviz.solvers.bundle import pixel_residuals_and_jacobian
from agvviz.solvers.cnoem import CornerWindow
from agvviz.solvers.uncertainty import UncertaintyError, _inverse_information


def window_crlb(window: CornerWindow, T_true_world_F: np.ndarray, sigma_px: float) -> np.ndarray:
    """CRLB (6, 6) on ``T_F_world`` in its left tangent space (ρ, φ) at the true pose.

    Raises :class:`agvviz.solvers.uncertainty.UncertaintyError` when the window does not
    determine the pose (singular information) or a corner is behind its camera.
    """
    if not sigma_px > 0.0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    T_F_world = np.linalg.inv(np.asarray(T_true_world_F, dtype=float))
    if not np.all(window.points_cam(T_F_world)[:, 2] > 0.0):
        raise UncertaintyError("a window corner is behind its camera at the true pose: no CRLB")
    _, J = pixel_residuals_and_jacobian(window, T_F_world)
    return sigma_px**2 * _inverse_information(J.T @ J, "window CRLB")


def position_bound_m(cov_F_world: np.ndarray) -> float:
    """RMS position bound (m) of F's origin in the world: ``sqrt(trace Σ_ρρ)``."""
    return float(np.sqrt(max(np.trace(np.asarray(cov_F_world)[:3, :3]), 0.0)))


def condition_number(window: CornerWindow, T_true_world_F: np.ndarray) -> float:
    """Condition number of the (translation-in-m, rotation-in-rad) information matrix: how close
    the window is to not determining the pose (large for far, on-axis markers)."""
    _, J = pixel_residuals_and_jacobian(window, np.linalg.inv(np.asarray(T_true_world_F, dtype=float)))
    e = np.linalg.eigvalsh(J.T @ J)
    return float(e[-1] / e[0]) if e[0] > 0 else float("inf")
