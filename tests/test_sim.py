"""Simulator: pixel convention of the renderer, QR orientation, determinism, trajectory,
odometry, camera mount, default-scenario coverage and option validation."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from agvviz.geometry import euler, se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.markers.payload import parse_payload
from agvviz.sim import render as render_module
from agvviz.sim.qr_texture import make_floor_code, qr_symbol_modules
from agvviz.sim.render import FloorCode, FloorScene, encode_jpeg, render_frame, render_irradiance, true_corners_px
from agvviz.sim.trajectory import RoundedRectangleTrack, dead_reckoning, forward_camera_mount, sample_track
from agvviz.scenarios import qr_floor

WHITE_DN, BLACK_DN = 220.0, 25.0


def _camera(width_px, height_px, focal_px, dist=(0.0, 0.0)) -> PinholeCamera:
    K = np.array([[focal_px, 0.0, (width_px - 1) / 2.0], [0.0, focal_px, (height_px - 1) / 2.0], [0.0, 0.0, 1.0]])
    return PinholeCamera(K, np.array([*dist, 0.0, 0.0, 0.0]), width_px, height_px)


def _looking_down(x_m: float, y_m: float, height_m: float) -> np.ndarray:
    """T_world_cam of a camera straight above (x, y): image u along world +x, v along world −y."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    return se3.make(R, [x_m, y_m, height_m])


def _black_square_scene(side_m: float, T_world_marker: np.ndarray) -> FloorScene:
    """One black square (a 1-module 'symbol') in a white quiet zone on a white floor, so the
    only dark area in the image is the square itself."""
    code = FloorCode(
        marker_id="sq",
        payload="",
        T_world_marker=T_world_marker,
        side_m=side_m,
        modules=np.ones((1, 1), dtype=bool),
        points_marker_m=np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]]) * side_m / 2.0,
        quiet_zone_modules=1,
    )
    return FloorScene(codes=(code,), floor_dn=WHITE_DN, black_dn=BLACK_DN, white_dn=WHITE_DN)


def _reference_centroid_and_area(code: FloorCode, camera: PinholeCamera, T_world_cam: np.ndarray, cells: int = 400):
    """Image centroid and area (px²) of the code's square, integrated with the forward model
    only (independent of the renderer's back-projection): the square is cut into cells² small
    quads, each projected with PinholeCamera.project and weighted by its image area."""
    h = code.side_m / 2.0
    t = np.linspace(-h, h, cells + 1)
    X, Y = np.meshgrid(t, t)
    grid = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    T_cam_marker = se3.inverse(T_world_cam) @ code.T_world_marker
    px = camera.project(se3.transform_points(T_cam_marker, grid)).reshape(cells + 1, cells + 1, 2)
    a, b, c, d = px[:-1, :-1], px[:-1, 1:], px[1:, 1:], px[1:, :-1]
    quad = np.stack([a, b, c, d])  # (4, cells, cells, 2)
    x, y = quad[..., 0], quad[..., 1]
    area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=0) - np.roll(x, -1, axis=0) * y, axis=0))
    centre = quad.mean(axis=0)
    return (centre * area[..., None]).sum(axis=(0, 1)) / area.sum(), area.sum()


def _measured_centroid_and_area(image: np.ndarray):
    darkness = (WHITE_DN - image.astype(float)) / (WHITE_DN - BLACK_DN)
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    total = darkness.sum()
    return np.array([(darkness * u).sum(), (darkness * v).sum()]) / total, total


