"""Planar-prior pose solver for ground vehicles: x, y and heading only (SE(2)). Numpy/SciPy only.

Prior: the AGV frame's origin is on the floor (world z = 0) and its z axis is vertical (pitch
= roll = 0); the camera is rigidly mounted at the known ``T_agv_cam`` (height and tilt); the
code lies on the floor plane, printed face up. Then only the AGV's floor position (x, y) and
heading ψ are unknown, and every other degree of freedom of the 6-DoF solution — the ones a
fronto-parallel view determines worst (tilt against lateral translation) — is fixed.

Solution
    1. Closed form: each pixel's viewing ray, expressed in the AGV frame through the mount,
       meets the floor z = 0 at a point in AGV coordinates; a 2-D least-squares rigid fit
       (Kabsch) of those points to the code's world (x, y) gives x, y, ψ.
    2. Levenberg–Marquardt (:func:`agvviz.solvers.lm_core.minimize`) on the pixel reprojection
       error (paper 000 eq 22, the maximum-likelihood objective) over δ = (δx, δy, δψ), a
       perturbation in the AGV body frame: ``T_world_agv ← T_world_agv · Exp((δx, δy, 0, 0, 0, δψ))``.
    3. Prior check (a likelihood-ratio test): a free 6-DoF fit (pixel objective, started from
       the planar solution) must not explain the pixels significantly better. With a known
       pixel σ: ``(RSS₃ − RSS₆)/σ² ~ χ²(3)``; without: ``((RSS₃ − RSS₆)/3)/(RSS₆/(2N − 6)) ~
       F(3, 2N − 6)``. Above the ``test_level`` quantile the prior is declared violated.

Failures are returned as a reason that starts with "planar prior violated:" when the prior
does not hold (code off the floor, ray above the horizon, the test rejects), so a user sees
which assumption broke.

Covariance: ``σ²(JᵀJ)⁻¹`` (3, 3) over (x, y, ψ) in the body-frame perturbation above, J the
pixel Jacobian (2N, 3) of :func:`pixel_jacobian_planar`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from agvviz.geometry import se3, so3
from agvviz.geometry.camera import ideal_camera
from agvviz.geometry.euler import Rz
from agvviz.solvers import chi2, lm_core
from agvviz.solvers.lm import refine_lm

#: Columns (δx, δy, δψ) of the 6-vector (ρ, φ) the planar solver perturbs.
PLANAR_DOF = (0, 1, 5)


@dataclass(frozen=True)
class PlanarPrior:
    """What the planar solver assumes and needs.

    T_agv_cam : (4, 4) camera mounting (height, tilt) in the AGV frame.
    T_world_marker : (4, 4) the code's marker frame in the world (from its payload).
    sigma_px : pixel noise σ for the χ² prior test; ``None`` uses the F test (σ unknown).
    floor_tol_m : largest |z| of the code centre above/below the floor plane.
    floor_tol_deg : largest angle between the code's normal and world +z.
    test_level : quantile of the prior test above which the prior counts as violated.
    """

    T_agv_cam: np.ndarray
    T_world_marker: np.ndarray
    sigma_px: float | None = None
    floor_tol_m: float = 0.01
    floor_tol_deg: float = 1.0
    test_level: float = 0.999


@dataclass
class PlanarSolution:
    """T_world_agv (4, 4) planar pose, T_cam_marker (4, 4) the implied marker pose,
    test_statistic and test_threshold of the prior check, rss_px2 (Σ squared residuals)."""

    T_world_agv: np.ndarray
    T_cam_marker: np.ndarray
    test_statistic: float
    test_threshold: float
    rss_px2: float


def planar_pose(x_m: float, y_m: float, heading_rad: float) -> np.ndarray:
    """T_world_agv on the floor: position (x, y, 0), rotation Rz(heading)."""
    return se3.make(Rz(heading_rad), [x_m, y_m, 0.0])


def _points_cam(T_world_agv, T_agv_cam, points_world_m) -> np.ndarray:
    return se3.transform_points(se3.inverse(T_world_agv @ T_agv_cam), points_world_m)


def _residuals(T_world_agv, T_agv_cam, points_world_m, pixels_px, K) -> np.ndarray:
    """Pixel residuals (2N,) of the pose (every point must be in front of the camera)."""
    projected = _points_cam(T_world_agv, T_agv_cam, points_world_m) @ K.T
    return (projected[:, :2] / projected[:, 2:3] - pixels_px).reshape(-1)


def _retract_body(T_world_agv: np.ndarray, delta3: np.ndarray) -> np.ndarray:
    """``T_world_agv · Exp((δx, δy, 0, 0, 0, δψ))`` (module docstring)."""
    delta = np.zeros(6)
    delta[list(PLANAR_DOF)] = delta3
    return T_world_agv @ se3.exp(delta)


def pixel_jacobian_planar(
    T_world_agv: np.ndarray, T_agv_cam: np.ndarray, points_world_m: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """``J_pixels_wrt_(δx, δy, δψ)`` (2N, 3) for the body-frame perturbation
    ``T_world_agv · Exp(δ)`` (module docstring), at points ``points_world_m`` (N, 3)."""
    T_agv_world = se3.inverse(T_world_agv)
    p_agv = se3.transform_points(T_agv_world, points_world_m)
    T_cam_agv = se3.inverse(T_agv_cam)
    w = se3.transform_points(T_cam_agv, p_agv)
    _, J_px_wrt_w = ideal_camera(K).project_with_jacobian(w)
    # p_agv ← Exp(−δ)·p_agv, so ∂p_agv/∂δ = −[I, −p^]; then w = T_cam_agv·p_agv.
    J_w_wrt_delta = -T_cam_agv[:3, :3] @ se3.J_point_wrt_left_perturbation(p_agv)
    return (J_px_wrt_w @ J_w_wrt_delta[:, :, PLANAR_DOF]).reshape(-1, 3)


def pixel_jacobian_planar_wrt_extrinsic(
    T_world_agv: np.ndarray, T_agv_cam: np.ndarray, points_world_m: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """``J_pixels_wrt_(δt, δφ)`` (2N, 6) of an error of the extrinsic as recorded,
    ``T_agv_cam = [Exp(δφ)·R, t + δt]`` (δφ in the AGV frame) = ``Exp(ξ)·T_agv_cam`` with
    ``ξ = (δt + t^·δφ, δφ)``: the planar model's residuals go through it."""
    p_agv = se3.transform_points(se3.inverse(T_world_agv), points_world_m)
    T_cam_agv = se3.inverse(T_agv_cam)
    w = se3.transform_points(T_cam_agv, p_agv)
    _, J_px_wrt_w = ideal_camera(K).project_with_jacobian(w)
    # w = T_agv_cam⁻¹·Exp(−ξ)·p_agv, so ∂w/∂ξ = −R_cam_agv·[I, −p_agv^].
    J_w_wrt_xi = -T_cam_agv[:3, :3] @ se3.J_point_wrt_left_perturbation(p_agv)
    G = np.eye(6)
    G[:3, 3:] = so3.hat(np.asarray(T_agv_cam, dtype=float)[:3, 3])
    return (J_px_wrt_w @ J_w_wrt_xi).reshape(-1, 6) @ G


