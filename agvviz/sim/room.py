"""Paper 003's room (§3.1): wall cameras watching an ArUco code on the AGV's roof, UWB anchors
on the walls, a path through the middle and the static test grid. Numpy/OpenCV only.

World: the floor is z = 0, the room spans x ∈ [0, length_m], y ∈ [0, width_m]. Cameras and
anchors sit on the four walls (one of each per wall, at the wall's middle); each camera looks
at ``cam_target_m``. The ArUco code lies face up on the roof at the AGV origin, its printed
top edge towards the AGV's front (+y), so ``T_agv_marker`` is a pure lift; the UWB tag sits
above the AGV origin.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from agvviz.geometry import euler, se3
from agvviz.sim.render import FloorCode

#: Wall names, cameras ``cam_<wall>`` and anchors ``A_<wall>`` (south is the y = 0 wall).
WALLS = ("south", "east", "north", "west")


def wall_points(length_m: float, width_m: float, inset_m: float, z_m: float) -> dict[str, np.ndarray]:
    """The middle of each wall, ``inset_m`` inside the room, at height ``z_m``."""
    return {
        "south": np.array([length_m / 2.0, inset_m, z_m]),
        "east": np.array([length_m - inset_m, width_m / 2.0, z_m]),
        "north": np.array([length_m / 2.0, width_m - inset_m, z_m]),
        "west": np.array([inset_m, width_m / 2.0, z_m]),
    }


def look_at(position_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
    """``T_world_cam`` of a camera at ``position_m`` whose optical axis (z) points at
    ``target_m``, image x horizontal (no roll), image y pointing down-ish."""
    z_axis = np.asarray(target_m, float) - np.asarray(position_m, float)
    norm = np.linalg.norm(z_axis)
    if norm < 1e-9:
        raise ValueError("camera position and target coincide")
    z_axis /= norm
    x_axis = np.cross(z_axis, [0.0, 0.0, 1.0])
    if np.linalg.norm(x_axis) < 1e-9:
        raise ValueError("a camera looking straight up or down has no defined horizontal image axis")
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    return se3.make(np.stack([x_axis, y_axis, z_axis], axis=1), position_m)


def roof_code(modules: np.ndarray, marker_id: str, side_m: float, quiet_zone_modules: int) -> FloorCode:
    """An ArUco code (dark ``modules`` incl. its black border) lying flat at the marker frame's
    origin; place it with :func:`placed`."""
    h = side_m / 2.0
    points = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    return FloorCode(marker_id, "", np.eye(4), side_m, np.asarray(modules, bool), points, quiet_zone_modules)


def placed(code: FloorCode, T_world_marker: np.ndarray) -> FloorCode:
    """``code`` moved to ``T_world_marker``."""
    return dataclasses.replace(code, T_world_marker=np.asarray(T_world_marker, float))


def grid_points(spacing_m: float, nx: int = 6, ny: int = 5) -> np.ndarray:
    """Paper 003 §3.2's static test points: ``nx × ny`` points every ``spacing_m`` from
    (spacing, spacing), x fastest — (120, 120) … (720, 600) cm for 1.2 m. Shape (nx·ny, 2)."""
    xs = spacing_m * np.arange(1, nx + 1)
    ys = spacing_m * np.arange(1, ny + 1)
    return np.array([(x, y) for y in ys for x in xs])


def agv_pose(xy_m: np.ndarray, heading_rad: float) -> np.ndarray:
    """``T_world_agv`` on the floor at ``xy_m`` with heading ψ (conventions: ψ = 0 → +y)."""
    return se3.make(euler.Rz(heading_rad), [xy_m[0], xy_m[1], 0.0])


def horizontal_fov_focal_px(width_px: int, hfov_deg: float) -> float:
    """Focal length (px) that gives a horizontal field of view of ``hfov_deg``."""
    return (width_px / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
