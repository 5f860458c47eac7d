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

Systematic sources (:func:`frame_covariance_full`)
    Besides the pixel noise, a pose inherits the errors of everything it is computed from and
    takes as exact: the camera's calibration, its extrinsic, the map, and each marker's own
    systematic corner error. Each is a parameter θ (error zero-mean Gaussian, covariance Σ_θ,
    independent of the others and of the noise) propagated to first order through the solution
    by the implicit-function theorem: the estimate minimises ``Σ wᵢ rᵢ(T, θ)²`` so
    ``dT/dθ = −(JᵀWJ)⁻¹JᵀW ∂r/∂θ`` and ``Σ = Σ_noise + Σ_θ (dT/dθ) Σ_θ (dT/dθ)ᵀ``. The pose
    solved is ``T_cam_F`` — the camera against the frame F the markers are fixed in (the world
    for floor codes, the AGV for a code on the AGV), so a map error moves the points the
    residuals are computed from (a single marker's pose absorbs its placement exactly: the
    first-order result is that rigid shift). Per frame:

    * noise — independent σ (px) on every ideal pixel coordinate (the pooled residual estimate).
      Any error independent between corners — the detector's noise AND a corner's own printed
      or refined offset, even one that stays the same in every frame — is in the residuals in
      the same proportion (2N − 6 of 2N dimensions), so the dof-corrected residual σ already
      holds it: it is not added again;
    * corner bias — what the residuals cannot hold: each marker's outline seen grown or shrunk
      (ink spread, light bleeding into dark areas, the refiner's template against a blurred
      edge), every point moved away from the marker's centre by a common fraction s — an
      apparent scale the pose's fit turns into range without a residual (for one marker
      exactly). σ_s = ``corner_bias_px`` ÷ the marker's RMS pixel distance of its points from
      their mean in this frame, so the outline moves by about ``corner_bias_px`` in the image;
      drawn once per marker (independent between markers) and kept in every frame;
    * intrinsics — fx, fy (σ ``focal_px`` each), cx, cy (σ ``principal_point_px`` each), through
      the projection ``u = fx·x/z + cx``;
    * distortion — k1, k2, p1, p2 of the undistortion that made the ideal pixels: an error δk1
      moves an ideal pixel by ``f·δk1·r²·(x, y)`` (normalised x, y, r² = x² + y²), k2 by r⁴,
      p1 by ``f·(2xy, r² + 2y²)``, p2 by ``f·(r² + 2x², 2xy)``;
    * map — each marker's mapped pose ``T_F_marker``: position (σ ``map_position_m`` along F's
      x and y, ``map_height_m`` along z), rotation right-perturbed in the marker frame
      ``R·Exp((tx, ty, yaw))`` (σ ``map_tilt_rad`` about x and y, ``map_yaw_rad`` about the
      normal), printed scale ``(1 + s)`` about its centre (σ ``map_scale``) — the draws of
      :mod:`agvviz.sim.realism`'s map source, independent per marker;
    * extrinsic — the camera's mounting ``T_parent_cam`` (AGV or world), ``R = Exp(δφ)·R̂``
      (δφ in the parent frame, σ ``extrinsic_rotation_rad`` per axis), ``t = t̂ + δt``
      (σ ``extrinsic_translation_m`` per axis): it is not in the residuals and moves
      ``T_world_agv`` directly (:func:`extrinsic_covariance_world`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.errors import RunError

from agvviz.geometry import se3, so3
from agvviz.geometry.camera import ideal_camera

#: Covariance-producing objectives (see the module docstring).
OBJECTIVES = ("depth", "pixel")


class UncertaintyError(RunError):
    """The geometry does not determine the pose (singular information matrix) or bad input."""


def pixel_jacobian(T_cam_marker: np.ndarray, points_marker_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``J_pixels_wrt_left_perturbation`` (2N, 6) of the ideal pixels of ``points_marker_m``
    (N, 3) at pose ``T_cam_marker``; rows stacked per point as (u, v), δ = (ρ, φ)."""
    w = se3.transform_points(T_cam_marker, points_marker_m)
    if not (w[:, 2] > 0.0).all():
        raise UncertaintyError("a point is not in front of the camera: no pixel Jacobian")
    _, J_px_wrt_w = ideal_camera(K).project_with_jacobian(w)
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


@dataclass(frozen=True)
class SystematicSigmas:
    """σ of each systematic error source of a frame's pose (module docstring; 0 = exact).
    Angles in radians, lengths in metres, pixels in px, scale and distortion unitless."""

    corner_bias_px: float = 0.0  # each marker's outline shift (px): an apparent scale about its centre
    #: The outline shift of a QR symbol (px), for the caller to give per marker (``markers``'
    #: third element): no solid border, so its refined outline moves less (docs/uncertainty.md).
    qr_outline_px: float = 0.0
    focal_px: float = 0.0
    principal_point_px: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    extrinsic_rotation_rad: float = 0.0
    extrinsic_translation_m: float = 0.0
    map_position_m: float = 0.0
    map_height_m: float = 0.0
    map_yaw_rad: float = 0.0
    map_tilt_rad: float = 0.0
    map_scale: float = 0.0


#: Sources of :func:`frame_covariance_parts`, in order (``extrinsic`` is added in the world).
SOURCES = ("noise", "corner_bias", "intrinsics", "distortion", "map")


def _stack(markers) -> tuple[np.ndarray, list[slice]]:
    """Points in F (N, 3) and each marker's row slice of them."""
    points_F, slices, start = [], [], 0
    for T_F_marker, points_marker_m, *_ in markers:
        pts = se3.transform_points(np.asarray(T_F_marker, dtype=float), np.asarray(points_marker_m, dtype=float))
        points_F.append(pts)
        slices.append(slice(start, start + len(pts)))
        start += len(pts)
    return np.vstack(points_F), slices


def frame_covariance_parts(
    T_cam_F: np.ndarray,
    markers: list[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    sigma_px: float,
    sigmas: SystematicSigmas,
    objective: str = "pixel",
) -> dict[str, np.ndarray]:
    """Covariance (6, 6) of ``T_cam_F`` (left, (ρ, φ)) from each source of :data:`SOURCES`.

    ``markers`` lists each marker's mapped pose ``T_F_marker`` (4, 4) and its points (n, 3) in
    its own frame, in the order of the residual rows, and optionally third its outline shift σ
    (px; default ``sigmas.corner_bias_px``); ``T_cam_F`` is the solution. The
    estimator is the ``objective``'s (weights 1 or z², as :func:`covariance`): each part is
    ``H B Σ_θ Bᵀ Hᵀ`` with ``H = (JᵀWJ)⁻¹JᵀW`` and B the pixels' Jacobian w.r.t. θ.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; valid: {', '.join(OBJECTIVES)}")
    view = _View(np.asarray(T_cam_F, dtype=float), markers, np.asarray(K, dtype=float))
    J = (view.J_px_wrt_w @ se3.J_point_wrt_left_perturbation(view.w_cam)).reshape(-1, 6)
    weight = np.ones(2 * view.n) if objective == "pixel" else np.repeat(view.w_cam[:, 2] ** 2, 2)
    bread = _inverse_information(J.T @ (weight[:, None] * J), "covariance")
    H = bread @ (J * weight[:, None]).T  # (6, 2N): dδ = −H dr
    parts = {"noise": sigma_px**2 * H @ H.T}  # pixel: σ²(JᵀJ)⁻¹; depth: the sandwich
    parts.update(view.systematic_parts(H, sigmas))
    return {name: 0.5 * (parts[name] + parts[name].T) for name in SOURCES}


class _View:
    """One frame's points seen by the camera at ``T_cam_F``: what every source's B needs."""

    def __init__(self, T_cam_F: np.ndarray, markers, K: np.ndarray):
        self.markers = markers
        self.K = K
        points_F, self.slices = _stack(markers)
        self.w_cam = se3.transform_points(T_cam_F, points_F)
        if not (self.w_cam[:, 2] > 0.0).all():
            raise UncertaintyError("a point is not in front of the camera: no pixel Jacobian")
        self.n = len(points_F)
        self.pixels, self.J_px_wrt_w = ideal_camera(K).project_with_jacobian(self.w_cam)  # (N, 2), (N, 2, 3)
        self.J_px_wrt_F = self.J_px_wrt_w @ T_cam_F[:3, :3]  # (N, 2, 3): points moved in F

    def systematic_parts(self, H: np.ndarray, sigmas: SystematicSigmas) -> dict[str, np.ndarray]:
        """``H B Σ_θ Bᵀ Hᵀ`` (k, k) of corner bias, intrinsics, distortion and map for the
        sensitivity ``H`` (k, 2N) of the estimate's k parameters to the residuals."""
        factors = self.systematic_factors(H, sigmas)
        k = H.shape[0]
        return {
            name: sum((S @ S.T for S in (value if isinstance(value, list) else [value])), np.zeros((k, k)))
            for name, value in factors.items()
        }

    def systematic_factors(self, H: np.ndarray, sigmas: SystematicSigmas) -> dict:
        """Signed factors of the systematic sources: each column is the change of the estimate's
        k parameters for a one-σ error of one source parameter, ``−H B_j σ_j`` (dδ = −H dr):
        ``intrinsics`` (k, 4: fx, fy, cx, cy), ``distortion`` (k, 4: k1, k2, p1, p2) and, one per
        marker in the order of ``markers``, ``corner_bias`` (k, 1: the marker's outline grown or
        shrunk by its outline σ in px — a marker's third element, else ``corner_bias_px``) and ``map`` (k, 7: position x, y, z, tilt x, y, yaw, scale). A source's
        covariance is S Sᵀ (summed over the markers)."""
        k, n = H.shape[0], self.n
        H_pt = H.reshape(k, n, 2).transpose(1, 0, 2)  # (N, k, 2): H's columns of each point
        factors = {}
        # Intrinsics: u = fx·x/z + cx, v = fy·y/z + cy (ideal pixels: no skew, no distortion).
        xn, yn = self.w_cam[:, 0] / self.w_cam[:, 2], self.w_cam[:, 1] / self.w_cam[:, 2]
        B_K = np.zeros((n, 2, 4))
        B_K[:, 0, 0], B_K[:, 1, 1], B_K[:, 0, 2], B_K[:, 1, 3] = xn, yn, 1.0, 1.0
        sigma_K = np.array([sigmas.focal_px, sigmas.focal_px, sigmas.principal_point_px, sigmas.principal_point_px])
        factors["intrinsics"] = -(H @ B_K.reshape(-1, 4)) * sigma_K
        r2 = xn**2 + yn**2
        fx, fy = self.K[0, 0], self.K[1, 1]
        # u (row 0) scales with fx, v (row 1) with fy; column by column, without stacking them
        B_D = np.zeros((n, 2, 4))
        B_D[:, 0, 0], B_D[:, 1, 0] = r2 * xn * fx, r2 * yn * fy
        B_D[:, 0, 1], B_D[:, 1, 1] = r2**2 * xn * fx, r2**2 * yn * fy
        B_D[:, 0, 2], B_D[:, 1, 2] = 2 * xn * yn * fx, (r2 + 2 * yn**2) * fy
        B_D[:, 0, 3], B_D[:, 1, 3] = (r2 + 2 * xn**2) * fx, 2 * xn * yn * fy
        factors["distortion"] = -(H @ B_D.reshape(-1, 4)) * np.array([sigmas.k1, sigmas.k2, sigmas.p1, sigmas.p2])
        # Per marker: points in F move by dX_F; pixels by J_px_wrt_F · dX_F.
        sigma_map = np.array([sigmas.map_position_m, sigmas.map_position_m, sigmas.map_height_m,
                              sigmas.map_tilt_rad, sigmas.map_tilt_rad, sigmas.map_yaw_rad, sigmas.map_scale])
        factors["corner_bias"], factors["map"] = [], []
        for (T_F_marker, points_marker_m, *outline), rows in zip(self.markers, self.slices):
            R = np.asarray(T_F_marker, dtype=float)[:3, :3]
            x = np.asarray(points_marker_m, dtype=float)
            Jm = self.J_px_wrt_F[rows]  # (n_i, 2, 3)
            Hm = H_pt[rows]  # (n_i, k, 2)
            bias = np.zeros((k, 1))
            outline_px = float(outline[0]) if outline else sigmas.corner_bias_px
            if outline_px > 0.0 and len(x) >= 2:
                px = self.pixels[rows]
                spread_px = np.sqrt(np.mean(np.sum((px - px.mean(axis=0)) ** 2, axis=1)))
                if spread_px > 0.0:
                    # The outline grown or shrunk: every point moves away from the marker's
                    # centre by a common fraction s, σ_s = outline_px ÷ its RMS pixel radius.
                    sigma_s = outline_px / spread_px
                    d_px = np.einsum("nij,nj->ni", Jm, (x - x.mean(axis=0)) @ R.T)  # (n_i, 2) per unit s
                    bias = -sigma_s * np.einsum("nij,nj->i", Hm, d_px)[:, None]  # (k, 1)
            factors["corner_bias"].append(bias)
            dX = np.zeros((len(x), 3, 7))
            dX[:, :, :3] = np.eye(3)
            dX[:, :, 3:6] = -np.einsum("ij,njk->nik", R, _hat_rows(x))  # R·Exp(φ)·x: −R·x^·φ
            dX[:, :, 6] = x @ R.T
            HB = np.einsum("nij,njk->ik", Hm, Jm @ dX)  # (k, 7): summed over the marker's points
            factors["map"].append(-HB * sigma_map)
        return factors


def planar_covariance_full(
    J_planar: np.ndarray,
    J_planar_wrt_extrinsic: np.ndarray,
    T_cam_world: np.ndarray,
    markers: list[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    sigma_px: float,
    sigmas: SystematicSigmas,
) -> np.ndarray:
    """Covariance (3, 3) of the ``planar`` solver's (x, y, ψ) with every systematic source.

    ``J_planar`` (2N, 3) is the pixels' Jacobian w.r.t. the planar parameters,
    ``J_planar_wrt_extrinsic`` (2N, 6) w.r.t. the extrinsic's (δt, δφ) (the extrinsic is in the
    planar model's residuals); markers in the world (F = world, ``T_cam_world``). The ML
    estimator: ``H = (JᵀJ)⁻¹Jᵀ``, noise ``σ²(JᵀJ)⁻¹``."""
    view = _View(np.asarray(T_cam_world, dtype=float), markers, np.asarray(K, dtype=float))
    bread = _inverse_information(J_planar.T @ J_planar, "planar covariance")
    H = bread @ J_planar.T
    cov = sigma_px**2 * bread + sum(view.systematic_parts(H, sigmas).values())
    HB = H @ J_planar_wrt_extrinsic
    variances = np.array([sigmas.extrinsic_translation_m] * 3 + [sigmas.extrinsic_rotation_rad] * 3) ** 2
    cov = cov + (HB * variances) @ HB.T
    return 0.5 * (cov + cov.T)


def _hat_rows(x: np.ndarray) -> np.ndarray:
    """(n, 3, 3) skew matrices of the rows of ``x`` (n, 3)."""
    out = np.zeros((len(x), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -x[:, 2], x[:, 1]
    out[:, 1, 0], out[:, 1, 2] = x[:, 2], -x[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -x[:, 1], x[:, 0]
    return out


def extrinsic_factor_world(
    T_world_agv: np.ndarray, T_parent_cam: np.ndarray, camera_on_agv: bool, sigmas: SystematicSigmas
) -> np.ndarray:
    """Signed factor (6, 6) of the extrinsic's share of ``T_world_agv``'s covariance (left,
    world, (ρ, φ)): column j is the pose's change for a one-σ error of the extrinsic's
    parameter j = (δt x, y, z, δφ x, y, z); the share is S Sᵀ.

    The recorded ``T_parent_cam = [Exp(δφ)·R, t + δt]`` is ``Exp(ξ)·T_parent_cam`` with
    ``ξ = (δt + t^·δφ, δφ)`` to first order. A camera on the AGV (parent = AGV):
    ``T_world_agv = T_world_cam·T_agv_cam⁻¹`` moves by ``−Ad(T_world_agv)·ξ``; a camera fixed in
    the world (parent = world): ``T_world_agv = T_world_cam·T_cam_agv`` moves by ξ.
    """
    t = np.asarray(T_parent_cam, dtype=float)[:3, 3]
    G = np.eye(6)
    G[:3, 3:] = so3.hat(t)
    if camera_on_agv:
        G = -se3.adjoint(np.asarray(T_world_agv, dtype=float)) @ G
    return G * np.array([sigmas.extrinsic_translation_m] * 3 + [sigmas.extrinsic_rotation_rad] * 3)


def extrinsic_covariance_world(
    T_world_agv: np.ndarray, T_parent_cam: np.ndarray, camera_on_agv: bool, sigmas: SystematicSigmas
) -> np.ndarray:
    """Covariance (6, 6) of ``T_world_agv`` (left, world, (ρ, φ)) from the camera's extrinsic
    (:func:`extrinsic_factor_world`)."""
    S = extrinsic_factor_world(T_world_agv, T_parent_cam, camera_on_agv, sigmas)
    cov = S @ S.T
    return 0.5 * (cov + cov.T)


def frame_covariance_full(
    T_cam_F: np.ndarray,
    markers: list[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    sigma_px: float,
    sigmas: SystematicSigmas,
    T_world_cam: np.ndarray,
    T_world_agv: np.ndarray,
    T_parent_cam: np.ndarray | None,
    camera_on_agv: bool,
    objective: str = "pixel",
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Covariance (6, 6) of ``T_world_agv`` (left, world, (ρ, φ)) with every systematic source,
    and each source's share ``{source: (6, 6)}`` (:data:`SOURCES` and ``extrinsic``).
    ``T_parent_cam`` is the camera's extrinsic (``T_agv_cam`` when ``camera_on_agv``, else
    ``T_world_cam``); ``None`` leaves the extrinsic out."""
    parts = {
        name: covariance_world_agv(cov, T_world_cam)
        for name, cov in frame_covariance_parts(T_cam_F, markers, K, sigma_px, sigmas, objective).items()
    }
    parts["extrinsic"] = (
        np.zeros((6, 6)) if T_parent_cam is None
        else extrinsic_covariance_world(T_world_agv, T_parent_cam, camera_on_agv, sigmas)
    )
    total = sum(parts.values())
    return 0.5 * (total + total.T), parts


# -- common-mode split: what two poses of one camera share ---------------------------------------
#: Key of the camera's own factor in :func:`frame_covariance_split`; each marker's is ``marker:<id>``.
CAMERA_GROUP = "camera"


def marker_group(marker_id: str) -> str:
    return f"marker:{marker_id}"


def frame_covariance_split(
    T_cam_F: np.ndarray,
    markers: list[tuple[np.ndarray, np.ndarray]],
    marker_ids: list[str],
    K: np.ndarray,
    sigma_px: float,
    sigmas: SystematicSigmas,
    T_world_cam: np.ndarray,
    T_world_agv: np.ndarray,
    T_parent_cam: np.ndarray | None,
    camera_on_agv: bool,
    objective: str = "pixel",
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """:func:`frame_covariance_full`'s covariance (6, 6) of ``T_world_agv`` and its **common-mode
    factors** ``{group: S (6, p)}``, signed, in the same tangent space: the sources whose
    parameters recur in another frame — :data:`CAMERA_GROUP`, the camera's intrinsics,
    distortion and extrinsic (4 + 4 + 6 columns), the same in every frame of the camera; and
    ``marker:<id>`` (:func:`marker_group`, ``marker_ids`` in the order of ``markers``), the
    marker's corner offsets and map entry (2n + 7 columns), the same in every frame that uses
    it. Column j is the pose's change for a one-σ error of parameter j, so a group's share is
    S Sᵀ; the rest (pixel noise) is independent between frames. Two poses sharing a group's
    parameters have correlated errors: :func:`difference_covariance`."""
    if len(marker_ids) != len(markers):
        raise ValueError(f"{len(marker_ids)} marker ids for {len(markers)} markers")
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; valid: {', '.join(OBJECTIVES)}")
    view = _View(np.asarray(T_cam_F, dtype=float), markers, np.asarray(K, dtype=float))
    J = (view.J_px_wrt_w @ se3.J_point_wrt_left_perturbation(view.w_cam)).reshape(-1, 6)
    weight = np.ones(2 * view.n) if objective == "pixel" else np.repeat(view.w_cam[:, 2] ** 2, 2)
    bread = _inverse_information(J.T @ (weight[:, None] * J), "covariance")
    H = bread @ (J * weight[:, None]).T
    # A left perturbation δ of T_cam_F moves T_world_agv by −Ad(T_world_cam)·δ when the markers are
    # fixed in the world (camera on the AGV), by +Ad(T_world_cam)·δ when they ride on the AGV.
    to_world = (-1.0 if camera_on_agv else 1.0) * se3.adjoint(np.asarray(T_world_cam, dtype=float))
    noise = covariance_world_agv(sigma_px**2 * H @ H.T, T_world_cam)
    factors = view.systematic_factors(H, sigmas)
    camera = [to_world @ factors["intrinsics"], to_world @ factors["distortion"]]
    camera.append(
        np.zeros((6, 6)) if T_parent_cam is None
        else extrinsic_factor_world(T_world_agv, T_parent_cam, camera_on_agv, sigmas)
    )
    groups = {CAMERA_GROUP: np.hstack(camera)}
    for marker_id, bias, placement in zip(marker_ids, factors["corner_bias"], factors["map"]):
        groups[marker_group(marker_id)] = to_world @ np.hstack([bias, placement])
    total = noise + sum(S @ S.T for S in groups.values())
    return 0.5 * (total + total.T), groups


def _point_jacobian(point_world_m: np.ndarray) -> np.ndarray:
    """(6, 6) from a left perturbation (ρ, φ) of a pose to (the change of a world point rigidly
    attached to it, φ): ``[[I, −p^], [0, I]]``."""
    J = np.eye(6)
    J[:3, 3:] = -so3.hat(np.asarray(point_world_m, dtype=float))
    return J


def difference_covariance(
    cov_a: np.ndarray, factors_a: dict[str, np.ndarray] | None, point_a_m: np.ndarray,
    cov_b: np.ndarray, factors_b: dict[str, np.ndarray] | None, point_b_m: np.ndarray,
) -> np.ndarray:
    """Covariance (6, 6) of the difference (``point_b − point_a``, rotation vector of
    ``R_b·R_aᵀ``) between two pose estimates a and b, each with its covariance (left, world,
    (ρ, φ)) and common-mode factors (:func:`frame_covariance_split`; None: all independent).
    ``point_*_m`` is the world point compared, rigidly attached to its pose (the AGV origin; for a
    pose carried on by a step, ``T_a·step``, the carried origin: a left perturbation of ``T_a``
    is one of ``T_a·step``). A group both share contributes ``(J_b S_b − J_a S_a)(…)ᵀ`` — the same
    error moves both poses alike and cancels as far as their geometry agrees; the rest of each
    covariance is independent. First order, like the covariances themselves."""
    factors_a, factors_b = factors_a or {}, factors_b or {}
    J_a, J_b = _point_jacobian(point_a_m), _point_jacobian(point_b_m)
    own_a = np.asarray(cov_a, dtype=float) - sum((S @ S.T for S in factors_a.values()), np.zeros((6, 6)))
    own_b = np.asarray(cov_b, dtype=float) - sum((S @ S.T for S in factors_b.values()), np.zeros((6, 6)))
    C = J_a @ own_a @ J_a.T + J_b @ own_b @ J_b.T
    for group in set(factors_a) | set(factors_b):
        S_a, S_b = factors_a.get(group), factors_b.get(group)
        if S_a is not None and S_b is not None and S_a.shape == S_b.shape:
            D = J_b @ S_b - J_a @ S_a
            C += D @ D.T
        else:  # only one of them has it (or the parameters differ): independent
            for S, J in ((S_a, J_a), (S_b, J_b)):
                if S is not None:
                    JS = J @ S
                    C += JS @ JS.T
    return 0.5 * (C + C.T)
