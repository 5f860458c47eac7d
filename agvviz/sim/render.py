"""Honest rendering of printed floor codes through a distorted pinhole camera. Numpy/OpenCV only.

Pixel convention (OpenCV, :mod:`agvviz.conventions`): integer pixel coordinates sit at pixel
centres; pixel (u, v) covers [u - 0.5, u + 0.5) × [v - 0.5, v + 0.5). Ground-truth corners from
:func:`true_corners_px` use the same convention through :meth:`PinholeCamera.project`.

Image formation, in order:

1. area integration — every pixel that can see a code is supersampled with s × s samples at
   ``u + a·((i + 0.5)/s - 0.5)`` (pixel aperture a, 1 by default); each sample is back-projected through the lens distortion,
   intersected with the floor and looked up in the code's module grid (nearest module, so module
   edges are exact); the samples are averaged;
   (a code's ``texture_dn``, when given, replaces its module grid: a finer printed texture,
   e.g. with the print effects of :mod:`agvviz.sim.imaging`);
2. optical blur — Gaussian, ``blur_sigma_px``;
3. sensor noise — Gaussian, ``noise_sigma_dn``, from the caller's ``rng``;
4. quantisation to uint8 (JPEG encoding is :func:`encode_jpeg`).

The other error sources of a real camera (defocus, motion blur, rolling shutter, vignetting,
uneven light, shot noise, print effects) are in :mod:`agvviz.sim.imaging`, which builds on
:func:`render_irradiance` (its ``row_range`` renders a band of rows, e.g. at one pose of a
rolling shutter).

Back-projection: the exact inverse distortion is computed once per camera at every pixel centre
(Gauss–Newton of :meth:`PinholeCamera.undistort_normalized`), together with its Jacobian; a
sub-sample at offset (du, dv) ≤ 0.5 px from the centre uses the first-order expansion. The
second-order remainder is ½·|∂²x/∂u²|·du² ≈ 1e-5 px for |k1| ≤ 0.1 on a 1000 px focal length
(checked against :meth:`PinholeCamera.undistort_normalized` in tests/test_sim.py). The floor is a plane, so the map from
undistorted normalised coordinates to code coordinates is an exact homography.
"""

from __future__ import annotations

from agvviz.errors import InputError

from dataclasses import dataclass

import cv2
import numpy as np

from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera


@dataclass(frozen=True)
class FloorCode:
    """One printed code lying on the floor.

    Attributes
    ----------
    marker_id : str
        Identifier carried in the payload.
    payload : str
        The text encoded in the symbol.
    T_world_marker : (4, 4) array
        Marker frame (:mod:`agvviz.conventions`): origin at the symbol centre, z up out of the
        floor, x along the printed top edge, y from the printed bottom edge to the top edge.
    side_m : float
        Side of the symbol between its outer vertices (quiet zone excluded).
    modules : (n, n) bool array
        Dark modules of the symbol as printed: row 0 is the printed top row, column 0 the
        printed left column.
    points_marker_m : (4 | 8, 3) array
        Feature points in the marker frame: TL, TR, BR, BL (+ midpoints top, right, bottom, left).
    quiet_zone_modules : int
        Width of the white margin printed around the symbol, in modules.
    texture_dn : (m, m) float array or None
        The label as printed (symbol + quiet zone), reflectance in digital numbers, with
        m = (n + 2·quiet_zone_modules)·r for an integer r ≥ 1 texels per module; row 0 is the
        printed top. None (default): the ideal print, dark modules ``FloorScene.black_dn`` and
        light ones ``white_dn``.
    """

    marker_id: str
    payload: str
    T_world_marker: np.ndarray
    side_m: float
    modules: np.ndarray
    points_marker_m: np.ndarray
    quiet_zone_modules: int = 4
    texture_dn: np.ndarray | None = None

    @property
    def module_m(self) -> float:
        """Side of one module in metres."""
        return self.side_m / self.modules.shape[0]

    @property
    def label_side_m(self) -> float:
        """Side of the printed label (symbol + quiet zone) in metres."""
        return self.module_m * (self.modules.shape[0] + 2 * self.quiet_zone_modules)

    @property
    def points_world_m(self) -> np.ndarray:
        """Feature points (N, 3) in the world frame."""
        return se3.transform_points(self.T_world_marker, self.points_marker_m)


