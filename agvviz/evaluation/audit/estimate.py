"""From :class:`~agvviz.evaluation.audit.problem.AuditData` to findings: initialise, solve, estimate the
corner noise, covariance, gauge, flags. Pure math: no files, no Rerun, no printing.

1. Robust start (:func:`agvviz.evaluation.audit.problem.initialise`).
2. Solve with the corner σ given (``sigma_px``) or, when 0, first with 0.5 px, then set σ to
   the RMS corner residual corrected for the degrees of freedom the frame poses take
   (variance-component estimation, floored at ``sigma_px_floor``) and solve again from there.
3. Covariance ``σ0²·(JᵀJ)⁻¹`` of the marker, camera and odometry blocks (sparse LU of JᵀJ),
   σ0² = max(1, χ²/dof): never more confident than the stated σ.
4. Gauge (:meth:`agvviz.evaluation.audit.bundle.Problem.gauge_matrix`) on the gauge markers: those seen
   in ``min_frames`` frames that the start found consistent with their neighbours (when at least
   half are; else all but the grossly wrong ones). Gauge markers seen too little (or whose place
   is not observed) leave the set at once; flagged ones leave one at a time, worst first, and the
   problem is solved again each time (a misplaced marker must not drag the frame its neighbours
   are measured in; the neighbours it dragged stay eligible).
5. Flags: per group (position, yaw, tilt, scale; camera translation, rotation) the Mahalanobis
   distance beyond :func:`~agvviz.evaluation.audit.problem.flag_threshold` (k σ, shared among the marker's
   or camera's groups: a clean one is flagged with the probability of |z| > k) AND the size
   beyond its minimum. A group whose posterior σ stays above ``seen_ratio`` × its prior σ is *not
   observed* and not judged (a small marker's print scale, say, while its position is); a
   marker seen in fewer than ``min_frames`` frames, or with no group observed, is listed as
   *seen too little* and never flagged.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import f as f_dist

from agvviz.evaluation.audit.bundle import Problem
from agvviz.evaluation.audit.problem import (
    CAMERA_GROUPS,
    MARKER_GROUPS,
    AuditData,
    AuditSettings,
    camera_pose,
    corrected_marker_pose,
    flag_threshold,
    initialise,
    mahalanobis,
    level_reference,
    on_the_floor,
    marginal_covariance,
    marker_points_world,
    observation_poses,
)
from agvviz.errors import RunError

#: Corner σ of the first solve when it is estimated (px).
FIRST_SIGMA_PX = 0.5


@dataclass
class MarkerFinding:
    """One marker: its correction δ (7, :data:`agvviz.evaluation.audit.problem.MARKER_PARAMS`; the
    components not solved are 0 with σ NaN), σ, frames seen, status and why."""

    marker_id: str
    delta: np.ndarray
    sigma: np.ndarray
    frames: int
    observations: int
    floor: bool
    status: str  # "flagged", "ok", "seen too little"
    reasons: list[str] = field(default_factory=list)
    distances: dict = field(default_factory=dict)  # group -> Mahalanobis distance
    T_world_marker_mapped: np.ndarray | None = None
    T_world_marker_estimated: np.ndarray | None = None
    side_mapped_m: float = 0.0
    init_gross: tuple | None = None  # (yaw_deg, dx_m, dy_m) when the start found it grossly off
    rms_px: float = float("nan")  # RMS corner residual of its observations at the solution
    corners_world_mapped: np.ndarray | None = None  # (4, 3) TL, TR, BR, BL as mapped
    corners_world_estimated: np.ndarray | None = None  # (4, 3) under the estimated correction
    #: groups (position, yaw, tilt, scale) the data barely sees (posterior σ above ``seen_ratio``
    #: × prior σ): not judged, though the marker's other groups are
    unobserved: list[str] = field(default_factory=list)
    seen_little_why: str = ""  # why it is seen too little, when it is

    @property
    def flagged(self) -> bool:
        return self.status == "flagged"


@dataclass
class CameraFinding:
    """One camera: correction (ρ (m), φ (rad), AGV frame) with σ, status and reasons."""

    cam_name: str
    correction: np.ndarray
    sigma: np.ndarray
    status: str
    reasons: list[str]
    T_agv_cam_recorded: np.ndarray
    T_agv_cam_estimated: np.ndarray
    distances: dict = field(default_factory=dict)
    #: (dfx, dfy, dcx, dcy) px and σ when intrinsics are solved, else None
    intrinsics: np.ndarray | None = None
    intrinsics_sigma: np.ndarray | None = None
    K_recorded: np.ndarray | None = None

    @property
    def flagged(self) -> bool:
        return self.status == "flagged"


@dataclass
class AuditEstimate:
    """Everything the solve found (values only)."""

    markers: list[MarkerFinding]
    cameras: list[CameraFinding]
    odometry: dict | None  # scale, scale_sigma, bias_deg_per_s, bias_sigma
    sigma_px: float
    sigma0: float
    T_world_agv: np.ndarray  # (N, 4, 4) solved vehicle poses (in the fixed gauge)
    T_world_agv_start: np.ndarray
    corner_residuals_px: np.ndarray  # (n, 4, 2)
    gauge: str
    gauge_markers: list[str]
    cost: float
    iterations: int
    solve_s: float
    n_params: int
    n_residuals: int
    messages: list[str] = field(default_factory=list)
    #: per camera (share, p) of :func:`calibration_structure`
    calibration_structure: list = field(default_factory=list)


def _sigma_from_residuals(problem: Problem, x: np.ndarray, data: AuditData) -> float:
    r = problem.corner_residuals(x)
    n_res = r.size
    frames_seen = len(np.unique(data.obs_frame))
    dof = n_res - 6 * frames_seen - sum(len(c) for c in problem.layout.marker_cols)
    if dof <= 0:
        return FIRST_SIGMA_PX
    return float(math.sqrt(float(np.sum(r**2)) / dof))


#: p-value below which the corner residuals' image-position structure is reported.
STRUCTURE_P = 1e-4
#: A run with at least this many flagged markers, and more than this share of the judged ones,
#: gets a note: a map has a few wrong entries; a wrong calibration makes most look wrong.
MANY_FLAGGED_MIN = 4
MANY_FLAGGED_SHARE = 1.0 / 3.0


def calibration_structure(data: AuditData, residuals_px: np.ndarray) -> list[tuple[float, float]]:
    """Per camera (share, p): how much of the corner residuals (n, 4, 2) px follows the image
    position the way an error of the recorded calibration would — the first-order change of a
    corner under dfx, dfy, dcx, dcy, radial k1, k2 and tangential p1, p2 at its normalised
    position (x, y) — and the F-test's p-value of that fit against none. The audit does not
    model distortion (nor, by default, the intrinsics): when p is tiny, what it leaves in the
    corners is a calibration error, which biases the placements and makes σ too small."""
    out = []
    for c in range(len(data.cam_names)):
        sel = data.obs_cam == c
        K = data.K[c]
        px, r = data.obs_px[sel].reshape(-1, 2), residuals_px[sel].reshape(-1, 2)
        n_basis = 8
        if len(px) * 2 <= n_basis + 2:
            out.append((0.0, 1.0))
            continue
        x, y = (px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1]
        r2, one, zero = x * x + y * y, np.ones_like(x), np.zeros_like(x)
        basis_u = np.column_stack([x, zero, one, zero, x * r2, x * r2 * r2, 2 * x * y, r2 + 2 * x * x])
        basis_v = np.column_stack([zero, y, zero, one, y * r2, y * r2 * r2, r2 + 2 * y * y, 2 * x * y])
        B, rr = np.vstack([basis_u, basis_v]), np.concatenate([r[:, 0], r[:, 1]])
        coef, *_ = np.linalg.lstsq(B, rr, rcond=None)
        ss_total, ss_left = float(rr @ rr), float(np.sum((rr - B @ coef) ** 2))
        dof = len(rr) - n_basis
        if ss_total <= 0 or ss_left <= 0:
            out.append((0.0, 1.0))
            continue
        F = ((ss_total - ss_left) / n_basis) / (ss_left / dof)
        out.append((1.0 - ss_left / ss_total, float(f_dist.sf(F, n_basis, dof))))
    return out


def _best_seen(candidates: np.ndarray, frames_per: np.ndarray, most: int) -> np.ndarray:
    """The ``most`` candidates seen in the most frames (ties: the first): the gauge rows touch
    only their columns, so the Jacobian's column groups — and the cost of one — stay bounded
    however many markers the run sees."""
    order = np.flatnonzero(candidates)[np.argsort(-frames_per[candidates], kind="stable")]
    out = np.zeros_like(candidates)
    out[order[:most]] = True
    return out


def _with_offsets(problem: Problem, x: np.ndarray) -> np.ndarray:
    """``x`` of a problem without corner offsets, extended by zero offsets to ``problem``'s layout."""
    return np.concatenate([x, np.zeros(problem.layout.size - len(x))])


