"""CNOEM (paper 002): the pose of a correction cycle's start frame F from marker corners seen in
many frames and cameras. Numpy only.

The window
    Over a correction cycle the vehicle sees markers in several frames and cameras. Sighting j
    gives the world corners ``P_i^Wj`` of one marker (from the map), their measured ideal pixels
    ``u_i^j, v_i^j`` in camera ``Oj`` with matrix ``K^j``, and — from the navigation — the pose
    of that camera in the start frame, ``T_F_cam = T_F_agv(j) · T_agv_cam`` (paper §1.2, step 4:
    ``T_F^Oj`` there is our ``T_cam_F``). The unknown is the start frame's pose; the paper
    optimises ``T_W^F`` = our ``T_F_world`` (eq 9), so this module does too and reports both it
    and ``T_world_F``.

Cost (eqs 11–13)
    ``P_i^Oj = T_cam_F · T_F_world · P_i^Wj`` is the corner where the current pose puts it;
    ``p_i^Oj`` is the viewing ray of its measured pixel (eq 8). ``L_i^j = |p × P| / |p|`` is the
    distance of the corner from the ray, ``E^j = Σ_i (L_i^j)²`` the sighting's imaging error and
    the cost is ``E = Σ_j E^j`` (the object-space point-to-ray cost). For a fixed rotation it is
    quadratic in the translation of ``T_F_world``, so :func:`translation_first` solves the
    translation exactly by linear least squares before any iteration: a start 10 m off costs
    nothing.

Updates (``update`` of :func:`solve_cnoem`)
    ``"lm"`` (default) — Levenberg–Marquardt (:func:`agvviz.solvers.lm_core.minimize`, the
    damping schedule and stopping rule of every agvviz solver) on the left perturbation
    ``T_F_world ← Exp(δ)·T_F_world``, δ = (ρ, φ), with residual vectors ``r_i = p̂_i × P_i``
    (|r_i| = L_i).
    ``"paper"`` — the paper's first-order update, eqs 14–20: the parameters are
    ``n_W^F = (α, β, γ, X, Y, Z)`` of eq 3/4 (``T_F_world = J(n)``, R = Rz(γ)·Rx(α)·Ry(β)); each
    sighting back-propagates ``eP = E^j·∂E^j/∂P`` (eq 14) through eqs 15–19 into ``en^j`` (eq 20)
    and ``n ← n − Σ_j s ⊙ en^j``. ``Σ_j en^j`` is exactly the gradient of ``½ Σ_j (E^j)²``
    (tests/test_cnoem.py checks it against finite differences). The paper gives no step s; ours
    is a per-parameter Gauss–Newton-diagonal scaling with a safeguard (:func:`refine_window_paper`).
    On this cost (condition numbers 1e5–1e9) first-order steps crawl: from the paper's start noise
    they barely leave the translation-first start in 2000 iterations (bench/bench_cnoem.py).

Speed
    The ray cost is a quadratic form in the 12 entries of [R | t'] (t' relative to the window's
    centroid): :class:`CornerWindow` builds the 13×13 form once, and each LM iteration
    (:func:`ray_normal_equations`) is then O(1) whatever the number of corners.

Two minima
    Far windows with few frames have a second, mirror-like minimum; :func:`solve_cnoem_multistart`
    adds the IPPE starts but keeps the navigation's solution unless another is clearly better.
"""

from __future__ import annotations

from agvviz.errors import RunError

from dataclasses import dataclass, field

import numpy as np

from agvviz.geometry import se3, so3
from agvviz.geometry.euler import Rx, Ry, Rz, hpr_from_matrix
from agvviz.solvers import lm_core

UPDATES = ("lm", "paper")

_EYE3 = np.eye(3)


class WindowError(RunError):
    """A correction window that cannot be solved (no sightings, bad shapes, non-finite input)."""


