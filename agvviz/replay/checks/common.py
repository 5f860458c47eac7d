"""The check stage's shared arithmetic: the σ scale (:func:`chi2_sigma`), a pose's covariance with
its systematic floors, pose differences, the parameters and the constants (docs/suspects.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agvviz.geometry import so3
from agvviz.solvers.chi2 import chi2_sf, normal_isf
from agvviz.model.frames import FrameResult
from agvviz.model.suspects import (
    CAUSE_EXTRINSIC,
    CAUSE_MAP_ENTRY,
    CAUSE_MIRROR_FLIP,
    CAUSE_PAYLOAD,
    CAUSE_TIME_OFFSET,
    CAUSE_TIME_STAMPS,
    CAUSE_UNKNOWN,
    CAUSE_UWB,
    CHECK_AMBIGUITY,
    CHECK_CAMERAS,
    CHECK_MOTION,
    CHECK_UWB,
)
from agvviz.settings import RunSettings
from agvviz.solvers import uncertainty

#: A failing stretch longer than this (metres of odometry travel) moves the motion check's reference on.
REANCHOR_M = 5.0
#: With planar (wheel) odometry: the distance over which the floor's tilt and height under the AGV
#: change by their full σ (``checks_floor_tilt_deg``, ``checks_floor_height_m``): about a wheelbase.
FLOOR_LENGTH_M = 0.5
#: Without odometry: the constant-velocity model's σ of acceleration (m/s², rad/s²).
CV_ACCEL_MPS2 = 2.0
CV_ANGULAR_ACCEL_RADPS2 = 2.0
#: The UWB fix a frame is compared with is at most this much older than the frame.
UWB_MAX_DT_NS = 200_000_000
#: A camera disagreeing with the others on at least this share of at least this many stamps: "on every frame".
PERSISTENT_SHARE = 0.8
PERSISTENT_MIN = 5
#: Frame-period estimate: steps remembered per camera; a stamp step is judged with a jitter σ of
#: max(TIME_JITTER_S, TIME_JITTER_SHARE × period).
TIME_HISTORY = 50
TIME_JITTER_S = 0.002
TIME_JITTER_SHARE = 0.05
#: A time offset explains a camera disagreement when the offset fitted to it lies within these bounds (s).
TIME_OFFSET_MIN_S = 0.003
TIME_OFFSET_MAX_S = 0.5
#: Time offset against the odometry: reported from this many clean steps on, failed from this size
#: on (a few ms is what rolling shutters and odometry filters do), velocities over ± this (ns).
ODOMETRY_OFFSET_MIN_STEPS = 20
ODOMETRY_OFFSET_MIN_S = 0.01
ODOMETRY_VELOCITY_NS = 20_000_000
#: The run-level time offset (a finding on every frame of the camera, at the end of the run) needs at
#: least RUN_OFFSET_MIN_TURNING steps whose change of twist |∂r/∂dt| (weighted, m/s and rad/s) is at
#: least OFFSET_TURNING_TWIST: turns, starts and stops are what make an offset observable, and the
#: fit is not to rest on one step (one turn of qr_floor gives 3–5 such steps at 10 Hz).
OFFSET_TURNING_TWIST = 0.1
RUN_OFFSET_MIN_TURNING = 2
#: The run-level fit: Gauss–Newton iterations from the streaming fit, and the half step (s) of
#: the central differences of the residual by dt (the odometry is piecewise linear between samples).
RUN_OFFSET_ITERATIONS = 2
RUN_OFFSET_EPS_S = 0.005
#: Weights of (position m, rotation rad) in the time-offset fits: 1 mm ~ 0.06° (1 mrad).
OFFSET_WEIGHT = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])

#: Checks whose failure doubts the pose itself (a failing frame is then no reference for the next).
POSE_CHECKS = (CHECK_MOTION, CHECK_AMBIGUITY, CHECK_CAMERAS, CHECK_UWB)

NEXT_STEP = {
    CAUSE_MAP_ENTRY: "`agvviz audit` can estimate where it is",
    CAUSE_PAYLOAD: "compare the code's payload with the marker map (`agvviz inspect`), re-print the code",
    CAUSE_MIRROR_FLIP: "try `--set ambiguity=odometry`, or look at the code more squarely",
    CAUSE_EXTRINSIC: "`agvviz audit` can estimate the camera's extrinsic",
    CAUSE_TIME_OFFSET: "check the camera's time stamps (driver latency); `--set time_source=header` if the headers are right",
    CAUSE_TIME_STAMPS: "check the recording for dropped or repeated frames (`agvviz inspect`)",
    CAUSE_UWB: "look at the UWB ranges of this stretch (NLOS?) and the camera's markers",
    CAUSE_UNKNOWN: "look at the frame's markers and the odometry around it",
}


def chi2_sigma(d2: float, dof: int) -> float:
    """A χ²_dof value as the normal σ of the same upper tail (≥ 0): 1 dof gives √d²; 6 dof at
    d² = 41.0 gives 5 σ. Exact (:mod:`agvviz.solvers.chi2`, closed forms) while the tail is representable, then the
    Wilson–Hilferty approximation (slightly low there: conservative)."""
    if not math.isfinite(d2):
        return math.inf
    if d2 <= 0:
        return 0.0
    if dof == 1:
        return math.sqrt(d2)
    p = chi2_sf(d2, dof)
    if p > 1e-300:
        return max(0.0, normal_isf(p))
    k = float(dof)
    z = ((d2 / k) ** (1.0 / 3.0) - (1.0 - 2.0 / (9.0 * k))) / math.sqrt(2.0 / (9.0 * k))
    return max(0.0, z)


@dataclass(frozen=True)
class CheckSettings:
    """The check stage's parameters (``checks_*`` run settings, docs/suspects.md)."""

    limit_sigma: float = 5.0
    pose_floor_m: float = 0.0005
    pose_floor_rad: float = math.radians(0.02)
    odom_m_per_m: float = 0.02
    odom_rad_per_m: float = math.radians(0.5)
    odom_rad_per_rad: float = 0.02
    ambiguity_ratio: float = 4.0
    map_sigma_m: float = 0.005
    uwb_sigma_m: float = 0.1
    floor_tilt_rad: float = math.radians(0.35)
    floor_height_m: float = 0.005

    @classmethod
    def of(cls, settings: RunSettings) -> "CheckSettings":
        return cls(
            limit_sigma=settings.checks_limit_sigma, pose_floor_m=settings.checks_pose_floor_m,
            pose_floor_rad=math.radians(settings.checks_pose_floor_deg), odom_m_per_m=settings.checks_odom_m_per_m,
            odom_rad_per_m=math.radians(settings.checks_odom_deg_per_m),
            odom_rad_per_rad=settings.checks_odom_deg_per_deg, ambiguity_ratio=settings.checks_ambiguity_ratio,
            map_sigma_m=settings.checks_map_sigma_m, uwb_sigma_m=settings.uwb_sigma_m,
            floor_tilt_rad=math.radians(settings.checks_floor_tilt_deg), floor_height_m=settings.checks_floor_height_m,
        )


