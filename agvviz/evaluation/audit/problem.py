"""The audit problem's inputs and model: its settings (:class:`AuditSettings`), the observations
it solves over (:class:`AuditData`), the correction model (how a marker's δ and a camera's η move
them), the vehicle's level reference, the robust start (:func:`initialise`) and the statistics
the flags use. The least-squares problem itself — unknowns, residuals, gauge, solve — is
:mod:`agvviz.evaluation.audit.bundle`.

Pure math (numpy, scipy): no files, no Rerun, no printing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.stats import chi2, norm

from agvviz.errors import InputError, RunError
from agvviz.geometry import euler, se3, so3
from agvviz.geometry.plane import quad_axis_lengths
from agvviz.settings import setting, validate

#: Marker correction components (:mod:`agvviz.evaluation.audit.bundle`); the floor codes' subset.
MARKER_PARAMS = ("dx_m", "dy_m", "dz_m", "yaw_rad", "tilt_x_rad", "tilt_y_rad", "scale")
FLOOR_SLOTS = (0, 1, 3, 4, 5, 6)
ALL_SLOTS = tuple(range(7))
CAMERA_PARAMS = ("dx_m", "dy_m", "dz_m", "rx_rad", "ry_rad", "rz_rad")
#: Report groups of a marker's correction (slot indices) and of a camera's.
MARKER_GROUPS = {"position": (0, 1, 2), "yaw": (3,), "tilt": (4, 5), "scale": (6,)}
CAMERA_GROUPS = {"translation": (0, 1, 2), "rotation": (3, 4, 5)}
#: A marker whose every pairing with a neighbour (the start's marker-to-marker placements)
#: agrees this well, and which puts the vehicle at the others' height within CONSISTENT_M, is a
#: candidate for the first gauge: fewer re-solves when one is flagged.
CONSISTENT_M = 0.015
CONSISTENT_DEG = 1.0


@dataclass(frozen=True)
class AuditSettings:
    """Priors, noise model and flag thresholds of ``agvviz audit`` (``--set key=value``)."""

    sigma_px: float = setting(0.0, "corner σ in px; 0: estimated from the corner residuals of a first solve", min=0.0, max=50.0)
    corner_bias_px: float = setting(0.3, "σ of each marker's systematic corner error (px): one offset per corner, shared by all the "
                                    "marker's detections (print, detector bias on that code; 0.3 px on real photos); a random effect "
                                    "in every marker's σ. 0: corners independent", min=0.0, max=20.0)
    sigma_px_floor: float = setting(0.02, "smallest corner σ (px) the estimate may give", min=1e-4, max=10.0)
    odom_sigma_m: float = setting(0.002, "odometry step noise per axis (m)", min=1e-5, max=1.0)
    odom_sigma_frac: float = setting(0.01, "odometry step noise per metre driven (slip), added in quadrature", min=0.0, max=0.5)
    odom_sigma_deg: float = setting(0.05, "odometry heading noise per step (deg)", min=1e-4, max=10.0)
    floor_prior: str = setting("auto", "the vehicle's height, pitch and roll are the odometry's (an AGV's planar odometry: the floor z = 0, level; "
                               "an AUV's INS/DVL: its depth and attitude) — separates the camera mounting from the vehicle attitude; "
                               "auto: on when the start puts the vehicle there (|Δz| < 5 cm or 3° at the marker range, tilt < 3°)",
                               ("auto", "on", "off"))
    floor_sigma_m: float = setting(0.005, "σ of the vehicle's height about the odometry's (z = 0 on a floor) per frame (m)", min=1e-5, max=1.0)
    floor_tilt_sigma_deg: float = setting(0.5, "σ of the vehicle's pitch and roll per frame (deg; floor bumps)", min=1e-4, max=30.0)
    map_sigma_m: float = setting(0.1, "map prior: σ of a marker's position per axis (m)", min=1e-4, max=100.0)
    map_yaw_sigma_deg: float = setting(10.0, "map prior: σ of a marker's yaw (deg)", min=1e-3, max=180.0)
    map_tilt_sigma_deg: float = setting(2.0, "map prior: σ of a non-floor marker's tilt per axis (deg)", min=1e-3, max=90.0)
    map_scale_sigma: float = setting(0.02, "map prior: σ of a marker's print scale (fraction)", min=1e-5, max=0.5)
    extrinsic_sigma_m: float = setting(0.1, "prior σ of the recorded extrinsic's position per axis (m)", min=1e-5, max=10.0)
    extrinsic_sigma_deg: float = setting(5.0, "prior σ of the recorded extrinsic's rotation per axis (deg)", min=1e-4, max=90.0)
    odom_scale_sigma: float = setting(0.05, "prior σ of the odometry's distance scale error", min=1e-5, max=0.5)
    odom_bias_sigma_deg_per_s: float = setting(1.0, "prior σ of the odometry's heading drift (deg/s)", min=1e-5, max=90.0)
    gauge_markers: int = setting(10, "the gauge: at most this many markers (the best seen) whose mean correction is 0", min=2, max=100000)
    k_sigma: float = setting(3.0, "flag when an error exceeds k·σ (and its minimum size)", min=0.5, max=100.0)
    min_position_m: float = setting(0.01, "smallest marker displacement that is flagged (m)", min=0.0, max=10.0)
    min_angle_deg: float = setting(1.0, "smallest marker yaw or tilt that is flagged (deg)", min=0.0, max=180.0)
    min_scale: float = setting(0.005, "smallest print scale error that is flagged (fraction)", min=0.0, max=0.5)
    min_camera_m: float = setting(0.005, "smallest camera displacement that is flagged (m)", min=0.0, max=10.0)
    min_camera_deg: float = setting(0.25, "smallest camera rotation that is flagged (deg)", min=0.0, max=180.0)
    min_frames: int = setting(3, "a marker seen in fewer frames is reported as seen too little", min=1, max=100000)
    seen_ratio: float = setting(0.5, "a group of a marker's correction (position, yaw, tilt, scale) whose posterior σ exceeds this fraction of "
                                "its prior σ is not observed and not judged; a marker with no group observed is seen too little",
                                min=0.01, max=1.0)
    init_window_frames: int = setting(20, "initialisation: odometry links frames at most this far apart", min=1, max=10000)
    init_yaw_tol_deg: float = setting(20.0, "initialisation: two markers disagreeing by more yaw are a gross error", min=1.0, max=90.0)
    init_pos_tol_m: float = setting(0.15, "initialisation: two markers disagreeing by more (plus 3 × odom_sigma_frac × their distance) "
                                    "are a gross error", min=0.001, max=100.0)
    intrinsics: bool = setting(False, "also solve each camera's fx, fy, cx, cy (weakly separable from print scale and mounting: priors below)")
    focal_sigma_px: float = setting(5.0, "prior σ of the recorded fx and fy (px), when intrinsics are solved", min=1e-3, max=1000.0)
    centre_sigma_px: float = setting(5.0, "prior σ of the recorded cx and cy (px), when intrinsics are solved", min=1e-3, max=1000.0)
    min_intrinsics_px: float = setting(1.0, "smallest fx/fy/cx/cy correction that is flagged (px)", min=0.0, max=1000.0)
    loss: str = setting("linear", "least_squares loss (linear: the errors looked for are modelled, not down-weighted)",
                        ("linear", "soft_l1", "huber", "cauchy"))
    f_scale: float = setting(3.0, "robust loss: residual (in σ) where it starts to down-weight", min=0.1, max=100.0)
    max_nfev: int = setting(100, "least_squares: most iterations per solve", min=5, max=100000)

    def __post_init__(self):
        validate(self)


def audit_setting_names() -> set[str]:
    return {f.name for f in fields(AuditSettings)}


@dataclass(frozen=True)
class AuditData:
    """What the audit solves over (arrays; N frames, C cameras, M markers, n observations).

    ``T_odom_agv`` (N, 4, 4) with ``has_odom`` (N,); ``T_init`` (N, 4, 4) a first vehicle pose
    per frame or NaN (the solve stage's, when it solved the frame). Observations: frame, camera
    and marker index and the 4 corners TL, TR, BR, BL in *undistorted* pixels (n, 4, 2).
    ``points_marker_m`` (M, 4, 3) the mapped corners in the mapped marker frame."""

    stamps_ns: np.ndarray
    T_odom_agv: np.ndarray
    has_odom: np.ndarray
    T_init: np.ndarray
    cam_names: tuple[str, ...]
    K: np.ndarray
    T_agv_cam: np.ndarray
    marker_ids: tuple[str, ...]
    T_world_marker: np.ndarray
    points_marker_m: np.ndarray
    obs_frame: np.ndarray
    obs_cam: np.ndarray
    obs_marker: np.ndarray
    obs_px: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.stamps_ns)

    def check(self) -> None:
        """:class:`InputError` (one line) for data the audit cannot use."""
        if len(self.obs_frame) == 0:
            raise InputError("no marker detection to audit: no frame of the recording shows a code that parses and is in the map")
        used = np.unique(self.obs_frame)
        if len(used) < 2:
            raise InputError("only one frame shows a marker: an audit needs a run of frames (at least 2 with detections)")
        for name, arr in (("corners", self.obs_px), ("marker map", self.T_world_marker), ("extrinsic", self.T_agv_cam),
                          ("calibration", self.K), ("marker corners", self.points_marker_m)):
            if not np.all(np.isfinite(arr)):
                raise InputError(f"the {name} hold NaN or infinite values: nothing to audit")
        if np.any(self.has_odom) and not np.all(np.isfinite(self.T_odom_agv[self.has_odom])):
            raise InputError("the odometry holds NaN or infinite values")

    def floor_markers(self) -> np.ndarray:
        """(M,) bool: mapped face up (normal within 1° of +z) on the floor (|z| < 1 cm)."""
        normal_z = self.T_world_marker[:, 2, 2]
        return (normal_z > math.cos(math.radians(1.0))) & (np.abs(self.T_world_marker[:, 2, 3]) < 0.01)

    def frames_per_marker(self) -> np.ndarray:
        counts = np.zeros(len(self.marker_ids), dtype=int)
        for m in range(len(self.marker_ids)):
            counts[m] = len(np.unique(self.obs_frame[self.obs_marker == m]))
        return counts


# -- rotations, vectorised ---------------------------------------------------------------------
def _rzrxry(yaw: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Rz(yaw)·Rx(tx)·Ry(ty) for arrays (M,) → (M, 3, 3) (:func:`agvviz.geometry.euler.matrix_from_hpr`)."""
    cz, sz, cx, sx, cy, sy = np.cos(yaw), np.sin(yaw), np.cos(tx), np.sin(tx), np.cos(ty), np.sin(ty)
    R = np.empty(yaw.shape + (3, 3))
    R[..., 0, 0] = cz * cy - sz * sx * sy
    R[..., 0, 1] = -sz * cx
    R[..., 0, 2] = cz * sy + sz * sx * cy
    R[..., 1, 0] = sz * cy + cz * sx * sy
    R[..., 1, 1] = cz * cx
    R[..., 1, 2] = sz * sy - cz * sx * cy
    R[..., 2, 0] = -cx * sy
    R[..., 2, 1] = sx
    R[..., 2, 2] = cx * cy
    return R


def marker_points_world(data: AuditData, delta: np.ndarray, offsets_m: np.ndarray | None = None) -> np.ndarray:
    """World corners (M, 4, 3) of every marker under corrections ``delta`` (M, 7) and corner
    offsets ``offsets_m`` (M, 4, 2) in the marker's plane (none: 0)."""
    R_d = _rzrxry(delta[:, 3], delta[:, 4], delta[:, 5])
    R = data.T_world_marker[:, :3, :3] @ R_d
    P = data.points_marker_m
    if offsets_m is not None:
        P = P.copy()
        P[..., :2] += offsets_m
    P = P * (1.0 + delta[:, 6])[:, None, None]
    return np.einsum("mij,mkj->mki", R, P) + (data.T_world_marker[:, :3, 3] + delta[:, :3])[:, None, :]


def corrected_marker_pose(T_world_marker: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The corrected ``T_world_marker`` (4, 4) of one marker (scale not included)."""
    T = np.array(T_world_marker, dtype=float)
    T[:3, :3] = T[:3, :3] @ _rzrxry(np.array(delta[3]), np.array(delta[4]), np.array(delta[5]))
    T[:3, 3] = T[:3, 3] + delta[:3]
    return T


def camera_pose(T_agv_cam: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """``T_agv_cam`` corrected by ``eta`` = (ρ, φ) (:mod:`agvviz.evaluation.audit.bundle`)."""
    T = np.array(T_agv_cam, dtype=float)
    T[:3, :3] = so3.exp(eta[3:]) @ T[:3, :3]
    T[:3, 3] = T[:3, 3] + eta[:3]
    return T


def planar(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(xy (…, 2), heading (…,)) of poses (…, 4, 4): heading = atan2(R10, R00), as the
    odometry model measures a step (:func:`agvviz.sim.trajectory.dead_reckoning`)."""
    return T[..., :2, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])


def metres_per_pixel(data: AuditData) -> np.ndarray:
    """(M, 2): each marker's metres per image pixel along its own x and y axes — its mapped side
    over the median image length of its edges along that axis (TL→TR and BL→BR for x, TR→BR
    and TL→BL for y). Per axis because an oblique view foreshortens one axis: there a pixel of
    corner error is many more millimetres of the marker's plane."""
    side_m = quad_axis_lengths(data.points_marker_m[:, :4])  # (M, 2)
    side_px = quad_axis_lengths(data.obs_px)  # (n, 2)
    out = np.zeros((len(data.marker_ids), 2))
    for m in range(len(out)):
        sel = data.obs_marker == m
        if not np.any(sel):
            continue
        median_px = np.median(side_px[sel], axis=0)
        out[m] = np.where(median_px > 1e-9, side_m[m] / np.maximum(median_px, 1e-9), 0.0)
    return out


# -- initialisation ------------------------------------------------------------------------------------
def observation_poses(data: AuditData, solve_pose) -> np.ndarray:
    """``T_world_agv`` (n, 4, 4) each observation says on its own, through the mapped marker
    and the recorded extrinsic (NaN where the solve failed). ``solve_pose(points_marker_m,
    pixels_px, K)`` → ``T_cam_marker`` or None (the run's solver)."""
    out = np.full((len(data.obs_frame), 4, 4), np.nan)
    for k in range(len(data.obs_frame)):
        m, c = data.obs_marker[k], data.obs_cam[k]
        T_cam_marker = solve_pose(data.points_marker_m[m], data.obs_px[k], data.K[c])
        if T_cam_marker is None:
            continue
        # agvviz.replay.solve.agv_pose_from_marker, a marker in the world seen from the AGV:
        out[k] = data.T_world_marker[m] @ se3.inverse(T_cam_marker) @ se3.inverse(data.T_agv_cam[c])
    return out


def _planar_transform(yaw: float, centre: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """World-frame transform rotating by ``yaw`` about ``centre`` (xy) and moving it by
    ``displacement`` (xy): maps the centre to centre + displacement."""
    T = np.eye(4)
    T[:3, :3] = euler.Rz(yaw)
    c = np.array([centre[0], centre[1], 0.0])
    T[:3, 3] = c + np.array([displacement[0], displacement[1], 0.0]) - T[:3, :3] @ c
    return T


def height_pitch_roll(T: np.ndarray) -> np.ndarray:
    """(N, 3): z (m), pitch, roll (rad) of poses (N, 4, 4)."""
    return np.column_stack([T[:, 2, 3], np.arcsin(np.clip(T[:, 2, 1], -1.0, 1.0)), np.arctan2(-T[:, 2, 0], T[:, 2, 2])])


def level_reference(data: AuditData) -> np.ndarray:
    """(N, 3): the height (m), pitch and roll (rad) the floor prior holds each frame to: the
    odometry's where the frame has odometry (its model — :func:`agvviz.sim.trajectory.dead_reckoning`
    — drifts only in distance scale and heading: an AGV's odometry is planar, so this is the floor
    z = 0, level; an AUV's INS/DVL gives its depth and gravity-referenced attitude), else 0."""
    ref = np.zeros((data.n_frames, 3))
    if np.any(data.has_odom):
        ref[data.has_odom] = height_pitch_roll(data.T_odom_agv[data.has_odom])
    return ref


def on_the_floor(T_world_agv: np.ndarray, reference: np.ndarray, tol_m: float = 0.05) -> bool:
    """Whether start poses (N, 4, 4) put the vehicle on the floor — at ``reference`` (N, 3:
    :func:`level_reference`): median |Δz| < ``tol_m`` and median |Δpitch|, |Δroll| < 3° (the
    ``auto`` of the floor prior)."""
    ok = np.isfinite(T_world_agv[:, 0, 0])
    if not np.any(ok):
        return False
    d = height_pitch_roll(T_world_agv[ok]) - reference[ok]
    d[:, 1:] = np.degrees(euler.wrap_angle_rad(d[:, 1:]))
    return bool(np.median(np.abs(d[:, 0])) < tol_m and np.median(np.abs(d[:, 1])) < 3.0 and np.median(np.abs(d[:, 2])) < 3.0)


def _add_candidate(cand: dict, m: int, m2: int, C: np.ndarray, centre: np.ndarray, gap: int) -> None:
    """One measurement of marker m's world correction relative to m2's: C's yaw and the
    displacement it gives m's centre."""
    yaw = math.atan2(C[1, 0], C[0, 0])
    disp = C[:2, :2] @ centre + C[:2, 3] - centre
    cand.setdefault((m, m2), []).append((yaw, disp[0], disp[1], gap))


@dataclass
class Initial:
    """The start of the solve: vehicle poses, marker corrections and what the robust
    initialisation decided (markers found grossly wrong, and how)."""

    T0: np.ndarray
    delta0: np.ndarray
    gross: dict  # marker index -> (yaw_deg, dx_m, dy_m) assigned by the initialisation
    #: (M,) bool: every pairing with a neighbour agrees within :data:`CONSISTENT_M` and
    #: :data:`CONSISTENT_DEG` (a candidate for the first gauge)
    consistent: np.ndarray | None = None


def initialise(data: AuditData, settings: AuditSettings, V: np.ndarray) -> Initial:
    """Robust start (module docstring of :mod:`agvviz.app.audit`): each pair of markers seen close
    in time (odometry over at most ``init_window_frames`` frames, or the same frame) says how
    one is placed relative to the other; markers that disagree grossly (yaw > init_yaw_tol_deg
    or centre > init_pos_tol_m) with most of their neighbours are peeled off one at a time and
    given the placement their consistent neighbours imply — so a code turned 90° starts at 90°,
    not in the local minimum where every frame seeing it is turned instead."""
    s = settings
    M, N = len(data.marker_ids), data.n_frames
    ok = np.all(np.isfinite(V.reshape(len(V), -1)), axis=1)
    centres = data.T_world_marker[:, :2, 3]
    by_frame: dict[int, list[int]] = {}
    for k in np.flatnonzero(ok):
        by_frame.setdefault(int(data.obs_frame[k]), []).append(int(k))
    frames_sorted = sorted(by_frame)
    # candidates per ordered marker pair (m seen in obs a, m2 in obs b): C = (V_b Δ_b→a) V_a⁻¹
    cand: dict[tuple[int, int], list[tuple[float, float, float]]] = {}
    W = s.init_window_frames
    V_inv = {int(k): se3.inverse(V[k]) for k in np.flatnonzero(ok)}
    odom_inv = {i: se3.inverse(data.T_odom_agv[i]) for i in frames_sorted if data.has_odom[i]}
    for gap in range(W + 1):  # nearest pairs first; each marker pair keeps at most 10
        for i in frames_sorted:
            for j in (i - gap, i + gap) if gap else (i,):
                if j not in by_frame or (gap and not (data.has_odom[i] and data.has_odom[j])):
                    continue
                delta_ji = np.eye(4) if gap == 0 else odom_inv[j] @ data.T_odom_agv[i]
                for a in by_frame[i]:
                    for b in by_frame[j]:
                        m, m2 = int(data.obs_marker[a]), int(data.obs_marker[b])
                        if m == m2 or len(cand.get((m, m2), ())) >= 10:
                            continue
                        _add_candidate(cand, m, m2, V[b] @ delta_ji @ V_inv[a], centres[m], gap)
    edges: dict[tuple[int, int], np.ndarray] = {}
    for key, values in cand.items():
        arr = np.array(values)
        # the nearest pairs in time only (least odometry drift), at most 10
        arr = arr[np.argsort(arr[:, 3], kind="stable")[:10]]
        ref = arr[0, 0]
        yaw = ref + float(np.median(euler.wrap_angle_rad(arr[:, 0] - ref)))
        edges[key] = np.array([euler.wrap_angle_rad(yaw), np.median(arr[:, 1]), np.median(arr[:, 2]), len(arr)])
    yaw_tol, pos_tol = math.radians(s.init_yaw_tol_deg), s.init_pos_tol_m

    def inconsistent(e: np.ndarray, m: int, m2: int) -> bool:
        # the odometry linking two markers drifts with the distance between them (3σ of its
        # stated per-metre error): markers 12 m apart under ice are 36 cm less sure of each other
        tol = pos_tol + 3.0 * s.odom_sigma_frac * float(np.linalg.norm(centres[m] - centres[m2]))
        return abs(e[0]) > yaw_tol or math.hypot(e[1], e[2]) > tol

    good = set(range(M))
    while True:
        bad_count = {m: 0 for m in good}
        total = {m: 0 for m in good}
        for (m, m2), e in edges.items():
            if m in good and m2 in good:
                total[m] += 1
                if inconsistent(e, m, m2):
                    bad_count[m] += 1
        worst = max(good, key=lambda m: (bad_count[m], bad_count[m] / max(total[m], 1), -total[m], -m), default=None)
        if worst is None or bad_count[worst] == 0:
            break
        good.discard(worst)
    C_marker = {m: np.eye(4) for m in good}
    pending = [m for m in range(M) if m not in good]
    gross = {}
    progress = True
    while pending and progress:
        progress = False
        for m in list(pending):
            options = [(e[3], m2, e) for (a, m2), e in edges.items() if a == m and m2 in C_marker]
            if not options:
                continue
            _, m2, e = max(options, key=lambda o: (o[0], -o[1]))
            E = _planar_transform(e[0], centres[m], e[1:3])  # m relative to m2
            C_marker[m] = C_marker[m2] @ E
            pending.remove(m)
            progress = True
    for m in pending:
        C_marker[m] = np.eye(4)
    delta0 = np.zeros((M, 7))
    for m in range(M):
        C = C_marker[m]
        if np.allclose(C, np.eye(4)):
            continue
        T_new = C @ data.T_world_marker[m]
        delta0[m, :3] = T_new[:3, 3] - data.T_world_marker[m][:3, 3]
        R_local = data.T_world_marker[m][:3, :3].T @ T_new[:3, :3]
        yaw, tx, ty = euler.hpr_from_matrix(R_local)
        delta0[m, 3:6] = (yaw, tx, ty)
        gross[m] = (math.degrees(yaw), float(delta0[m, 0]), float(delta0[m, 1]))
    # vehicle poses: per frame the largest observation of a marker, corrected
    T0 = np.full((N, 4, 4), np.nan)
    for i, ks in by_frame.items():
        def area(k):
            p = data.obs_px[k]
            return 0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))
        k = max(ks, key=area)
        T0[i] = C_marker[int(data.obs_marker[k])] @ V[k]
    known = np.flatnonzero(np.isfinite(T0[:, 0, 0]))
    if not len(known):
        raise RunError("no observation could be solved on its own: the audit has no start")
    for i in range(N):
        if np.isfinite(T0[i, 0, 0]):
            continue
        j = int(known[np.argmin(np.abs(known - i))])
        if data.has_odom[i] and data.has_odom[j]:
            T0[i] = T0[j] @ se3.inverse(data.T_odom_agv[j]) @ data.T_odom_agv[i]
        else:
            T0[i] = T0[j]
    consistent = np.ones(M, dtype=bool)
    # the height a marker puts the vehicle at, against the others' (a print scale error or a
    # tilt moves it; a camera mounting error moves every marker's alike)
    heights = np.full(M, np.nan)
    for m in range(M):
        z = V[(data.obs_marker == m) & ok, 2, 3]
        if len(z):
            heights[m] = np.median(z)
    if np.any(np.isfinite(heights)):
        consistent &= ~(np.abs(heights - np.nanmedian(heights)) > CONSISTENT_M)
    agree, disagree = np.zeros(M), np.zeros(M)
    for (m, m2), e in edges.items():  # against the markers the start did not find grossly wrong
        if m in gross or m2 in gross:
            continue
        if abs(math.degrees(e[0])) > CONSISTENT_DEG or math.hypot(e[1], e[2]) > CONSISTENT_M:
            disagree[m] += 1
        else:
            agree[m] += 1
    consistent &= disagree <= agree
    return Initial(T0, delta0, gross, consistent)