@dataclass(frozen=True)
class Sighting:
    """One marker seen in one frame by one camera.

    marker_id, cam_name : names; frame_index : index of the frame in the window (0 = F).
    points_world_m : (P, 3) the marker's corners in the world (TL, TR, BR, BL).
    pixels_px : (P, 2) their measured pixels in the IDEAL (undistorted) image.
    K : (3, 3) camera matrix of that ideal image.
    T_F_cam : (4, 4) the camera's pose in the start frame F, from the navigation.
    """

    marker_id: str
    cam_name: str
    frame_index: int
    points_world_m: np.ndarray
    pixels_px: np.ndarray
    K: np.ndarray
    T_F_cam: np.ndarray


@dataclass
class CornerWindow:
    """Every corner of a window, flattened (N corners in all), for vectorised solvers.

    points_world_m : (N, 3); pixels_px : (N, 2); K : (N, 3, 3).
    R_cam_F : (N, 3, 3), t_cam_F : (N, 3) — ``T_cam_F`` of each corner's sighting.
    rays_cam : (N, 3) unit viewing rays of the measured pixels (eq 8, normalised).
    sighting_index : (N,) index j of each corner's sighting in ``sightings``.
    M, m : (N, 3, 3), (N, 3) — ``r_i = M_i · P_F + m_i`` is the ray residual of a corner
        whose start-frame position is ``P_F`` (``M = p̂^ R_cam_F``, ``m = p̂^ t_cam_F``).
    rays_F, centres_F : (N, 3) the same ray in F: unit direction ``d = R_F_cam p`` (p the unit
        ray) through the camera centre ``c``; ``|r_i| = |d × (P_F − c)|``.
    origin_world_m, ray_quadratic_form : (3,), (13, 13) — the ray cost as a quadratic form
        (:func:`ray_normal_equations`), built once per window.
    """

    sightings: list[Sighting]
    points_world_m: np.ndarray
    pixels_px: np.ndarray
    K: np.ndarray
    R_cam_F: np.ndarray
    t_cam_F: np.ndarray
    rays_cam: np.ndarray
    sighting_index: np.ndarray
    M: np.ndarray
    m: np.ndarray
    rays_F: np.ndarray
    centres_F: np.ndarray

    def __post_init__(self):
        # The 13×13 quadratic form of the ray cost (:func:`ray_normal_equations`): rows of C are
        # (a ⊗ (p − o), a, −a·c) and (b ⊗ (p − o), b, −b·c) for unit a, b ⟂ d.
        d = self.rays_F
        helper = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        a = np.cross(d, helper)
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b = np.cross(d, a)
        self.origin_world_m = self.points_world_m.mean(axis=0)
        p = self.points_world_m - self.origin_world_m
        C = np.empty((2 * self.n_corners, 13))
        for rows, u in ((slice(0, self.n_corners), a), (slice(self.n_corners, None), b)):
            C[rows, :9] = (u[:, :, None] * p[:, None, :]).reshape(-1, 9)
            C[rows, 9:12] = u
            C[rows, 12] = -np.sum(u * self.centres_F, axis=1)
        self.ray_quadratic_form = C.T @ C

    @property
    def n_sightings(self) -> int:
        return len(self.sightings)

    @property
    def n_corners(self) -> int:
        return int(self.points_world_m.shape[0])

    @classmethod
    def from_sightings(cls, sightings: list[Sighting]) -> "CornerWindow":
        """Flatten ``sightings``; raises :class:`WindowError` on empty or malformed input."""
        if not sightings:
            raise WindowError("the correction window has no marker sightings; nothing to solve")
        pts, px, Ks, Ts, idx = [], [], [], [], []
        for j, s in enumerate(sightings):
            p = np.asarray(s.points_world_m, dtype=float)
            u = np.asarray(s.pixels_px, dtype=float)
            K = np.asarray(s.K, dtype=float)
            T = np.asarray(s.T_F_cam, dtype=float)
            if p.ndim != 2 or p.shape[1] != 3 or u.shape != (p.shape[0], 2) or p.shape[0] < 1:
                raise WindowError(
                    f"sighting {j} ({s.marker_id}/{s.cam_name}): need points (P, 3) and pixels "
                    f"(P, 2), got {p.shape} and {u.shape}"
                )
            if K.shape != (3, 3) or not _is_rigid_fast(T):
                raise WindowError(f"sighting {j}: K must be (3, 3) and T_F_cam a rigid 4×4 transform")
            if not (np.all(np.isfinite(p)) and np.all(np.isfinite(u)) and np.all(np.isfinite(K))):
                raise WindowError(f"sighting {j} ({s.marker_id}/{s.cam_name}): non-finite input")
            T_cam_F = se3.inverse(T)
            pts.append(p)
            px.append(u)
            Ks.append(np.broadcast_to(K, (p.shape[0], 3, 3)))
            Ts.append(np.broadcast_to(T_cam_F, (p.shape[0], 4, 4)))
            idx.append(np.full(p.shape[0], j))
        points = np.concatenate(pts)
        pixels = np.concatenate(px)
        K = np.concatenate(Ks).copy()
        T_cam_F = np.concatenate(Ts)
        # Eq 8 up to scale: K⁻¹ (u, v, 1).
        homog = np.concatenate([pixels, np.ones((pixels.shape[0], 1))], axis=1)
        rays = np.linalg.solve(K, homog[:, :, None])[:, :, 0]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        R_cam_F = T_cam_F[:, :3, :3].copy()
        t_cam_F = T_cam_F[:, :3, 3].copy()
        ray_hat = so3.hat_batch(rays)
        return cls(
            list(sightings), points, pixels, K, R_cam_F, t_cam_F, rays, np.concatenate(idx),
            ray_hat @ R_cam_F, (ray_hat @ t_cam_F[:, :, None])[:, :, 0],
            (R_cam_F.transpose(0, 2, 1) @ rays[:, :, None])[:, :, 0],
            -(R_cam_F.transpose(0, 2, 1) @ t_cam_F[:, :, None])[:, :, 0],
        )

    def points_cam(self, T_F_world: np.ndarray) -> np.ndarray:
        """(N, 3) corners in their cameras at start pose ``T_F_world`` (eqs 10–11)."""
        P_F = self.points_world_m @ T_F_world[:3, :3].T + T_F_world[:3, 3]
        return (self.R_cam_F @ P_F[:, :, None])[:, :, 0] + self.t_cam_F

    def project(self, T_F_world: np.ndarray) -> np.ndarray:
        """(N, 2) ideal pixels where ``T_F_world`` puts each corner (the 'theoretical' corners)."""
        P = self.points_cam(T_F_world)
        q = (self.K @ P[:, :, None])[:, :, 0]
        return q[:, :2] / q[:, 2:3]


