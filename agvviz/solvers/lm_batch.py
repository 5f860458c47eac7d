"""Vectorised P4P and Levenberg–Marquardt: many frames at once in numpy. Numpy only.

Frame k has its own marker points ``points_marker_m[k]`` (P, 3), pixels ``pixels_px[k]`` (P, 2)
and camera matrix ``K[k]`` (3, 3); every frame has the same number of points P. Each frame
follows the arithmetic of the single-frame code — :func:`agvviz.solvers.p4p.solve_p4p`, and for
LM the same residuals (:func:`agvviz.solvers.lm.residuals_and_jacobian`, which takes stacks)
and the same core (:func:`agvviz.solvers.lm_core.minimize_batch`: the damping schedule,
acceptance and stopping rule of :func:`agvviz.solvers.lm.refine_lm`, per frame) — so results
agree with it to the accuracy its stopping rule guarantees; only the loop over frames is
replaced by array operations (batched 6×6 normal equations). Frames that converge stop
changing; the loop ends when all have converged or ``max_iterations`` is reached.

Not included: the single-frame LM's fallback to an IPPE start when P4P fails, and the input
checks of :func:`agvviz.solvers.solve`; frames whose P4P fails come back with
``ok = False`` and a reason, for the caller to solve one by one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.geometry import se3
from agvviz.solvers import lm_core
from agvviz.solvers.lm import (
    FAILURE_REASONS,
    OBJECTIVES,
    reprojection_rms_px,
    residuals_and_jacobian,
    retract_left_batch,
)
from agvviz.solvers.p4p import COLLINEAR_REL_TOL

_TRIPLES = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))


@dataclass
class BatchResult:
    """T_cam_marker (N, 4, 4), NaN where not ok; ok (N,) bool; reason (N,) str ("" when ok);
    iterations (N,) trial steps taken; reproj_rms_px (N,) (NaN where not ok)."""

    T_cam_marker: np.ndarray
    ok: np.ndarray
    reason: np.ndarray
    iterations: np.ndarray
    reproj_rms_px: np.ndarray


# -- batched P4P --------------------------------------------------------------------------------


def _collinear_any(xy: np.ndarray) -> np.ndarray:
    """(N, 4, 2) → (N,) True where any three of the four points are collinear (p4p's test)."""
    bad = np.zeros(xy.shape[0], dtype=bool)
    for i, j, k in _TRIPLES:
        ab, ac, bc = xy[:, j] - xy[:, i], xy[:, k] - xy[:, i], xy[:, k] - xy[:, j]
        longest = np.maximum.reduce([np.sum(ab * ab, 1), np.sum(ac * ac, 1), np.sum(bc * bc, 1)])
        cross = np.abs(ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0])
        bad |= (longest == 0.0) | (cross <= COLLINEAR_REL_TOL * longest)
    return bad


