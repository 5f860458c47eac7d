"""Pinhole camera with OpenCV distortion (plumb_bob, rational_polynomial). Numpy only.

Pixel convention: OpenCV — integer coordinates at pixel centres. Distortion coefficients
are OpenCV's: (k1, k2, p1, p2, k3) — ROS ``plumb_bob`` — padded with zeros when fewer are
given, or (k1, k2, p1, p2, k3, k4, k5, k6) — ROS ``rational_polynomial``, radial factor
(1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶). Eight coefficients whose last
three are zero are stored as five.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics ``K`` (3×3), distortion ``dist`` (k1, k2, p1, p2, k3[, k4, k5, k6]), image
    size in px."""

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    width_px: int = 0
    height_px: int = 0

    def __post_init__(self):
        K = np.asarray(self.K, dtype=float).reshape(3, 3)
        given = np.asarray(self.dist, dtype=float).ravel()
        if given.size > 8 or 5 < given.size < 8:
            raise ValueError(
                f"distortion needs at most 5 (plumb_bob) or exactly 8 (rational_polynomial) "
                f"coefficients, got {given.size}"
            )
        d = np.zeros(8 if given.size == 8 and np.any(given[5:] != 0.0) else 5)
        d[: min(given.size, d.size)] = given[: d.size]
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(d))):
            raise ValueError("camera intrinsics or distortion contain NaN/inf")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
            raise ValueError(f"invalid camera matrix K={K.tolist()}: need fx, fy > 0 and K[2,2] = 1")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", d)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    @property
    def is_rational(self) -> bool:
        """True for the 8-coefficient rational_polynomial model."""
        return self.dist.size == 8

    def _radial(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radial factor and its derivative with respect to r²."""
        k1, k2, k3 = self.dist[0], self.dist[1], self.dist[4]
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dnum = k1 + 2 * k2 * r2 + 3 * k3 * r2 * r2
        if not self.is_rational:
            return num, dnum
        k4, k5, k6 = self.dist[5:8]
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dden = k4 + 2 * k5 * r2 + 3 * k6 * r2 * r2
        return num / den, (dnum * den - num * dden) / (den * den)

    def without_distortion(self) -> "PinholeCamera":
        """The same camera with zero distortion (the ideal pinhole of an undistorted image)."""
        return PinholeCamera(self.K, np.zeros(5), self.width_px, self.height_px)

    # -- projection ---------------------------------------------------------------------
    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply distortion to normalised image coordinates (N, 2)."""
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial, _ = self._radial(r2)
        return _columns(*self._distorted(x, y, r2, radial))

    def _distorted(self, x, y, r2, radial) -> tuple[np.ndarray, np.ndarray]:
        """(xd, yd): normalised ``x``, ``y`` distorted, given ``r2 = x² + y²`` and its radial factor."""
        p1, p2 = self.dist[2], self.dist[3]
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def normalized_to_pixels(self, xy_d: np.ndarray) -> np.ndarray:
        return self._pixels(xy_d[:, 0], xy_d[:, 1])

    def _pixels(self, xd, yd) -> np.ndarray:
        """Pixels (N, 2) of distorted normalised coordinates ``xd``, ``yd``."""
        K = self.K
        u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        v = K[1, 1] * yd + K[1, 2]
        return _columns(u, v)

    def pixels_to_normalized_distorted(self, px: np.ndarray) -> np.ndarray:
        K = self.K
        yd = (px[:, 1] - K[1, 2]) / K[1, 1]
        xd = (px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        return _columns(xd, yd)

    def project(self, points_cam_m: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of points (N, 3) in the camera frame (z must be > 0)."""
        p = np.asarray(points_cam_m, dtype=float).reshape(-1, 3)
        xy = p[:, :2] / p[:, 2:3]
        return self.normalized_to_pixels(self.distort_normalized(xy))

    def project_with_jacobian(self, points_cam_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and ``J_px_wrt_point`` (N, 2, 3), distortion included."""
        p = np.asarray(points_cam_m, dtype=float).reshape(-1, 3)
        X, Y, Z = p[:, 0], p[:, 1], p[:, 2]
        x, y = X / Z, Y / Z
        p1, p2 = self.dist[2], self.dist[3]
        r2 = x * x + y * y
        radial, dradial_dr2 = self._radial(r2)
        # d(xd, yd) / d(x, y)
        dxd_dx = radial + 2 * x * x * dradial_dr2 + 2 * p1 * y + 6 * p2 * x
        dxd_dy = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
        dyd_dx = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
        dyd_dy = radial + 2 * y * y * dradial_dr2 + 6 * p1 * y + 2 * p2 * x
        K = self.K
        # d(u, v) / d(xd, yd)
        du_dxd, du_dyd, dv_dyd = K[0, 0], K[0, 1], K[1, 1]
        J_uv_xy = np.empty((p.shape[0], 2, 2))
        J_uv_xy[:, 0, 0] = du_dxd * dxd_dx + du_dyd * dyd_dx
        J_uv_xy[:, 0, 1] = du_dxd * dxd_dy + du_dyd * dyd_dy
        J_uv_xy[:, 1, 0] = dv_dyd * dyd_dx
        J_uv_xy[:, 1, 1] = dv_dyd * dyd_dy
        J_xy_p = np.zeros((p.shape[0], 2, 3))
        J_xy_p[:, 0, 0] = 1.0 / Z
        J_xy_p[:, 0, 2] = -X / Z**2
        J_xy_p[:, 1, 1] = 1.0 / Z
        J_xy_p[:, 1, 2] = -Y / Z**2
        # the pixels from the same x, y, r² and radial factor (what project(p) computes again)
        px = self._pixels(*self._distorted(x, y, r2, radial))
        return px, J_uv_xy @ J_xy_p

    # -- back-projection ------------------------------------------------------------------
    def undistort_normalized(self, px: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Normalised, undistorted coordinates (N, 2) of distorted pixels (N, 2).

        Gauss–Newton on the forward model; exact for the pinhole-only case.
        """
        px = np.asarray(px, dtype=float).reshape(-1, 2)
        xy_d = self.pixels_to_normalized_distorted(px)
        if not self.has_distortion:
            return xy_d
        xy = xy_d.copy()
        for _ in range(iterations):
            pts = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
            pred, J = PinholeCamera(np.eye(3), self.dist).project_with_jacobian(pts)
            r = pred - xy_d
            J2 = J[:, :, :2]  # z = 1, so d/dx and d/dy of the point equal d/d(normalised)
            step = np.linalg.solve(J2, r[:, :, None])[:, :, 0]
            xy = xy - step
            if np.max(np.abs(step)) < 1e-14:
                break
        return xy

    def undistort_pixels(self, px: np.ndarray) -> np.ndarray:
        """Pixels of the ideal (distortion-free) camera with the same K."""
        return self.without_distortion().normalized_to_pixels(self.undistort_normalized(px))

    def rays(self, px: np.ndarray) -> np.ndarray:
        """Unit viewing rays (N, 3) in the camera frame through pixels (N, 2)."""
        xy = self.undistort_normalized(px)
        r = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        return r / np.linalg.norm(r, axis=1, keepdims=True)


def _columns(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 2) of two (N,) columns: ``np.stack([a, b], axis=1)`` without its per-call cost."""
    out = np.empty((len(a), 2), dtype=np.result_type(a, b))
    out[:, 0] = a
    out[:, 1] = b
    return out


#: Ideal (distortion-free) cameras of :func:`ideal_camera`, by their K's bytes; a few at most.
_IDEAL_CAMERAS: dict[bytes, PinholeCamera] = {}


def ideal_camera(K: np.ndarray) -> PinholeCamera:
    """``PinholeCamera(K)``: the distortion-free camera of ``K`` (3, 3), built once per K value
    (the covariance of every frame projects through it; building checks K each time)."""
    K = np.asarray(K, dtype=float)
    key = K.tobytes()
    camera = _IDEAL_CAMERAS.get(key)
    if camera is None:
        camera = PinholeCamera(K)
        if len(_IDEAL_CAMERAS) >= 16:
            _IDEAL_CAMERAS.clear()
        _IDEAL_CAMERAS[key] = camera
    return camera
