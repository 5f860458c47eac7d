"""Per-frame pose diagnostics of a replay: planar ambiguity and its resolution, and uncertainty
(covariance, Cramér–Rao bound, NEES). State carried between frames; no I/O.

Used by :class:`agvviz.replay.solve.Replay`; the math is in :mod:`agvviz.solvers.ambiguity`,
:mod:`agvviz.solvers.uncertainty` and :mod:`agvviz.solvers.planar`.

Ambiguity (every frame with a 6-DoF solver): both IPPE poses are computed and their
reprojection-error ratio recorded. The solver's pose is one candidate; the other IPPE branch —
refined by LM when the solver is ``lm``, so both candidates had the same treatment — is the
second. The ``ambiguity`` setting chooses (``lowest_error``, ``continuity``, ``odometry``: see
:mod:`agvviz.solvers.ambiguity`; poses are compared as ``T_world_agv``); the pose not chosen is
kept as the frame's *ghost*. A frame is
*flipped* when its chosen pose lies on the branch the previous solved frame rejected.

Uncertainty (every solved frame): pixel σ is the ``sigma_px`` setting, or with ``auto`` the
pooled residual estimate sqrt(Σ‖r‖² / Σ dof) over all solved frames so far, this one included
(one frame of 4 points has only 2 degrees of freedom — far too few for a per-frame σ). The
covariance of ``T_world_agv`` is in the left tangent space in the world frame, (ρ, φ). With
``covariance=full`` (``systematic`` given) it adds each marker's systematic corner error (its
outline seen grown or shrunk: ``qr_outline_px`` for a QR code, ``corner_bias_px`` for any other
marker), the intrinsics and distortion, the camera's extrinsic and every used marker's map placement,
propagated through the solution (:func:`agvviz.solvers.uncertainty.frame_covariance_split`,
which also keeps the common-mode factors two frames share; per source: ``frame_covariance_full``;
their σ's are the run's settings); with ``covariance=pixel`` the map and the extrinsics are
taken as exact and pixel noise is the only source. The ``planar`` solver's (x, y, ψ) take the
same sources (:func:`agvviz.solvers.uncertainty.planar_covariance_full`; its extrinsic is in the
residuals).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from agvviz.geometry import se3
from agvviz.model.frames import FrameResult
from agvviz.solvers import ambiguity, planar, uncertainty
from agvviz.solvers.lm import refine_lm, reprojection_rms_px
from agvviz.solvers.registry import SolveResult, SolverOptions

#: Candidates closer than this (rotation angle, rad) are one pose, not an ambiguity.
SAME_POSE_RAD = 1e-6
#: An LM-refined alternative that lands within this angle of the solver's pose has collapsed
#: onto it (the other branch is not a local minimum); the raw IPPE branch is kept instead.
COLLAPSED_RAD = 1e-3

#: Degrees of freedom the pooled σ needs before :meth:`PoseDiagnostics.corner_sigma_px` uses it
#: (its relative standard error is then ≈ 1/sqrt(2·20) = 16 %).
MIN_POOLED_DOF = 20
#: Corner noise σ (px) assumed before the pool has :data:`MIN_POOLED_DOF` degrees of freedom: the
#: top of what OpenCV's refiners measure on real photos (DESIGN §9).
FALLBACK_NOISE_PX = 0.5

#: ``to_world(T_cam_marker) -> (T_world_cam, T_world_agv)`` for the current frame.
ToWorld = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class PoseDiagnostics:
    """Ambiguity resolution and uncertainty for one replay (state between frames).

    Parameters
    ----------
    solver : solver name of the run.
    objective : LM objective of the run ("depth" or "pixel").
    policy : ambiguity policy (:data:`agvviz.solvers.ambiguity.POLICIES`).
    sigma_px : fixed pixel σ, or ``None`` for the pooled residual estimate.
    options : LM settings used to refine the alternative IPPE branch.
    systematic : σ's of the covariance's systematic sources, or ``None`` for pixel noise only.
    """

    def __init__(
        self,
        solver: str,
        objective: str,
        policy: str,
        sigma_px: float | None,
        options: SolverOptions,
        systematic: uncertainty.SystematicSigmas | None = None,
    ):
        self.solver = solver
        #: σ's of the systematic sources (``covariance=full``), ``None``: pixel noise only
        self.systematic = systematic
        self.objective = objective
        self.policy = policy
        self.fixed_sigma_px = sigma_px
        self.options = options
        self._sum_sq_px2 = 0.0
        self._dof = 0
        self._single_sum_sq_px2 = 0.0  # residuals of markers solved on their own (note_single_marker)
        self._single_dof = 0
        self._previous_world_agv: np.ndarray | None = None
        self._previous_ghost_world_agv: np.ndarray | None = None
        self._previous_odometry: np.ndarray | None = None
        self._pending: np.ndarray | None = None  # this frame's rejected T_world_agv
        #: Latest odometry pose ``T_odom_agv`` (set by the replay from /agv/odometry).
        self.odometry: np.ndarray | None = None

    # -- ambiguity ----------------------------------------------------------------------------
    def resolve(
        self,
        solved: SolveResult,
        points_marker_m: np.ndarray,
        pixels_px: np.ndarray,
        K: np.ndarray,
        to_world: ToWorld,
        result: FrameResult,
    ) -> SolveResult:
        """The pose to keep for this frame (``solved`` or the other IPPE branch); fills
        ``result.ambiguity_ratio``, ``ambiguity_rule``, ``flipped`` and ``T_world_agv_ghost``."""
        self._pending = None
        pair, why = ambiguity.ippe_pair(points_marker_m, pixels_px, K)
        if pair is None:
            result.ambiguity_rule = f"no IPPE pair: {why}"
            return solved
        result.ambiguity_ratio = pair.ratio
        if self.solver == "planar":
            result.ambiguity_rule = "planar solver: 3 DoF, no mirror branch"
            return solved
        T0 = solved.T_cam_marker
        near_best = ambiguity.rotation_distance_rad(T0, pair.T_best_cam_marker) <= ambiguity.rotation_distance_rad(
            T0, pair.T_other_cam_marker
        )
        T_alt = pair.T_other_cam_marker if near_best else pair.T_best_cam_marker
        alt = SolveResult(T_alt, "", [], reprojection_rms_px(T_alt, points_marker_m, pixels_px, K))
        if self.solver == "lm":
            path: list[np.ndarray] = []
            T_ref, reason, iterations = refine_lm(
                T_alt, points_marker_m, pixels_px, K,
                objective=self.options.objective, max_iterations=self.options.max_iterations,
                initial_damping=self.options.initial_damping, step_tol=self.options.step_tol,
                cost_rel_tol=self.options.cost_rel_tol, path_out=path,
            )
            if T_ref is not None and ambiguity.rotation_distance_rad(T_ref, T0) > COLLAPSED_RAD:
                alt = SolveResult(
                    T_ref, "", iterations, reprojection_rms_px(T_ref, points_marker_m, pixels_px, K), path
                )
        if ambiguity.rotation_distance_rad(alt.T_cam_marker, T0) < SAME_POSE_RAD:
            result.ambiguity_rule = "one pose (both IPPE branches agree)"
            return solved
        try:
            world = [to_world(T0), to_world(alt.T_cam_marker)]
        except ValueError:
            return solved
        predicted_world_agv = None
        if self._previous_world_agv is not None and self._previous_odometry is not None and self.odometry is not None:
            predicted_world_agv = self._previous_world_agv @ se3.inverse(self._previous_odometry) @ self.odometry
        index, rule = ambiguity.choose(
            self.policy,
            (solved.reproj_rms_px, alt.reproj_rms_px),
            (world[0][1], world[1][1]),
            self._previous_world_agv,
            predicted_world_agv,
        )
        chosen = solved if index == 0 else alt
        chosen_world_agv, rejected_world_agv = world[index][1], world[1 - index][1]
        result.ambiguity_rule = rule
        result.flipped = ambiguity.is_flip(chosen_world_agv, self._previous_world_agv, self._previous_ghost_world_agv)
        result.T_world_agv_ghost = rejected_world_agv
        self._pending = rejected_world_agv
        return chosen

    def joint_resolved(self, result: FrameResult, n_markers: int) -> None:
        """The frame's pose came from ``n_markers`` ≥ 2 markers jointly: their corners do not
        lie on one small plane patch, so there is no mirror pose to keep as a ghost."""
        result.ambiguity_rule = f"joint solve over {n_markers} markers (no mirror pose)"
        result.flipped = False
        result.T_world_agv_ghost = None
        self._pending = None

    def note_single_marker(self, T_cam_marker: np.ndarray, points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray) -> None:
        """Pool the residuals of one marker solved on its own: the detector's corner noise,
        free of what a single marker's pose absorbs (its map placement, its printed size)."""
        sum_sq, dof = uncertainty.residual_sum_sq_px2(T_cam_marker, points_marker_m, pixels_px, K)
        if dof > 0 and np.isfinite(sum_sq):
            self._single_sum_sq_px2 += sum_sq
            self._single_dof += dof

    def corner_sigma_px(self, corner_bias_px: float, fallback_px: float = FALLBACK_NOISE_PX) -> float:
        """Pixel σ of one corner coordinate for tests across markers (the joint solve's χ² per
        marker): sqrt(noise² + ``corner_bias_px``²). The noise is the fixed ``sigma_px`` setting,
        else the pooled residual σ of the markers solved on their own so far (once it rests on
        :data:`MIN_POOLED_DOF` degrees of freedom), else ``fallback_px``; ``corner_bias_px`` is
        each marker's systematic corner error, which a marker's own fit absorbs."""
        noise = self.fixed_sigma_px
        if noise is None:
            pooled = uncertainty.residual_sigma_px(self._single_sum_sq_px2, self._single_dof)
            noise = pooled if self._single_dof >= MIN_POOLED_DOF and pooled else fallback_px
        return float(np.hypot(noise, corner_bias_px))

    # -- uncertainty --------------------------------------------------------------------------
    def finish(
        self,
        result: FrameResult,
        T_cam_marker: np.ndarray,
        points_marker_m: np.ndarray,
        pixels_px: np.ndarray,
        K: np.ndarray,
        T_agv_cam: np.ndarray | None,
        camera_on_agv: bool,
        markers: list[tuple[np.ndarray, np.ndarray]] | None = None,
        T_frame_marker: np.ndarray | None = None,
        marker_ids: list[str] | None = None,
    ) -> None:
        """Covariance, bound and NEES of a solved frame; then remember it for the next one.

        ``points_marker_m`` are in the frame of ``T_cam_marker``, whose pose in the frame F the
        markers are fixed in is ``T_frame_marker`` (identity for a joint solve, whose points are
        in F); ``markers`` lists every used marker's mapped ``T_F_marker`` and its points in its
        own frame, in the order of the points (default: one marker, ``T_frame_marker``), and
        ``marker_ids`` their ids (for the covariance's common-mode factors)."""
        T_world_cam, T_world_agv = result.T_world_cam, result.T_world_agv
        T_world_marker = T_world_cam @ T_cam_marker
        is_planar = self.solver == "planar"
        sum_sq, dof = uncertainty.residual_sum_sq_px2(T_cam_marker, points_marker_m, pixels_px, K)
        if is_planar:
            dof += 3  # 3 parameters instead of 6
        self._sum_sq_px2 += sum_sq
        self._dof += max(dof, 0)
        sigma = self.fixed_sigma_px
        if sigma is None:
            sigma = uncertainty.residual_sigma_px(self._sum_sq_px2, self._dof)
        result.n_points = len(points_marker_m)
        result.sigma_px = sigma
        self._remember(result)
        if sigma is None or sigma <= 0.0:
            result.uncertainty_note = "no pixel σ yet (no residual degrees of freedom so far)"
            return
        try:
            points_world = se3.transform_points(T_world_marker, points_marker_m)
            if is_planar and self.systematic is not None:
                cov3 = uncertainty.planar_covariance_full(
                    planar.pixel_jacobian_planar(T_world_agv, T_agv_cam, points_world, K),
                    planar.pixel_jacobian_planar_wrt_extrinsic(T_world_agv, T_agv_cam, points_world, K),
                    se3.inverse(T_world_cam),
                    self._with_outlines(result, markers if markers is not None else [(T_world_marker, points_marker_m)]),
                    K, sigma, self.systematic,
                )
                cov = planar.embed_world_left(cov3, T_world_agv)
            elif is_planar:
                cov3 = planar.covariance_planar(T_world_agv, T_agv_cam, points_world, K, sigma)
                cov = planar.embed_world_left(cov3, T_world_agv)
            else:
                objective = self.objective if self.solver == "lm" else "pixel"
                if self.systematic is None:
                    cov = uncertainty.covariance_world_agv(
                        uncertainty.covariance(T_cam_marker, points_marker_m, K, sigma, objective), T_world_cam
                    )
                else:
                    T_F_m = np.eye(4) if T_frame_marker is None else np.asarray(T_frame_marker, dtype=float)
                    used = markers if markers is not None else [(T_F_m, points_marker_m)]
                    ids = list(marker_ids) if marker_ids is not None and len(marker_ids) == len(used) else [
                        f"#{i}" for i in range(len(used))]  # unnamed: shared with no other frame
                    cov, result.cov_common_factors = uncertainty.frame_covariance_split(
                        T_cam_marker @ se3.inverse(T_F_m), self._with_outlines(result, used), ids,
                        K, sigma, self.systematic, T_world_cam, T_world_agv,
                        T_agv_cam if camera_on_agv else T_world_cam, camera_on_agv, objective,
                    )
                    if marker_ids is None or len(marker_ids) != len(used):
                        result.cov_common_factors = {
                            g: S for g, S in result.cov_common_factors.items() if g == uncertainty.CAMERA_GROUP}
            result.cov_world_agv = cov
            result.position_cov_world_m2 = uncertainty.position_covariance(cov, T_world_agv)
            result.position_sigma_m = uncertainty.position_bound_m(result.position_cov_world_m2)
            truth = result.T_world_agv_truth
            if truth is None:
                return
            # Truth of whatever rides on the AGV (camera or marker); the other is fixed.
            moved = truth @ se3.inverse(T_world_agv)
            T_world_cam_true = moved @ T_world_cam if camera_on_agv else T_world_cam
            T_world_marker_true = T_world_marker if camera_on_agv else moved @ T_world_marker
            if is_planar:
                crlb3 = planar.covariance_planar(truth, T_agv_cam, points_world, K, sigma)
                crlb = planar.embed_world_left(crlb3, truth)
                error3 = planar.planar_error(T_world_agv, truth)
                result.nees = float(error3 @ np.linalg.solve(cov3, error3))
                result.nees_dof = 3
            else:
                T_cam_marker_true = se3.inverse(T_world_cam_true) @ T_world_marker_true
                crlb = uncertainty.covariance_world_agv(
                    uncertainty.crlb(T_cam_marker_true, points_marker_m, K, sigma), T_world_cam_true
                )
                result.nees = uncertainty.nees(T_world_agv, truth, cov)
                result.nees_dof = 6
            result.crlb_position_m = uncertainty.position_bound_m(uncertainty.position_covariance(crlb, truth))
            if result.position_error_m is not None and result.crlb_position_m > 0.0:
                result.position_over_crlb = result.position_error_m / result.crlb_position_m
        except (uncertainty.UncertaintyError, np.linalg.LinAlgError) as exc:
            result.uncertainty_note = f"no covariance: {exc}"

    def _with_outlines(self, result: FrameResult, markers: list) -> list:
        """``markers`` with each one's outline shift σ (px) third: ``qr_outline_px`` for a QR
        code (its observation carries a payload), ``corner_bias_px`` for every other marker
        (ArUco, AprilTag, board squares: a solid border). Markers are matched to
        ``result.used_marker_ids`` in order; any mismatch keeps ``corner_bias_px`` for all."""
        ids = tuple(getattr(result, "used_marker_ids", ()) or ())
        payloads = {o.marker_id: o.payload for o in (getattr(result, "observations", None) or ())}
        if len(ids) != len(markers):
            return markers
        return [
            (m[0], m[1], self.systematic.qr_outline_px if payloads.get(i) else self.systematic.corner_bias_px)
            for m, i in zip(markers, ids)
        ]

    def _remember(self, result: FrameResult) -> None:
        """Keep this solved frame's chosen and rejected poses and odometry for the next frame."""
        self._previous_ghost_world_agv, self._pending = self._pending, None
        self._previous_world_agv = result.T_world_agv
        self._previous_odometry = self.odometry