# -- pixel convention (DESIGN §8) ------------------------------------------------------------------
def test_fronto_parallel_square_edges_match_true_corners():
    """Axis-aligned square, no distortion: each edge's sub-pixel position follows from the
    column/row coverage of the area-integrated image and must equal true_corners_px.

    With supersample 8 the coverage of an edge pixel is quantised to 1/8 px, but the edge is
    placed at a fractional position whose error is < 1/16 px per row; averaged over ~80 rows
    at one fixed fraction it is the quantisation of that fraction: we choose fractions that
    are multiples of 1/8 so the expected error is 0 and the tolerance 0.01 px only absorbs
    float32 rounding. A half-pixel slip between renderer and truth moves every edge by 0.5 px.
    """
    camera = _camera(200, 160, 400.0)
    # Square 0.2 m seen from 1 m: 80 px. Centre at pixel (100.375, 79.625).
    T_world_cam = _looking_down(0.0, 0.0, 1.0)
    centre_px = np.array([100.375, 79.625])
    center_m = (centre_px - camera.K[:2, 2]) / 400.0 * np.array([1.0, -1.0])
    scene = _black_square_scene(0.2, se3.make(np.eye(3), [center_m[0], center_m[1], 0.0]))
    image = render_irradiance(scene, camera, T_world_cam, supersample=8)
    coverage = (WHITE_DN - image) / (WHITE_DN - BLACK_DN)
    col_cover = coverage[60:100].mean(axis=0)  # rows fully inside the square
    row_cover = coverage[:, 80:120].mean(axis=1)
    left_px = np.flatnonzero(col_cover > 0)[0] + 0.5 - col_cover[col_cover > 0][0]
    right_px = np.flatnonzero(col_cover > 0)[-1] - 0.5 + col_cover[col_cover > 0][-1]
    top_px = np.flatnonzero(row_cover > 0)[0] + 0.5 - row_cover[row_cover > 0][0]
    bottom_px = np.flatnonzero(row_cover > 0)[-1] - 0.5 + row_cover[row_cover > 0][-1]
    corners = true_corners_px(scene, camera, T_world_cam)["sq"]
    expected = np.array([[left_px, top_px], [right_px, top_px], [right_px, bottom_px], [left_px, bottom_px]])
    np.testing.assert_allclose(corners, expected, atol=0.01)
    np.testing.assert_allclose(corners.mean(axis=0), centre_px, atol=1e-9)


@pytest.mark.parametrize("distorted", [False, True])
def test_rendered_square_centroid_matches_forward_model(distorted):
    """Tilted view of an off-centre square, with and without lens distortion: the darkness
    centroid of the rendered (noise-free, blur-free) image equals the forward-model centroid
    within 0.01 px, and the dark area matches within 0.1 %.

    Supersampling 4×4 with nearest-module look-up makes per-pixel coverage errors ≤ 1/16 px²
    that largely cancel along an edge; measured here: 0.0013 px at s = 4, 0.0001 px at s = 8
    (converging to 0, so no systematic offset). A half-pixel slip (DESIGN §8), or ignoring the
    distortion, which moves this square by ~3 px, fails by a wide margin.
    """
    dist = (-0.05, 0.01) if distorted else (0.0, 0.0)
    camera = _camera(640, 512, 500.0, dist)
    T_world_cam = se3.make(euler.Rz(0.2) @ euler.Rx(0.5) @ np.diag([1.0, -1.0, -1.0]), [0.05, -0.3, 1.2])
    T_world_marker = se3.make(euler.Rz(0.4), [0.55, 0.45, 0.0])  # towards the image corner
    scene = _black_square_scene(0.3, T_world_marker)
    image = render_irradiance(scene, camera, T_world_cam, supersample=4)
    measured, measured_area = _measured_centroid_and_area(image)
    reference, reference_area = _reference_centroid_and_area(scene.codes[0], camera, T_world_cam)
    assert np.all(reference > 20) and reference[0] < 620 and reference[1] < 492  # fully inside
    np.testing.assert_allclose(measured, reference, atol=0.01)
    assert abs(measured_area / reference_area - 1.0) < 1e-3
    if distorted:
        undistorted, _ = _reference_centroid_and_area(scene.codes[0], camera.without_distortion(), T_world_cam)
        assert np.linalg.norm(undistorted - reference) > 2.5  # distortion moves it ~3 px


def test_subsample_ray_expansion_matches_exact_undistortion():
    """The renderer's first-order expansion of the per-pixel undistortion map, at sub-sample
    offsets up to ±0.4 px, agrees with the exact inverse (Gauss–Newton) to < 1e-3 px — the
    second-order remainder is ½·|∂²x/∂u²|·du² ≈ 1e-4 px for this strongly distorted
    short-focal camera."""
    camera = _camera(320, 256, 250.0, (-0.05, 0.01))
    ray_map = render_module._ray_map(camera)
    rng = np.random.default_rng(11)
    u = rng.integers(0, 320, 500)
    v = rng.integers(0, 256, 500)
    du, dv = rng.uniform(-0.4, 0.4, (2, 500))
    x = ray_map.x[v, u] + ray_map.J_x_wrt_u[v, u] * du + ray_map.J_x_wrt_v[v, u] * dv
    y = ray_map.y[v, u] + ray_map.J_y_wrt_u[v, u] * du + ray_map.J_y_wrt_v[v, u] * dv
    exact = camera.undistort_normalized(np.stack([u + du, v + dv], axis=1))
    assert np.max(np.abs(np.stack([x, y], axis=1) - exact)) * 250.0 < 1e-3


