"""Image-space alternative to CNOEM: the start frame's pose minimising the pixel reprojection
error over a whole correction window (the maximum-likelihood estimator under isotropic Gaussian
pixel noise). Numpy only.

Same window, parameters and left perturbation as :mod:`agvviz.solvers.cnoem`
(``T_F_world ← Exp(δ)·T_F_world``); residuals ``f_i = π(K_j P_i^Oj) − (u_i, v_i)``, cost ½‖f‖².
The pixel cost is not quadratic in the translation, so the default start is CNOEM's solution
(translation first, then the ray-cost LM), which sits within noise of the pixel minimum.
"""

from __future__ import annotations

import numpy as np

from agvviz.geometry import se3
from agvviz.solvers.cnoem import CornerWindow, WindowError, WindowSolution, refine_window_lm, solve_cnoem


def pixel_residuals_and_jacobian(window: CornerWindow, T_F_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel residuals (2N,) and ``J_f_wrt_left_perturbation`` (2N, 6) of ``T_F_world``."""
    P_F = window.points_world_m @ T_F_world[:3, :3].T + T_F_world[:3, 3]
    P = (window.R_cam_F @ P_F[:, :, None])[:, :, 0] + window.t_cam_F
    K = window.K
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    x, y = X / Z, Y / Z
    f = np.stack([K[:, 0, 0] * x + K[:, 0, 1] * y + K[:, 0, 2], K[:, 1, 1] * y + K[:, 1, 2]], axis=1)
    f -= window.pixels_px
    J_xy = np.zeros((P.shape[0], 2, 3))
    J_xy[:, 0, 0] = J_xy[:, 1, 1] = 1.0 / Z
    J_xy[:, 0, 2] = -x / Z
    J_xy[:, 1, 2] = -y / Z
    J_f_P = K[:, :2, :2] @ J_xy  # (N, 2, 3)
    J_f_PF = J_f_P @ window.R_cam_F
    px, py, pz = P_F[:, 0], P_F[:, 1], P_F[:, 2]
    J = np.empty((P.shape[0], 2, 6))
    J[:, :, :3] = J_f_PF
    J[:, :, 3] = J_f_PF[:, :, 2] * py[:, None] - J_f_PF[:, :, 1] * pz[:, None]
    J[:, :, 4] = J_f_PF[:, :, 0] * pz[:, None] - J_f_PF[:, :, 2] * px[:, None]
    J[:, :, 5] = J_f_PF[:, :, 1] * px[:, None] - J_f_PF[:, :, 0] * py[:, None]
    return f.reshape(-1), J.reshape(-1, 6)


def pixel_normal_equations(window: CornerWindow, T_F_world: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(½‖f‖², JᵀJ, Jᵀf) of the pixel cost (:func:`pixel_residuals_and_jacobian`)."""
    f, J = pixel_residuals_and_jacobian(window, T_F_world)
    return 0.5 * float(f @ f), J.T @ J, J.T @ f


def solve_bundle(
    window: CornerWindow,
    T_start_world_F: np.ndarray,
    *,
    cnoem_start: bool = True,
    max_iterations: int = 50,
) -> WindowSolution:
    """Pose of F minimising the window's pixel reprojection error.

    Parameters
    ----------
    window : the cycle's sightings.
    T_start_world_F : (4, 4) start pose of F (navigation or IPPE).
    cnoem_start : first solve CNOEM from that start (translation first + LM) and refine its
        solution; otherwise refine ``T_start_world_F`` directly.
    max_iterations : LM steps.

    Returns
    -------
    WindowSolution whose iterations hold the pixel cost ½Σ|f|² (px²); when ``cnoem_start``
    fails its reason is passed on.
    """
    T_start = np.asarray(T_start_world_F, dtype=float)
    if not se3.is_rigid(T_start):
        raise WindowError("the start pose T_world_F must be a finite rigid 4×4 transform")
    if cnoem_start:
        start = solve_cnoem(window, T_start)
        if not start.success:
            return WindowSolution(None, f"CNOEM start failed: {start.reason}", start.iterations)
        T_F_world = start.T_F_world
    else:
        T_F_world = se3.inverse(T_start)
    return refine_window_lm(window, T_F_world, pixel_normal_equations, max_iterations=max_iterations)
