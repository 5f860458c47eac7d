"""The check stage's shared arithmetic: the σ scale (:func:`chi2_sigma`), a pose's covariance with
its systematic floors, pose differences, the parameters and the constants (docs/suspects.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc, ndtri

from agvviz.geometry import so3
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

#: A failing stretch longer than this (metres of odometry travel) moves the motion check's reference on.
REANCHOR_M = 5.0
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
    d² = 41.0 gives 5 σ. Exact (scipy.special) while the tail is representable, then the
    Wilson–Hilferty approximation (slightly low there: conservative)."""
    if not math.isfinite(d2):
        return math.inf
    if d2 <= 0:
        return 0.0
    if dof == 1:
        return math.sqrt(d2)
    p = float(chdtrc(dof, d2))
    if p > 1e-300:
        return max(0.0, float(-ndtri(p)))
    k = float(dof)
    z = ((d2 / k) ** (1.0 / 3.0) - (1.0 - 2.0 / (9.0 * k))) / math.sqrt(2.0 / (9.0 * k))
    return max(0.0, z)


@dataclass(frozen=True)
class CheckSettings:
    """The check stage's parameters (``checks_*`` run settings, docs/suspects.md)."""

    limit_sigma: float = 5.0
    pose_floor_m: float = 0.002
    pose_floor_rad: float = math.radians(0.1)
    odom_m_per_m: float = 0.02
    odom_rad_per_m: float = math.radians(0.5)
    odom_rad_per_rad: float = 0.02
    ambiguity_ratio: float = 4.0
    map_sigma_m: float = 0.005
    uwb_sigma_m: float = 0.1

    @classmethod
    def of(cls, settings: RunSettings) -> "CheckSettings":
        return cls(
            limit_sigma=settings.checks_limit_sigma, pose_floor_m=settings.checks_pose_floor_m,
            pose_floor_rad=math.radians(settings.checks_pose_floor_deg), odom_m_per_m=settings.checks_odom_m_per_m,
            odom_rad_per_m=math.radians(settings.checks_odom_deg_per_m),
            odom_rad_per_rad=settings.checks_odom_deg_per_deg, ambiguity_ratio=settings.checks_ambiguity_ratio,
            map_sigma_m=settings.checks_map_sigma_m, uwb_sigma_m=settings.uwb_sigma_m,
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


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """(6,) ``T_b`` − ``T_a``: position difference in the world and the rotation vector of R_b R_aᵀ."""
    return np.concatenate([T_b[:3, 3] - T_a[:3, 3], so3.log(T_b[:3, :3] @ T_a[:3, :3].T)])


def mahalanobis_sigma(delta: np.ndarray, cov: np.ndarray) -> float:
    """The difference ``delta`` against ``cov`` as σ (:func:`chi2_sigma` of d², dof = its length)."""
    try:
        d2 = float(delta @ np.linalg.solve(cov, delta))
    except np.linalg.LinAlgError:
        d2 = float(delta @ np.linalg.pinv(cov) @ delta)
    return chi2_sigma(d2, len(delta))


def angle_deg(delta: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(delta[3:])))


def size_text(delta: np.ndarray) -> str:
    """"2.78 m, 90.0°" / "42 mm, 0.3°"."""
    d = float(np.linalg.norm(delta[:3]))
    return (f"{d:.2f} m" if d >= 1.0 else f"{d * 1000:.0f} mm") + f", {angle_deg(delta):.1f}°"


