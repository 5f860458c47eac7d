"""Paper 002's under-ice AUV: two forward cameras, ArUco markers ahead, a straight approach, and
the correction-cycle windows of its simulation study (§3.1, Table 3). Numpy only.

Frames (:mod:`agvviz.conventions`): the vehicle frame ``agv`` has x right (starboard), y forward,
z up. The paper's simulation places the marker relative to the cycle's start frame F at forward
distance L, lateral offset X (to starboard) and vertical offset Y (up), its printed face towards
the vehicle: marker x = F's +x, marker y = F's +z, marker z = F's −y.

Our choices where the paper is silent (its Table 1 and 2 are images):
cameras 1280×1024 px, f = 1100 px (≈60° horizontal field), no distortion, mounted 0.3 m either
side of the centre line and toed out by 10° (``left`` to port, ``right`` to starboard); marker
side 0.6 m, hung 2° off plumb about both of its axes; 10 frames per second; a correction cycle closes after 1.5 m of travel (so 31, 16 and
11 frames at 0.5, 1 and 1.5 m/s — about 60 sightings at 0.5 m/s, the paper's "66 markers").
A corner counts as seen when all four corners project inside the image with a 2 px margin, in
front of the camera, and the printed face points at it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.geometry.euler import Rx, Ry, Rz, matrix_from_hpr
from agvviz.model.studies import CycleTrial, GridCell
from agvviz.solvers.cnoem import Sighting, euler_params_from_transform, transform_from_euler_params

WIDTH_PX = 1280
HEIGHT_PX = 1024
FOCAL_PX = 1100.0
CAMERA_HALF_BASELINE_M = 0.3
CAMERA_TOE_OUT_DEG = 10.0
MARKER_SIDE_M = 0.6
MARKER_TILT_DEG = 2.0
FRAME_RATE_HZ = 10.0
CYCLE_DISTANCE_M = 1.5
EDGE_MARGIN_PX = 2.0

#: The paper's simulation grid (§3.1, Table 3).
GRID_DISTANCES_M = (5.0, 10.0, 15.0)
GRID_LATERAL_FRACTIONS = (0.0, 0.2, 0.4)
GRID_VERTICAL_FRACTIONS = (0.0, 0.1, 0.2)
GRID_SPEEDS_MPS = (0.5, 1.0, 1.5)
GRID_SIGMAS_PX = (0.5, 1.0, 1.5)
#: The paper's start noise of n_W^F: attitude σ 0.0174 rad, position σ 10 m.
START_ATTITUDE_SIGMA_RAD = 0.0174
START_POSITION_SIGMA_M = 10.0


def camera() -> PinholeCamera:
    """The (identical) left and right cameras."""
    K = np.array([[FOCAL_PX, 0.0, (WIDTH_PX - 1) / 2.0], [0.0, FOCAL_PX, (HEIGHT_PX - 1) / 2.0], [0.0, 0.0, 1.0]])
    return PinholeCamera(K, np.zeros(5), WIDTH_PX, HEIGHT_PX)


def camera_mounts() -> dict[str, np.ndarray]:
    """``T_agv_cam`` of the ``left`` and ``right`` cameras (optical axis forward, image x to
    starboard, image y down), toed out by ``CAMERA_TOE_OUT_DEG``."""
    R_forward = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # cam axes in agv
    toe = math.radians(CAMERA_TOE_OUT_DEG)
    return {
        "left": se3.make(Rz(toe) @ R_forward, [-CAMERA_HALF_BASELINE_M, 0.0, 0.0]),
        "right": se3.make(Rz(-toe) @ R_forward, [CAMERA_HALF_BASELINE_M, 0.0, 0.0]),
    }


def marker_corners_marker(side_m: float = MARKER_SIDE_M) -> np.ndarray:
    """(4, 3) TL, TR, BR, BL in the marker frame."""
    h = side_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def T_F_marker_ahead(distance_m: float, lateral_m: float, vertical_m: float) -> np.ndarray:
    """Pose in F of a marker ``distance_m`` ahead, offset to starboard and up, facing F, hung
    ``MARKER_TILT_DEG`` off plumb about its own x and y axes (a marker is never exactly plumb;
    an exactly plumb one also trips an OpenCV 5.0 IPPE quirk on noise-free pixels, see
    :mod:`agvviz.solvers.window_baselines`)."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # columns: marker x, y, z in F
    tilt = math.radians(MARKER_TILT_DEG)
    return se3.make(R @ Rx(tilt) @ Ry(tilt), [lateral_m, distance_m, vertical_m])


def visible_pixels(
    cam: PinholeCamera, T_cam_marker: np.ndarray, corners_marker_m: np.ndarray
) -> np.ndarray | None:
    """(4, 2) ideal pixels of the corners, or ``None`` when the marker is not fully seen."""
    P = se3.transform_points(T_cam_marker, corners_marker_m)
    if not np.all(P[:, 2] > 0.1):
        return None
    normal_cam = T_cam_marker[:3, 2]
    if float(normal_cam @ T_cam_marker[:3, 3]) >= 0.0:  # printed face turned away
        return None
    px = cam.project(P)
    lo, hi_u, hi_v = -0.5 + EDGE_MARGIN_PX, cam.width_px - 0.5 - EDGE_MARGIN_PX, cam.height_px - 0.5 - EDGE_MARGIN_PX
    if np.any(px[:, 0] < lo) or np.any(px[:, 1] < lo) or np.any(px[:, 0] > hi_u) or np.any(px[:, 1] > hi_v):
        return None
    return px