def p4p_batch(points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray) -> BatchResult:
    """Paper 000 eqs 7–21 on the first four points of every frame (see :mod:`.p4p`)."""
    n = points_marker_m.shape[0]
    K = np.broadcast_to(np.asarray(K, dtype=float), (n, 3, 3))
    xy = points_marker_m[:, :4, :2]
    uv = pixels_px[:, :4]
    reason = np.full(n, "", dtype=object)
    reason[_collinear_any(xy)] = "degenerate: marker points collinear"
    reason[_collinear_any(uv)] = "degenerate: pixels collinear"
    ok = reason == ""
    q = np.concatenate([xy, np.ones((n, 4, 1))], axis=2).transpose(0, 2, 1)  # (N, 3, 4)
    p = np.concatenate([uv, np.ones((n, 4, 1))], axis=2).transpose(0, 2, 1)
    P, Q = p[:, :, :3].copy(), q[:, :, :3].copy()
    P[~ok], Q[~ok] = np.eye(3), np.eye(3)  # keep degenerate frames from raising
    v = np.linalg.solve(P, p[:, :, 3:])[..., 0]
    r = np.linalg.solve(Q, q[:, :, 3:])[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        w1 = r[:, 2] * v[:, 0] / (r[:, 0] * v[:, 2])
        w2 = r[:, 2] * v[:, 1] / (r[:, 1] * v[:, 2])
        w4 = r[:, 2] / v[:, 2]
    behind = ok & ~((w1 > 0) & (w2 > 0) & (w4 > 0))
    reason[behind] = "point behind camera"
    ok &= ~behind
    W = np.zeros((n, 3, 3))
    W[:, 0, 0], W[:, 1, 1], W[:, 2, 2] = np.where(ok, w1, 1.0), np.where(ok, w2, 1.0), 1.0
    T_h = P @ W @ np.linalg.inv(Q)
    g = np.linalg.solve(K, T_h)
    n1, n2 = np.linalg.norm(g[:, :, 0], axis=1), np.linalg.norm(g[:, :, 1], axis=1)
    s = (n1 + n2) / (n1 * n1 + n2 * n2)
    r1, r2, t = s[:, None] * g[:, :, 0], s[:, None] * g[:, :, 1], s[:, None] * g[:, :, 2]
    c1 = r1 / np.linalg.norm(r1, axis=1, keepdims=True)
    c2 = r2 - np.sum(c1 * r2, axis=1, keepdims=True) * c1
    c2 = c2 / np.linalg.norm(c2, axis=1, keepdims=True)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = np.stack([c1, c2, np.cross(c1, c2)], axis=2)
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    finite = np.all(np.isfinite(T), axis=(1, 2))
    reason[ok & ~finite] = "non-finite result"
    ok &= finite
    T[~ok] = np.nan
    return BatchResult(T, ok, reason, np.zeros(n, dtype=int), _rms(T, points_marker_m, pixels_px, K, ok))


# -- batched LM ---------------------------------------------------------------------------------


def _rms(T, points, pixels, K, ok) -> np.ndarray:
    rms = np.full(T.shape[0], np.nan)
    if np.any(ok):
        rms[ok] = reprojection_rms_px(T[ok], points[ok], pixels[ok], K[ok])
    return rms


def refine_lm_batch(
    T_start_cam_marker: np.ndarray,
    points_marker_m: np.ndarray,
    pixels_px: np.ndarray,
    K: np.ndarray,
    *,
    objective: str = "depth",
    max_iterations: int = 50,
    initial_damping: float = 1e-3,
    step_tol: float = 1e-12,
    cost_rel_tol: float = 1e-14,
) -> BatchResult:
    """LM refinement of N poses at once; per frame as :func:`lm.refine_lm`.

    Parameters
    ----------
    T_start_cam_marker : (N, 4, 4) start poses (NaN rows are skipped, reason "no start pose").
    points_marker_m : (N, P, 3); pixels_px : (N, P, 2); K : (N, 3, 3) or (3, 3).
    objective, max_iterations, initial_damping, step_tol, cost_rel_tol : as
        :class:`agvviz.solvers.SolverOptions`.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; valid: {OBJECTIVES}")
    T = np.array(T_start_cam_marker, dtype=float)
    n = T.shape[0]
    points_marker_m = np.asarray(points_marker_m, dtype=float)
    pixels_px = np.asarray(pixels_px, dtype=float)
    K = np.broadcast_to(np.asarray(K, dtype=float), (n, 3, 3))
    started = np.all(np.isfinite(T), axis=(1, 2))
    result = lm_core.minimize_batch(
        T,
        retract_left_batch,
        lambda T_, k: residuals_and_jacobian(T_, points_marker_m[k], pixels_px[k], K[k], objective),
        # A NaN start has no point in front either: it is refused before any evaluation.
        feasible=lambda T_, k: np.all(se3.transform_points_batch(T_, points_marker_m[k])[..., 2] > 0.0, axis=1),
        options=lm_core.LmOptions(max_iterations, initial_damping, step_tol, cost_rel_tol),
    )
    reason = np.array([FAILURE_REASONS.get(why, "") for why in result.stop_reason], dtype=object).reshape(n)
    reason[~started] = "no start pose"
    ok = reason == ""
    # Frames still iterating when the budget runs out keep their best pose (as refine_lm).
    T = result.x
    T[~ok] = np.nan
    return BatchResult(T, ok, reason, result.iterations, _rms(T, points_marker_m, pixels_px, K, ok))


def solve_lm_batch(
    points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray, **lm_options
) -> BatchResult:
    """P4P start (:func:`p4p_batch`) then :func:`refine_lm_batch`, for (N, P, 3) points and
    (N, P, 2) pixels with (3, 3) or (N, 3, 3) K. Frames whose P4P fails keep its reason."""
    points_marker_m = np.asarray(points_marker_m, dtype=float)
    pixels_px = np.asarray(pixels_px, dtype=float)
    K = np.broadcast_to(np.asarray(K, dtype=float), (points_marker_m.shape[0], 3, 3))
    start = p4p_batch(points_marker_m, pixels_px, K)
    result = refine_lm_batch(start.T_cam_marker, points_marker_m, pixels_px, K, **lm_options)
    result.reason[~start.ok] = start.reason[~start.ok]
    return result
