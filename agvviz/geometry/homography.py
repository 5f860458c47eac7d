"""Plane-induced homographies: how a plane seen by one pinhole view looks in another. Numpy only.

A camera moves from pose "from" to pose "to" (``T_to_from`` maps points of the "from" camera
frame into the "to" camera frame: ``X_to = R X_from + t``). A plane ``nᵀ X_from = d`` (unit
normal ``n`` and offset ``d`` in the "from" camera frame, ``d ≠ 0``: the camera is not on the
plane) satisfies ``nᵀ X_from / d = 1``, so every point on it maps as
``X_to = (R + t nᵀ / d) X_from`` and its pixels (of ideal, undistorted images) as

    x_to ~ H_to_from x_from,   H_to_from = K_to (R + t nᵀ / d) K_from⁻¹

(Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., §13.1). The homography is defined up
to scale; it is returned as computed (not normalised).

:func:`floor_homography` applies this to a camera riding on a vehicle that moves on the floor:
the floor is the plane z = 0 of the vehicle's body frame (:mod:`agvviz.conventions`: the body
origin is on the floor), and the vehicle's motion between two images comes from odometry.
"""

from __future__ import annotations

import numpy as np

from agvviz.geometry import se3
from agvviz.geometry.plane import DegenerateGeometryError

#: A plane closer than this to the camera's centre (m) gives no usable homography (the camera
#: sees the plane edge-on).
MIN_PLANE_DISTANCE_M = 1e-6


def plane_homography(
    K_to: np.ndarray, K_from: np.ndarray, T_to_from: np.ndarray, normal_from: np.ndarray, offset_from_m: float
) -> np.ndarray:
    """``H_to_from`` (3×3): pixels of the "from" view → pixels of the "to" view, for points on
    the plane ``normal_from · X = offset_from_m`` (in the "from" camera frame; ``normal_from``
    need not be unit length — the pair is scaled together).

    Raises
    ------
    DegenerateGeometryError
        Non-finite input, a zero normal, or a plane through the "from" camera's centre
        (closer than :data:`MIN_PLANE_DISTANCE_M`).
    """
    K_to = np.asarray(K_to, dtype=float).reshape(3, 3)
    K_from = np.asarray(K_from, dtype=float).reshape(3, 3)
    T_to_from = np.asarray(T_to_from, dtype=float).reshape(4, 4)
    normal = np.asarray(normal_from, dtype=float).reshape(3)
    offset_m = float(offset_from_m)
    if not all(np.all(np.isfinite(a)) for a in (K_to, K_from, T_to_from, normal)) or not np.isfinite(offset_m):
        raise DegenerateGeometryError("plane homography: intrinsics, pose or plane contain NaN or inf")
    length = float(np.linalg.norm(normal))
    if length == 0.0:
        raise DegenerateGeometryError("plane homography: the plane normal is zero")
    normal, offset_m = normal / length, offset_m / length
    if abs(offset_m) < MIN_PLANE_DISTANCE_M:
        raise DegenerateGeometryError(
            f"plane homography: the camera lies on the plane ({abs(offset_m):.2g} m from it)"
        )
    R, t = T_to_from[:3, :3], T_to_from[:3, 3]
    return K_to @ (R + np.outer(t, normal) / offset_m) @ np.linalg.inv(K_from)


def floor_homography(
    K: np.ndarray,
    T_odom_agv_from: np.ndarray,
    T_odom_agv_to: np.ndarray,
    T_agv_cam_from: np.ndarray,
    T_agv_cam_to: np.ndarray | None = None,
) -> np.ndarray:
    """``H_to_from`` (3×3) of the floor for a camera on a vehicle: pixels of the undistorted
    image taken at odometry pose ``T_odom_agv_from`` → pixels of the one taken at
    ``T_odom_agv_to``, for points on the floor (the plane z = 0 of the body frame ``agv`` at
    the "from" pose). ``K`` is the (undistorted) camera matrix of both images;
    ``T_agv_cam_to`` defaults to ``T_agv_cam_from`` (a rigid mount).

    Raises
    ------
    DegenerateGeometryError
        As :func:`plane_homography` (e.g. a camera at floor height).
    """
    T_agv_cam_to = T_agv_cam_from if T_agv_cam_to is None else T_agv_cam_to
    T_odom_cam_from = np.asarray(T_odom_agv_from, dtype=float) @ np.asarray(T_agv_cam_from, dtype=float)
    T_odom_cam_to = np.asarray(T_odom_agv_to, dtype=float) @ np.asarray(T_agv_cam_to, dtype=float)
    T_to_from = se3.inverse(T_odom_cam_to) @ T_odom_cam_from
    # The floor in the "from" camera frame: body z axis as normal, through the body origin.
    T_cam_agv_from = se3.inverse(np.asarray(T_agv_cam_from, dtype=float))
    normal_cam = T_cam_agv_from[:3, :3] @ np.array([0.0, 0.0, 1.0])
    offset_m = float(normal_cam @ T_cam_agv_from[:3, 3])
    return plane_homography(K, K, T_to_from, normal_cam, offset_m)
