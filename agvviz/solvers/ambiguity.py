"""Planar pose ambiguity: both IPPE solutions, the choice between two candidate poses, and flip
detection. Numpy/OpenCV only.

A plane seen in perspective has (up to) two poses that explain its pixels almost equally well:
mirror images of the plane's tilt about the line of sight (Schweighofer & Pinz; Collins &
Bartoli's IPPE returns both). When the two reprojection errors are close, noise decides which
one a solver returns and the pose *flips* from frame to frame — the most reported complaint of
planar-tag users.

``ambiguity ratio`` = RMS reprojection error of the worse IPPE solution ÷ that of the better
one (≥ 1). Near 1: ambiguous, the data cannot tell the two poses apart. Large: the second
solution is clearly wrong. It is ``inf`` when the better solution fits exactly.

Policies (:data:`POLICIES`) choose between two candidate poses of the same frame:

``lowest_error``  the candidate with the lower reprojection RMS;
``continuity``    the candidate whose rotation is closest to a reference pose — the previous
                  frame's chosen camera pose (falls back to lowest_error without one);
``odometry``      the same, with the reference predicted from the previous chosen pose and the
                  odometry's relative motion since then (falls back to continuity, then
                  lowest_error).

The two branches differ in the tilt of the code plane, i.e. in rotation; so closeness is the
rotation angle ‖Log(R_aᵀR_b)‖ of the poses in the world frame. The replay compares AGV poses
(``T_world_agv``): for one camera the angle is the same as between its camera poses, and it
stays meaningful when consecutive frames come from different cameras.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from agvviz.geometry import se3, so3
from agvviz.solvers.lm import reprojection_rms_px

POLICIES = ("lowest_error", "continuity", "odometry")


@dataclass(frozen=True)
class IppePair:
    """Both IPPE poses of one frame, the better (lower reprojection RMS) first.

    T_best_cam_marker, T_other_cam_marker : (4, 4) marker poses in the camera frame.
    rms_best_px, rms_other_px : RMS reprojection errors (px) over all given points.
    """

    T_best_cam_marker: np.ndarray
    T_other_cam_marker: np.ndarray
    rms_best_px: float
    rms_other_px: float

    @property
    def ratio(self) -> float:
        """rms_other / rms_best (≥ 1; inf when the best fits exactly)."""
        if self.rms_best_px <= 0.0:
            return float("inf")
        return self.rms_other_px / self.rms_best_px


def ippe_poses_batch(
    points_marker_m: list[np.ndarray], pixels_px: list[np.ndarray], K: np.ndarray
) -> tuple[np.ndarray, list[str]]:
    """Both solutions ``T_cam_marker`` of ``cv2.solvePnPGeneric(SOLVEPNP_IPPE)`` for each of B
    coplanar point sets (z = 0), in OpenCV's order, unranked (:func:`ippe_pair` ranks them by
    reprojection error; a caller that needs both, not which is better, skips that).

    Returns ``(T, reasons)``: T (B, 2, 4, 4), NaN for a set without two valid solutions, and
    per set ``""`` or why not (OpenCV fails, returns fewer than two solutions, or a solution is
    non-finite or puts a point behind the camera).
    """
    K = np.ascontiguousarray(K, dtype=np.float64)
    T = np.full((len(points_marker_m), 2, 4, 4), np.nan)
    reasons = [""] * len(points_marker_m)
    for k, (points, pixels) in enumerate(zip(points_marker_m, pixels_px)):
        obj = np.ascontiguousarray(points, dtype=np.float64)
        try:
            count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                obj, np.ascontiguousarray(pixels, dtype=np.float64), K, None, flags=cv2.SOLVEPNP_IPPE
            )
        except cv2.error as exc:
            lines = str(exc).strip().splitlines()
            reasons[k] = f"opencv error: {lines[-1] if lines else type(exc).__name__}"
            continue
        if count < 2:
            reasons[k] = f"IPPE returned {count} solution(s), need 2"
            continue
        for j, (rvec, tvec) in enumerate(zip(rvecs[:2], tvecs[:2])):
            pose = se3.make(so3.exp(np.asarray(rvec, float).ravel()), np.asarray(tvec, float).ravel())
            if not (np.isfinite(pose).all() and (se3.transform_points(pose, obj)[:, 2] > 0.0).all()):
                reasons[k] = "an IPPE solution is non-finite or puts a point behind the camera"
                T[k] = np.nan
                break
            T[k, j] = pose
    return T, reasons


def ippe_poses(
    points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray] | None, str]:
    """:func:`ippe_poses_batch` of one point set: ``((T_a, T_b), "")`` or ``(None, reason)``."""
    T, (reason,) = ippe_poses_batch([points_marker_m], [pixels_px], K)
    return (None, reason) if reason else ((T[0, 0], T[0, 1]), "")


def ippe_pair(
    points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray
) -> tuple[IppePair | None, str]:
    """Both solutions of ``cv2.solvePnPGeneric(SOLVEPNP_IPPE)`` for coplanar points (z = 0).

    Returns ``(pair, "")`` or ``(None, reason)`` when OpenCV fails, returns fewer than two
    solutions, or a solution puts a point behind the camera.
    """
    both, reason = ippe_poses(points_marker_m, pixels_px, K)
    if both is None:
        return None, reason
    obj = np.ascontiguousarray(points_marker_m, dtype=np.float64)
    img = np.ascontiguousarray(pixels_px, dtype=np.float64)
    poses = [(reprojection_rms_px(T, obj, img, K), T) for T in both]
    poses.sort(key=lambda item: item[0])
    (rms_a, T_a), (rms_b, T_b) = poses
    return IppePair(T_a, T_b, rms_a, rms_b), ""


def rotation_distance_rad(T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Angle (rad) of the rotation between two poses (or rotation matrices)."""
    return float(np.linalg.norm(so3.log(T_a[:3, :3].T @ T_b[:3, :3])))