@dataclass
class WindowIteration:
    """One iteration of a window solver: the cost after it (the solver's own cost), the RMS
    pixel reprojection error, the damping used (NaN for the paper update), the step norm, whether
    it was accepted, and the pose kept after it."""

    cost: float
    reproj_rms_px: float
    damping: float
    step_norm: float
    accepted: bool
    T_F_world: np.ndarray


@dataclass
class WindowSolution:
    """Result of a window solver.

    T_F_world, T_world_F : (4, 4) the solution (``None`` when it failed) — the paper's
    ``T_W^F`` and its inverse. reason : "" or why it failed. iterations[0] is the start.
    """

    T_F_world: np.ndarray | None
    reason: str
    iterations: list[WindowIteration] = field(default_factory=list)

    @property
    def T_world_F(self) -> np.ndarray | None:
        return None if self.T_F_world is None else se3.inverse(self.T_F_world)

    @property
    def success(self) -> bool:
        return self.T_F_world is not None and self.reason == ""


def _is_rigid_fast(T: np.ndarray) -> bool:
    """As :func:`se3.is_rigid` (tolerance 1e-6) without its per-call overhead."""
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.max(np.abs(R.T @ R - np.eye(3))) < 1e-6
        and abs(np.linalg.det(R) - 1.0) < 1e-6
        and np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) < 1e-6
    )