def grid_cells() -> list[GridCell]:
    """All 243 cells of the paper's grid, distance slowest, σ fastest."""
    return [
        GridCell(L, x, y, v, s)
        for L in GRID_DISTANCES_M
        for x in GRID_LATERAL_FRACTIONS
        for y in GRID_VERTICAL_FRACTIONS
        for v in GRID_SPEEDS_MPS
        for s in GRID_SIGMAS_PX
    ]


@dataclass
class CycleGeometry:
    """The noise-free geometry of one cycle, relative to F.

    T_F_agv : (K, 4, 4) vehicle pose of each frame in F (frame 0 is F itself).
    clean : list of (frame_index, cam_name, T_F_cam, pixels (4, 2)) for every visible sighting.
    T_F_marker : (4, 4) the marker's pose in F.
    """

    T_F_agv: np.ndarray
    clean: list[tuple[int, str, np.ndarray, np.ndarray]]
    T_F_marker: np.ndarray


def cycle_geometry(
    cell: GridCell, *, frame_rate_hz: float = FRAME_RATE_HZ, cycle_distance_m: float = CYCLE_DISTANCE_M
) -> CycleGeometry:
    """Straight approach at ``cell.speed_mps`` along F's +y for ``cycle_distance_m``, frames at
    ``frame_rate_hz`` (frame 0 at F), with every visible (frame, camera) sighting."""
    if not (frame_rate_hz > 0 and cycle_distance_m > 0 and cell.speed_mps > 0):
        raise ValueError("frame rate, cycle distance and speed must be > 0")
    n_frames = int(math.floor(cycle_distance_m / cell.speed_mps * frame_rate_hz + 1e-9)) + 1
    T_F_marker = T_F_marker_ahead(
        cell.distance_m, cell.lateral_fraction * cell.distance_m, cell.vertical_fraction * cell.distance_m
    )
    cam, mounts = camera(), camera_mounts()
    corners = marker_corners_marker()
    T_F_agv = np.stack([se3.make(np.eye(3), [0.0, cell.speed_mps * k / frame_rate_hz, 0.0]) for k in range(n_frames)])
    clean = []
    for k in range(n_frames):
        for name, T_agv_cam in mounts.items():
            T_F_cam = T_F_agv[k] @ T_agv_cam
            px = visible_pixels(cam, se3.inverse(T_F_cam) @ T_F_marker, corners)
            if px is not None:
                clean.append((k, name, T_F_cam, px))
    return CycleGeometry(T_F_agv, clean, T_F_marker)


def random_start_frame(rng: np.random.Generator) -> np.ndarray:
    """A random ``T_world_F``: position uniform in a 200 m box (depth 5–50 m below the ice),
    heading uniform, pitch and roll N(0, 3°)."""
    heading = rng.uniform(-math.pi, math.pi)
    pitch, roll = rng.normal(0.0, math.radians(3.0), 2)
    return se3.make(matrix_from_hpr(heading, pitch, roll), [*rng.uniform(-100.0, 100.0, 2), -rng.uniform(5.0, 50.0)])


def perturbed_start(
    T_world_F: np.ndarray,
    rng: np.random.Generator,
    attitude_sigma_rad: float = START_ATTITUDE_SIGMA_RAD,
    position_sigma_m: float = START_POSITION_SIGMA_M,
) -> np.ndarray:
    """The paper's start: n_W^F with N(0, σ_att²) added to its three Euler angles and N(0, σ_pos²)
    to its three translation components (§3.1)."""
    n = euler_params_from_transform(se3.inverse(T_world_F))
    n = n + np.concatenate([rng.normal(0.0, attitude_sigma_rad, 3), rng.normal(0.0, position_sigma_m, 3)])
    return se3.inverse(transform_from_euler_params(n))


def draw_trial(geometry: CycleGeometry, sigma_px: float, rng: np.random.Generator, marker_id: str = "7") -> CycleTrial:
    """A random placement of F in the world, the paper's perturbed start and pixel noise σ."""
    T_world_F = random_start_frame(rng)
    T_world_nav = perturbed_start(T_world_F, rng)
    corners_world = se3.transform_points(T_world_F @ geometry.T_F_marker, marker_corners_marker())
    K = camera().K
    noise = rng.normal(0.0, sigma_px, (len(geometry.clean), 4, 2))
    sightings = [
        Sighting(marker_id, name, k, corners_world, px + noise[i], K, T_F_cam)
        for i, (k, name, T_F_cam, px) in enumerate(geometry.clean)
    ]
    return CycleTrial(T_world_F, T_world_nav, sightings)