def choose(
    policy: str,
    rms_px: tuple[float, float],
    T_world: tuple[np.ndarray, np.ndarray],
    T_world_previous: np.ndarray | None = None,
    T_world_predicted: np.ndarray | None = None,
) -> tuple[int, str]:
    """Index (0 or 1) of the candidate ``policy`` keeps, and which rule decided.

    Parameters
    ----------
    policy : one of :data:`POLICIES`.
    rms_px : reprojection RMS of the two candidates.
    T_world : the two candidate poses in the world (of the AGV, or of the camera).
    T_world_previous : the pose chosen in the previous solved frame, if any.
    T_world_predicted : that pose moved by the odometry since then, if known.

    Returns
    -------
    (index, rule): rule is the policy actually applied after fallbacks
    ("lowest_error", "continuity" or "odometry"). Ties keep candidate 0.
    """
    if policy not in POLICIES:
        raise ValueError(f"unknown ambiguity policy {policy!r}; valid: {', '.join(POLICIES)}")
    reference, rule = None, "lowest_error"
    if policy == "odometry" and T_world_predicted is not None:
        reference, rule = T_world_predicted, "odometry"
    elif policy in ("odometry", "continuity") and T_world_previous is not None:
        reference, rule = T_world_previous, "continuity"
    if reference is None:
        return (1 if rms_px[1] < rms_px[0] else 0), rule
    d0 = rotation_distance_rad(T_world[0], reference)
    d1 = rotation_distance_rad(T_world[1], reference)
    return (1 if d1 < d0 else 0), rule


def is_flip(
    T_world_chosen: np.ndarray,
    T_world_previous_chosen: np.ndarray | None,
    T_world_previous_rejected: np.ndarray | None,
) -> bool:
    """True when this frame's chosen pose sits on the branch the previous frame rejected: it is
    closer in rotation to the previous frame's rejected pose than to its chosen one."""
    if T_world_previous_chosen is None or T_world_previous_rejected is None:
        return False
    return rotation_distance_rad(T_world_chosen, T_world_previous_rejected) < rotation_distance_rad(
        T_world_chosen, T_world_previous_chosen
    )