# -- the paper's parameters (eqs 3–5) ---------------------------------------------------------


def euler_params_from_transform(T: np.ndarray) -> np.ndarray:
    """n = (α, β, γ, X, Y, Z) of eq 5 (α about x = pitch, β about y = roll, γ about z = heading)."""
    heading, pitch, roll = hpr_from_matrix(T[:3, :3])
    return np.array([pitch, roll, heading, *T[:3, 3]])


def transform_from_euler_params(n: np.ndarray) -> np.ndarray:
    """``J(n)`` of eq 4: R = Rz(γ)·Rx(α)·Ry(β), translation (X, Y, Z)."""
    alpha, beta, gamma = n[:3]
    return se3.make(Rz(gamma) @ Rx(alpha) @ Ry(beta), n[3:6])


def euler_derivatives(n: np.ndarray) -> np.ndarray:
    """(3, 3, 3): ∂R/∂α, ∂R/∂β, ∂R/∂γ of eq 4 (the rotation blocks of eq 18)."""
    alpha, beta, gamma = n[:3]
    dz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    dx = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    dy = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    A, B, G = Rx(alpha), Ry(beta), Rz(gamma)
    return np.stack([G @ A @ dx @ B, G @ A @ B @ dy, G @ dz @ A @ B])


# -- cost, residuals, Jacobian ----------------------------------------------------------------


def ray_residuals(window: CornerWindow, T_F_world: np.ndarray) -> np.ndarray:
    """(N, 3) residual vectors ``p̂ × P^O`` (|r_i| = L_i, eq 12)."""
    P_F = window.points_world_m @ T_F_world[:3, :3].T + T_F_world[:3, 3]
    return (window.M @ P_F[:, :, None])[:, :, 0] + window.m


def sighting_errors(window: CornerWindow, T_F_world: np.ndarray) -> np.ndarray:
    """(J,) imaging errors ``E^j = Σ_i (L_i^j)²`` (eqs 12–13), m²."""
    r = ray_residuals(window, T_F_world)
    return np.bincount(window.sighting_index, np.sum(r * r, axis=1), minlength=window.n_sightings)


def ray_cost(window: CornerWindow, T_F_world: np.ndarray) -> float:
    """``E = Σ_j E^j``, the CNOEM cost (m²)."""
    r = ray_residuals(window, T_F_world)
    return float(np.sum(r * r))