# -- pose arithmetic ------------------------------------------------------------------------------
def pose_cov(frame: FrameResult, cs: CheckSettings) -> np.ndarray:
    """(6, 6) covariance of (position in the world, rotation vector) of the frame's AGV pose:
    its own (position block and rotation block; none: zeros) plus the systematic floors."""
    C = np.zeros((6, 6))
    if frame.cov_world_agv is not None and np.all(np.isfinite(frame.cov_world_agv)):
        C[3:, 3:] = frame.cov_world_agv[3:, 3:]
        if frame.position_cov_world_m2 is not None:
            C[:3, :3] = frame.position_cov_world_m2
        else:
            C[:3, :3] = frame.cov_world_agv[:3, :3]
    C[:3, :3] += np.eye(3) * cs.pose_floor_m**2
    C[3:, 3:] += np.eye(3) * cs.pose_floor_rad**2
    return C


def floor_cov(cs: CheckSettings) -> np.ndarray:
    """(6, 6) the systematic floors of one pose in (position, rotation vector)."""
    return np.diag([cs.pose_floor_m**2] * 3 + [cs.pose_floor_rad**2] * 3)


def _lever(offset_m: np.ndarray) -> np.ndarray:
    """(6, 6): (position, rotation) of a pose to those of a point ``offset_m`` away, rigidly attached."""
    J = _EYE6.copy()
    J[:3, 3:] = -so3.hat(offset_m)
    return J


_EYE6 = np.eye(6)
_EYE6.setflags(write=False)  # shared: _lever copies it


def _left_cov(frame: FrameResult) -> np.ndarray:
    cov = frame.cov_world_agv
    return cov if cov is not None and np.all(np.isfinite(cov)) else np.zeros((6, 6))


def unambiguous(frame: FrameResult, cs: CheckSettings) -> bool:
    """Whether the frame's pose is clear of its mirror pose (no ghost, or an IPPE ratio of at
    least ``ambiguity_ratio``): only then is its first-order covariance, linearised at that
    pose, trusted to say which errors it shares with another frame."""
    return frame.T_world_agv_ghost is None or frame.ambiguity_ratio is None or frame.ambiguity_ratio >= cs.ambiguity_ratio


