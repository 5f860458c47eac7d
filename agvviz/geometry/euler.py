"""Euler angles Z-X-Y: R = Rz(ψ)·Rx(θ)·Ry(γ) — heading ψ, pitch θ, roll γ (paper 000 eq 38).

Numpy only. The inverse follows paper 000 eq 57, including its gimbal-lock rule.
"""

from __future__ import annotations

import math

import numpy as np

from agvviz.conventions import DEFAULT_GIMBAL_THRESHOLD


def Rz(angle_rad: float) -> np.ndarray:
    """Rotation about z (paper 000 eq 34)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def Rx(angle_rad: float) -> np.ndarray:
    """Rotation about x (paper 000 eq 35)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def Ry(angle_rad: float) -> np.ndarray:
    """Rotation about y (paper 000 eq 36)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def matrix_from_hpr(heading_rad: float, pitch_rad: float, roll_rad: float) -> np.ndarray:
    """R = Rz(heading)·Rx(pitch)·Ry(roll)."""
    return Rz(heading_rad) @ Rx(pitch_rad) @ Ry(roll_rad)


def hpr_from_matrix(
    R: np.ndarray, gimbal_threshold: float = DEFAULT_GIMBAL_THRESHOLD
) -> tuple[float, float, float]:
    """(heading, pitch, roll) in rad from R, paper 000 eq 57.

    Pitch lies in [-π/2, π/2], heading and roll in (-π, π]. When ``|r32| > gimbal_threshold``
    (0 < T < 1) the pitch is taken as ±π/2, heading is set to 0 and the whole rotation about
    the vertical is reported as roll (eqs 54–56).
    """
    if not 0.0 < gimbal_threshold < 1.0:
        raise ValueError(f"gimbal_threshold must lie in (0, 1), got {gimbal_threshold}")
    R = np.asarray(R, dtype=float)
    r32 = min(max(float(R[2, 1]), -1.0), 1.0)
    if abs(r32) > gimbal_threshold:
        pitch = np.pi / 2 if r32 > 0 else -np.pi / 2
        return 0.0, pitch, wrap_angle_rad(np.arctan2(R[0, 2], R[0, 0]))
    pitch = float(np.arcsin(r32))
    # eq 40/41 divide by cos θ > 0; atan2 needs only the signs, so the division is dropped.
    # atan2 returns -π for a -0.0 numerator; wrap into the documented (-π, π].
    heading = wrap_angle_rad(np.arctan2(-R[0, 1], R[1, 1]))
    roll = wrap_angle_rad(np.arctan2(-R[2, 0], R[2, 2]))
    return heading, pitch, roll


def wrap_angle_rad(angle_rad):
    """Wrap an angle (or array of angles) into (-π, π]."""
    if isinstance(angle_rad, (float, np.floating)):
        # One angle in Python floats: ``%`` is np.mod's floor remainder (same sign rule), without
        # numpy's per-call cost (this wraps every pose's heading, pitch and roll).
        wrapped = (float(angle_rad) + math.pi) % (2.0 * math.pi) - math.pi
        return math.pi if wrapped == -math.pi else wrapped
    wrapped = np.mod(np.asarray(angle_rad, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    wrapped = np.where(wrapped == -np.pi, np.pi, wrapped)
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped
