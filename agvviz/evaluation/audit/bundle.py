"""The audit's bundle adjustment: every frame's vehicle pose, each camera's extrinsic correction
and each marker's placement correction from every detected corner, the odometry and priors.

Pure math (numpy, scipy): no files, no Rerun, no printing.

Unknowns (the vector ``x`` of :class:`Layout`)
----------------------------------------------
* per frame i: ``ξ_i = (ρ, φ)`` (6): ``T_world_agv,i = [Exp(φ)·R_i⁰, t_i⁰ + ρ]`` — the left
  perturbation about the vehicle's own position (world axes), which keeps the rotation and
  translation columns apart (a left perturbation about the world origin couples them through
  the lever arm of every position and slows the solve);
* per marker m: its placement correction in the model of :mod:`agvviz.sim.realism` (source
  ``map``) — ``δ = (dx, dy, dz, yaw, tilt_x, tilt_y, scale)``: a point P of the mapped marker
  frame lies at ``p_map + (dx, dy, dz) + R_map·Rz(yaw)·Rx(tilt_x)·Ry(tilt_y)·(1 + scale)·P``.
  A *floor code* (mapped face up, on z = 0) solves all but dz (it lies on the floor; its tilt,
  a code not flat, is solved: left out it biases the others under ``harsh``); any other marker
  all seven;
* optionally (``intrinsics=true``) per camera (dfx, dfy, dcx, dcy) px on the recorded K — weakly
  separable: a focal length error looks like a camera height or a print scale error;
* per camera c: ``(ρ_c, φ_c)``, ``T_agv_cam = [Exp(φ_c)·R_recorded, t_recorded + ρ_c]``
  (rotation left-perturbed in the AGV frame, as the ``calibration`` source draws it);
* with odometry: its distance scale error ``s`` and heading-rate bias ``b`` (rad/s), the model
  of :func:`agvviz.sim.trajectory.dead_reckoning`;
* per marker m (``corner_bias_px`` > 0): a systematic offset of each of its 4 corners in its
  own plane (m; 8 numbers), shared by every detection of that marker — a corner printed or
  detected slightly off on that code (real corners carry ≈0.3 px of it: issue 14's real-photo
  residual). A random effect with prior σ ``corner_bias_px`` × the marker's metres per pixel:
  independent corner noise averages down over frames, this does not, and the offsets' common,
  turning and expanding modes are exactly a position, yaw and scale correction — so a
  marker's σ includes what no number of frames can separate from a wrong print.

Residuals (each divided by its σ)
---------------------------------
* every detected corner (undistorted pixels) against the projection through K;
* odometry between consecutive frames: body-frame step ``(1 + s)·Δxy`` and heading step
  ``Δψ + b·Δt`` against the measured ones (σ = hypot(odom_sigma_m, odom_sigma_frac·|Δ|) and
  odom_sigma_deg per step, ×√steps over dropped frames);
* the vehicle's level: each frame's height, pitch and roll against the odometry's
  (:func:`~agvviz.evaluation.audit.problem.level_reference`: 0 for an AGV on the floor z = 0, an AUV's depth and attitude;
  σ floor_sigma_m, floor_tilt_sigma_deg) — what separates the camera's mounting from the
  vehicle's attitude;
* priors: the map (each δ component against 0), the recorded extrinsic, the odometry error,
  the corner offsets.

Gauge: corners, odometry and the floor are unchanged when the whole map and every vehicle pose
move together in the floor plane (x, y, yaw): the data cannot see the map's overall frame; and
they see the map's overall size only through the odometry's scale, itself unknown; markers
off the floor can all rise with the cameras' mounting unseen too. Four constraint rows, five
when the gauge markers solve their height (σ :data:`GAUGE_SIGMA`, :meth:`Problem.gauge_matrix`),
fix them: the mean x, y, yaw, radial (and height) correction of the *gauge markers* (seen
enough, not flagged; the caller re-solves when a flag changes the set) are zero. Every marker's correction and σ is relative to them; the
map's overall place, heading and scale are taken as recorded.

Solved by :func:`scipy.optimize.least_squares` (``method="trf"``) with finite differences on
the sparse Jacobian pattern (``jac_sparsity``): columns that share no residual row are perturbed
together, so a Jacobian costs a few dozen residual evaluations however long the run.
"""