@dataclass(frozen=True)
class FloorScene:
    """A grey floor (z = 0) with printed codes; reflectances in digital numbers (0–255)."""

    codes: tuple[FloorCode, ...]
    floor_dn: float = 125.0
    black_dn: float = 25.0
    white_dn: float = 220.0


class RenderError(InputError):
    """The camera or render settings cannot produce an image (e.g. zero image size)."""


# -- per-camera back-projection map ------------------------------------------------------------
@dataclass(frozen=True)
class _RayMap:
    """Exact undistorted normalised coordinates at pixel centres and their pixel Jacobian.

    All arrays have shape (height, width). ``x, y`` are float64; ``J_x_wrt_u`` etc. are the
    partial derivatives of the undistorted normalised coordinates w.r.t. the pixel (u, v).
    """

    x: np.ndarray
    y: np.ndarray
    J_x_wrt_u: np.ndarray
    J_x_wrt_v: np.ndarray
    J_y_wrt_u: np.ndarray
    J_y_wrt_v: np.ndarray
    xy_min: tuple[float, float]  # smallest x and y over the image: bounds of the view pyramid
    xy_max: tuple[float, float]


_RAY_MAP_CACHE: dict[tuple, _RayMap] = {}
_RAY_MAP_CACHE_SIZE = 2


def _ray_map(camera: PinholeCamera) -> _RayMap:
    """The camera's :class:`_RayMap`, computed once (≈3 s at 1280×1024) and cached."""
    key = (camera.K.tobytes(), camera.dist.tobytes(), camera.width_px, camera.height_px)
    cached = _RAY_MAP_CACHE.get(key)
    if cached is not None:
        return cached
    u, v = np.meshgrid(np.arange(camera.width_px, dtype=float), np.arange(camera.height_px, dtype=float))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    xy = camera.undistort_normalized(px)
    # d(u, v)/d(x, y) at the undistorted point, inverted: d(x, y)/d(u, v).
    points = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
    _, J_px_wrt_point = camera.project_with_jacobian(points)
    a, b = J_px_wrt_point[:, 0, 0], J_px_wrt_point[:, 0, 1]
    c, d = J_px_wrt_point[:, 1, 0], J_px_wrt_point[:, 1, 1]
    det = a * d - b * c
    shape = (camera.height_px, camera.width_px)
    ray_map = _RayMap(
        x=xy[:, 0].reshape(shape),
        y=xy[:, 1].reshape(shape),
        J_x_wrt_u=(d / det).reshape(shape),
        J_x_wrt_v=(-b / det).reshape(shape),
        J_y_wrt_u=(-c / det).reshape(shape),
        J_y_wrt_v=(a / det).reshape(shape),
        xy_min=(float(xy[:, 0].min()), float(xy[:, 1].min())),
        xy_max=(float(xy[:, 0].max()), float(xy[:, 1].max())),
    )
    if len(_RAY_MAP_CACHE) >= _RAY_MAP_CACHE_SIZE:
        _RAY_MAP_CACHE.pop(next(iter(_RAY_MAP_CACHE)))
    _RAY_MAP_CACHE[key] = ray_map
    return ray_map


