"""AGV motion for the simulator: a rounded-rectangle track, dead-reckoning odometry and the
forward-looking camera mount. Numpy only; randomness comes from the caller's ``rng``.

Frames and heading follow :mod:`agvviz.conventions`: the AGV's y axis points along the
direction of travel, heading ψ = 0 means travel along world +y, positive ψ turns
counter-clockwise seen from above; ``T_world_agv = [Rz(ψ), (x, y, 0)]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.geometry import euler, se3

#: Recording clock origin of simulated scenarios (2023-11-14T22:13:20Z), so that times look
#: like real log times in viewers. Fixed, so recordings are reproducible.
SIM_START_TIME_NS = 1_700_000_000 * 1_000_000_000


@dataclass(frozen=True)
class Trajectory:
    """Poses sampled at a fixed rate.

    Attributes
    ----------
    log_time_ns : (N,) int64
    T_world_agv : (N, 4, 4)
    heading_rad : (N,) heading ψ, unwrapped (continuous)
    curvature_per_m : (N,) path curvature (0 on straights, 1/radius in turns, left positive)
    """

    log_time_ns: np.ndarray
    T_world_agv: np.ndarray
    heading_rad: np.ndarray
    curvature_per_m: np.ndarray


@dataclass(frozen=True)
class RoundedRectangleTrack:
    """Closed counter-clockwise track around ``center_xy_m``: straights of ``length_m``
    (along world x) and ``width_m`` (along y) joined by quarter circles of ``radius_m``.

    Arc length 0 is the middle of the lower straight, travelling towards +x.
    """

    length_m: float
    width_m: float
    radius_m: float
    center_xy_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        if not (self.length_m >= 0 and self.width_m >= 0 and self.radius_m > 0):
            raise ValueError(
                f"track needs length_m, width_m ≥ 0 and radius_m > 0, got {self.length_m}, "
                f"{self.width_m}, {self.radius_m}"
            )

    @property
    def perimeter_m(self) -> float:
        return 2.0 * (self.length_m + self.width_m) + 2.0 * np.pi * self.radius_m

    def _segments(self) -> list[tuple[np.ndarray, float, float, float]]:
        """(start point, start direction of travel [rad from +x], length, curvature) each."""
        a, b, r = self.length_m / 2.0, self.width_m / 2.0, self.radius_m
        quarter = np.pi * r / 2.0
        c = np.asarray(self.center_xy_m, dtype=float)
        return [
            (c + [0.0, -b - r], 0.0, a, 0.0),
            (c + [a, -b - r], 0.0, quarter, 1.0 / r),
            (c + [a + r, -b], np.pi / 2, 2 * b, 0.0),
            (c + [a + r, b], np.pi / 2, quarter, 1.0 / r),
            (c + [a, b + r], np.pi, 2 * a, 0.0),
            (c + [-a, b + r], np.pi, quarter, 1.0 / r),
            (c + [-a - r, b], 1.5 * np.pi, 2 * b, 0.0),
            (c + [-a - r, -b], 1.5 * np.pi, quarter, 1.0 / r),
            (c + [-a, -b - r], 2.0 * np.pi, a, 0.0),
        ]

    def at(self, arc_length_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (N, 2), direction of travel (N,) [rad from +x, unwrapped over laps] and
        curvature (N,) at arc lengths (N,) — any real value, the track repeats every lap."""
        s = np.asarray(arc_length_m, dtype=float).ravel()
        laps = np.floor(s / self.perimeter_m)
        s_lap = s - laps * self.perimeter_m
        xy = np.zeros((s.size, 2))
        direction = np.zeros(s.size)
        curvature = np.zeros(s.size)
        start = 0.0
        segments = self._segments()
        for index, (p0, phi0, length, kappa) in enumerate(segments):
            d = s_lap - start
            # The last segment also takes the rounding residue of the perimeter.
            sel = (d >= 0) & ((d <= length) | (index == len(segments) - 1))
            d = d[sel]
            if kappa == 0.0:
                phi = np.full(d.shape, phi0)
                xy[sel] = p0 + d[:, None] * [np.cos(phi0), np.sin(phi0)]
            else:
                phi = phi0 + kappa * d
                xy[sel] = p0 + np.stack(
                    [np.sin(phi) - np.sin(phi0), -(np.cos(phi) - np.cos(phi0))], axis=1
                ) / kappa
            direction[sel] = phi
            curvature[sel] = kappa
            start += length
        return xy, direction + 2.0 * np.pi * laps, curvature


