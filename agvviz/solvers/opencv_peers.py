"""OpenCV's planar-capable PnP solvers as peers of P4P/LM: ``cv2.solvePnP`` with one flag.

Inputs are ideal (undistorted) pixels, so the distortion passed to OpenCV is zero.

Known OpenCV 5.0 limitation, passed through unchanged (the peers are OpenCV as users call
it): SOLVEPNP_EPNP is wrong on planar points in most views where the marker's z axis points
at the camera — i.e. most real views in this package's marker convention — and when the
points' centroid is on the optical axis. It reports success; the pose is off by up to twice
the tilt and the reprojection error (``SolveResult.reproj_rms_px``) is tens of pixels, so a
reprojection gate rejects it. tests/test_solvers.py pins this with strict xfails.
"""

from __future__ import annotations

import cv2
import numpy as np

from agvviz.geometry import se3, so3

#: Solver name → ``cv2.solvePnP`` flag.
OPENCV_FLAGS = {
    "ippe": cv2.SOLVEPNP_IPPE,
    "ippe_square": cv2.SOLVEPNP_IPPE_SQUARE,
    "sqpnp": cv2.SOLVEPNP_SQPNP,
    "epnp": cv2.SOLVEPNP_EPNP,
    "iterative": cv2.SOLVEPNP_ITERATIVE,
}

#: Largest corner deviation from the canonical square, relative to the side, that
#: ``ippe_square`` accepts. OpenCV silently uses the ideal square whatever points it is
#: given, so a deviation d becomes a model error of about d/side in the pose; 1e-4 of a
#: 0.5 m code is 50 µm, well under what corner noise costs.
SQUARE_REL_TOL = 1e-4


def canonical_square_side_m(points_marker_m: np.ndarray) -> tuple[float | None, str]:
    """Side s of the first four points if they are TL (-s/2, s/2, 0), TR (s/2, s/2, 0),
    BR (s/2, -s/2, 0), BL (-s/2, -s/2, 0) within ``SQUARE_REL_TOL``·s; else ``None`` and why."""
    pts = np.asarray(points_marker_m, dtype=float)[:4]
    side_m = float(pts[1, 0] - pts[0, 0])
    if not side_m > 0.0:
        return None, "not a canonical square: top-right is not to the right of top-left"
    h = side_m / 2.0
    canonical = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    deviation_m = float(np.max(np.abs(pts - canonical)))
    if deviation_m > SQUARE_REL_TOL * side_m:
        return None, (
            f"not a canonical square: the first 4 points deviate {deviation_m:.3g} m from the "
            f"centred square of side {side_m:.6g} m in TL, TR, BR, BL order"
        )
    return side_m, ""


def solve_opencv(
    name: str, points_marker_m: np.ndarray, pixels_px: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray | None, str]:
    """Marker pose in the camera frame from ``cv2.solvePnP`` with the flag of ``name``.

    Parameters
    ----------
    name : a key of :data:`OPENCV_FLAGS`.
    points_marker_m : (N, 3) marker-frame points (z = 0); ``ippe_square`` uses the first 4,
        which must form the canonical square (:func:`canonical_square_side_m`).
    pixels_px : (N, 2) ideal pixels.
    K : (3, 3) camera matrix.

    Returns
    -------
    (T_cam_marker, reason): the (4, 4) pose and "" on success, else ``None`` and why.
    """
    obj = np.ascontiguousarray(points_marker_m, dtype=np.float64)
    img = np.ascontiguousarray(pixels_px, dtype=np.float64)
    if name == "ippe_square":
        _, why = canonical_square_side_m(obj)
        if why:
            return None, why
        obj, img = obj[:4].copy(), img[:4].copy()
    try:
        ok, rvec, tvec = cv2.solvePnP(
            obj,
            img,
            np.ascontiguousarray(K, dtype=np.float64),
            np.zeros(5),
            flags=OPENCV_FLAGS[name],
        )
    except cv2.error as exc:
        message = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        return None, f"opencv error: {message}"
    if not ok:
        return None, "opencv found no solution"
    rvec, tvec = np.asarray(rvec, float).ravel(), np.asarray(tvec, float).ravel()
    if not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        return None, "non-finite result"
    return se3.make(so3.exp(rvec), tvec), ""
