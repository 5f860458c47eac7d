"""Marker frames from world corner coordinates. Numpy only.

A QR code carries the world coordinates of its feature points (paper 000); the solvers
work in the marker frame (z = 0 on the code). See :mod:`agvviz.conventions` for the frame.
"""

from __future__ import annotations

from agvviz.errors import RunError

import numpy as np

from agvviz.geometry import se3


class DegenerateGeometryError(RunError):
    """Points that do not define a marker plane (collinear, coincident, non-finite)."""


def square_points_marker(side_m: float, with_midpoints: bool = False) -> np.ndarray:
    """Marker-frame feature points of a square code: TL, TR, BR, BL, then optionally the
    edge midpoints top, right, bottom, left. Shape (4 or 8, 3)."""
    h = side_m / 2.0
    pts = [[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]]
    if with_midpoints:
        pts += [[0.0, h, 0.0], [h, 0.0, 0.0], [0.0, -h, 0.0], [-h, 0.0, 0.0]]
    return np.array(pts)


def quad_axis_lengths(corners: np.ndarray) -> np.ndarray:
    """(…, 2): the mean length of a quad's edges along its own x (TL→TR, BL→BR) and y (TR→BR,
    TL→BL), for corners (…, 4, k) in the order TL, TR, BR, BL (metres on the marker, or pixels)."""
    c = np.asarray(corners, dtype=float)
    along_x = 0.5 * (np.linalg.norm(c[..., 1, :] - c[..., 0, :], axis=-1) + np.linalg.norm(c[..., 2, :] - c[..., 3, :], axis=-1))
    along_y = 0.5 * (np.linalg.norm(c[..., 2, :] - c[..., 1, :], axis=-1) + np.linalg.norm(c[..., 3, :] - c[..., 0, :], axis=-1))
    return np.stack([along_x, along_y], axis=-1)


def quad_area_px2(corners_px: np.ndarray) -> float:
    """Area (px²) of the polygon through the first four image points ``corners_px`` (N ≥ 4, 2),
    in order (shoelace formula; NaN when a point is not finite)."""
    x, y = corners_px[:4, 0], corners_px[:4, 1]
    x_next, y_next = np.concatenate((x[1:], x[:1])), np.concatenate((y[1:], y[:1]))  # np.roll(·, -1)
    return 0.5 * abs(float(np.dot(x, y_next) - np.dot(y, x_next)))


def marker_frame_from_corners(
    corners_world_m: np.ndarray, planarity_tol_m: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    """Marker frame from world feature points whose first four are TL, TR, BR, BL.

    Returns ``(T_world_marker, points_marker_m)``: the origin is the centroid of the four
    vertices, x runs along the top edge, y from the bottom edge to the top edge, z out of
    the face. ``points_marker_m`` (N, 3) are the given points in that frame, with z set
    to 0 after checking every point lies within ``planarity_tol_m`` of the plane.

    Raises :class:`DegenerateGeometryError` for non-finite, coincident or non-planar points.
    """
    P = np.asarray(corners_world_m, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 4:
        raise DegenerateGeometryError(f"need at least 4 points of shape (N, 3), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise DegenerateGeometryError("corner coordinates contain NaN or inf")
    tl, tr, br, bl = P[:4]
    x_dir = (tr - tl) + (br - bl)
    y_dir = (tl - bl) + (tr - br)
    nx, ny = np.linalg.norm(x_dir), np.linalg.norm(y_dir)
    if nx < 1e-9 or ny < 1e-9:
        raise DegenerateGeometryError("marker corners coincide: zero-length edges")
    x_axis = x_dir / nx
    z_axis = np.cross(x_axis, y_dir / ny)
    nz = np.linalg.norm(z_axis)
    if nz < 1e-6:
        raise DegenerateGeometryError("marker corners are collinear")
    z_axis /= nz
    y_axis = np.cross(z_axis, x_axis)
    R = np.stack([x_axis, y_axis, z_axis], axis=1)
    origin = P[:4].mean(axis=0)
    T_world_marker = se3.make(R, origin)
    pts = se3.transform_points(se3.inverse(T_world_marker), P)
    off_plane = float(np.max(np.abs(pts[:, 2])))
    if off_plane > planarity_tol_m:
        raise DegenerateGeometryError(
            f"feature points are not coplanar: {off_plane * 1000:.1f} mm off the code plane"
        )
    pts[:, 2] = 0.0
    return T_world_marker, pts