from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from agvviz.evaluation.audit.problem import (
    ALL_SLOTS,
    FLOOR_SLOTS,
    AuditData,
    AuditSettings,
    camera_pose,
    height_pitch_roll,
    level_reference,
    marker_points_world,
    metres_per_pixel,
    planar,
)
from agvviz.geometry import euler, se3
#: σ of the gauge constraints (mean x, y (m), yaw (rad), radial (m) correction of the gauge
#: markers = 0): tight enough to be a constraint, loose enough to keep JᵀJ well conditioned.
GAUGE_SIGMA = 1e-5


# -- layout --------------------------------------------------------------------------------------
@dataclass
class Layout:
    """Where each unknown lives in ``x``."""

    n_frames: int
    marker_slots: list[tuple[int, ...]]
    n_cameras: int
    with_odometry: bool
    with_intrinsics: bool = False
    with_offsets: bool = False
    frame0: int = 0
    marker_cols: list[np.ndarray] = field(default_factory=list)
    camera0: int = 0
    odom0: int = 0
    intr0: int = 0
    offsets0: int = 0
    size: int = 0

    def __post_init__(self):
        col = 6 * self.n_frames
        self.marker_cols = []
        for slots in self.marker_slots:
            self.marker_cols.append(np.arange(col, col + len(slots)))
            col += len(slots)
        self.camera0 = col
        col += 6 * self.n_cameras
        self.odom0 = col
        col += 2 if self.with_odometry else 0
        self.intr0 = col
        col += 4 * self.n_cameras if self.with_intrinsics else 0
        self.offsets0 = col  # last: the covariance blocks the report reads end before it
        col += 8 * len(self.marker_slots) if self.with_offsets else 0
        self.size = col

    def frame_cols(self, i: int) -> np.ndarray:
        return np.arange(6 * i, 6 * i + 6)

    def camera_cols(self, c: int) -> np.ndarray:
        return np.arange(self.camera0 + 6 * c, self.camera0 + 6 * c + 6)

    def intrinsics_cols(self, c: int) -> np.ndarray:
        if not self.with_intrinsics:
            return np.zeros(0, dtype=int)
        return np.arange(self.intr0 + 4 * c, self.intr0 + 4 * c + 4)

    def intrinsics(self, x: np.ndarray) -> np.ndarray:
        """(C, 4): the corrections (dfx, dfy, dcx, dcy) in px (zeros when not solved)."""
        if not self.with_intrinsics:
            return np.zeros((self.n_cameras, 4))
        return x[self.intr0: self.intr0 + 4 * self.n_cameras].reshape(self.n_cameras, 4)

    def offset_cols(self, m: int) -> np.ndarray:
        """Marker m's 8 corner-offset columns (TL x, y, TR x, y, …), or none."""
        if not self.with_offsets:
            return np.zeros(0, dtype=int)
        return np.arange(self.offsets0 + 8 * m, self.offsets0 + 8 * m + 8)

    def offsets(self, x: np.ndarray) -> np.ndarray | None:
        """(M, 4, 2) corner offsets in each marker's plane (m), or None when not solved."""
        if not self.with_offsets:
            return None
        return x[self.offsets0: self.offsets0 + 8 * len(self.marker_slots)].reshape(-1, 4, 2)

    def odom_cols(self) -> np.ndarray:
        return np.arange(self.odom0, self.odom0 + (2 if self.with_odometry else 0))

    def unpack(self, x: np.ndarray):
        xi = x[: 6 * self.n_frames].reshape(self.n_frames, 6)
        if not hasattr(self, "_flat"):
            self._flat = np.concatenate([m * 7 + np.asarray(sl, dtype=int) for m, sl in enumerate(self.marker_slots)]
                                        + [np.zeros(0, dtype=int)])
        delta = np.zeros(7 * len(self.marker_slots))
        delta[self._flat] = x[6 * self.n_frames: self.camera0]
        delta = delta.reshape(-1, 7)
        eta = x[self.camera0: self.camera0 + 6 * self.n_cameras].reshape(self.n_cameras, 6)
        odom = x[self.odom0: self.odom0 + 2] if self.with_odometry else np.zeros(2)
        return xi, delta, eta, odom

    def pack_delta(self, x: np.ndarray, delta: np.ndarray) -> None:
        for m, (slots, cols) in enumerate(zip(self.marker_slots, self.marker_cols)):
            x[cols] = delta[m, list(slots)]