def undistorted_rays(camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates (x, y) of every pixel centre, two (height, width)
    float64 arrays (read-only, cached with the camera's back-projection map)."""
    _check_camera(camera)
    ray_map = _ray_map(camera)
    x, y = ray_map.x.view(), ray_map.y.view()
    x.flags.writeable = False
    y.flags.writeable = False
    return x, y


def _check_camera(camera: PinholeCamera) -> None:
    if camera.width_px <= 0 or camera.height_px <= 0:
        raise RenderError(
            f"camera image size is {camera.width_px}×{camera.height_px} px; give width_px and "
            "height_px > 0 to render"
        )


# -- geometry helpers ------------------------------------------------------------------------------
def _clip_polygon(points: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Sutherland–Hodgman: the part of a convex polygon (N, 3) where ``normal · p ≥ offset``."""
    if points.shape[0] == 0:
        return points
    side = points @ normal - offset
    kept = []
    for i in range(points.shape[0]):
        j = (i + 1) % points.shape[0]
        if side[i] >= 0:
            kept.append(points[i])
        if (side[i] >= 0) != (side[j] >= 0):
            t = side[i] / (side[i] - side[j])
            kept.append(points[i] + t * (points[j] - points[i]))
    return np.array(kept).reshape(-1, 3)


def _label_bbox_px(
    code: FloorCode, camera: PinholeCamera, ray_map: _RayMap, T_cam_marker: np.ndarray
) -> tuple[int, int, int, int] | None:
    """Pixel rows/columns ``(v0, v1, u0, u1)`` (half-open) that can see the label, or None.

    The label square is clipped (in the camera frame) to the pyramid spanned by the
    undistorted rays of all image pixels; the clipped polygon's edges, sampled densely and
    projected with distortion, bound the pixels that see it.
    """
    h = code.label_side_m / 2.0
    square_marker = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    polygon = se3.transform_points(T_cam_marker, square_marker)
    # The pyramid through the pixel centres, widened by ~2 px so the outer half of the border
    # pixels (their sub-samples reach 0.5 px beyond the centres) is inside it too.
    pad_x, pad_y = 2.0 / camera.K[0, 0], 2.0 / camera.K[1, 1]
    x_min, y_min = ray_map.xy_min[0] - pad_x, ray_map.xy_min[1] - pad_y
    x_max, y_max = ray_map.xy_max[0] + pad_x, ray_map.xy_max[1] + pad_y
    for normal, offset in (
        ((0.0, 0.0, 1.0), 1e-6),  # in front of the camera
        ((1.0, 0.0, -x_min), 0.0),  # x ≥ x_min·z
        ((-1.0, 0.0, x_max), 0.0),  # x ≤ x_max·z
        ((0.0, 1.0, -y_min), 0.0),
        ((0.0, -1.0, y_max), 0.0),
    ):
        polygon = _clip_polygon(polygon, np.array(normal), offset)
    if polygon.shape[0] < 3:
        return None
    t = np.linspace(0.0, 1.0, 32, endpoint=False)[:, None]
    edges = [polygon[i] + t * (polygon[(i + 1) % len(polygon)] - polygon[i]) for i in range(len(polygon))]
    px = camera.project(np.concatenate(edges))
    margin = 2  # whole pixels beyond the projected outline (sub-sample footprint ±0.5 px)
    u0 = max(int(np.floor(px[:, 0].min())) - margin, 0)
    u1 = min(int(np.ceil(px[:, 0].max())) + margin + 1, camera.width_px)
    v0 = max(int(np.floor(px[:, 1].min())) - margin, 0)
    v1 = min(int(np.ceil(px[:, 1].max())) + margin + 1, camera.height_px)
    if u0 >= u1 or v0 >= v1:
        return None
    return v0, v1, u0, u1


def codes_in_view(scene: FloorScene, camera: PinholeCamera, T_world_cam: np.ndarray) -> tuple[int, ...]:
    """Indexes of the scene's codes of which some part of the label (quiet zone included) may
    be seen by the camera at ``T_world_cam``: the codes :func:`render_irradiance` draws."""
    _check_camera(camera)
    ray_map = _ray_map(camera)
    T_cam_world = se3.inverse(np.asarray(T_world_cam, dtype=float))
    return tuple(
        index
        for index, code in enumerate(scene.codes)
        if _label_bbox_px(code, camera, ray_map, T_cam_world @ code.T_world_marker) is not None
    )


def _subsample_offsets_px(supersample: int) -> np.ndarray:
    """Offsets (s, ) of the sub-samples from the pixel centre: (i + 0.5)/s − 0.5."""
    return (np.arange(supersample) + 0.5) / supersample - 0.5


# -- rendering -------------------------------------------------------------------------------------
def render_irradiance(
    scene: FloorScene,
    camera: PinholeCamera,
    T_world_cam: np.ndarray,
    supersample: int = 4,
    *,
    row_range: tuple[int, int] | None = None,
    pixel_aperture: float = 1.0,
) -> np.ndarray:
    """Area-integrated reflectance image (height, width) float32 in DN: no blur, no noise.

    Parameters
    ----------
    scene : FloorScene
    camera : PinholeCamera
        Full model, distortion included; ``width_px``/``height_px`` must be set.
    T_world_cam : (4, 4) array
        Camera pose in the world.
    supersample : int
        s: each pixel is integrated with s × s samples.
    row_range : (start, stop) or None
        Render only the rows ``start ≤ v < stop`` (the other rows hold the floor's value);
        None renders every row. Each row's values do not depend on the range.
    pixel_aperture : float
        Side of the square each pixel integrates over, as a fraction of the pixel pitch
        (0 < a ≤ 1): 1 is the whole pixel; a small value point-samples the pixel centre, as a
        sensor read out in a decimation (line-skipping) mode or an image downscaled by
        dropping pixels does — edges then alias.
    """
    _check_camera(camera)
    if supersample < 1:
        raise RenderError(f"supersample must be ≥ 1, got {supersample}")
    if not 0 < pixel_aperture <= 1:
        raise RenderError(f"pixel_aperture must lie in (0, 1], got {pixel_aperture}")
    row_start, row_stop = (0, camera.height_px) if row_range is None else row_range
    if not 0 <= row_start < row_stop <= camera.height_px:
        raise RenderError(
            f"row_range {row_range} must satisfy 0 ≤ start < stop ≤ height_px ({camera.height_px})"
        )
    for code in scene.codes:
        _check_texture(code)
    image = np.full((camera.height_px, camera.width_px), scene.floor_dn, dtype=np.float32)
    ray_map = _ray_map(camera)
    T_cam_world = se3.inverse(np.asarray(T_world_cam, dtype=float))
    for code in scene.codes:
        T_cam_marker = T_cam_world @ code.T_world_marker
        # (X, Y, 1) on the marker plane → camera point: M @ (X, Y, 1).
        M = np.stack([T_cam_marker[:3, 0], T_cam_marker[:3, 1], T_cam_marker[:3, 3]], axis=1)
        if abs(np.linalg.det(M)) < 1e-12:
            continue  # camera centre on the floor plane: the floor is seen edge-on
        bbox = _label_bbox_px(code, camera, ray_map, T_cam_marker)
        if bbox is None:
            continue
        v0, v1, u0, u1 = bbox
        v0, v1 = max(v0, row_start), min(v1, row_stop)
        if v0 >= v1:
            continue
        image[v0:v1, u0:u1] += _integrate_label(
            code, scene, ray_map, M, (v0, v1, u0, u1), supersample, pixel_aperture
        )
    return image


def _texels_per_module(code: FloorCode) -> int:
    """r: texels per module of the code's texture (1 for the ideal print)."""
    if code.texture_dn is None:
        return 1
    return code.texture_dn.shape[0] // (code.modules.shape[0] + 2 * code.quiet_zone_modules)


def _check_texture(code: FloorCode) -> None:
    """RenderError unless ``code.texture_dn`` is None or (m, m) finite with m = (n + 2q)·r."""
    if code.texture_dn is None:
        return
    texture = np.asarray(code.texture_dn)
    modules = code.modules.shape[0] + 2 * code.quiet_zone_modules
    m = texture.shape[0] if texture.ndim == 2 else 0
    if texture.ndim != 2 or texture.shape[1] != m or m < modules or m % modules:
        raise RenderError(
            f"code {code.marker_id}: texture_dn has shape {texture.shape}; it must be square with a "
            f"side that is a multiple of the label's {modules} modules"
        )
    if not np.all(np.isfinite(texture)):
        raise RenderError(f"code {code.marker_id}: texture_dn holds non-finite values")


def _label_texture_dn(code: FloorCode, scene: FloorScene) -> np.ndarray:
    """Label reflectance minus the floor's, (m + 2)² float32, m = (n + 2q)·r texels.

    The printed label — the symbol's modules inside a white quiet zone of q modules, or the
    code's ``texture_dn`` — inside a one-texel ring of floor (value 0) that stands for the
    whole floor beyond the label.
    """
    if code.texture_dn is not None:
        label = np.asarray(code.texture_dn, dtype=float) - scene.floor_dn
        return np.pad(label, 1, constant_values=0.0).astype(np.float32)
    q = code.quiet_zone_modules
    dark = np.pad(code.modules, q, constant_values=False)
    label = np.where(dark, scene.black_dn, scene.white_dn) - scene.floor_dn
    return np.pad(label, 1, constant_values=0.0).astype(np.float32)


def _integrate_label(
    code: FloorCode,
    scene: FloorScene,
    ray_map: _RayMap,
    M: np.ndarray,
    bbox: tuple[int, int, int, int],
    supersample: int,
    pixel_aperture: float = 1.0,
) -> np.ndarray:
    """Area-integrated (label − floor) reflectance over the pixel box ``bbox`` (float32).

    ``M`` (3×3) maps marker-plane points (X, Y, 1) to camera points. A pixel whose four extreme
    sub-samples fall in texels that all have one value is uniform: the sub-samples are a
    projective image of a square grid, so they all lie in the texel range spanned by those four
    (convexity), and its value is exact without the other sub-samples. Only the remaining
    pixels (module edges) are integrated sample by sample.
    """
    v0, v1, u0, u1 = bbox
    texture = _label_texture_dn(code, scene)
    n_padded = texture.shape[0]
    # Homography from undistorted normalised (x, y, 1) to padded-texture (column, row, 1):
    # texel k covers [k, k + 1); row 0 of the label (printed top) is texel row 1.
    half = code.label_side_m / 2.0
    m = code.module_m / _texels_per_module(code)  # texel side (the module's for r = 1)
    T_tex_marker = np.array([[1.0 / m, 0.0, half / m + 1.0], [0.0, -1.0 / m, half / m + 1.0], [0.0, 0.0, 1.0]])
    H = T_tex_marker @ np.linalg.inv(M)
    # The homogeneous w of H @ (x, y, 1) is 1/z_cam: > 0 for floor points in front.
    x = ray_map.x[v0:v1, u0:u1].ravel()
    y = ray_map.y[v0:v1, u0:u1].ravel()
    J_x_wrt_u = ray_map.J_x_wrt_u[v0:v1, u0:u1].ravel()
    J_x_wrt_v = ray_map.J_x_wrt_v[v0:v1, u0:u1].ravel()
    J_y_wrt_u = ray_map.J_y_wrt_u[v0:v1, u0:u1].ravel()
    J_y_wrt_v = ray_map.J_y_wrt_v[v0:v1, u0:u1].ravel()
    # Per pixel: homogeneous texture coordinates at the centre (a) and their rates per pixel
    # of sub-sample offset along u (b_u) and v (b_v); rows are (column, row, w).
    a = np.stack([H[k, 0] * x + H[k, 1] * y + H[k, 2] for k in range(3)]).astype(np.float32)
    b_u = np.stack([H[k, 0] * J_x_wrt_u + H[k, 1] * J_y_wrt_u for k in range(3)]).astype(np.float32)
    b_v = np.stack([H[k, 0] * J_x_wrt_v + H[k, 1] * J_y_wrt_v for k in range(3)]).astype(np.float32)

    def texel(a_, b_u_, b_v_, du, dv):
        """(texel row, texel column, in front) of the sub-sample at offset (du, dv)."""
        h = a_ + du * b_u_ + dv * b_v_
        in_front = h[2] > 0
        inv_w = 1.0 / np.where(in_front, h[2], 1.0)
        col = np.clip(np.floor(h[0] * inv_w), 0, n_padded - 1).astype(np.intp)
        row = np.clip(np.floor(h[1] * inv_w), 0, n_padded - 1).astype(np.intp)
        return row, col, in_front

    offsets = (_subsample_offsets_px(supersample) * pixel_aperture).astype(np.float32)
    lo, hi = offsets[0], offsets[-1]
    extreme = [texel(a, b_u, b_v, du, dv) for du, dv in ((lo, lo), (hi, lo), (lo, hi), (hi, hi))]
    rows = np.stack([e[0] for e in extreme])
    cols = np.stack([e[1] for e in extreme])
    r_min, r_max = rows.min(axis=0), rows.max(axis=0)
    c_min, c_max = cols.min(axis=0), cols.max(axis=0)
    value = texture[r_min, c_min]
    uniform = (
        np.logical_and.reduce([e[2] for e in extreme])
        & (r_max - r_min <= 1)
        & (c_max - c_min <= 1)
        & (texture[r_min, c_max] == value)
        & (texture[r_max, c_min] == value)
        & (texture[r_max, c_max] == value)
    )
    out = np.where(uniform, value, np.float32(0.0))
    mixed = np.flatnonzero(~uniform)
    if mixed.size:
        a_m, b_u_m, b_v_m = a[:, mixed], b_u[:, mixed], b_v[:, mixed]
        acc = np.zeros(mixed.size, dtype=np.float32)
        for dv in offsets:
            for du in offsets:
                row, col, in_front = texel(a_m, b_u_m, b_v_m, du, dv)
                acc += np.where(in_front, texture[row, col], np.float32(0.0))
        out[mixed] = acc / np.float32(supersample * supersample)
    return out.reshape(v1 - v0, u1 - u0)


def render_frame(
    scene: FloorScene,
    camera: PinholeCamera,
    T_world_cam: np.ndarray,
    rng: np.random.Generator,
    *,
    supersample: int = 4,
    blur_sigma_px: float = 0.8,
    noise_sigma_dn: float = 2.0,
) -> np.ndarray:
    """One camera frame (height, width) uint8 gray: area integration, blur, noise, quantisation.

    ``rng`` supplies the sensor noise only (one draw of height × width normals when
    ``noise_sigma_dn > 0``), so equal rng states give identical frames.
    """
    if blur_sigma_px < 0 or noise_sigma_dn < 0:
        raise RenderError(
            f"blur_sigma_px ({blur_sigma_px}) and noise_sigma_dn ({noise_sigma_dn}) must be ≥ 0"
        )
    image = render_irradiance(scene, camera, T_world_cam, supersample)
    if blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    if noise_sigma_dn > 0:
        image += np.float32(noise_sigma_dn) * rng.standard_normal(image.shape, dtype=np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def encode_jpeg(image: np.ndarray, quality: int = 95) -> bytes:
    """JPEG bytes of a uint8 gray image (OpenCV encoder, deterministic)."""
    if not 1 <= quality <= 100:
        raise RenderError(f"JPEG quality must lie in 1..100, got {quality}")
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RenderError("OpenCV failed to JPEG-encode the frame")
    return buffer.tobytes()


def true_corners_px(
    scene: FloorScene, camera: PinholeCamera, T_world_cam: np.ndarray, margin_px: float = 0.0
) -> dict[str, np.ndarray]:
    """True pixel positions (N, 2) of the feature points of every wholly visible code.

    A code is visible when its whole symbol (its outline, sampled along the edges so lens
    distortion is respected) lies in front of the camera and inside the image shrunk by
    ``margin_px`` (image edges at −0.5 and size − 0.5). Points are in the payload's order
    TL, TR, BR, BL (+ midpoints), projected with the full camera model.
    """
    _check_camera(camera)
    if not scene.codes:
        return {}
    T_cam_world = se3.inverse(np.asarray(T_world_cam, dtype=float))
    # Outline of the unit symbol (side 1), 8 intervals per edge, scaled per code below.
    t = np.linspace(-0.5, 0.5, 9)
    unit_outline = np.concatenate(
        [
            np.stack([t, np.full_like(t, 0.5)], axis=1),
            np.stack([t, np.full_like(t, -0.5)], axis=1),
            np.stack([np.full_like(t, 0.5), t], axis=1),
            np.stack([np.full_like(t, -0.5), t], axis=1),
        ]
    )
    outlines_cam = []
    for code in scene.codes:
        T_cam_marker = T_cam_world @ code.T_world_marker
        outlines_cam.append(unit_outline * code.side_m @ T_cam_marker[:3, :2].T + T_cam_marker[:3, 3])
    outlines_cam = np.stack(outlines_cam)  # (codes, points, 3)
    in_front = np.all(outlines_cam[:, :, 2] > 1e-6, axis=1)
    candidates = outlines_cam[in_front]
    px = camera.project(candidates.reshape(-1, 3)).reshape(candidates.shape[0], -1, 2)
    lo = -0.5 + margin_px
    hi = np.array([camera.width_px - 0.5 - margin_px, camera.height_px - 0.5 - margin_px])
    inside = np.all((px >= lo) & (px <= hi), axis=(1, 2))
    corners: dict[str, np.ndarray] = {}
    for index in np.flatnonzero(in_front)[inside]:
        code = scene.codes[index]
        T_cam_marker = T_cam_world @ code.T_world_marker
        corners[code.marker_id] = camera.project(se3.transform_points(T_cam_marker, code.points_marker_m))
    return corners
