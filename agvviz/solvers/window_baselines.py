"""Single-frame IPPE baselines for a correction window (paper 002 compares CNOEM with IPPE).
Numpy/OpenCV only.

Each returns ``T_world_F`` (the start frame's pose) or ``None`` with a reason:

``ippe_first``     IPPE on the earliest sighting of the window (frame F itself when the marker is
                   seen there; the left camera first), the lower-reprojection-error solution,
                   mapped to F through the navigation's ``T_F_cam``. What a single-frame
                   localiser reports at the cycle start.
``ippe_first_nav`` the same sighting, the IPPE solution whose attitude is closer to the
                   navigation's (paper 002's start attitude is good to 1°; this resolves the
                   planar two-fold ambiguity that dominates far, small markers).
``ippe_mean_nav``  ``ippe_first_nav`` on every sighting of the window, each mapped to F through
                   the navigation, positions averaged (rotation of the first): a naive
                   multi-frame use of a single-frame solver.

OpenCV 5.0 quirk: ``solvePnPGeneric(SOLVEPNP_IPPE)`` returns a pose 0.1–0.6 px off on
noise-free (and 1e-6 px noisy) pixels of a marker whose plane is exactly parallel to the image's
vertical axis. With σ = 0.5 px the error statistics match those of a marker tilted by 1e-3 rad
to within 0.1 % (checked), so noisy studies are unaffected; agvviz.sim.auv hangs its markers 2°
off plumb anyway.
"""

from __future__ import annotations

import numpy as np

from agvviz.geometry import se3
from agvviz.geometry.plane import marker_frame_from_corners
from agvviz.solvers.ambiguity import ippe_pair
from agvviz.solvers.cnoem import Sighting

BASELINES = ("ippe_first", "ippe_first_nav", "ippe_mean_nav")


def ippe_candidates(s: Sighting, marker_frame=None) -> tuple[list[np.ndarray] | None, str]:
    """Both IPPE ``T_world_F`` of one sighting, the better fit first. ``marker_frame`` is
    ``marker_frame_from_corners(s.points_world_m)`` when the caller already has it."""
    T_world_marker, points_marker = marker_frame or marker_frame_from_corners(np.asarray(s.points_world_m))
    pair, reason = ippe_pair(points_marker, np.asarray(s.pixels_px), np.asarray(s.K))
    if pair is None:
        return None, reason
    T_cam_F = se3.inverse(np.asarray(s.T_F_cam))
    return [
        T_world_marker @ se3.inverse(T) @ T_cam_F for T in (pair.T_best_cam_marker, pair.T_other_cam_marker)
    ], ""


def earliest(sightings: list[Sighting]) -> Sighting:
    order = {"left": 0, "right": 1}
    return min(sightings, key=lambda s: (s.frame_index, order.get(s.cam_name, 2), s.cam_name))


def ippe_first(sightings: list[Sighting]) -> tuple[np.ndarray | None, str]:
    """IPPE's lower-error solution on the earliest sighting, as ``T_world_F``."""
    if not sightings:
        return None, "no sightings"
    cands, reason = ippe_candidates(earliest(sightings))
    return (None, reason) if cands is None else (cands[0], "")


def ippe_first_nav(sightings: list[Sighting], T_nav_world_F: np.ndarray) -> tuple[np.ndarray | None, str]:
    """IPPE on the earliest sighting, the solution closer in attitude to the navigation's."""
    if not sightings:
        return None, "no sightings"
    return _nav_choice(earliest(sightings), T_nav_world_F)


def _nav_choice(s: Sighting, T_nav_world_F: np.ndarray, marker_frame=None) -> tuple[np.ndarray | None, str]:
    cands, reason = ippe_candidates(s, marker_frame)
    if cands is None:
        return None, reason
    # Rotation angle to the navigation's attitude: trace(Rᵀ R_nav) grows as the angle shrinks.
    closeness = [float(np.sum(T[:3, :3] * T_nav_world_F[:3, :3])) for T in cands]
    return cands[int(np.argmax(closeness))], ""


def ippe_mean_nav(sightings: list[Sighting], T_nav_world_F: np.ndarray) -> tuple[np.ndarray | None, str]:
    """Mean position of :func:`ippe_first_nav`'s choice over every sighting, mapped to F."""
    frames = {}
    for s in sightings:
        if s.marker_id not in frames:
            frames[s.marker_id] = marker_frame_from_corners(np.asarray(s.points_world_m))
    poses = [T for T, _ in (_nav_choice(s, T_nav_world_F, frames[s.marker_id]) for s in sightings) if T is not None]
    if not poses:
        return None, "IPPE failed on every sighting"
    return se3.make(poses[0][:3, :3], np.mean([T[:3, 3] for T in poses], axis=0)), ""
