"""One camera pose from every marker a frame sees: a joint LM over all their corners. Numpy/scipy only.

Paper 000 solves each frame from one code (the largest); a frame that sees several markers
holds more information. Here the unknown is ``T_cam_F``, the pose of a reference frame ``F`` in
the camera — ``F`` is the frame the markers are fixed in (``world`` for a floor or wall map,
``agv`` for markers on the vehicle watched by a world-fixed camera) — and every corner of
every marker is one pixel residual of :func:`agvviz.solvers.lm.refine_lm` (left perturbation,
δ = (ρ, φ), :mod:`agvviz.conventions`).

Steps of :func:`solve_joint`:

1. **Hypotheses.** The caller's start (the best single-marker pose, after its ambiguity rule)
   and both IPPE poses of every marker on its own. The latter are only computed when the start
   does not explain every marker (it wins ties, so they could not change the choice).
2. **Consensus.** Under each hypothesis every marker's RMS reprojection error is compared with
   a loose gate (:data:`HYPOTHESIS_GATE_SIGMA` σ, at least :data:`HYPOTHESIS_GATE_MIN_PX`: a
   single marker's pose is imprecise in depth, so far markers land pixels away); the hypothesis
   that explains the most markers wins (the caller's start on ties: paper 000's largest code).
   When none explains all, each is first refitted on the markers it puts within
   :data:`LOCAL_GATE_PX` (local optimisation, as in LO-RANSAC) and counted again.
   When none explains half of them, all are fitted together (step 4 then says whether they
   disagree as a group).
3. **Joint LM** over the corners of the markers that hypothesis explains; a marker it did not
   explain joins when the joint pose passes it through the test below.
4. **χ² test per marker.** Under the joint pose, marker k's squared residuals over σ² follow
   χ² with ``2·n_k − h_k`` degrees of freedom (``h_k`` its share of the 6 fitted parameters,
   the trace of its block of the hat matrix). The worst marker above the
   ``1 − p_outlier`` quantile is left out and the joint LM repeated. When at least half of
   three or more markers fail (in the fit or left out of it) the fault is not one marker's (a
   wrong marker size, a wrong calibration, σ too small): all are fitted together and the
   solution says so (:attr:`JointSolution.note`).

Every marker gets a :class:`MarkerCheck`: its χ² under the joint pose, its RMS, and how far its
own (single-marker) camera position lies from the joint one.

Cost: the markers' points are stacked once, and a pose is tested against all markers by one
projection (a stack of hypotheses by one batched projection); the χ² test takes one Jacobian
of all points. For 32 markers (128 points) a frame costs a few ms, most of it OpenCV's IPPE for
the own-pose offsets and the LM (``bench/bench_dense_board.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agvviz.geometry import se3
from agvviz.solvers.types import LmIteration
from agvviz.solvers import ambiguity, chi2, uncertainty
from agvviz.solvers.lm import refine_lm, reprojection_rms_px
from agvviz.solvers.registry import SolverOptions

#: Hypothesis gate: a marker is explained by a start pose when its RMS error is within this
#: many σ ...
HYPOTHESIS_GATE_SIGMA = 10.0
#: ... and at least this many pixels (a single-marker pose's depth error moves far markers).
HYPOTHESIS_GATE_MIN_PX = 4.0
#: When no hypothesis explains every marker, each is refitted on the markers it puts within
#: this many pixels (a far marker under a near marker's pose), with at most this many LM steps.
LOCAL_GATE_PX = 25.0
LOCAL_ITERATIONS = 10


@dataclass(frozen=True)
class MarkerView:
    """One marker in one frame.

    marker_id : its id (QR payload id or ArUco/AprilTag id, as text).
    points_marker_m : (N, 3) its feature points in its own frame (z = 0).
    T_F_marker : (4, 4) the marker in the reference frame F.
    ideal_px : (N, 2) the points' pixels in the ideal (undistorted) image.
    """

    marker_id: str
    points_marker_m: np.ndarray
    T_F_marker: np.ndarray
    ideal_px: np.ndarray

    @property
    def points_F_m(self) -> np.ndarray:
        return se3.transform_points(self.T_F_marker, self.points_marker_m)


@dataclass(frozen=True)
class MarkerCheck:
    """One marker against the joint pose.

    chi2 : Σ‖r‖²/σ² of its points at the joint pose; chi2_limit : the test's quantile.
    rms_px : its RMS reprojection error at the joint pose.
    own_offset_m : distance between the camera position its own pose gives and the joint
        one (None when its own pose could not be computed).
    used : whether its corners are in the joint solution.
    """

    marker_id: str
    chi2: float
    chi2_limit: float
    rms_px: float
    own_offset_m: float | None
    used: bool


@dataclass(frozen=True)
class JointSolution:
    """What :func:`solve_joint` found.

    T_cam_F : (4, 4) the joint pose, ``None`` when no LM converged (``reason`` says why).
    used : ids of the markers whose corners made the pose; checks : one per marker given.
    iterations, path : the final LM's records and poses (as :func:`refine_lm`).
    reproj_rms_px : RMS over the used markers' points.
    note : a plain-words finding (markers left out, or markers that disagree as a group).
    disagree_as_group : most markers failed the χ² test together, so all were fitted.
    """

    T_cam_F: np.ndarray | None
    reason: str = ""
    used: tuple[str, ...] = ()
    checks: tuple[MarkerCheck, ...] = ()
    iterations: list[LmIteration] = field(default_factory=list)
    path: list[np.ndarray] = field(default_factory=list)
    reproj_rms_px: float | None = None
    note: str = ""
    disagree_as_group: bool = False

    @property
    def excluded(self) -> tuple[str, ...]:
        return tuple(c.marker_id for c in self.checks if not c.used)


def _chi2_quantile(q: float, dofs: np.ndarray) -> np.ndarray:
    """χ² quantile ``q`` for each degrees of freedom: scipy.stats.chi2.ppf's arithmetic
    (2·P⁻¹(dof/2, q)) in :mod:`agvviz.solvers.chi2` — importing scipy.stats costs ≈1 s of
    every run's start-up, scipy.special ≈0.25 s."""
    return chi2.chi2_quantile(q, dofs)