def ray_residuals_and_jacobian(window: CornerWindow, T_F_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (3N,) and ``J_r_wrt_left_perturbation`` (3N, 6) of ``T_F_world``, δ = (ρ, φ).

    ``∂P_F/∂δ = [I, −P_F^]`` so ``∂r_i/∂δ = [M_i, −M_i P_F^]`` and column k of ``M P^`` is
    ``M (P × e_k)``.
    """
    P = window.points_world_m @ T_F_world[:3, :3].T + T_F_world[:3, 3]
    M = window.M
    r = (M @ P[:, :, None])[:, :, 0] + window.m
    x, y, z = P[:, 0:1], P[:, 1:2], P[:, 2:3]
    J = np.empty((P.shape[0], 3, 6))
    J[:, :, :3] = M
    # −M·P^ : P^ e_x = (0, z, −y), P^ e_y = (−z, 0, x), P^ e_z = (y, −x, 0)
    J[:, :, 3] = M[:, :, 2] * y - M[:, :, 1] * z
    J[:, :, 4] = M[:, :, 0] * z - M[:, :, 2] * x
    J[:, :, 5] = M[:, :, 1] * x - M[:, :, 0] * y
    return r.reshape(-1), J.reshape(-1, 6)


def reprojection_rms_px(window: CornerWindow, T_F_world: np.ndarray) -> float:
    """RMS pixel distance between the projected and the measured corners (NaN if one is behind)."""
    P = window.points_cam(T_F_world)
    if not np.all(P[:, 2] > 0.0):
        return float("nan")
    d = window.project(T_F_world) - window.pixels_px
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def all_in_front(window: CornerWindow, T_F_world: np.ndarray) -> bool:
    """True when every corner lies in front of its camera."""
    return bool(np.all(window.points_cam(T_F_world)[:, 2] > 0.0))


def ray_normal_equations(window: CornerWindow, T_F_world: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(½E, JᵀJ (6, 6), Jᵀr (6,)) of the ray cost at ``T_F_world``, in O(1) per iteration.

    With the ray in F (unit direction d through centre c) and a, b completing an orthonormal
    basis with d: ``L² = (a·(P − c))² + (b·(P − c))²`` with ``P = R p + t`` (p a world corner).
    Relative to the window's centroid o, ``P = R (p − o) + t'`` with ``t' = R o + t``; each
    residual is then LINEAR in ``x = (R row-major, t', 1)`` (13 numbers): ``a·(P − c) =
    (a ⊗ (p − o), a, −a·c) · x``. So ``E = xᵀ Q x`` with the 13×13 ``Q = CᵀC`` built once per window
    (:class:`CornerWindow`), and under the left perturbation (R ← Exp(φ)R, t' ← Exp(φ)t' + ρ)
    ``∂x/∂δ = G`` gives ``JᵀJ = GᵀQG`` and ``Jᵀr = GᵀQx`` — exactly the sums over corners of
    :func:`ray_residuals_and_jacobian` (tests/test_cnoem.py), whatever the number of corners.
    """
    R = T_F_world[:3, :3]
    t_prime = R @ window.origin_world_m + T_F_world[:3, 3]
    x = np.empty(13)
    x[:9] = R.ravel()
    x[9:12] = t_prime
    x[12] = 1.0
    G = np.zeros((13, 6))
    G[9:12, :3] = _EYE3
    # ∂x/∂φ_m: rows of E_m R (E_m = e_m^) and E_m t'.  e_x^ R = (0, −R2, R1), etc.
    for m, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        # e_m^ maps row i ← −row j and row j ← row i of the matrix it multiplies (cyclic i, j).
        G[3 * j : 3 * j + 3, 3 + m] = R[i]
        G[3 * i : 3 * i + 3, 3 + m] = -R[j]
        G[9 + j, 3 + m] = t_prime[i]
        G[9 + i, 3 + m] = -t_prime[j]
    Qx = window.ray_quadratic_form @ x
    QG = window.ray_quadratic_form @ G
    return 0.5 * float(x @ Qx), G.T @ QG, G.T @ Qx


def gauss_newton_step(window: CornerWindow, T_F_world: np.ndarray) -> np.ndarray:
    """One undamped Gauss–Newton step on the ray cost: the new ``T_F_world`` (the timed unit of
    bench/bench_cnoem.py)."""
    _, H, g = ray_normal_equations(window, T_F_world)
    return se3.exp(np.linalg.solve(H, -g)) @ T_F_world


# -- translation first --------------------------------------------------------------------------


def translation_first(window: CornerWindow, R_F_world: np.ndarray) -> np.ndarray:
    """``T_F_world`` with rotation ``R_F_world`` and the translation that minimises the ray cost
    exactly (it is linear least squares in t: ``r_i = M_i (R P_i + t) + m_i``)."""
    R = np.asarray(R_F_world, dtype=float)
    b = (window.M @ (window.points_world_m @ R.T)[:, :, None])[:, :, 0] + window.m  # r at t = 0
    A = window.M.reshape(-1, 3)
    t, *_ = np.linalg.lstsq(A, -b.reshape(-1), rcond=None)
    return se3.make(R, t)


# -- Levenberg–Marquardt on a window (shared with bundle) --------------------------------------


def refine_window_lm(
    window: CornerWindow,
    T_start_F_world: np.ndarray,
    normal_equations,
    *,
    max_iterations: int = 50,
    initial_damping: float = 1e-3,
    step_tol: float = 1e-10,
    cost_rel_tol: float = 1e-12,
) -> WindowSolution:
    """Levenberg–Marquardt on ``T_F_world`` (left perturbation): :func:`lm_core.minimize`.

    ``normal_equations(window, T_F_world) -> (cost, JᵀJ, Jᵀf)`` with cost = ½‖f‖². A trial step
    that puts a corner behind its camera is refused. Converged when ‖δ‖ < step_tol or a step
    changes the cost by at most cost_rel_tol·cost; out of iterations, the best pose so far. The
    first iteration entry is the start; each later one is a trial step, accepted or not.
    """
    result = lm_core.minimize(
        np.array(T_start_F_world, dtype=float),
        lambda T, delta: se3.exp(delta) @ T,
        normal_equations=lambda T: normal_equations(window, T),
        feasible=lambda T: all_in_front(window, T),
        reproj_rms_px=lambda T: reprojection_rms_px(window, T),
        options=lm_core.LmOptions(max_iterations, initial_damping, step_tol, cost_rel_tol),
    )
    iterations = [
        WindowIteration(it.cost, it.reproj_rms_px, it.damping, it.step_norm, it.accepted, T)
        for it, T in zip(result.iterations, result.path)
    ]
    if result.stop_reason == lm_core.START_INFEASIBLE:
        return WindowSolution(None, "start pose puts a marker corner behind its camera")
    if result.failed:
        return WindowSolution(None, result.stop_reason, iterations)
    return WindowSolution(result.x, "", iterations)


# -- the paper's first-order update (eqs 14–20) -----------------------------------------------


def paper_error_propagation(window: CornerWindow, n_F_world: np.ndarray) -> np.ndarray:
    """(J, 6) ``en^j`` of every sighting (eqs 14–20) at parameters ``n_F_world`` (eq 3 order).

    Eq 14: ``eP_i = E^j ∂E^j/∂P_i`` with ``∂E/∂P = 2 (P − (p̂·P) p̂)`` (the expanded form of
    eq 14, written with the unit ray). Eq 15: ``eT_W^Oj = Σ_i eP_i [P_i^W; 1]ᵀ``. Eq 16:
    ``eT_W^Fj = R_F_cam · eT_W^Oj``. Eqs 17–19: contract with ∂T/∂(α, β, γ) and read the
    translation column.
    """
    T = transform_from_euler_params(n_F_world)
    P = window.points_cam(T)
    u = window.rays_cam
    L_vec = P - np.sum(u * P, axis=1, keepdims=True) * u  # P minus its projection on the ray
    E = np.bincount(window.sighting_index, np.sum(L_vec * L_vec, axis=1), minlength=window.n_sightings)
    eP = E[window.sighting_index][:, None] * 2.0 * L_vec  # eq 14
    eP_F = (window.R_cam_F.transpose(0, 2, 1) @ eP[:, :, None])[:, :, 0]  # eq 16 (per corner)
    # eq 15 summed per sighting: eT^j = Σ_i eP_F,i [P_W,i; 1]ᵀ  → (J, 3, 4)
    outer = eP_F[:, :, None] * np.concatenate([window.points_world_m, np.ones((P.shape[0], 1))], 1)[:, None, :]
    eT = np.zeros((window.n_sightings, 3, 4))
    np.add.at(eT, window.sighting_index, outer)
    dR = euler_derivatives(n_F_world)  # (3, 3, 3)
    e_angles = np.einsum("jab,kab->jk", eT[:, :, :3], dR)  # eq 17
    return np.concatenate([e_angles, eT[:, :, 3]], axis=1)  # eqs 19–20


def paper_cost(window: CornerWindow, T_F_world: np.ndarray) -> float:
    """``½ Σ_j (E^j)²``: the function whose gradient the paper's ``Σ_j en^j`` is."""
    E = sighting_errors(window, T_F_world)
    return 0.5 * float(E @ E)


def refine_window_paper(
    window: CornerWindow,
    T_start_F_world: np.ndarray,
    *,
    max_iterations: int = 2000,
    step_scale: float = 0.5,
    cost_rel_tol: float = 1e-12,
) -> WindowSolution:
    """The paper's update ``n ← n − Σ_j s ⊙ en^j`` (eqs 14–20).

    The paper gives no step s. Ours is ``s = η / diag(H)`` with H the Gauss–Newton Hessian of
    ``½ Σ_j (E^j)²``; it comes free from eq 14, since ``en^j = E^j ∂E^j/∂n`` gives
    ``∂E^j/∂n = en^j / E^j``. η starts at ``step_scale``; a step that raises the cost (or puts a
    corner behind its camera) is refused and halves η, an accepted one multiplies it by 1.5
    (at most 1). Stops when an accepted step lowers the cost by at most ``cost_rel_tol`` of it.
    """
    n = euler_params_from_transform(np.asarray(T_start_F_world, dtype=float))
    T = transform_from_euler_params(n)
    if not all_in_front(window, T):
        return WindowSolution(None, "start pose puts a marker corner behind its camera")
    cost = paper_cost(window, T)
    eta = float(step_scale)
    iterations = [WindowIteration(cost, reprojection_rms_px(window, T), float("nan"), 0.0, True, T.copy())]
    en = paper_error_propagation(window, n)
    for _ in range(max_iterations):
        if cost == 0.0:
            break
        E = sighting_errors(window, T)
        dE = en / np.where(E > 0.0, E, 1.0)[:, None]
        s = eta / np.maximum(np.sum(dE * dE, axis=0), 1e-300)
        step = s * np.sum(en, axis=0)
        n_trial = n - step
        T_trial = transform_from_euler_params(n_trial)
        cost_trial = paper_cost(window, T_trial) if all_in_front(window, T_trial) else float("inf")
        accepted = cost_trial < cost
        decrease = cost - cost_trial
        if accepted:
            n, T, cost = n_trial, T_trial, cost_trial
            en = paper_error_propagation(window, n)
            eta = min(1.0, 1.5 * eta)
        else:
            eta *= 0.5
        iterations.append(
            WindowIteration(cost, reprojection_rms_px(window, T), float("nan"), float(np.linalg.norm(step)), accepted, T.copy())
        )
        if accepted and decrease <= cost_rel_tol * (cost + decrease):
            break
    return WindowSolution(T, "", iterations)


# -- entry point ------------------------------------------------------------------------------------


def solve_cnoem(
    window: CornerWindow,
    T_start_world_F: np.ndarray,
    *,
    update: str = "lm",
    translation_start: bool = True,
    max_iterations: int | None = None,
    paper_step_scale: float = 0.5,
) -> WindowSolution:
    """Pose of the start frame F from a window of sightings.

    Parameters
    ----------
    window : the cycle's sightings.
    T_start_world_F : (4, 4) start pose of F (the navigation's, or IPPE's).
    update : "lm" (default) or "paper" (eqs 14–20); see the module docstring.
    translation_start : keep the start rotation and replace its translation by the exact
        least-squares one before iterating (:func:`translation_first`).
    max_iterations : LM steps (default 50) or paper steps (default 2000).
    paper_step_scale : the paper update's step scale (module docstring).

    Returns
    -------
    WindowSolution; the cost in its iterations is ½E for "lm" and ½Σ(E^j)² for "paper". With
    ``translation_start`` iterations[0] is the given start and iterations[1] the translation-first
    pose (its step_norm the translation change).
    """
    if update not in UPDATES:
        raise ValueError(f"unknown CNOEM update {update!r}; valid: {', '.join(UPDATES)}")
    T_start = np.asarray(T_start_world_F, dtype=float)
    if not se3.is_rigid(T_start):
        raise WindowError("the start pose T_world_F must be a finite rigid 4×4 transform")
    T_raw = se3.inverse(T_start)
    T_F_world = translation_first(window, T_raw[:3, :3]) if translation_start else T_raw
    if update == "paper":
        solution = refine_window_paper(
            window, T_F_world, max_iterations=max_iterations or 2000, step_scale=paper_step_scale
        )
        raw_cost = paper_cost(window, T_raw)
    else:
        solution = refine_window_lm(window, T_F_world, ray_normal_equations, max_iterations=max_iterations or 50)
        raw_cost = 0.5 * ray_cost(window, T_raw)
    if translation_start and solution.iterations:
        # Iteration 0 is the given start, iteration 1 the translation-first pose (paper Fig. 4
        # shows the corners moving from where the navigation puts them).
        step = float(np.linalg.norm(T_F_world[:3, 3] - T_raw[:3, 3]))
        solution.iterations.insert(0, WindowIteration(raw_cost, reprojection_rms_px(window, T_raw), float("nan"), 0.0, True, T_raw))
        solution.iterations[1].step_norm = step
    return solution


def solve_cnoem_multistart(
    window: CornerWindow,
    starts_world_F: list[np.ndarray],
    *,
    T_reference_world_F: np.ndarray | None = None,
    max_attitude_deviation_rad: float = np.radians(15.0),
    switch_chi2: float = 9.0,
    **options,
) -> WindowSolution:
    """:func:`solve_cnoem` from every start in ``starts_world_F``; the first start (the
    navigation's) is preferred.

    Far windows with few frames have a second, mirror-like ray-cost minimum metres away whose cost
    can be lower than the true one's by a few per cent (the planar two-fold ambiguity, not
    resolved by a short baseline); the data cannot tell them apart, the navigation can. So another
    start's solution replaces the first start's only when (a) the first failed, or (b) its cost is
    lower by more than ``switch_chi2`` in units of the per-residual variance
    ``σ² = E_first / (2N − 6)`` (E = Σ L², 2 residuals per corner) and, with
    ``T_reference_world_F``, its attitude lies within ``max_attitude_deviation_rad`` of the
    reference's. The default 15° keeps the right solution (its attitude error reaches ≈6° at
    15 m with σ = 1.5 px) and drops the mirror (≈50° away at 15 m, 40 % lateral offset).
    """
    if not starts_world_F:
        raise WindowError("solve_cnoem_multistart needs at least one start pose")
    solutions = [solve_cnoem(window, T, **options) for T in starts_world_F]
    good = [s for s in solutions[1:] if s.success]
    if T_reference_world_F is not None:
        R_ref = np.asarray(T_reference_world_F, dtype=float)[:3, :3]
        good = [
            s for s in good
            if np.arccos(np.clip((np.trace(s.T_world_F[:3, :3].T @ R_ref) - 1.0) / 2.0, -1.0, 1.0)) <= max_attitude_deviation_rad
        ]
    first = solutions[0]
    if not first.success:
        return min(good, key=lambda s: s.iterations[-1].cost) if good else first
    cost_first = first.iterations[-1].cost
    dof = 2 * window.n_corners - 6
    variance = 2.0 * cost_first / dof if dof > 0 else float("inf")  # cost = ½E
    better = [s for s in good if 2.0 * (cost_first - s.iterations[-1].cost) > switch_chi2 * variance]
    return min(better, key=lambda s: s.iterations[-1].cost) if better else first
