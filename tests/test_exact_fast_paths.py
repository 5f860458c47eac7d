"""The per-frame fast paths of issue 27 compute exactly what the numpy calls they replaced did.

A warm replay's CPU was cut by writing numpy's per-call overhead out of the hot helpers (np.clip,
np.trace, np.linalg.norm, np.mod, np.median, np.stack, np.roll, np.mean on a few values) without
changing one floating-point operation, so a run's ``.rrd`` and every RMSE stay bit-identical. Each
test here holds a fast path equal — ``==``, no tolerance — to the numpy formulation it replaced,
written out below as the reference, on seeded inputs that include the branch edges (angles near 0
and π, ±π, signed zeros, NaN and inf, distorted and ideal cameras).
"""

from __future__ import annotations

import struct
from io import BytesIO

import numpy as np
import pytest
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import Message

from agvviz.geometry import euler, se3, so3
from agvviz.geometry.camera import PinholeCamera, ideal_camera
from agvviz.geometry.plane import quad_area_px2
from agvviz.recording.mcap_records import parse_record
from agvviz.replay.checks.timing import _median
from agvviz.solvers.lm import reprojection_rms_px


def _log_reference(R: np.ndarray) -> np.ndarray:
    """so3.log as it was: np.clip, np.trace and np.linalg.norm."""
    cos_theta = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin_theta = 0.5 * float(np.linalg.norm(w))
    theta = float(np.arctan2(sin_theta, cos_theta))
    if theta < 1e-6:
        return 0.5 * w
    if np.pi - theta < 1e-3:
        B = (R + R.T) / 2.0 - cos_theta * np.eye(3)
        B /= 1.0 - cos_theta
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / np.sqrt(max(B[i, i], 1e-300))
        axis /= np.linalg.norm(axis)
        if np.dot(axis, w) < 0.0:
            axis = -axis
        sin_theta = 0.5 * float(np.dot(axis, w))
        theta = float(np.arctan2(sin_theta, cos_theta))
        return axis * theta
    return w * (theta / (2.0 * sin_theta))