class _Stacked:
    """Every marker's points in F and pixels stacked once, with each marker's rows, so a pose
    is tested against all markers by one projection (:func:`_rms_each`, :func:`_chi2_each`)."""

    def __init__(self, views: list[MarkerView]):
        counts = np.array([len(v.ideal_px) for v in views])
        if np.any(counts < 1):
            raise ValueError("every marker view needs at least one point")
        self.counts = counts
        self.starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.marker_of_row = np.repeat(np.arange(len(views)), counts)
        self.points_F = np.vstack([v.points_F_m for v in views])
        self.pixels = np.vstack([np.asarray(v.ideal_px, dtype=float) for v in views])

    def select(self, used) -> tuple[np.ndarray, np.ndarray]:
        """(points F, pixels) of the markers flagged in ``used``, in the views' order."""
        rows = np.asarray(used, dtype=bool)[self.marker_of_row]
        return self.points_F[rows], self.pixels[rows]

    def per_marker(self, per_row: np.ndarray) -> np.ndarray:
        """Sums over each marker's rows along the last axis: (…, N) → (…, M)."""
        return np.add.reduceat(per_row, self.starts, axis=-1)


def _squared_errors_px2(T_cam_F: np.ndarray, stacked: _Stacked, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(squared pixel error of every point (…, N), each marker in front of the camera (…, M))
    at one pose (4, 4) or a stack of poses (H, 4, 4)."""
    w = se3.transform_points_batch(T_cam_F, stacked.points_F)
    in_front = np.minimum.reduceat(w[..., 2], stacked.starts, axis=-1) > 0.0
    projected = w @ np.asarray(K, dtype=float).T
    with np.errstate(divide="ignore", invalid="ignore"):
        error = projected[..., :2] / projected[..., 2:3] - stacked.pixels
    return np.sum(error**2, axis=-1), in_front


def _rms_each(T_cam_F: np.ndarray, stacked: _Stacked, K: np.ndarray) -> np.ndarray:
    """RMS px per marker at ``T_cam_F`` (4, 4) → (M,), or at each of a stack of poses
    (H, 4, 4) → (H, M); inf for a marker with a point behind the camera."""
    squared, in_front = _squared_errors_px2(T_cam_F, stacked, K)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(stacked.per_marker(squared) / stacked.counts)
    return np.where(in_front, rms, np.inf)


def _own_poses(views: list[MarkerView], K: np.ndarray) -> list[list[np.ndarray]]:
    """Both IPPE poses ``T_cam_F`` of each marker on its own (best first; [] when none)."""
    poses = []
    for view in views:
        pair, _ = ambiguity.ippe_pair(view.points_marker_m, view.ideal_px, K)
        if pair is None:
            poses.append([])
            continue
        T_marker_F = se3.inverse(view.T_F_marker)
        poses.append([pair.T_best_cam_marker @ T_marker_F, pair.T_other_cam_marker @ T_marker_F])
    return poses


def _own_offsets_m(views: list[MarkerView], own: list[list[np.ndarray]] | None, T_cam_F: np.ndarray, K: np.ndarray) -> list[float | None]:
    """Per marker, how far its own camera position (the IPPE branch nearer the joint one: a lone
    marker's mirror ambiguity is not a disagreement) lies from the joint pose's; None when IPPE
    fails. ``own``: the poses ``T_cam_F`` of :func:`_own_poses` when already computed; else
    IPPE runs here unranked (the nearer branch does not need the two ranked)."""
    p_joint_F = se3.inverse(T_cam_F)[:3, 3]
    if own is None:
        T_cam_marker, _ = ambiguity.ippe_poses_batch([v.points_marker_m for v in views], [v.ideal_px for v in views], K)
        # camera position in F = T_F_marker · (camera position −Rᵀt in the marker frame)
        p_cam_marker = -np.einsum("mjkl,mjk->mjl", T_cam_marker[:, :, :3, :3], T_cam_marker[:, :, :3, 3])
        T_F_marker = np.stack([v.T_F_marker for v in views])
        p_cam_F = np.einsum("mkl,mjl->mjk", T_F_marker[:, :3, :3], p_cam_marker) + T_F_marker[:, None, :3, 3]
        distance = np.min(np.linalg.norm(p_cam_F - p_joint_F, axis=-1), axis=1)
        return [float(d) if np.isfinite(d) else None for d in distance]
    return [
        min(float(np.linalg.norm(se3.inverse(T_own)[:3, 3] - p_joint_F)) for T_own in poses) if poses else None
        for poses in own
    ]


def _chi2_each(T_cam_F: np.ndarray, stacked: _Stacked, used: list[bool], K: np.ndarray, sigma_px: float):
    """(χ², degrees of freedom) per marker at the joint pose; dof = 2·n_k − (leverage of the
    used marker's rows on the 6 parameters; 0 for a marker not in the fit). One Jacobian of
    every point; a marker's leverage is the trace of its block of the hat matrix
    ``J (J_usedᵀ J_used)⁺ Jᵀ``."""
    J = uncertainty.pixel_jacobian(T_cam_F, stacked.points_F, K)  # (2N, 6), rows (u, v) per point
    used_rows = np.repeat(np.asarray(used, dtype=bool)[stacked.marker_of_row], 2)
    J_used = J[used_rows]
    information_inv = np.linalg.pinv(J_used.T @ J_used)
    leverage_rows = np.einsum("ij,jk,ik->i", J, information_inv, J)
    leverage = np.where(used, stacked.per_marker(leverage_rows[0::2] + leverage_rows[1::2]), 0.0)
    squared, _ = _squared_errors_px2(T_cam_F, stacked, K)
    chi2_values = stacked.per_marker(squared) / sigma_px**2
    dofs = np.maximum(2 * stacked.counts - leverage, 0.5)
    return chi2_values, dofs


def solve_joint(
    views: list[MarkerView],
    K: np.ndarray,
    T_start_cam_F: np.ndarray,
    sigma_px: float,
    options: SolverOptions = SolverOptions(objective="pixel"),
    p_outlier: float = 1e-3,
) -> JointSolution:
    """The camera pose ``T_cam_F`` from every marker in ``views`` (module docstring).

    Parameters
    ----------
    views : ≥ 1 markers of one frame, all fixed in the same frame F.
    K : (3, 3) camera matrix of the ideal image.
    T_start_cam_F : (4, 4) the best single-marker pose (every point of its marker in front).
    sigma_px : pixel σ of the corners, for the gates and the χ² test (> 0).
    options : LM settings (objective, iterations, tolerances).
    p_outlier : a consistent marker is flagged with this probability.
    """
    K = np.asarray(K, dtype=float)
    stacked = _Stacked(views)
    gate_px = max(HYPOTHESIS_GATE_SIGMA * sigma_px, HYPOTHESIS_GATE_MIN_PX)
    start = np.asarray(T_start_cam_F, dtype=float)
    best_used = _rms_each(start, stacked, K) <= gate_px
    best_count = int(best_used.sum())
    own = None
    if best_count < len(views):
        # The caller's start does not explain every marker: try each marker's own poses. (When
        # it does, none can explain more and the start wins ties, so they are not computed.)
        own = _own_poses(views, K)
        hypotheses = [start] + [T for poses in own for T in poses]
        rms_hypotheses = _rms_each(np.stack(hypotheses), stacked, K)  # (H, M)
        for T, rms in zip(hypotheses[1:], rms_hypotheses[1:]):
            inliers = rms <= gate_px
            if int(inliers.sum()) > best_count:  # strict: the caller's start wins ties
                best_count, best_used, start = int(inliers.sum()), inliers, T
    if best_count < len(views):
        # Local optimisation (as in LO-RANSAC): one marker's pose is poor in depth, so refit
        # each hypothesis on the markers it roughly explains and count again.
        for T, rms in zip(hypotheses, rms_hypotheses):
            near = rms <= max(gate_px, LOCAL_GATE_PX)
            if near.sum() < 2:
                continue
            points_F, pixels = stacked.select(near)
            T_local, _, _ = refine_lm(
                T, points_F, pixels, K, objective=options.objective, max_iterations=LOCAL_ITERATIONS,
                initial_damping=options.initial_damping, step_tol=options.step_tol, cost_rel_tol=options.cost_rel_tol,
            )
            if T_local is None:
                continue
            inliers = _rms_each(T_local, stacked, K) <= gate_px
            if int(inliers.sum()) > best_count:
                best_count, best_used, start = int(inliers.sum()), inliers, T_local
            if best_count == len(views):
                break
    used = [bool(u) for u in best_used]
    if not any(used):
        return JointSolution(None, f"no pose explains any marker within {gate_px:.1f} px")
    if 2 * sum(used) < len(views):
        # No single marker's pose explains half of them: not one marker at fault but all
        # (a wrong marker size, a wrong calibration). Fit all; the test below says so.
        used = [True] * len(views)
    note = ""
    removed: set[int] = set()
    group = False
    while True:
        points_F, pixels = stacked.select(used)
        path: list[np.ndarray] = []
        T, reason, iterations = refine_lm(
            start, points_F, pixels, K,
            objective=options.objective, max_iterations=options.max_iterations,
            initial_damping=options.initial_damping, step_tol=options.step_tol,
            cost_rel_tol=options.cost_rel_tol, path_out=path,
        )
        if T is None:
            return JointSolution(None, f"joint LM: {reason}", iterations=iterations, path=path)
        chi2_values, dofs = _chi2_each(T, stacked, used, K, sigma_px)
        limits = _chi2_quantile(1.0 - p_outlier, dofs)
        # A marker the start pose could not explain (depth error of one marker's pose) joins
        # once the joint pose explains it; one the χ² test left out stays out.
        readmit = [] if group else [
            i for i in range(len(views)) if not used[i] and i not in removed and chi2_values[i] <= limits[i]
        ]
        if readmit:
            for i in readmit:
                used[i] = True
            start = T
            continue
        if group:
            break
        failing = [i for i in range(len(views)) if i not in removed and chi2_values[i] > limits[i]]
        flagged = [i for i in failing if used[i]]
        n_candidates = len(views) - len(removed)
        if len(views) > 2 and failing and 2 * len(failing) >= n_candidates:
            # Most markers fail together: not one marker at fault. Fit all, say so.
            ids = ", ".join(views[i].marker_id for i in failing[:6]) + (", …" if len(failing) > 6 else "")
            note = (
                f"markers disagree as a group ({len(failing)} of {n_candidates} fail the χ² test at σ {sigma_px:.2g} px: "
                f"{ids}): a wrong marker size, calibration or σ, not one marker"
            )
            group, used, start = True, [True] * len(views), T
            removed.clear()
            continue
        if not flagged or sum(used) <= 1:
            break
        worst = max(flagged, key=lambda i: chi2_values[i] / limits[i])
        used[worst] = False
        removed.add(worst)
        start = T
    rms_each = _rms_each(T, stacked, K)
    offsets = _own_offsets_m(views, own, T, K)
    checks = tuple(
        MarkerCheck(view.marker_id, float(chi2_values[i]), float(limits[i]), float(rms_each[i]), offsets[i], bool(used[i]))
        for i, view in enumerate(views)
    )
    left_out = [c for c in checks if not c.used]
    if left_out and not note:
        kept = ", ".join(c.marker_id for c in checks if c.used)
        note = "left out " + "; ".join(
            f"{c.marker_id} (RMS {c.rms_px:.2f} px, χ² {c.chi2:.0f} > {c.chi2_limit:.0f}"
            + (f", its own pose {c.own_offset_m * 1000:.0f} mm away" if c.own_offset_m is not None else "")
            + ")"
            for c in left_out
        ) + f": disagrees with {kept}"
    points_F, pixels = stacked.select(used)
    return JointSolution(
        T, "", tuple(v.marker_id for v, u in zip(views, used) if u), checks, iterations, path,
        reprojection_rms_px(T, points_F, pixels, K), note, group,
    )