def _floor_points_agv(pixels_px, K, T_agv_cam) -> np.ndarray | None:
    """Where each pixel's ray meets the floor z = 0, in AGV coordinates (N, 2), or None."""
    rays_cam = np.c_[pixels_px, np.ones(len(pixels_px))] @ np.linalg.inv(K).T
    rays_agv = rays_cam @ T_agv_cam[:3, :3].T
    origin = T_agv_cam[:3, 3]
    if not np.all(rays_agv[:, 2] < 0.0):
        return None
    scale = -origin[2] / rays_agv[:, 2]
    return (origin[None, :] + scale[:, None] * rays_agv)[:, :2]


def _rigid_2d(source_xy: np.ndarray, target_xy: np.ndarray) -> tuple[float, float, float]:
    """(x, y, ψ) of the rotation + translation that best maps source onto target (Kabsch)."""
    cs, ct = source_xy.mean(axis=0), target_xy.mean(axis=0)
    a, b = source_xy - cs, target_xy - ct
    heading = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b))
    t = ct - Rz(heading)[:2, :2] @ cs
    return float(t[0]), float(t[1]), float(heading)


def solve_planar(
    points_marker_m: np.ndarray,
    pixels_px: np.ndarray,
    K: np.ndarray,
    prior: PlanarPrior,
    max_iterations: int = 50,
) -> tuple[PlanarSolution | None, str]:
    """Planar pose from N ≥ 4 coplanar marker points and their ideal pixels.

    Returns ``(solution, "")`` or ``(None, reason)``; a reason starting with "planar prior
    violated:" means an assumption of :class:`PlanarPrior` does not hold for this frame.
    """
    K = np.asarray(K, dtype=float)
    T_world_marker = np.asarray(prior.T_world_marker, dtype=float)
    T_agv_cam = np.asarray(prior.T_agv_cam, dtype=float)
    tilt_deg = float(np.degrees(np.arccos(np.clip(T_world_marker[2, 2], -1.0, 1.0))))
    height_m = float(T_world_marker[2, 3])
    if tilt_deg > prior.floor_tol_deg or abs(height_m) > prior.floor_tol_m:
        return None, (
            f"planar prior violated: the code is not on the floor plane (its normal is "
            f"{tilt_deg:.1f}° from vertical, its centre {height_m:+.3f} m from z = 0; tolerance "
            f"{prior.floor_tol_deg:g}°, {prior.floor_tol_m:g} m) — use a 6-DoF solver"
        )
    points_world_m = se3.transform_points(T_world_marker, points_marker_m)
    floor_agv = _floor_points_agv(pixels_px, K, T_agv_cam)
    if floor_agv is None:
        return None, (
            "planar prior violated: a pixel's viewing ray does not meet the floor in front of "
            "the camera (check the camera mounting T_agv_cam)"
        )
    result = lm_core.minimize(
        planar_pose(*_rigid_2d(floor_agv, points_world_m[:, :2])),
        _retract_body,
        residuals_and_jacobian=lambda T: (
            _residuals(T, T_agv_cam, points_world_m, pixels_px, K),
            pixel_jacobian_planar(T, T_agv_cam, points_world_m, K),
        ),
        feasible=lambda T: bool(np.all(_points_cam(T, T_agv_cam, points_world_m)[:, 2] > 0.0)),
        options=lm_core.LmOptions(max_iterations=max_iterations),
    )
    if result.stop_reason == lm_core.START_INFEASIBLE:
        return None, "planar prior violated: the planar start pose puts a point behind the camera"
    if not result.converged:
        return None, "did not converge" if result.stop_reason == lm_core.MAX_ITERATIONS else result.stop_reason
    T, cost = result.x, result.cost
    T_cam_marker = se3.inverse(T @ T_agv_cam) @ T_world_marker
    rss3 = 2.0 * cost

    _, _, iterations = refine_lm(
        T_cam_marker, points_marker_m, pixels_px, K, objective="pixel",
        max_iterations=max_iterations, initial_damping=1e-3, step_tol=1e-12, cost_rel_tol=1e-14,
    )
    rss6 = 2.0 * iterations[-1].cost if iterations else rss3
    rss6 = min(rss6, rss3)  # the 6-DoF model contains the planar one
    n_residuals = 2 * len(points_marker_m)
    if prior.sigma_px is not None:
        statistic = (rss3 - rss6) / prior.sigma_px**2
        threshold = _quantile("chi2", prior.test_level, 3)
        test = f"χ²(3) = {statistic:.1f} > {threshold:.1f} at σ = {prior.sigma_px:g} px"
    elif n_residuals > 6 and rss6 > 0.0:
        statistic = ((rss3 - rss6) / 3.0) / (rss6 / (n_residuals - 6))
        threshold = _quantile("f", prior.test_level, 3, n_residuals - 6)
        test = f"F(3, {n_residuals - 6}) = {statistic:.1f} > {threshold:.1f}"
    else:
        statistic, threshold, test = 0.0, np.inf, ""
    if statistic > threshold:
        return None, (
            f"planar prior violated: a free 6-DoF pose fits the pixels significantly better "
            f"(RMS {np.sqrt(rss3 / len(points_marker_m)):.2f} px planar vs "
            f"{np.sqrt(rss6 / len(points_marker_m)):.2f} px 6-DoF; {test}) — the AGV is not "
            "level on the floor, the mounting is wrong, or the code is not where its payload says"
        )
    return PlanarSolution(T, T_cam_marker, float(statistic), float(threshold), rss3), ""