# -- QR codes: payload, orientation and corner order ---------------------------------------------
def test_qr_symbol_modules_have_finder_patterns():
    modules = qr_symbol_modules("AGV1;id=A17;mm=1000,2000;1500,2000;1500,1500;1000,1500")
    n = modules.shape[0]
    assert modules.shape == (n, n) and (n - 17) % 4 == 0
    finder = np.ones((7, 7), bool)
    finder[1:6, 1:6] = False
    finder[2:5, 2:5] = True
    for rows, cols in ((slice(0, 7), slice(0, 7)), (slice(0, 7), slice(n - 7, n)), (slice(n - 7, n), slice(0, 7))):
        np.testing.assert_array_equal(modules[rows, cols], finder)
    assert not np.array_equal(modules[n - 7 :, n - 7 :], finder)  # no finder bottom-right


def test_rendered_codes_decode_with_their_payload_and_corner_order():
    """Four codes rotated by 0/90/180/270°: OpenCV decodes each to its own payload, and its
    corners (returned TL, TR, BR, BL as printed) lie within 4 px of true_corners_px in the same
    order — DESIGN §8 measures detectAndDecode corners at ≈1 px RMS, p90 2.3 px; a wrong
    orientation or a mirrored texture would move corners by a whole code side (~100 px)."""
    codes = tuple(
        make_floor_code(f"R{turns}", ((turns % 2) * 0.6 - 0.3, (turns // 2) * 0.6 - 0.3), turns, 0.3)
        for turns in range(4)
    )
    scene = FloorScene(codes=codes)
    camera = _camera(800, 640, 625.0, (-0.05, 0.01))
    T_world_cam = _looking_down(0.0, 0.0, 1.5) @ se3.make(euler.Rz(0.3), [0.0, 0.0, 0.0])
    image = render_frame(scene, camera, T_world_cam, np.random.default_rng(3))
    truth = true_corners_px(scene, camera, T_world_cam)
    assert sorted(truth) == ["R0", "R1", "R2", "R3"]
    detector = cv2.QRCodeDetector()
    for code in codes:
        # Decode each code in its own crop (multi-code detection is less reliable than the
        # single-code path the pipeline measures).
        lo = np.maximum(np.floor(truth[code.marker_id].min(axis=0)).astype(int) - 40, 0)
        hi = np.ceil(truth[code.marker_id].max(axis=0)).astype(int) + 40
        text, points, _ = detector.detectAndDecode(image[lo[1] : hi[1], lo[0] : hi[0]])
        assert text == code.payload
        np.testing.assert_allclose(parse_payload(text).points_world_m, code.points_world_m, atol=1e-9)
        corners = points.reshape(4, 2) + lo
        assert np.max(np.linalg.norm(corners - truth[code.marker_id], axis=1)) < 4.0


def test_make_floor_code_payload_carries_printed_vertices():
    code = make_floor_code("Q1", (1.5, -3.0), 1, 0.5, with_midpoints=True)
    # 90° CCW: the printed top edge (TL → TR) runs along world +y.
    np.testing.assert_allclose(code.points_world_m[0], [1.25, -3.25, 0.0], atol=1e-12)
    np.testing.assert_allclose(code.points_world_m[1], [1.25, -2.75, 0.0], atol=1e-12)
    np.testing.assert_allclose(parse_payload(code.payload).points_world_m, code.points_world_m, atol=1e-12)
    with pytest.raises(ValueError, match="0.1 mm grid"):
        make_floor_code("Q2", (0.00003, 0.0), 0, 0.5)


# -- determinism --------------------------------------------------------------------------------------
def test_render_frame_is_deterministic_and_seeded():
    scene = FloorScene(codes=(make_floor_code("D1", (0.0, 0.0), 2, 0.4),))
    camera = _camera(320, 256, 300.0, (-0.05, 0.01))
    T_world_cam = _looking_down(0.02, -0.03, 1.0)
    a = render_frame(scene, camera, T_world_cam, np.random.default_rng(5))
    b = render_frame(scene, camera, T_world_cam, np.random.default_rng(5))
    c = render_frame(scene, camera, T_world_cam, np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    assert encode_jpeg(a, 95) == encode_jpeg(b, 95)
    # Different seeds differ only by noise: σ = 2 DN each, so the difference has σ ≈ 2.8 DN.
    assert 2.0 < np.std(a.astype(float) - c.astype(float)) < 3.6


class _CapturingWriter:
    """Stands in for RecordingWriter: records every call with its arguments."""

    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        if not name.startswith("write_"):
            raise AttributeError(name)
        return lambda *args: self.calls.append((name, args))


def _record(seed: int, **overrides) -> list:
    """The writer calls of a tiny ideal qr_floor (the typical world adds a realism record and
    capture-time truth samples)."""
    options = dataclasses.replace(
        qr_floor.Options(), duration_s=0.3, width_px=200, height_px=160, focal_px=160.0,
        **{"realism": "ideal", **overrides},
    )
    writer = _CapturingWriter()
    progress = []
    qr_floor.record(writer, options, seed, lambda done, total: progress.append((done, total)))
    assert progress == [(1, 3), (2, 3), (3, 3)]
    return writer.calls


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(a, b)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, PinholeCamera):
        return np.array_equal(a.K, b.K) and np.array_equal(a.dist, b.dist)
    return a == b


def test_record_is_deterministic_and_ordered():
    first, again, other = _record(7), _record(7), _record(8)
    assert _same(first, again)
    images = [args[1] for name, args in first if name == "write_image"]
    other_images = [args[1] for name, args in other if name == "write_image"]
    assert all(a != b for a, b in zip(images, other_images))
    names = [name for name, _ in first]
    assert names[:3] == ["write_calibration", "write_tf_static", "write_marker_map"]
    assert names[3:] == ["write_pose", "write_pose", "write_image"] * 3
    t0 = first[0][1][-1]
    assert all(args[-1] == t0 for _, args in first[:4])
    for k in range(3):
        truth, odom, image = first[3 + 3 * k : 6 + 3 * k]
        assert truth[1][0] == "/agv/ground_truth" and truth[1][2] == "world"
        assert odom[1][0] == "/agv/odometry" and odom[1][2] == "odom"
        assert truth[1][-1] == odom[1][-1] == image[1][-1] == t0 + k * 100_000_000
        assert image[1][0] == "front" and image[1][2] == "jpeg" and image[1][1][:2] == b"\xff\xd8"
    (parent, child, T_agv_cam), = first[1][1][0]
    assert (parent, child) == ("agv", "cam_front")
    marker_map = first[2][1][0]
    assert marker_map["dictionary"] == "qr" and len(marker_map["markers"]) > 20
    for marker in marker_map["markers"][:5]:
        np.testing.assert_allclose(parse_payload(marker["payload"]).points_world_m, marker["corners_world_m"], atol=1e-9)


# -- trajectory, odometry, mount ----------------------------------------------------------------
def test_track_speed_heading_and_turns():
    track = RoundedRectangleTrack(6.0, 3.0, 1.0)
    trajectory = sample_track(track, speed_mps=1.2, rate_hz=20.0, duration_s=track.perimeter_m / 1.2)
    T = trajectory.T_world_agv
    steps = np.diff(T[:, :3, 3], axis=0)
    straight = (trajectory.curvature_per_m[:-1] == 0) & (trajectory.curvature_per_m[1:] == 0)
    # On straights the chord is the arc: speed exact to float rounding.
    np.testing.assert_allclose(np.linalg.norm(steps[straight], axis=1) * 20.0, 1.2, atol=1e-9)
    # AGV y axis (column 1) points along the motion on straights (conventions: y forward).
    forward = steps[straight] / np.linalg.norm(steps[straight], axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("ij,ij->i", T[:-1][straight, :3, 1], forward), 1.0, atol=1e-9)
    # Heading continuous: per step it changes by at most κ·v·Δt = 1/1 · 1.2 / 20.
    dpsi = np.diff(trajectory.heading_rad)
    assert np.all(np.abs(dpsi) <= 0.06 + 1e-9)
    assert np.all(dpsi >= 0)  # counter-clockwise track
    assert np.count_nonzero(trajectory.curvature_per_m > 0) > 0.2 * len(dpsi)  # it turns
    assert trajectory.heading_rad[-1] - trajectory.heading_rad[0] == pytest.approx(2 * np.pi, abs=0.07)
    # heading_rad agrees with the rotation matrix (eq 57 heading).
    for k in range(0, len(T), 37):
        hpr = euler.hpr_from_matrix(T[k, :3, :3])
        assert euler.wrap_angle_rad(hpr[0] - trajectory.heading_rad[k]) == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_array_equal(np.diff(trajectory.log_time_ns), 50_000_000)


def test_dead_reckoning_drift():
    trajectory = sample_track(RoundedRectangleTrack(10.0, 2.0, 1.0), 1.0, 10.0, 4.0)  # a straight
    exact = dead_reckoning(trajectory, np.random.default_rng(0), 0.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(exact, trajectory.T_world_agv, atol=1e-9)
    scaled = dead_reckoning(trajectory, np.random.default_rng(0), 0.02, 0.0, 0.0, 0.0)
    travelled_true = np.linalg.norm(trajectory.T_world_agv[-1, :3, 3] - trajectory.T_world_agv[0, :3, 3])
    travelled_odom = np.linalg.norm(scaled[-1, :3, 3] - scaled[0, :3, 3])
    assert travelled_odom == pytest.approx(1.02 * travelled_true, rel=1e-9)
    biased = dead_reckoning(trajectory, np.random.default_rng(0), 0.0, math.radians(1.0), 0.0, 0.0)
    heading_error = euler.hpr_from_matrix(biased[-1, :3, :3])[0] - euler.hpr_from_matrix(trajectory.T_world_agv[-1, :3, :3])[0]
    assert math.degrees(heading_error) == pytest.approx(3.9, abs=1e-6)  # 39 steps of 0.1 s


def test_forward_camera_mount_axis_hits_floor_ahead():
    T_agv_cam = forward_camera_mount(1.5, 1.0)
    assert se3.is_rigid(T_agv_cam)
    origin, axis = T_agv_cam[:3, 3], T_agv_cam[:3, 2]
    hit = origin + axis * (origin[2] / -axis[2])
    np.testing.assert_allclose(hit, [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T_agv_cam[:3, 0], [1.0, 0.0, 0.0])  # image x = AGV right
    assert T_agv_cam[2, 1] < 0  # image down points towards the floor


# -- scenario ---------------------------------------------------------------------------------------
def test_default_scenario_sees_a_whole_code_in_90_percent_of_frames():
    options = qr_floor.Options()
    scene = qr_floor.build_scene(options, np.random.default_rng(0))
    camera = qr_floor.make_camera(options)
    T_agv_cam = forward_camera_mount(options.cam_height_m, options.cam_lookahead_m)
    trajectory = sample_track(qr_floor.make_track(options), options.speed_mps, options.rate_hz, options.duration_s)
    visible = [len(true_corners_px(scene, camera, T @ T_agv_cam)) for T in trajectory.T_world_agv]
    assert np.mean(np.array(visible) >= 1) >= 0.9
    assert np.mean(np.array(visible) <= 3) >= 0.9  # "1-3 codes usually in view"
    assert np.any(trajectory.curvature_per_m > 0)


def test_options_are_documented():
    for f in dataclasses.fields(qr_floor.Options):
        assert f.type in ("float", "int", "bool", "str"), f.name
        assert f.default is not dataclasses.MISSING, f.name
        assert f.metadata.get("help"), f.name
    qr_floor.validate(qr_floor.Options())


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"duration_s": -1.0}, "duration_s"),
        ({"rate_hz": 0.0}, "rate_hz"),
        ({"cam_height_m": 0.0}, "cam_height_m"),
        ({"cam_height_m": -1.5}, "above the floor"),
        ({"cam_lookahead_m": -0.5}, "cam_lookahead_m"),
        ({"code_size_m": 1.2}, "overlap"),
        ({"code_size_m": 0.50003}, "0.2 mm"),
        ({"jpeg_quality": 0}, "jpeg_quality"),
        ({"supersample": 0}, "supersample"),
        ({"k1": -1.0}, "fold"),
        ({"noise_sigma_dn": float("nan")}, "finite"),
        ({"width_px": 640.5}, "width_px"),
        ({"duration_s": 0.01}, "no frame"),
    ],
)
def test_validate_rejects_bad_options(overrides, message):
    with pytest.raises(ValueError, match=message):
        qr_floor.validate(dataclasses.replace(qr_floor.Options(), **overrides))
