"""One AGV pose from the marker corners seen by several world-fixed cameras (joint LM).

Paper 003 picks the single best camera; with four wall cameras watching one roof code, their
corners can instead be solved together: unknown ``T_world_agv``, every corner of every camera
a pixel residual ``π(K, T_cam_world · T_world_agv · p_agv) − u`` in that camera's ideal
(undistorted) image. Levenberg–Marquardt (:func:`agvviz.solvers.lm_core.minimize`) with the left
perturbation ``T ← Exp(δ)·T``, δ = (ρ, φ) (:mod:`agvviz.conventions`); a step that puts a
corner behind a camera is refused. Cameras far from the code constrain it across their line of sight,
where a single camera is weakest (depth), so the joint pose is better than any one camera's.

``planar=True`` keeps the AGV on the floor: only (x, y, heading) move — the perturbation's
ρx, ρy, φz — from a start projected onto the floor (z = 0, no roll or pitch). A small marker
seen obliquely from far away has two nearly equally good poses (the planar ambiguity); the
wrong one is tilted and its position off by decimetres, which the floor constraint excludes.
Numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.geometry import euler, se3

#: How a multi-camera rig's frame fixes are used (setting ``camera_select``): the best camera's
#: pose, or one pose refined over every camera (:mod:`agvviz.replay.multicam`).
CAMERA_SELECT = ("best", "combine")
from agvviz.solvers import lm_core


@dataclass(frozen=True)
class RigView:
    """What one camera saw: intrinsics ``K`` (3, 3), its fixed pose as ``T_cam_world``, the
    marker points in the agv frame (N, 3) and their ideal pixels (N, 2)."""

    K: np.ndarray
    T_cam_world: np.ndarray
    points_agv_m: np.ndarray
    ideal_px: np.ndarray


def _residuals_and_jacobian(T_world_agv: np.ndarray, views: list[RigView]) -> tuple[np.ndarray, np.ndarray]:
    residuals, jacobians = [], []
    for view in views:
        p_world = se3.transform_points(T_world_agv, view.points_agv_m)
        p_cam = se3.transform_points(view.T_cam_world, p_world)
        X, Y, Z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
        K = view.K
        u = K[0, 0] * X / Z + K[0, 1] * Y / Z + K[0, 2]
        v = K[1, 1] * Y / Z + K[1, 2]
        residuals.append(np.stack([u, v], axis=1) - view.ideal_px)
        J_px_wrt_pcam = np.zeros((len(Z), 2, 3))
        J_px_wrt_pcam[:, 0, 0] = K[0, 0] / Z
        J_px_wrt_pcam[:, 0, 1] = K[0, 1] / Z
        J_px_wrt_pcam[:, 0, 2] = -(K[0, 0] * X + K[0, 1] * Y) / Z**2
        J_px_wrt_pcam[:, 1, 1] = K[1, 1] / Z
        J_px_wrt_pcam[:, 1, 2] = -K[1, 1] * Y / Z**2
        J_pworld_wrt_delta = se3.J_point_wrt_left_perturbation(p_world)  # (N, 3, 6)
        jacobians.append(J_px_wrt_pcam @ view.T_cam_world[:3, :3] @ J_pworld_wrt_delta)
    return np.concatenate(residuals).ravel(), np.concatenate(jacobians).reshape(-1, 6)


def on_floor(T_world_agv: np.ndarray) -> np.ndarray:
    """``T_world_agv`` projected onto the floor: same x, y and heading, z = 0, no roll/pitch."""
    heading = euler.hpr_from_matrix(np.asarray(T_world_agv)[:3, :3])[0]
    return se3.make(euler.Rz(heading), [T_world_agv[0, 3], T_world_agv[1, 3], 0.0])


def _all_in_front(T_world_agv: np.ndarray, views: list[RigView]) -> bool:
    return all(
        np.all(se3.transform_points(view.T_cam_world @ T_world_agv, view.points_agv_m)[:, 2] > 0.0)
        for view in views
    )


def refine_rig_pose(
    T_world_agv: np.ndarray,
    views: list[RigView],
    planar: bool = False,
    max_iterations: int = 30,
    step_tol: float = 1e-12,
) -> tuple[np.ndarray, float]:
    """Refine ``T_world_agv`` on the corners of every view. Returns (pose, RMS pixel error):
    the best pose when the iteration budget runs out.

    Raises ``ValueError`` when there are no views, a point is behind a camera at the start, or
    the pose is not determined (non-finite numbers, singular normal equations).
    """
    if not views:
        raise ValueError("no camera views to refine the pose on")
    T = on_floor(T_world_agv) if planar else np.asarray(T_world_agv, dtype=float).copy()
    free = [0, 1, 5] if planar else list(range(6))

    def retract(T_: np.ndarray, delta: np.ndarray) -> np.ndarray:
        step = np.zeros(6)
        step[free] = delta
        return se3.exp(step) @ T_

    def residuals_and_jacobian(T_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, J = _residuals_and_jacobian(T_, views)
        return r, J[:, free]

    result = lm_core.minimize(
        T,
        retract,
        residuals_and_jacobian=residuals_and_jacobian,
        feasible=lambda T_: _all_in_front(T_, views),
        options=lm_core.LmOptions(max_iterations=max_iterations, step_tol=step_tol),
    )
    if result.stop_reason == lm_core.START_INFEASIBLE:
        raise ValueError("a marker point is behind a camera at the start pose")
    if result.failed:
        raise ValueError(f"the joint pose is not determined: {result.stop_reason}")
    n_points = sum(len(view.points_agv_m) for view in views)
    return result.x, float(np.sqrt(2.0 * result.cost / n_points))