@functools.lru_cache(maxsize=64)
def _quantile(distribution: str, level: float, *dof: int) -> float:
    """The ``level`` quantile of χ²(dof) or F(dof₁, dof₂) (scipy.stats' ppf), cached (the
    arguments repeat), from :mod:`agvviz.solvers.chi2`: importing scipy.stats costs ≈0.8 s of
    CPU, and a sweep over ``solver=planar`` would pay it in every worker."""
    if distribution == "chi2":
        return float(chi2.chi2_quantile(level, [dof[0]])[0])
    return chi2.f_quantile(level, dof[0], dof[1])


def covariance_planar(
    T_world_agv: np.ndarray, T_agv_cam: np.ndarray, points_world_m: np.ndarray, K: np.ndarray, sigma_px: float
) -> np.ndarray:
    """σ²(JᵀJ)⁻¹ (3, 3) over (x, y, ψ) (body-frame perturbation). At the true pose it is the
    Cramér–Rao bound of the planar model."""
    J = pixel_jacobian_planar(T_world_agv, T_agv_cam, points_world_m, K)
    cov = sigma_px**2 * np.linalg.inv(J.T @ J)
    return 0.5 * (cov + cov.T)


def embed_world_left(cov_planar: np.ndarray, T_world_agv: np.ndarray) -> np.ndarray:
    """The (3, 3) body-frame planar covariance as a (6, 6) covariance of ``T_world_agv`` in the
    left world tangent space (ρ, φ) (rank 3): ``Ad(T)·E·Σ·Eᵀ·Ad(T)ᵀ``."""
    E = np.zeros((6, 3))
    E[list(PLANAR_DOF), [0, 1, 2]] = 1.0
    Ad = se3.adjoint(T_world_agv)
    cov = Ad @ E @ cov_planar @ E.T @ Ad.T
    return 0.5 * (cov + cov.T)


def planar_error(T_est_world_agv: np.ndarray, T_true_world_agv: np.ndarray) -> np.ndarray:
    """(δx, δy, δψ) with ``T_est ≈ T_true·Exp(δ)`` (body frame), from the full 6-vector."""
    return se3.log(se3.inverse(T_true_world_agv) @ T_est_world_agv)[list(PLANAR_DOF)]