def sample_track(
    track: RoundedRectangleTrack,
    speed_mps: float,
    rate_hz: float,
    duration_s: float,
    start_time_ns: int = SIM_START_TIME_NS,
) -> Trajectory:
    """Drive ``track`` at constant speed; ``round(duration_s · rate_hz)`` samples at
    ``t_k = start_time_ns + round(k · 1e9 / rate_hz)``."""
    if not (speed_mps >= 0 and rate_hz > 0 and duration_s > 0):
        raise ValueError(
            f"need speed_mps ≥ 0, rate_hz > 0, duration_s > 0; got {speed_mps}, {rate_hz}, {duration_s}"
        )
    n = int(round(duration_s * rate_hz))
    if n < 1:
        raise ValueError(f"duration_s · rate_hz = {duration_s * rate_hz:g} gives no frame")
    k = np.arange(n)
    log_time_ns = start_time_ns + np.round(k * (1e9 / rate_hz)).astype(np.int64)
    t_s = k / rate_hz
    xy, direction, curvature = track.at(speed_mps * t_s)
    heading = direction - np.pi / 2.0  # AGV y axis along the direction of travel
    T = np.stack([se3.make(euler.Rz(h), [p[0], p[1], 0.0]) for p, h in zip(xy, heading)])
    return Trajectory(log_time_ns=log_time_ns, T_world_agv=T, heading_rad=heading, curvature_per_m=curvature)


def track_pose(track: RoundedRectangleTrack, speed_mps: float, t_s: float) -> np.ndarray:
    """Flat ``T_world_agv`` at ``t_s`` seconds after the start (as :func:`sample_track`, at any
    time)."""
    xy, direction, _ = track.at(np.array([speed_mps * t_s]))
    return se3.make(euler.Rz(float(direction[0]) - np.pi / 2.0), [xy[0, 0], xy[0, 1], 0.0])


def dead_reckoning(
    trajectory: Trajectory,
    rng: np.random.Generator,
    scale_error: float,
    heading_bias_rad_per_s: float,
    step_noise_m: float,
    heading_noise_rad: float,
    slip_fraction: np.ndarray | None = None,
) -> np.ndarray:
    """Odometry poses ``T_odom_agv`` (N, 4, 4) integrated from the true motion with drift.

    Each true body-frame step (Δx, Δy, Δψ) is measured as ``(1 + scale_error)·(Δx, Δy) +
    N(0, step_noise_m²)`` per axis and ``Δψ + heading_bias_rad_per_s·Δt + N(0,
    heading_noise_rad²)``, then composed. The odom frame equals the world frame at the first
    sample. Draws 3 normals per step from ``rng``. ``slip_fraction`` (N − 1,), when given,
    adds wheel slip: step k's distance factor becomes ``(1 + scale_error) + slip_fraction[k]``
    (:mod:`agvviz.sim.realism`); it draws nothing from ``rng``.
    """
    T_true = trajectory.T_world_agv
    n = T_true.shape[0]
    dt_s = np.diff(trajectory.log_time_ns) * 1e-9
    noise = rng.standard_normal((max(n - 1, 0), 3))
    T_odom_agv = np.empty_like(T_true)
    T_odom_agv[0] = T_true[0]
    for k in range(1, n):
        step = se3.inverse(T_true[k - 1]) @ T_true[k]
        factor = 1.0 + scale_error
        if slip_fraction is not None:
            factor += float(slip_fraction[k - 1])
        dxy = factor * step[:2, 3] + step_noise_m * noise[k - 1, :2]
        dpsi = (
            np.arctan2(step[1, 0], step[0, 0])
            + heading_bias_rad_per_s * dt_s[k - 1]
            + heading_noise_rad * noise[k - 1, 2]
        )
        T_odom_agv[k] = T_odom_agv[k - 1] @ se3.make(euler.Rz(dpsi), [dxy[0], dxy[1], 0.0])
    return T_odom_agv


def forward_camera_mount(cam_height_m: float, lookahead_m: float) -> np.ndarray:
    """``T_agv_cam`` of a camera above the AGV origin, looking forward (+y) and down.

    The camera sits at height ``cam_height_m``; its optical axis meets the floor
    ``lookahead_m`` ahead (0: straight down). Camera x = AGV x (right), so the image's
    top shows the far floor.
    """
    if not cam_height_m > 0:
        raise ValueError(f"cam_height_m must be > 0 (camera above the floor), got {cam_height_m}")
    if not lookahead_m >= 0:
        raise ValueError(f"lookahead_m must be ≥ 0, got {lookahead_m}")
    z_axis = np.array([0.0, lookahead_m, -cam_height_m])
    z_axis /= np.linalg.norm(z_axis)
    x_axis = np.array([1.0, 0.0, 0.0])
    y_axis = np.cross(z_axis, x_axis)
    return se3.make(np.stack([x_axis, y_axis, z_axis], axis=1), [0.0, 0.0, cam_height_m])