def _rotation_vectors(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    scales = (0.0, 1e-9, 1e-7, 1e-3, 0.5, 2.0, np.pi - 1e-2, np.pi - 1e-5, np.pi)
    out = []
    for k in range(n):
        phi = rng.normal(size=3)
        out.append(phi * scales[k % len(scales)] / np.linalg.norm(phi))
    return out


def test_so3_log_and_exp_equal_their_numpy_formulation():
    rng = np.random.default_rng(11)
    for k, phi in enumerate(_rotation_vectors(3000, 1)):
        theta = float(np.linalg.norm(phi))
        K = so3.hat(phi)
        if theta < 1e-6:
            R_reference = np.eye(3) + K + 0.5 * K @ K
        else:
            s = np.sin(0.5 * theta)
            R_reference = np.eye(3) + np.sin(theta) / theta * K + 2.0 * s * s / (theta * theta) * K @ K
        R = so3.exp(phi)
        assert np.array_equal(R, R_reference)
        if k % 3 == 0:  # off the manifold by a hair, as a product of poses is
            R = R + rng.normal(size=(3, 3)) * 1e-12
        assert np.array_equal(so3.log(R), _log_reference(R))
        T = se3.make(R, rng.normal(size=3))
        assert np.array_equal(so3.log(T[:3, :3]), _log_reference(T[:3, :3]))  # a view, as callers pass
    for R in (np.eye(3), np.diag([1.0, -1.0, -1.0]), np.full((3, 3), np.nan)):
        with np.errstate(invalid="ignore", divide="ignore"):
            assert np.array_equal(so3.log(R), _log_reference(R), equal_nan=True)


def test_wrap_angle_of_one_angle_equals_the_array_path():
    rng = np.random.default_rng(12)
    angles = list(rng.normal(size=4000) * 10.0 ** rng.uniform(-12, 6, 4000)) + [
        0.0, -0.0, np.pi, -np.pi, 2 * np.pi, -3 * np.pi, 1e300, -1e300, np.inf, -np.inf, np.nan,
        np.nextafter(np.pi, 0.0), np.nextafter(-np.pi, 0.0), np.nextafter(-np.pi, -4.0),
    ]
    with np.errstate(invalid="ignore"):
        wrapped_array = euler.wrap_angle_rad(np.array(angles))  # the numpy path, unchanged
        for angle, expected in zip(angles, wrapped_array):
            for value in (float(angle), np.float64(angle)):
                got = euler.wrap_angle_rad(value)
                assert type(got) is float
                assert got == expected or (np.isnan(got) and np.isnan(expected)), angle


def test_hpr_of_a_rotation_equals_np_clip_and_the_array_wrap():
    for phi in _rotation_vectors(600, 2):
        R = so3.exp(phi)
        r32 = float(np.clip(R[2, 1], -1.0, 1.0))
        pitch = float(np.arcsin(r32))
        heading = float(euler.wrap_angle_rad(np.array([np.arctan2(-R[0, 1], R[1, 1])]))[0])
        roll = float(euler.wrap_angle_rad(np.array([np.arctan2(-R[2, 0], R[2, 2])]))[0])
        assert euler.hpr_from_matrix(R, 0.999999) == (heading, pitch, roll)


def test_left_jacobians_and_quaternion_transform_equal_their_numpy_formulation():
    rng = np.random.default_rng(13)
    for phi in _rotation_vectors(900, 3):
        theta = float(np.linalg.norm(phi))
        K = so3.hat(phi)
        if theta >= 1e-6:
            half = theta / 2.0
            c = (1.0 - half / np.tan(half)) / theta**2
            assert np.array_equal(so3.left_jacobian_inv(phi), np.eye(3) - 0.5 * K + c * K @ K)
            b = (theta - np.sin(theta)) / theta**3
            s = np.sin(0.5 * theta)
            assert np.array_equal(so3.left_jacobian(phi), np.eye(3) + 2.0 * s * s / (theta * theta) * K + b * K @ K)
    for _ in range(2000):
        q = rng.normal(size=4) * 10.0 ** rng.uniform(-3, 3)
        t = rng.normal(size=3) * 100.0
        x, y, z, w = (q / np.linalg.norm(q)).tolist()
        R = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        T_reference = np.eye(4)
        T_reference[:3, :3], T_reference[:3, 3] = R, t
        assert np.array_equal(se3.from_quaternion_xyzw(q, t), T_reference)
        assert np.array_equal(se3.from_quaternion_xyzw(list(q), tuple(t)), T_reference)


@pytest.mark.parametrize("dist", [
    np.zeros(5), [-0.12, 0.05, 1e-3, -8e-4, 0.01], [0.1, -0.05, 1e-3, 1e-3, 0.02, 0.03, -0.01, 0.005],
])
def test_projection_with_jacobian_gives_project_s_pixels(dist):
    rng = np.random.default_rng(14)
    camera = PinholeCamera(np.array([[900.0, 0.3, 640.0], [0.0, 910.0, 512.0], [0.0, 0.0, 1.0]]), np.asarray(dist, float))
    for _ in range(200):
        points = rng.normal(size=(int(rng.integers(1, 30)), 3))
        points[:, 2] = rng.uniform(0.2, 8.0, len(points))
        pixels, _ = camera.project_with_jacobian(points)
        assert np.array_equal(pixels, camera.project(points))
        xy = points[:, :2] / points[:, 2:3]
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial, _ = camera._radial(r2)
        p1, p2 = camera.dist[2], camera.dist[3]
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        assert np.array_equal(camera.distort_normalized(xy), np.stack([xd, yd], axis=1))
        K = camera.K
        assert np.array_equal(pixels, np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1))
        # ideal → normalised through K alone, as the undistorted camera's did
        assert np.array_equal(camera.pixels_to_normalized_distorted(pixels),
                              camera.without_distortion().pixels_to_normalized_distorted(pixels))
    assert ideal_camera(camera.K) is ideal_camera(camera.K.copy())  # built once per K
    assert np.array_equal(ideal_camera(camera.K).dist, np.zeros(5))


def test_median_of_steps_equals_np_median():
    rng = np.random.default_rng(15)
    for k in range(3000):
        steps = [int(s) for s in rng.integers(1, 2**40 if k % 2 else 10**8, int(rng.integers(1, 51)))]
        assert _median(steps) == float(np.median(steps))


def test_quad_area_and_reprojection_rms_equal_their_numpy_formulation():
    rng = np.random.default_rng(16)
    K = np.array([[800.0, 0.0, 640.0], [0.0, 800.0, 512.0], [0.0, 0.0, 1.0]])
    for _ in range(1000):
        corners = rng.normal(size=(int(rng.integers(4, 9)), 2)) * 300.0
        x, y = corners[:4, 0], corners[:4, 1]
        assert quad_area_px2(corners) == 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
        n = int(rng.integers(4, 20))
        T = se3.make(so3.exp(rng.normal(size=3) * 0.3), [0.1, -0.2, 4.0])
        points, pixels = rng.normal(size=(n, 3)), rng.normal(size=(n, 2)) * 200.0 + 500.0
        w = se3.transform_points(T, points) @ K.T
        error = w[:, :2] / w[:, 2:3] - pixels
        assert reprojection_rms_px(T, points, pixels, K) == float(np.sqrt(np.mean(np.sum(error**2, axis=-1), axis=-1)))


def test_a_message_record_parses_as_mcap_reads_it():
    rng = np.random.default_rng(17)
    for size in (0, 1, 7, 1000):
        data = rng.bytes(size)
        body = struct.pack("<HIQQ", 7, 123456, 2**62 + 5, 99) + data
        expected = Message.read(ReadDataStream(BytesIO(body)), len(body))
        assert parse_record(Opcode.MESSAGE, body) == expected
    for short in range(22):  # shorter than the fixed fields: a short read, as mcap's own
        with pytest.raises(EndOfFile):
            parse_record(Opcode.MESSAGE, bytes(short))