def carried_difference_cov(
    ref: FrameResult, T_carried: np.ndarray, frame: FrameResult, cs: CheckSettings, common: bool = True
) -> np.ndarray:
    """(6, 6) covariance of ``pose_difference(T_carried, frame.T_world_agv)``, ``T_carried`` the
    reference's pose carried on by a step (``ref.T_world_agv · step``; the step's own noise not
    included): the two covariances with the sources they share cancelling as far as their
    geometry agrees (the camera's calibration and extrinsic, the map entries and corners of the
    codes both used: :func:`agvviz.solvers.uncertainty.difference_covariance`), plus each pose's
    floor — the reference's carried to the carried origin, so its rotation swings the step.
    ``common=False`` takes the two as independent (their covariances add)."""
    C = uncertainty.difference_covariance(
        _left_cov(ref), ref.cov_common_factors if common else None, T_carried[:3, 3],
        _left_cov(frame), frame.cov_common_factors if common else None, frame.T_world_agv[:3, 3],
    )
    J = _lever(T_carried[:3, 3] - ref.T_world_agv[:3, 3])
    floor = floor_cov(cs)
    return C + J @ floor @ J.T + floor


def is_planar_step(step: np.ndarray) -> bool:
    """An odometry step that stays in its plane: a rotation about z only and no z motion (wheel
    odometry of a floor vehicle; DESIGN §3: the floor is z = 0, z up)."""
    return bool(abs(step[2, 0]) <= 1e-9 and abs(step[2, 1]) <= 1e-9 and abs(step[2, 3]) <= 1e-6)


def odometry_cov(step: np.ndarray, cs: CheckSettings) -> np.ndarray:
    """(6, 6) covariance (world position, rotation vector) of an odometry step's error: σ of
    heading ``odom_rad_per_m``·distance + ``odom_rad_per_rad``·angle turned, σ of position
    ``odom_m_per_m``·distance + distance·σ of heading. A planar step (:func:`is_planar_step`:
    wheel odometry) drifts only in the floor's plane (x, y, yaw); the AGV's tilt and height stay
    the reference's up to the floor's flatness, which changes over about :data:`FLOOR_LENGTH_M`:
    σ of tilt about x and y ``floor_tilt_rad``·min(1, distance ÷ FLOOR_LENGTH_M), σ of height
    ``floor_height_m``·min(1, distance ÷ FLOOR_LENGTH_M) + distance·``floor_tilt_rad`` (the step
    is carried along the reference's own tilt). A 3-D step drifts alike about every axis."""
    distance_m = float(np.linalg.norm(step[:3, 3]))
    turned_rad = float(np.linalg.norm(so3.log(step[:3, :3])))
    sigma_rot = cs.odom_rad_per_m * distance_m + cs.odom_rad_per_rad * turned_rad
    sigma_pos = cs.odom_m_per_m * distance_m + distance_m * sigma_rot
    if not is_planar_step(step):
        return np.diag([sigma_pos**2] * 3 + [sigma_rot**2] * 3)
    share = min(1.0, distance_m / FLOOR_LENGTH_M)
    sigma_tilt = cs.floor_tilt_rad * share
    sigma_z = cs.floor_height_m * share + distance_m * cs.floor_tilt_rad
    return np.diag([sigma_pos**2, sigma_pos**2, sigma_z**2, sigma_tilt**2, sigma_tilt**2, sigma_rot**2])


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """(6,) ``T_b`` − ``T_a``: position difference in the world and the rotation vector of R_b R_aᵀ."""
    return np.concatenate([T_b[:3, 3] - T_a[:3, 3], so3.log(T_b[:3, :3] @ T_a[:3, :3].T)])


def mahalanobis_d2(delta: np.ndarray, cov: np.ndarray) -> float:
    """Squared Mahalanobis distance d² = δᵀ C⁻¹ δ of ``delta`` under ``cov`` (pseudo-inverse when
    ``cov`` is singular)."""
    try:
        return float(delta @ np.linalg.solve(cov, delta))
    except np.linalg.LinAlgError:
        return float(delta @ np.linalg.pinv(cov) @ delta)


def mahalanobis_sigma(delta: np.ndarray, cov: np.ndarray) -> float:
    """The difference ``delta`` against ``cov`` as σ (:func:`chi2_sigma` of d², dof = its length)."""
    return chi2_sigma(mahalanobis_d2(delta, cov), len(delta))


def angle_deg(delta: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(delta[3:])))


def size_text(delta: np.ndarray) -> str:
    """"2.78 m, 90.0°" / "42 mm, 0.3°"."""
    d = float(np.linalg.norm(delta[:3]))
    return (f"{d:.2f} m" if d >= 1.0 else f"{d * 1000:.0f} mm") + f", {angle_deg(delta):.1f}°"