def _solve(problem: Problem, x0: np.ndarray, rough: bool = False):
    res = problem.solve(x0, rough=rough)
    if not np.all(np.isfinite(res.x)):
        raise RunError("the audit's solve diverged (non-finite values); check the recording's calibration and map")
    return res


def _judge_marker(values_by_group: dict, s: AuditSettings) -> dict:
    """Size test of each group: True when the correction reaches the group's minimum size."""
    out = {}
    for group, values in values_by_group.items():
        out[group] = {
            "position": np.linalg.norm(values) >= s.min_position_m,
            "yaw": abs(math.degrees(values[0])) >= s.min_angle_deg,
            "tilt": math.degrees(np.linalg.norm(values)) >= s.min_angle_deg,
            "scale": abs(values[0]) >= s.min_scale,
        }[group]
    return out


def estimate(data: AuditData, settings: AuditSettings, solve_pose) -> AuditEstimate:
    """Audit ``data`` (module docstring). ``solve_pose(points_marker_m, pixels_px, K)`` →
    ``T_cam_marker`` or None: the run's single-marker solver, for the start."""
    data.check()
    t0 = time.perf_counter()
    s = settings
    M = len(data.marker_ids)
    frames_per = data.frames_per_marker()
    obs_per = np.bincount(data.obs_marker, minlength=M)
    V = observation_poses(data, solve_pose)
    init = initialise(data, s, V)
    # first gauge: the markers seen in enough frames that the start did not find grossly wrong
    enough = frames_per >= s.min_frames
    gauge = enough & np.array([m not in init.gross for m in range(M)], dtype=bool)
    if np.sum(gauge & init.consistent) >= max(3, 0.5 * np.sum(gauge)):
        gauge &= init.consistent  # leave out the ones the start already doubts: fewer re-solves
    if not np.any(gauge):
        gauge = enough if np.any(enough) else np.ones(M, dtype=bool)
    candidates = gauge.copy()
    gauge = _best_seen(candidates, frames_per, s.gauge_markers)
    # auto: the start agrees with the odometry's height, pitch and roll (0 for an AGV's planar odometry); the
    # height within 5 cm or the 3° the attitude test allows at the median camera–marker range (a far marker's
    # single-frame pose is no better: an AUV 10 m from its markers starts ≈10 cm off)
    ranges = np.linalg.norm(data.T_world_marker[data.obs_marker, :3, 3] - V[:, :3, 3], axis=1)
    range_m = float(np.nanmedian(ranges)) if np.any(np.isfinite(ranges)) else 0.0
    tol_m = max(0.05, math.tan(math.radians(3.0)) * range_m)
    floor = s.floor_prior == "on" or (s.floor_prior == "auto" and on_the_floor(init.T0, level_reference(data), tol_m))
    sigma_px = s.sigma_px if s.sigma_px > 0 else FIRST_SIGMA_PX
    # with the corner σ to estimate, the corner offsets (a random effect) join in the second
    # pass: in the first they would take up residual that the σ estimate must see
    problem = Problem(data, s, init.T0, sigma_px, gauge, floor, s.corner_bias_px if s.sigma_px > 0 else 0.0)
    x = np.zeros(problem.layout.size)
    problem.layout.pack_delta(x, init.delta0)
    res = _solve(problem, x, rough=s.sigma_px == 0)
    iterations = int(res.nfev)
    if s.sigma_px == 0:
        sigma_px = max(s.sigma_px_floor, _sigma_from_residuals(problem, res.x, data))
        problem = Problem(data, s, init.T0, sigma_px, gauge, floor, s.corner_bias_px)
        res = _solve(problem, _with_offsets(problem, res.x))
        iterations += int(res.nfev)
    L = problem.layout
    offsets, o = [], 0  # each marker's columns within the marker block
    for m in range(M):
        offsets.append(np.arange(o, o + len(L.marker_slots[m])))
        o += len(L.marker_slots[m])
    n_marker_cols = o
    prior_sigma = problem.marker_prior_sigma
    # until no gauge marker is flagged or unseen: the unseen leave at once, the flagged one at a
    # time, worst first — a misplaced gauge marker drags the frame the others are measured in, so
    # its neighbours may look wrong until it has left; they stay candidates
    for _ in range(s.gauge_markers + 2):
        m_res, n_par = len(res.fun), L.size
        chi2_value = float(np.sum(res.fun**2))
        sigma0_sq = max(1.0, chi2_value / max(m_res - n_par, 1))
        cols = np.arange(6 * L.n_frames, L.offsets0)  # the corner offsets are nuisance: not reported
        try:
            cov = marginal_covariance(res.jac, cols) * sigma0_sq
        except RuntimeError as exc:  # singular JᵀJ: cannot happen with the priors, unless degenerate
            raise RunError(f"the audit's information matrix is singular ({exc}); the recording cannot be audited") from None
        xi, delta, eta, odom = L.unpack(res.x)
        findings, flagged, seen_little, placed = [], np.zeros(M, dtype=bool), np.zeros(M, dtype=bool), np.ones(M, dtype=bool)
        excess = np.zeros(M)  # a flagged marker's largest distance over its threshold
        corners_mapped = marker_points_world(data, np.zeros((M, 7)))
        corners_estimated = marker_points_world(data, delta)
        for m in range(M):
            slots = list(L.marker_slots[m])
            block = cov[np.ix_(offsets[m], offsets[m])]
            sigma = np.full(7, np.nan)
            sigma[slots] = np.sqrt(np.maximum(np.diag(block), 0.0))
            groups = {g: [q for q in members if q in slots] for g, members in MARKER_GROUPS.items()}
            groups = {g: q for g, q in groups.items() if q}
            # a group the data barely sees (posterior σ above seen_ratio × prior σ) is not judged
            unobserved = [g for g, q in groups.items() if np.any(sigma[q] / prior_sigma[q] > s.seen_ratio)]
            seen_little[m] = frames_per[m] < s.min_frames or len(unobserved) == len(groups)
            groups = {g: q for g, q in groups.items() if g not in unobserved}
            if frames_per[m] < s.min_frames:
                little_why = f"seen in {frames_per[m]} frame(s) (fewer than min_frames={s.min_frames}): too little to say anything"
            elif seen_little[m]:
                little_why = (f"seen in {frames_per[m]} frames, but every σ stays above {s.seen_ratio:g} × the map prior's: "
                              "the data cannot say")
            else:
                little_why = ""
            reasons, distances = [], {}
            if not seen_little[m]:
                size_ok = _judge_marker({g: delta[m, q] for g, q in groups.items()}, s)
                for group, present in groups.items():
                    sub = [slots.index(q) for q in present]
                    dist = mahalanobis(delta[m, present], block[np.ix_(sub, sub)])
                    distances[group] = dist
                    threshold = flag_threshold(s.k_sigma, len(present), len(groups))
                    if dist > threshold and size_ok[group]:
                        reasons.append(group)
                        excess[m] = max(excess[m], dist / threshold)
            flagged[m] = bool(reasons)
            status = "seen too little" if seen_little[m] else ("flagged" if reasons else "ok")
            findings.append(MarkerFinding(
                marker_id=data.marker_ids[m], delta=delta[m].copy(), sigma=sigma, frames=int(frames_per[m]),
                observations=int(obs_per[m]), floor=bool(problem.floor[m]), status=status, reasons=reasons,
                distances=distances, T_world_marker_mapped=data.T_world_marker[m].copy(),
                T_world_marker_estimated=corrected_marker_pose(data.T_world_marker[m], delta[m]),
                side_mapped_m=float(np.linalg.norm(data.points_marker_m[m, 1] - data.points_marker_m[m, 0])),
                init_gross=init.gross.get(m), corners_world_mapped=corners_mapped[m],
                corners_world_estimated=corners_estimated[m], unobserved=[] if seen_little[m] else unobserved,
                seen_little_why=little_why,
            ))
            placed[m] = "position" not in unobserved and "yaw" not in unobserved
        unseen = gauge & (seen_little | ~placed)
        if np.any(unseen):
            candidates &= ~unseen
        elif np.any(gauge & flagged):
            candidates[int(np.argmax(np.where(gauge & flagged, excess, -1.0)))] = False
        new_gauge = _best_seen(candidates & ~flagged & ~seen_little & placed, frames_per, s.gauge_markers)
        if not np.any(new_gauge) or np.array_equal(new_gauge, gauge):
            break
        gauge = new_gauge
        problem = Problem(data, s, init.T0, sigma_px, gauge, floor, s.corner_bias_px)
        res = _solve(problem, res.x)
        iterations += int(res.nfev)
    solve_s = time.perf_counter() - t0
    T = problem.poses(xi, eta)
    r_px = problem.corner_residuals(res.x)
    for m, f in enumerate(findings):
        sel = data.obs_marker == m
        if np.any(sel):
            f.rms_px = float(np.sqrt(np.mean(np.sum(r_px[sel] ** 2, axis=-1))))
    cameras = []
    for c, name in enumerate(data.cam_names):
        cc = np.arange(n_marker_cols + 6 * c, n_marker_cols + 6 * c + 6)
        block = cov[np.ix_(cc, cc)]
        sigma = np.sqrt(np.maximum(np.diag(block), 0.0))
        reasons, distances = [], {}
        for group, members in CAMERA_GROUPS.items():
            values = eta[c, list(members)]
            dist = mahalanobis(values, block[np.ix_(list(members), list(members))])
            distances[group] = dist
            size = np.linalg.norm(values)
            size_ok = size >= s.min_camera_m if group == "translation" else math.degrees(size) >= s.min_camera_deg
            if dist > flag_threshold(s.k_sigma, 3, len(CAMERA_GROUPS) + L.with_intrinsics) and size_ok:
                reasons.append(group)
        kappa = kappa_sigma = None
        if L.with_intrinsics:
            ic = L.intrinsics_cols(c) - 6 * L.n_frames
            iblock = cov[np.ix_(ic, ic)]
            kappa = L.intrinsics(res.x)[c].copy()
            kappa_sigma = np.sqrt(np.maximum(np.diag(iblock), 0.0))
            dist = mahalanobis(kappa, iblock)
            distances["intrinsics"] = dist
            if dist > flag_threshold(s.k_sigma, 4, len(CAMERA_GROUPS) + 1) and np.max(np.abs(kappa)) >= s.min_intrinsics_px:
                reasons.append("intrinsics")
        cameras.append(CameraFinding(
            cam_name=name, correction=eta[c].copy(), sigma=sigma, status="flagged" if reasons else "ok",
            reasons=reasons, T_agv_cam_recorded=data.T_agv_cam[c].copy(),
            T_agv_cam_estimated=camera_pose(data.T_agv_cam[c], eta[c]), distances=distances,
            intrinsics=kappa, intrinsics_sigma=kappa_sigma, K_recorded=data.K[c].copy(),
        ))
    odometry = None
    if L.with_odometry:
        oc = np.arange(L.odom0 - 6 * L.n_frames, L.odom0 - 6 * L.n_frames + 2)
        osig = np.sqrt(np.diag(cov[np.ix_(oc, oc)]))
        odometry = {"scale": float(odom[0]), "scale_sigma": float(osig[0]),
                    "bias_deg_per_s": math.degrees(odom[1]), "bias_sigma_deg_per_s": math.degrees(osig[1])}
    gauge_ids = [data.marker_ids[m] for m in range(M) if gauge[m]]
    gauge_text = (
        "the data cannot see where the map as a whole lies on the floor (moving every marker and vehicle pose "
        "together in x, y, yaw changes no corner, odometry step or floor residual), and its overall size only "
        "through the odometry's scale, itself unknown; fixed by the map: the mean x, y, yaw and radial correction "
        f"of the {len(gauge_ids)} gauge markers ({', '.join(gauge_ids)}: the best seen of those consistent with "
        "their neighbours, not flagged) are 0 — every correction is relative to them, and the map's overall place, "
        "heading and scale are taken as recorded"
    )
    if problem.gauge_matrix().shape[0] > 4:
        gauge_text += ("; the markers are off the floor, so raising them all with the cameras' mounting changes no "
                       "measurement either: their mean height correction is 0 too")
    if not floor:
        gauge_text += ("; no floor prior (floor_prior=" + s.floor_prior + "): the camera's height, pitch and roll trade "
                       "against the vehicle's and rest on the extrinsic prior")
    messages = []
    if not res.success:
        messages.append(f"least_squares stopped before converging: {res.message}")
    if not L.with_odometry:
        messages.append("the recording has no odometry: marker placements are seen only between markers in one frame")
    judged = [f for f in findings if f.status != "seen too little"]
    n_flagged = sum(f.flagged for f in judged)
    if n_flagged >= MANY_FLAGGED_MIN and n_flagged > MANY_FLAGGED_SHARE * len(judged):
        messages.append(
            f"{n_flagged} of {len(judged)} judged markers are flagged: one error common to all of them (the camera "
            "calibration, the odometry) is more likely than that many misplaced markers — check the calibration, try "
            "--set intrinsics=true, and read the flags with care")
    structure = calibration_structure(data, r_px)
    for name, (share, p) in zip(data.cam_names, structure):
        if p < STRUCTURE_P:
            advice = ("the recorded distortion is off (not solved by the audit): recalibrate" if L.with_intrinsics
                      else "try --set intrinsics=true, or recalibrate")
            messages.append(
                f"camera {name}: the corner residuals follow the image position as a calibration error would "
                f"({100 * share:.1f} % of their variance, F-test p = {p:.1g}): the recorded intrinsics or distortion are "
                f"off, which biases the placements and makes their σ too small — read the flags with care; {advice}")
    return AuditEstimate(
        markers=findings, cameras=cameras, odometry=odometry, sigma_px=float(sigma_px),
        sigma0=math.sqrt(chi2_value / max(m_res - n_par, 1)), T_world_agv=T, T_world_agv_start=init.T0,
        corner_residuals_px=r_px, gauge=gauge_text, gauge_markers=gauge_ids, cost=float(res.cost),
        iterations=iterations, solve_s=solve_s, n_params=n_par, n_residuals=m_res, messages=messages,
        calibration_structure=structure,
    )