# -- the problem ------------------------------------------------------------------------------------
class Problem:
    """Residuals, Jacobian pattern and priors of one audit (module docstring)."""

    def __init__(self, data: AuditData, settings: AuditSettings, T0: np.ndarray, sigma_px: float,
                 gauge: np.ndarray | None = None, floor_prior: bool = True, corner_bias_px: float = 0.0):
        self.floor_prior = bool(floor_prior)
        self.level_ref = level_reference(data)  # what the floor prior holds each frame's height, pitch, roll to
        self.corner_bias_px = float(corner_bias_px)
        self.data, self.settings, self.T0 = data, settings, np.asarray(T0, dtype=float)
        self.T_ref0 = self.T0 @ data.T_agv_cam[0]  # x = 0: the recorded extrinsic
        self.sigma_px = float(sigma_px)
        M = len(data.marker_ids)
        self.gauge = np.ones(M, dtype=bool) if gauge is None else np.asarray(gauge, dtype=bool)
        centres = data.T_world_marker[:, :2, 3]
        self.gauge_centre = centres[self.gauge].mean(axis=0) if np.any(self.gauge) else np.zeros(2)
        floor = data.floor_markers()
        self.floor = floor
        slots = [FLOOR_SLOTS if f else ALL_SLOTS for f in floor]
        # Odometry pairs: consecutive frames that both carry odometry.
        pairs = [i for i in range(data.n_frames - 1) if data.has_odom[i] and data.has_odom[i + 1]]
        self.odom_pairs = np.array(pairs, dtype=int)
        self.layout = Layout(data.n_frames, slots, len(data.cam_names), len(pairs) > 0, bool(settings.intrinsics),
                             self.corner_bias_px > 0)
        #: (M, 2) prior σ of each marker's corner offsets along its x and y (m): corner_bias_px at
        #: the median pixel scale its detections show each axis at
        self.offset_sigma_m = np.maximum(self.corner_bias_px * metres_per_pixel(data), 1e-9)
        s = settings
        prior = np.array([s.map_sigma_m] * 3 + [math.radians(s.map_yaw_sigma_deg)]
                         + [math.radians(s.map_tilt_sigma_deg)] * 2 + [s.map_scale_sigma])
        self.marker_prior_sigma = prior
        self.camera_prior_sigma = np.array([s.extrinsic_sigma_m] * 3 + [math.radians(s.extrinsic_sigma_deg)] * 3)
        self.odom_prior_sigma = np.array([s.odom_scale_sigma, math.radians(s.odom_bias_sigma_deg_per_s)])
        self.intrinsics_prior_sigma = np.array([s.focal_sigma_px, s.focal_sigma_px, s.centre_sigma_px, s.centre_sigma_px])
        if len(pairs):
            i = self.odom_pairs
            step = np.einsum("nji,njk->nik", data.T_odom_agv[i][:, :3, :3], data.T_odom_agv[i + 1][:, :3, :3])
            dt_world = data.T_odom_agv[i + 1][:, :3, 3] - data.T_odom_agv[i][:, :3, 3]
            d_body = np.einsum("nji,nj->ni", data.T_odom_agv[i][:, :3, :3], dt_world)
            self.odom_dxy = d_body[:, :2]
            self.odom_dpsi = np.arctan2(step[:, 1, 0], step[:, 0, 0])
            self.odom_dt_s = (data.stamps_ns[i + 1] - data.stamps_ns[i]) * 1e-9
            period = float(np.median(self.odom_dt_s)) if len(self.odom_dt_s) else 1.0
            steps = np.maximum(1.0, np.round(self.odom_dt_s / period)) if period > 0 else np.ones(len(pairs))
            self.odom_sigma_xy = np.hypot(s.odom_sigma_m * np.sqrt(steps), s.odom_sigma_frac * np.linalg.norm(self.odom_dxy, axis=1))
            self.odom_sigma_psi = math.radians(s.odom_sigma_deg) * np.sqrt(steps)
        self._build_pattern()

    # residual blocks, in this order: corners (8 per obs), odometry (3 per pair), floor (3 per
    # frame), marker prior (per active slot), camera prior (6 each), odometry prior (2)
    def _build_pattern(self) -> None:
        d, L = self.data, self.layout
        rows, cols = [], []
        r = 0
        self.row_corners = r
        for k in range(len(d.obs_frame)):
            cams = [L.camera_cols(0), L.camera_cols(d.obs_cam[k])] if d.obs_cam[k] != 0 else []
            c = np.concatenate([L.frame_cols(d.obs_frame[k]), L.marker_cols[d.obs_marker[k]], *cams,
                                L.intrinsics_cols(d.obs_cam[k])])
            rr = np.arange(r, r + 8)
            rows.append(np.repeat(rr, len(c)))
            cols.append(np.tile(c, 8))
            if L.with_offsets:  # corner j's u, v rows see only that corner's two offsets
                oc = L.offset_cols(d.obs_marker[k])
                rows.append(np.repeat(rr, 2))
                cols.append(oc[np.repeat(np.arange(4), 2)[:, None] * 2 + np.arange(2)].reshape(-1))
            r += 8
        self.row_odom = r
        for i in self.odom_pairs:
            c = np.concatenate([L.frame_cols(i), L.frame_cols(i + 1), L.odom_cols(), L.camera_cols(0)])
            rows.append(np.repeat(np.arange(r, r + 3), len(c)))
            cols.append(np.tile(c, 3))
            r += 3
        self.row_floor = r
        if self.floor_prior:
            for i in range(d.n_frames):
                c = np.concatenate([L.frame_cols(i), L.camera_cols(0)])
                rows.append(np.repeat(np.arange(r, r + 3), len(c)))
                cols.append(np.tile(c, 3))
                r += 3
        # the gauge: 4 rows over the gauge markers' x, y, yaw (and tilt) columns
        self.row_gauge = r
        Ct = self.gauge_matrix()
        gr, gc = np.nonzero(Ct)
        rows.append(r + gr)
        cols.append(6 * L.n_frames + gc)
        r += Ct.shape[0]
        self.row_prior = r
        n_prior = L.size - 6 * L.n_frames
        rows.append(np.arange(r, r + n_prior))
        cols.append(np.arange(6 * L.n_frames, L.size))
        r += n_prior
        self.n_rows = r
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        self.pattern = sp.csr_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(r, L.size))
        # prior σ of each non-frame column, in column order
        sig = []
        for m, slots in enumerate(L.marker_slots):
            sig.extend(self.marker_prior_sigma[list(slots)])
        sig.extend(np.tile(self.camera_prior_sigma, L.n_cameras))
        if L.with_odometry:
            sig.extend(self.odom_prior_sigma)
        if L.with_intrinsics:
            sig.extend(np.tile(self.intrinsics_prior_sigma, L.n_cameras))
        if L.with_offsets:
            sig.extend(np.tile(self.offset_sigma_m, (1, 4)).reshape(-1))  # per marker: x, y of TL, TR, BR, BL
        self.prior_sigma = np.array(sig)

    def gauge_matrix(self) -> np.ndarray:
        """(4 or 5, marker columns): the mean x, y, yaw and radial correction of the gauge markers
        (yaw: the rotation about the world z axis, through :func:`gauge_directions`; radial:
        ``(p − c)·d`` over the RMS distance from their centre c) and, when they solve dz (off the
        floor), their mean dz."""
        if hasattr(self, "_gauge_Ct"):
            return self._gauge_Ct
        d, L = self.data, self.layout
        A = gauge_directions(d, self.gauge_centre)
        n_cols = L.camera0 - 6 * L.n_frames
        # markers off the floor (dz solved): moving every marker and the cameras' mounting up together leaves the
        # corners, odometry and vehicle height unchanged — a 5th row, their mean dz = 0, fixes that too
        with_dz = any(self.gauge[m] and 2 in slots for m, slots in enumerate(L.marker_slots))
        Ct = np.zeros((5 if with_dz else 4, n_cols))
        n = max(int(self.gauge.sum()), 1)
        rel = d.T_world_marker[:, :2, 3] - self.gauge_centre
        spread = float(np.sqrt(np.mean(np.sum(rel[self.gauge] ** 2, axis=1)))) if np.any(self.gauge) else 1.0
        spread = max(spread, 1e-3)
        for m, (slots, cols) in enumerate(zip(L.marker_slots, L.marker_cols)):
            if not self.gauge[m]:
                continue
            for slot, col in zip(slots, cols - 6 * L.n_frames):
                if slot in (0, 1):
                    Ct[slot, col] = 1.0 / n
                    Ct[3, col] = rel[m, slot] / (n * spread)
                elif slot in (3, 4, 5):
                    Ct[2, col] = A[m, slot, 2] / n  # the world-yaw component of the rotation
                elif slot == 2:
                    Ct[4, col] = 1.0 / n
        self._gauge_Ct = Ct
        return Ct

    def ref_poses(self, xi: np.ndarray) -> np.ndarray:
        """``T_world_cam0`` (N, 4, 4): each frame's unknown is the pose of the first camera, so
        that its corners do not depend on its extrinsic (the extrinsic then only moves the
        vehicle, seen by odometry and floor): otherwise every extrinsic column couples to every
        frame and the weak extrinsic directions make the solve ill-conditioned (κ ≈ 2500)."""
        E = se3.exp_batch(np.column_stack([np.zeros((len(xi), 3)), xi[:, 3:]]))
        T = E @ self.T_ref0
        T[:, :3, 3] = self.T_ref0[:, :3, 3] + xi[:, :3]
        return T

    def poses(self, xi: np.ndarray, eta: np.ndarray) -> np.ndarray:
        """``T_world_agv`` (N, 4, 4) of frame unknowns ``xi`` and camera corrections ``eta``."""
        return self.ref_poses(xi) @ se3.inverse(camera_pose(self.data.T_agv_cam[0], eta[0]))

    def corner_residuals(self, x: np.ndarray) -> np.ndarray:
        """(n, 4, 2) corner residuals in pixels (not divided by σ)."""
        d, L = self.data, self.layout
        xi, delta, eta, _ = L.unpack(x)
        T_ref = self.ref_poses(xi)
        T_cam = np.stack([camera_pose(d.T_agv_cam[c], eta[c]) for c in range(L.n_cameras)])
        T_ref_cam = se3.inverse(T_cam[0]) @ T_cam  # (C, 4, 4): camera c in camera 0's frame
        T_ref_cam[0] = np.eye(4)
        T_wc = T_ref[d.obs_frame] @ T_ref_cam[d.obs_cam]
        P = marker_points_world(d, delta, L.offsets(x))[d.obs_marker]  # (n, 4, 3)
        R, t = T_wc[:, :3, :3], T_wc[:, :3, 3]
        pc = np.einsum("nji,nkj->nki", R, P - t[:, None, :])
        z = pc[..., 2]
        z = np.where(np.abs(z) < 1e-6, 1e-6, z)
        K = d.K[d.obs_cam]
        if L.with_intrinsics:
            kappa = L.intrinsics(x)[d.obs_cam]  # (n, 4): dfx, dfy, dcx, dcy
            K = K.copy()
            K[:, 0, 0] += kappa[:, 0]
            K[:, 1, 1] += kappa[:, 1]
            K[:, 0, 2] += kappa[:, 2]
            K[:, 1, 2] += kappa[:, 3]
        u = K[:, 0, 0, None] * pc[..., 0] / z + K[:, 0, 1, None] * pc[..., 1] / z + K[:, 0, 2, None]
        v = K[:, 1, 1, None] * pc[..., 1] / z + K[:, 1, 2, None]
        return np.stack([u, v], axis=-1) - d.obs_px

    def odometry_residuals(self, x: np.ndarray) -> np.ndarray:
        """(pairs, 3): measured − predicted body-frame step (x, y in m; heading in rad)."""
        if not len(self.odom_pairs):
            return np.zeros((0, 3))
        xi, _, eta, odom = self.layout.unpack(x)
        T = self.poses(xi, eta)
        i = self.odom_pairs
        step = se3.inverse_batch(T[i]) @ T[i + 1]
        xy, psi = planar(step)
        r_xy = self.odom_dxy - (1.0 + odom[0]) * xy
        r_psi = euler.wrap_angle_rad(self.odom_dpsi - psi - odom[1] * self.odom_dt_s)
        return np.column_stack([r_xy, r_psi])

    def floor_residuals(self, x: np.ndarray) -> np.ndarray:
        """(N, 3): height (m), pitch, roll (rad) of every frame's vehicle pose against
        :func:`level_reference` (0 on a floor; an INS/DVL's depth and attitude otherwise)."""
        xi, _, eta, _ = self.layout.unpack(x)
        T = self.poses(xi, eta)
        r = height_pitch_roll(T) - self.level_ref
        r[:, 1:] = euler.wrap_angle_rad(r[:, 1:])
        return r

    def residuals(self, x: np.ndarray) -> np.ndarray:
        s = self.settings
        parts = [self.corner_residuals(x).reshape(-1) / self.sigma_px]
        if len(self.odom_pairs):
            o = self.odometry_residuals(x)
            parts.append((o / np.column_stack([self.odom_sigma_xy, self.odom_sigma_xy,
                                               np.broadcast_to(self.odom_sigma_psi, len(o))])).reshape(-1))
        if self.floor_prior:
            f = self.floor_residuals(x)
            parts.append((f / [s.floor_sigma_m, math.radians(s.floor_tilt_sigma_deg), math.radians(s.floor_tilt_sigma_deg)]).reshape(-1))
        parts.append(self._gauge_Ct @ x[6 * self.layout.n_frames: self.layout.camera0] / GAUGE_SIGMA)
        parts.append(x[6 * self.layout.n_frames:] / self.prior_sigma)
        return np.concatenate(parts)

    def solve(self, x0: np.ndarray, rough: bool = False):
        """``least_squares`` from ``x0``; ``rough``: looser tolerances (a first pass whose
        residuals only set the corner σ)."""
        s = self.settings
        tol = 1e-6 if rough else 1e-8
        lsmr_tol = 1e-8 if rough else 1e-9
        return least_squares(
            self.residuals, x0, jac_sparsity=self.pattern, method="trf",
            # x_scale="jac": the unknowns mix metres, radians and fractions whose Jacobian
            # columns differ by orders of magnitude; scaling by the column norms evens them out
            # (3× faster here than unit scaling, and the same minimum)
            x_scale="jac", loss=s.loss, f_scale=s.f_scale, max_nfev=s.max_nfev, ftol=tol, xtol=tol,
            # LSMR solved to 1e-10 per step: with its default tolerances the trust-region steps
            # are too inexact and the solve crawls (>300 iterations instead of ~8)
            tr_solver="lsmr", tr_options={"atol": lsmr_tol, "btol": lsmr_tol, "maxiter": 20 * self.layout.size},
        )


def gauge_directions(data: AuditData, centre_xy: np.ndarray) -> np.ndarray:
    """(M, 7, 4): how each marker's δ changes when the whole map moves by (gx, gy, gyaw) in
    the floor plane and dilates by ε, the yaw and the dilation about ``centre_xy`` (linearised)."""
    M = len(data.marker_ids)
    A = np.zeros((M, 7, 4))
    A[:, 0, 0] = 1.0
    A[:, 1, 1] = 1.0
    p = data.T_world_marker[:, :2, 3] - centre_xy
    A[:, 0, 2] = -p[:, 1]
    A[:, 1, 2] = p[:, 0]
    # a world yaw is the rotation vector (0, 0, g) in the world: R_mapᵀ·e_z in the marker frame
    A[:, 3:6, 2] = data.T_world_marker[:, 2, :3][:, [2, 0, 1]]
    A[:, 0, 3] = p[:, 0]
    A[:, 1, 3] = p[:, 1]
    return A
