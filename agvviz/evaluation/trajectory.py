"""Trajectory errors as evo defines them: alignment, APE, RPE, and a time-offset estimate.

Numpy only. Poses are stacks of 4×4 transforms ``T_world_agv`` (N, 4, 4); positions are
(N, 3) in metres; times are integer nanoseconds.

APE (absolute pose error) of frame i: ``E_i = T_ref_i⁻¹ · T_est_i`` (evo ``ape``); its
translation part is ``‖t(E_i)‖`` (= ‖t_est − t_ref‖) and its rotation part the angle of
``R(E_i)``. RPE (relative pose error) of a pair (i, j): ``E_ij = (T_ref_i⁻¹ T_ref_j)⁻¹ ·
(T_est_i⁻¹ T_est_j)`` (evo ``rpe``), same two parts.

Alignment (applied to the estimate before APE; RPE is invariant to it) — ``T_ref_est`` maps
the estimate's world into the reference's, ``p_ref ≈ T_ref_est · p_est``:

==========  ====  =========================================================================
mode        DoF   what it removes
==========  ====  =========================================================================
``none``    0     nothing: errors in the map frame (what a localisation system is judged on)
``se3``     6     rotation + translation (Umeyama 1991 without scale; evo ``--align``)
``se2``     3     rotation about world z + translation in x, y (a planar vehicle's frame)
``yaw``     1     rotation about world z through the world origin only
==========  ====  =========================================================================
"""

from __future__ import annotations

from agvviz.errors import InputError

import numpy as np

ALIGNMENTS = ("none", "se3", "se2", "yaw")
#: Fewest pose pairs each alignment needs to be determined.
MIN_POINTS = {"none": 0, "se3": 3, "se2": 2, "yaw": 1}


class EvaluationError(InputError):
    """Input the evaluation cannot score (wrong shapes, too few poses, unknown mode)."""


