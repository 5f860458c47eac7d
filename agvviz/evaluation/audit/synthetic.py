"""Corner-level simulation of ``qr_floor`` for audit studies: the scenario's world, track,
odometry, error draws and injections, with the true corners projected through the true camera
plus Gaussian noise in place of rendering and detection (≈1000× faster). Used by the audit's
many-seed tests and its benchmark; a rendered recording goes through :func:`agvviz.app.audit.audit_recording`.

Pure (numpy): no files, no Rerun, no printing.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from agvviz.evaluation.audit.problem import AuditData
from agvviz.geometry import euler, se3, so3
from agvviz.geometry.plane import quad_axis_lengths
from agvviz.sim import inject as inj
from agvviz.sim import realism as rl
from agvviz.sim.trajectory import dead_reckoning, forward_camera_mount, sample_track

#: Smallest code side in the image (px) that counts as detected.
MIN_SIDE_PX = 20.0
#: Corners must lie this far inside the image (px).
BORDER_PX = 4.0


@dataclass
class Synthetic:
    """Simulated audit input and the exact truth: per marker id the true δ (7,
    :data:`agvviz.evaluation.audit.problem.MARKER_PARAMS`), per camera the true correction (ρ, φ)."""

    data: AuditData
    marker_truth: dict
    camera_truth: dict
    T_world_agv_truth: np.ndarray


def marker_truth(draw) -> np.ndarray:
    """The exact δ of a :class:`agvviz.sim.realism.MarkerDraw` (or its JSON) in the audit's
    parameters: position, (yaw, tilt_x, tilt_y) of ``R_mapᵀ·R_true``, scale."""
    if isinstance(draw, dict):
        T_map = np.asarray(draw["mapped"]["T_parent_marker"], dtype=float)
        T_true = np.asarray(draw["true"]["T_parent_marker"], dtype=float)
        side_map, side_true = draw["mapped"]["side_m"], draw["true"]["side_m"]
    else:
        T_map, T_true = draw.T_parent_marker_mapped, draw.T_parent_marker_true
        side_map, side_true = draw.side_mapped_m, draw.side_true_m
    yaw, tx, ty = euler.hpr_from_matrix(T_map[:3, :3].T @ T_true[:3, :3])
    d = T_true[:3, 3] - T_map[:3, 3]
    return np.array([d[0], d[1], d[2], yaw, tx, ty, side_true / side_map - 1.0])


def camera_truth(draw) -> np.ndarray:
    """The exact correction (ρ, φ) from a camera draw's recorded to its true extrinsic:
    ``R_true = Exp(φ)·R_recorded``, ``t_true = t_recorded + ρ``."""
    if isinstance(draw, dict):
        T_true = np.asarray(draw["true"]["T_parent_cam"], dtype=float)
        T_rec = np.asarray(draw["recorded"]["T_parent_cam"], dtype=float)
    else:
        T_true, T_rec = draw.T_parent_cam_true, draw.T_parent_cam_recorded
    return np.concatenate([T_true[:3, 3] - T_rec[:3, 3], so3.log(T_true[:3, :3] @ T_rec[:3, :3].T)])


@dataclass(frozen=True)
class _Code:
    """What the audit needs of a :class:`agvviz.sim.render.FloorCode` (no payload, no symbol)."""

    marker_id: str
    T_world_marker: np.ndarray
    side_m: float
    points_marker_m: np.ndarray


@dataclass(frozen=True)
class _Scene:
    codes: tuple


def scene_geometry(options, rng: np.random.Generator) -> _Scene:
    """The codes' ids and mapped poses of :func:`agvviz.scenarios.qr_floor.build_scene` with the same
    draws from ``rng`` (one integer per code, then three uniforms), without encoding a payload
    or a symbol (≈15 ms per code there). ``tests/test_audit.py`` checks it against build_scene."""
    from agvviz.scenarios import qr_floor as q
    from agvviz.geometry.plane import square_points_marker

    o = options
    track = q.make_track(o)
    half_x = o.track_length_m / 2.0 + o.turn_radius_m + q.GRID_MARGIN_M
    half_y = o.track_width_m / 2.0 + o.turn_radius_m + q.GRID_MARGIN_M
    spacing_mm = round(o.grid_spacing_m * 1e4) / 10.0
    nx, ny = int(half_x // o.grid_spacing_m), int(half_y // o.grid_spacing_m)
    centers = [(track.center_xy_m[0] + i * spacing_mm / 1000.0, track.center_xy_m[1] + j * spacing_mm / 1000.0)
               for j in range(-ny, ny + 1) for i in range(-nx, nx + 1)]
    turns = rng.integers(0, 4, size=len(centers))
    rng.uniform([110.0, 20.0, 210.0], [140.0, 30.0, 230.0])  # the grey levels: keeps the stream in step
    points = square_points_marker(o.code_size_m, o.with_midpoints)
    codes = tuple(
        _Code(f"Q{k:03d}", se3.make(euler.Rz(int(t) * np.pi / 2.0), [c[0], c[1], 0.0]), float(o.code_size_m), points)
        for k, (c, t) in enumerate(zip(centers, turns))
    )
    return _Scene(codes)


def simulate(options, seed: int, sigma_px: float = 0.1, corner_bias_px: float = 0.0) -> Synthetic:
    """Simulate ``qr_floor`` with ``options`` (:class:`agvviz.scenarios.qr_floor.Options`, its
    ``realism`` and ``inject`` included) and ``seed``: corners with σ = ``sigma_px`` noise,
    independent per detection, plus (``corner_bias_px`` > 0) each marker's systematic corner
    error — one offset per corner in the marker's plane, shared by all its detections, with σ
    ``corner_bias_px`` at the marker's median size in the image along each of its axes (the audit's random effect,
    :mod:`agvviz.evaluation.audit.problem`; measured on real photos by ``bench/bench_render_vs_photos.py``)."""
    from agvviz.scenarios import qr_floor as q

    q.validate(options)
    o = options
    realism = rl.make_realism(o.realism, o.realism_off, o.realism_set)
    rng = np.random.default_rng(seed)
    scene = scene_geometry(o, rng)
    camera = q.make_camera(o)
    T_agv_cam = forward_camera_mount(o.cam_height_m, o.cam_lookahead_m)
    trajectory = sample_track(q.make_track(o), o.speed_mps, o.rate_hz, o.duration_s)
    n = len(trajectory.log_time_ns)
    slip = rl.draw_slip(realism.slip, rl.source_rng(seed, "slip"), n - 1)
    T_odom = dead_reckoning(
        trajectory, rng, scale_error=o.odom_scale_error,
        heading_bias_rad_per_s=math.radians(o.odom_heading_bias_deg_per_s),
        step_noise_m=o.odom_step_noise_m, heading_noise_rad=math.radians(o.odom_heading_noise_deg), slip_fraction=slip,
    )
    calib = rl.draw_calibration(realism.calibration, rl.source_rng(seed, "calibration"), {q.CAM_NAME: (camera, T_agv_cam)})
    draws = rl.draw_map(realism.map, rl.source_rng(seed, "map"), [(c.marker_id, c.T_world_marker, c.side_m) for c in scene.codes])
    spec = inj.parse_inject(o.inject)
    inj.check_targets(spec, [c.marker_id for c in scene.codes], [q.CAM_NAME])
    draws = [inj.apply_to_marker(d, spec.markers().get(d.marker_id)) for d in draws]
    calib = {k: inj.apply_to_camera(d, spec.cameras().get(k)) for k, d in calib.items()}
    bumps = rl.draw_bumps(realism.bumps, rl.source_rng(seed, "bumps"))
    true_codes = [rl.placed_as_drawn(c, d) for c, d in zip(scene.codes, draws)]
    cam_draw = calib[q.CAM_NAME]
    T_true = np.stack([bumps.apply(T)[0] for T in trajectory.T_world_agv])
    noise_rng = np.random.default_rng([int(seed) % 2**64, 7])
    obs_frame, obs_marker, obs_px = [], [], []
    K = cam_draw.recorded_camera.K  # ideal pixels of the recorded calibration (undistorted)
    K_true = cam_draw.true_camera.K
    centres_world = np.array([c.T_world_marker[:3, 3] for c in true_codes])
    def in_camera(T_cam_world, code, points_marker):
        return se3.transform_points(T_cam_world, se3.transform_points(code.T_world_marker, points_marker))

    def pixels(points_cam):
        return (K_true @ (points_cam / points_cam[:, 2:3]).T).T[:, :2]

    seen_at = []  # (frame, marker, T_cam_world, true pixels) of every detection
    for i in range(n):
        T_cam_world = se3.inverse(T_true[i] @ cam_draw.T_parent_cam_true)
        centres_cam = centres_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        near = (centres_cam[:, 2] > 0.2) & (centres_cam[:, 2] < 20.0)
        near &= np.all(np.abs(centres_cam[:, :2]) < centres_cam[:, 2:3] * 2.0, axis=1)
        for m in np.flatnonzero(near):
            code = true_codes[m]
            pts = in_camera(T_cam_world, code, code.points_marker_m[:4])
            if np.any(pts[:, 2] < 0.1):
                continue
            px = pixels(pts)
            if np.any(px < BORDER_PX) or np.any(px[:, 0] > o.width_px - 1 - BORDER_PX) or np.any(px[:, 1] > o.height_px - 1 - BORDER_PX):
                continue
            if np.min(np.linalg.norm(px - np.roll(px, 1, axis=0), axis=1)) < MIN_SIDE_PX:
                continue
            seen_at.append((i, m, T_cam_world, px))
    offsets_m = np.zeros((len(true_codes), 4, 2))
    if corner_bias_px > 0 and seen_at:
        side_px = {}  # the image length of each detection's edges along the marker's x and y
        for _, m, _, px in seen_at:
            side_px.setdefault(m, []).append(quad_axis_lengths(px))
        bias_rng = np.random.default_rng([int(seed) % 2**64, 11])
        for m in sorted(side_px):
            metres_per_px = true_codes[m].side_m / np.median(np.array(side_px[m]), axis=0)  # (2,): x, y
            offsets_m[m] = corner_bias_px * metres_per_px * bias_rng.standard_normal((4, 2))
    for i, m, T_cam_world, px in seen_at:
        if corner_bias_px > 0:
            code = true_codes[m]
            points = code.points_marker_m[:4].copy()
            points[:, :2] += offsets_m[m]  # in the true marker's plane
            px = pixels(in_camera(T_cam_world, code, points))
        obs_frame.append(i)
        obs_marker.append(m)
        obs_px.append(px + sigma_px * noise_rng.standard_normal((4, 2)))
    seen = sorted(set(obs_marker))
    remap = {m: k for k, m in enumerate(seen)}
    data = AuditData(
        stamps_ns=np.asarray(trajectory.log_time_ns, dtype=np.int64),
        T_odom_agv=T_odom, has_odom=np.ones(n, dtype=bool), T_init=np.full((n, 4, 4), np.nan),
        cam_names=(q.CAM_NAME,), K=K[None].copy(), T_agv_cam=cam_draw.T_parent_cam_recorded[None].copy(),
        marker_ids=tuple(scene.codes[m].marker_id for m in seen),
        T_world_marker=np.stack([scene.codes[m].T_world_marker for m in seen]),
        points_marker_m=np.stack([scene.codes[m].points_marker_m[:4] for m in seen]),
        obs_frame=np.asarray(obs_frame, dtype=int), obs_cam=np.zeros(len(obs_frame), dtype=int),
        obs_marker=np.asarray([remap[m] for m in obs_marker], dtype=int),
        obs_px=np.asarray(obs_px, dtype=float).reshape(-1, 4, 2),
    )
    truth = {scene.codes[m].marker_id: marker_truth(draws[m]) for m in seen}
    return Synthetic(data, truth, {q.CAM_NAME: camera_truth(cam_draw)}, T_true)


def solver(name: str = "ippe"):
    """``solve_pose`` for :func:`agvviz.evaluation.audit.estimate.estimate` from an agvviz solver."""
    from agvviz.solvers import SolverOptions, solve

    options = SolverOptions()

    def solve_pose(points_marker_m, pixels_px, K):
        result = solve(name, np.asarray(points_marker_m, float), np.asarray(pixels_px, float), np.asarray(K, float), options)
        return result.T_cam_marker if result.success else None

    return solve_pose


def with_options(options, **changes):
    return dataclasses.replace(options, **changes)