# -- covariance and flags ----------------------------------------------------------------------
def marginal_covariance(jac, cols: np.ndarray) -> np.ndarray:
    """The block ``(JᵀJ)⁻¹[cols, cols]`` by a sparse LU of JᵀJ and one solve per column."""
    J = sp.csr_matrix(jac)
    H = (J.T @ J).tocsc()
    lu = splu(H)
    n = H.shape[0]
    E = np.zeros((n, len(cols)))
    E[cols, np.arange(len(cols))] = 1.0
    X = lu.solve(E)
    block = X[cols, :]
    return 0.5 * (block + block.T)


def flag_threshold(k_sigma: float, dim: int, tests: int = 1) -> float:
    """Mahalanobis distance of a ``dim``-dimensional group such that a clean marker (or camera)
    whose ``tests`` groups are each tested is flagged with the false-alarm probability of
    |z| > k in one dimension (Šidák: each group at 1 − (1 − p)^(1/tests)); k itself for
    dim = 1, tests = 1. Per marker, not per group: the user judges markers, and a marker with
    four groups tested at k = 3 each would be flagged falsely ≈4× as often as k says."""
    p = 2.0 * (1.0 - norm.cdf(k_sigma))
    p_each = 1.0 - (1.0 - p) ** (1.0 / max(int(tests), 1))
    return float(math.sqrt(chi2.ppf(1.0 - p_each, dim)))


def mahalanobis(values: np.ndarray, cov: np.ndarray) -> float:
    try:
        return float(math.sqrt(max(0.0, values @ np.linalg.solve(cov, values))))
    except np.linalg.LinAlgError:
        return float("nan")