def _positions(points_m: np.ndarray, what: str) -> np.ndarray:
    p = np.asarray(points_m, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise EvaluationError(f"{what} must have shape (N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise EvaluationError(f"{what} contains NaN or inf")
    return p


def _poses(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise EvaluationError(f"{what} must have shape (N, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise EvaluationError(f"{what} contains NaN or inf")
    return T


def _inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a stack of rigid transforms (N, 4, 4)."""
    R_t = np.transpose(T[:, :3, :3], (0, 2, 1))
    inv = np.zeros_like(T)
    inv[:, :3, :3] = R_t
    inv[:, :3, 3] = -np.einsum("nij,nj->ni", R_t, T[:, :3, 3])
    inv[:, 3, 3] = 1.0
    return inv


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle (deg, in [0, 180]) of each matrix of a stack (N, 3, 3), robust near 0."""
    R = np.asarray(R, dtype=float)
    cos = (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0
    # sin from the skew part keeps the precision of small angles that arccos(cos) loses.
    skew = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sin = np.linalg.norm(skew, axis=1) / 2.0
    return np.degrees(np.arctan2(sin, np.clip(cos, -1.0, 1.0)))


def align(p_est_m: np.ndarray, p_ref_m: np.ndarray, mode: str) -> np.ndarray:
    """Least-squares rigid alignment of estimated positions onto reference positions.

    Parameters
    ----------
    p_est_m, p_ref_m : (N, 3) arrays
        Corresponding positions (m), estimate and reference (truth).
    mode : str
        One of :data:`ALIGNMENTS` (see the module table).

    Returns
    -------
    T_ref_est : (4, 4) array
        Minimises ``Σ ‖p_ref − T_ref_est · p_est‖²`` over the transforms ``mode`` allows.
    """
    if mode not in ALIGNMENTS:
        raise EvaluationError(f"unknown alignment {mode!r}; choose one of: {', '.join(ALIGNMENTS)}")
    p_est = _positions(p_est_m, "p_est_m")
    p_ref = _positions(p_ref_m, "p_ref_m")
    if p_est.shape != p_ref.shape:
        raise EvaluationError(f"p_est_m {p_est.shape} and p_ref_m {p_ref.shape} must correspond")
    if len(p_est) < MIN_POINTS[mode]:
        raise EvaluationError(
            f"{mode} alignment needs at least {MIN_POINTS[mode]} poses, got {len(p_est)}"
        )
    T = np.eye(4)
    if mode == "none":
        return T
    if mode == "yaw":
        x_e, y_e, x_r, y_r = p_est[:, 0], p_est[:, 1], p_ref[:, 0], p_ref[:, 1]
        angle = np.arctan2(np.sum(x_e * y_r - y_e * x_r), np.sum(x_e * x_r + y_e * y_r))
        c, s = np.cos(angle), np.sin(angle)
        T[:2, :2] = [[c, -s], [s, c]]
        return T
    dims = 3 if mode == "se3" else 2
    a, b = p_est[:, :dims], p_ref[:, :dims]
    mu_a, mu_b = a.mean(axis=0), b.mean(axis=0)
    # Umeyama (1991) eqs 38–40 with scale 1: Σ = (1/N) Σ (b − μ_b)(a − μ_a)ᵀ = U D Vᵀ.
    U, _, Vt = np.linalg.svd((b - mu_b).T @ (a - mu_a) / len(a))
    S = np.eye(dims)
    S[-1, -1] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ S @ Vt
    T[:dims, :dims] = R
    T[:dims, 3] = mu_b - R @ mu_a
    return T


def ape(T_ref: np.ndarray, T_est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Absolute pose error per pose: translation part (m) and rotation angle (deg).

    Parameters
    ----------
    T_ref, T_est : (N, 4, 4) arrays
        Reference (truth) and (aligned) estimated poses, corresponding.

    Returns
    -------
    trans_m : (N,) array
    rot_deg : (N,) array
    """
    T_ref, T_est = _poses(T_ref, "T_ref"), _poses(T_est, "T_est")
    if T_ref.shape != T_est.shape:
        raise EvaluationError(f"T_ref {T_ref.shape} and T_est {T_est.shape} must correspond")
    E = _inverse(T_ref) @ T_est
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle_deg(E[:, :3, :3])


def rpe_pairs(frames: np.ndarray, delta: int) -> np.ndarray:
    """Index pairs (i, j) into ``frames`` with ``frames[j] == frames[i] + delta``.

    Pairs span exactly ``delta`` frames of the recording, so a rejected frame in between
    drops its pairs rather than silently stretching the interval (evo pairs by position in
    the synchronised sequence instead).

    Returns
    -------
    pairs : (M, 2) int array
    """
    if delta < 1:
        raise EvaluationError(f"RPE delta must be ≥ 1 frame, got {delta}")
    frames = np.asarray(frames, dtype=np.int64)
    where = {int(f): k for k, f in enumerate(frames)}
    pairs = [(k, where[int(f) + delta]) for k, f in enumerate(frames) if int(f) + delta in where]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def rpe(T_ref: np.ndarray, T_est: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose error of each pair (i, j): translation part (m), rotation angle (deg).

    Parameters
    ----------
    T_ref, T_est : (N, 4, 4) arrays
    pairs : (M, 2) int array
        From :func:`rpe_pairs`.
    """
    T_ref, T_est = _poses(T_ref, "T_ref"), _poses(T_est, "T_est")
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs) == 0:
        return np.zeros(0), np.zeros(0)
    i, j = pairs[:, 0], pairs[:, 1]
    d_ref = _inverse(T_ref[i]) @ T_ref[j]
    d_est = _inverse(T_est[i]) @ T_est[j]
    E = _inverse(d_ref) @ d_est
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle_deg(E[:, :3, :3])


def apply_alignment(T_ref_est: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """The estimated poses expressed in the reference world: ``T_ref_est · T_est_i``."""
    return np.asarray(T_ref_est, dtype=float)[None] @ _poses(T_est, "T_est")


def estimate_time_offset_s(
    t_est_ns: np.ndarray,
    p_est_m: np.ndarray,
    t_ref_ns: np.ndarray,
    p_ref_m: np.ndarray,
    max_iterations: int = 20,
) -> float:
    """Time offset ``dt`` (s) that best explains the estimate as the reference shifted in time:
    ``p_est(t) ≈ p_ref(t + dt)``, the reference linearly interpolated.

    A positive ``dt`` means the estimate shows where the vehicle was ``dt`` *later* than its
    stamp says (its stamps are early). Gauss–Newton on the scalar ``dt``:
    ``dt ← dt + Σ vᵢ·rᵢ / Σ ‖vᵢ‖²`` with residuals ``rᵢ = p_est,i − p_ref(tᵢ + dt)`` and the
    reference velocity ``vᵢ`` there. Estimates whose shifted stamp falls outside the reference
    span are left out.

    Raises
    ------
    EvaluationError
        Too few poses, unsorted reference stamps, or a reference that barely moves (the offset
        is then not observable).
    """
    t_est = np.asarray(t_est_ns, dtype=np.int64)
    t_ref = np.asarray(t_ref_ns, dtype=np.int64)
    p_est = _positions(p_est_m, "p_est_m")
    p_ref = _positions(p_ref_m, "p_ref_m")
    if len(t_est) != len(p_est) or len(t_ref) != len(p_ref):
        raise EvaluationError("each stamp array must match its position array in length")
    if len(t_ref) < 3 or len(t_est) < 3:
        raise EvaluationError("a time offset needs at least 3 estimated and 3 reference poses")
    if np.any(np.diff(t_ref) <= 0):
        raise EvaluationError("reference stamps must be strictly increasing")
    # Seconds relative to the first reference stamp keep float64 at sub-nanosecond precision.
    s_ref = (t_ref - t_ref[0]).astype(float) * 1e-9
    s_est = (t_est - t_ref[0]).astype(float) * 1e-9
    velocity = np.gradient(p_ref, s_ref, axis=0)
    dt = 0.0
    for _ in range(max_iterations):
        s = s_est + dt
        inside = (s >= s_ref[0]) & (s <= s_ref[-1])
        if np.count_nonzero(inside) < 3:
            raise EvaluationError("fewer than 3 estimated poses overlap the reference in time")
        p_at = np.stack([np.interp(s[inside], s_ref, p_ref[:, k]) for k in range(3)], axis=1)
        v_at = np.stack([np.interp(s[inside], s_ref, velocity[:, k]) for k in range(3)], axis=1)
        denominator = float(np.sum(v_at**2))
        if denominator < 1e-6 * np.count_nonzero(inside):  # mean speed below 1 mm/s
            raise EvaluationError("the reference barely moves: a time offset is not observable")
        step = float(np.sum(v_at * (p_est[inside] - p_at))) / denominator
        dt += step
        if abs(step) < 1e-7:
            break
    return dt
