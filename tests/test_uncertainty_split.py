"""The covariance split into common-mode factors (agvviz.solvers.uncertainty.frame_covariance_split)
and the covariance of the difference of two poses that share them (difference_covariance): the
signed factors against finite differences of re-solving, and the difference's covariance
against a Monte-Carlo of two frames drawn with one calibration, extrinsic and map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agvviz.geometry import se3, so3
from agvviz.geometry.camera import PinholeCamera
from agvviz.geometry.euler import Rx, Ry, Rz
from agvviz.solvers import uncertainty as unc
from agvviz.solvers.lm_batch import refine_lm_batch
from tests.test_uncertainty_systematic import (
    K, MARKERS, SIGMA_PX, SIGMAS, T_AGV_CAM, T_CAM_WORLD, T_WORLD_AGV, _outline_sigma, _pixels, _points_F, _solve,
)

IDS = ["A", "B"]


def _split(T_cam_F, markers=MARKERS, ids=IDS, T_agv_cam=T_AGV_CAM, objective="pixel", sigmas=SIGMAS, sigma_px=SIGMA_PX):
    T_world_cam = se3.inverse(T_cam_F)
    return unc.frame_covariance_split(T_cam_F, markers, ids, K, sigma_px, sigmas, T_world_cam,
                                      T_world_cam @ se3.inverse(T_agv_cam), T_agv_cam, True, objective)


@pytest.mark.parametrize("objective", ["pixel", "depth"])
def test_split_adds_up_to_the_full_covariance(objective):
    cov, groups = _split(T_CAM_WORLD, objective=objective)
    full, _ = unc.frame_covariance_full(T_CAM_WORLD, MARKERS, K, SIGMA_PX, SIGMAS, T_WORLD_AGV @ T_AGV_CAM, T_WORLD_AGV,
                                        T_AGV_CAM, True, objective)
    np.testing.assert_allclose(cov, full, rtol=1e-9, atol=1e-12 * np.max(np.abs(full)))
    assert set(groups) == {unc.CAMERA_GROUP, "marker:A", "marker:B"}
    assert groups[unc.CAMERA_GROUP].shape == (6, 14) and groups["marker:A"].shape == (6, 1 + 7)  # the outline, the map entry


def _world_agv(T_cam_F, T_agv_cam=T_AGV_CAM):
    return se3.inverse(T_cam_F) @ se3.inverse(T_agv_cam)


def test_signed_factors_match_finite_differences_of_re_solving():
    """Each column of a factor is the pose's change (left, world) for a one-σ error of one
    parameter: central differences of the re-solved T_world_agv, sign included."""
    _, groups = _split(T_CAM_WORLD)
    points_true = _points_F(MARKERS)
    px_true = _pixels(T_CAM_WORLD, points_true)

    def column(sigma, step, pose_at):
        return sigma * (unc.left_error(pose_at(step), T_WORLD_AGV) - unc.left_error(pose_at(-step), T_WORLD_AGV)) / (2 * step)

    numeric = []
    for (i, j), sigma in (((0, 0), SIGMAS.focal_px), ((1, 1), SIGMAS.focal_px),
                          ((0, 2), SIGMAS.principal_point_px), ((1, 2), SIGMAS.principal_point_px)):
        def at(e, i=i, j=j):
            Kp = K.copy()
            Kp[i, j] += e  # the recorded K off by e
            r = refine_lm_batch(T_CAM_WORLD[None], points_true[None], px_true[None], Kp, objective="pixel",
                                max_iterations=200, step_tol=1e-15, cost_rel_tol=1e-18)
            return _world_agv(r.T_cam_marker[0])
        numeric.append(column(sigma, 1e-2, at))
    for k, sigma in enumerate((SIGMAS.k1, SIGMAS.k2, SIGMAS.p1, SIGMAS.p2)):
        def at(e, k=k):
            dist = np.zeros(5)
            dist[k] = e
            return _world_agv(_solve(points_true, PinholeCamera(K, dist=dist).undistort_pixels(px_true), "pixel"))
        numeric.append(column(sigma, 1e-5, at))
    for p, sigma in enumerate([SIGMAS.extrinsic_translation_m] * 3 + [SIGMAS.extrinsic_rotation_rad] * 3):
        def at(e, p=p):
            d = np.zeros(6)
            d[p] = e
            recorded = se3.make(so3.exp(d[3:]) @ T_AGV_CAM[:3, :3], T_AGV_CAM[:3, 3] + d[:3])
            return _world_agv(T_CAM_WORLD, recorded)
        numeric.append(column(sigma, 1e-6, at))
    camera = np.column_stack(numeric)
    scale = np.max(np.abs(camera))
    np.testing.assert_allclose(groups[unc.CAMERA_GROUP], camera, atol=2e-3 * scale)

    T, x = MARKERS[0]
    # The marker's outline grown by a fraction e about its centre (its corners are centred on its
    # origin), σ of e = corner_bias_px ÷ its RMS pixel radius: one column.
    sigma_s = _outline_sigma(_pixels(T_CAM_WORLD, se3.transform_points(T, x)))
    numeric = []

    # (the sign convention of the map's columns below: the recorded outline grown, the pixels true)
    def at_outline(e):
        moved = [(T, x * (1.0 + e))] + MARKERS[1:]
        return _world_agv(_solve(_points_F(moved), px_true, "pixel"))

    numeric.append(column(sigma_s, 1e-5, at_outline))
    map_sigmas = (SIGMAS.map_position_m, SIGMAS.map_position_m, SIGMAS.map_height_m,
                  SIGMAS.map_tilt_rad, SIGMAS.map_tilt_rad, SIGMAS.map_yaw_rad, SIGMAS.map_scale)
    for p, sigma in enumerate(map_sigmas):
        def at(e, p=p):
            d = np.zeros(7)
            d[p] = e
            moved = [(se3.make(T[:3, :3] @ so3.exp(d[3:6]), T[:3, 3] + d[:3]), x * (1.0 + d[6]))] + MARKERS[1:]
            return _world_agv(_solve(_points_F(moved), px_true, "pixel"))
        numeric.append(column(sigma, 1e-5, at))
    marker = np.column_stack(numeric)
    np.testing.assert_allclose(groups["marker:A"], marker, atol=2e-3 * np.max(np.abs(marker)))


#: A second frame: the AGV 0.25 m on and turned 8°, the camera seeing marker A again and a third one.
STEP = se3.make(Rz(math.radians(8.0)), [0.05, 0.25, 0.0])
T_WORLD_AGV_B = T_WORLD_AGV @ STEP
T_CAM_WORLD_B = se3.inverse(T_WORLD_AGV_B @ T_AGV_CAM)
MARKERS_B = [MARKERS[0], (se3.make(Rz(0.7), [1.5, 1.2, 0.0]), MARKERS[0][1])]
IDS_B = ["A", "C"]


def test_difference_covariance_matches_monte_carlo_of_two_frames():
    """400 draws of one camera (intrinsics, distortion, extrinsic) and one map (markers A, B, C,
    their corners) seen in two frames with independent pixel noise; both solved by LM. The
    difference between frame b's pose and frame a's carried on by the true step, against
    difference_covariance: mean d² 6 ± 0.75 (±4.4 standard errors of a χ²₆ mean over 400). The
    sum of the two covariances (common sources counted twice) misses it by far."""
    sigmas = SIGMAS
    rng = np.random.default_rng(7)
    trials = 400
    shapes = {"A": MARKERS[0], "B": MARKERS[1], "C": MARKERS_B[1]}
    pixels = {"a": [], "b": []}
    recorded_ext = []
    for _ in range(trials):
        true = {}
        for name, (T, x) in shapes.items():
            d = rng.standard_normal(7) * [sigmas.map_position_m, sigmas.map_position_m, sigmas.map_height_m,
                                          sigmas.map_tilt_rad, sigmas.map_tilt_rad, sigmas.map_yaw_rad, sigmas.map_scale]
            bias = rng.standard_normal()  # the outline's shift in units of its σ: the same in both frames
            true[name] = (se3.make(T[:3, :3] @ Rz(d[5]) @ Rx(d[3]) @ Ry(d[4]), T[:3, 3] + d[:3]), x * (1.0 + d[6]), bias)
        K_true = K.copy()
        K_true[0, 0] += sigmas.focal_px * rng.standard_normal()
        K_true[1, 1] += sigmas.focal_px * rng.standard_normal()
        K_true[0, 2] += sigmas.principal_point_px * rng.standard_normal()
        K_true[1, 2] += sigmas.principal_point_px * rng.standard_normal()
        dist = np.zeros(5)
        dist[:4] = rng.standard_normal(4) * [sigmas.k1, sigmas.k2, sigmas.p1, sigmas.p2]
        for frame, T_cam_F, names in (("a", T_CAM_WORLD, IDS), ("b", T_CAM_WORLD_B, IDS_B)):
            points = []
            for name in names:
                T_true, x_true, bias = true[name]
                x_map = shapes[name][1]
                # the outline grown by `bias` σ: a fixed shift in pixels, a fraction of each frame's view
                sigma_s = _outline_sigma(_pixels(T_cam_F, se3.transform_points(shapes[name][0], x_map)))
                points.append(se3.transform_points(T_true, x_true * (1.0 + bias * sigma_s)))
            raw = _pixels(T_cam_F, np.vstack(points), K_true) + SIGMA_PX * rng.standard_normal((4 * len(names), 2))
            pixels[frame].append(PinholeCamera(K, dist=dist).undistort_pixels(raw))
        dphi = rng.standard_normal(3) * sigmas.extrinsic_rotation_rad
        dt = rng.standard_normal(3) * sigmas.extrinsic_translation_m
        recorded_ext.append(se3.make(so3.exp(dphi) @ T_AGV_CAM[:3, :3], T_AGV_CAM[:3, 3] + dt))
    solved = {}
    for frame, T_cam_F, markers in (("a", T_CAM_WORLD, MARKERS), ("b", T_CAM_WORLD_B, MARKERS_B)):
        points = _points_F(markers)
        r = refine_lm_batch(np.broadcast_to(T_cam_F, (trials, 4, 4)).copy(),
                            np.broadcast_to(points, (trials,) + points.shape), np.array(pixels[frame]), K, objective="pixel")
        assert r.ok.all()
        solved[frame] = r.T_cam_marker
    d2_split, d2_sum = [], []
    for T_a_cam_F, T_b_cam_F, T_agv_cam in zip(solved["a"], solved["b"], recorded_ext):
        cov_a, fac_a = _split(T_a_cam_F, T_agv_cam=T_agv_cam)
        cov_b, fac_b = _split(T_b_cam_F, MARKERS_B, IDS_B, T_agv_cam=T_agv_cam)
        T_a, T_b = _world_agv(T_a_cam_F, T_agv_cam), _world_agv(T_b_cam_F, T_agv_cam)
        carried = T_a @ STEP
        delta = np.concatenate([T_b[:3, 3] - carried[:3, 3], so3.log(T_b[:3, :3] @ carried[:3, :3].T)])
        C = unc.difference_covariance(cov_a, fac_a, carried[:3, 3], cov_b, fac_b, T_b[:3, 3])
        d2_split.append(float(delta @ np.linalg.solve(C, delta)))
        C_sum = unc.difference_covariance(cov_a, None, carried[:3, 3], cov_b, None, T_b[:3, 3])
        d2_sum.append(float(delta @ np.linalg.solve(C_sum, delta)))
    assert 5.25 <= np.mean(d2_split) <= 6.75, np.mean(d2_split)
    assert np.mean(d2_sum) < 3.0, np.mean(d2_sum)


def test_difference_of_a_pose_with_itself_is_its_noise_alone():
    """The same frame compared with itself: every common source cancels exactly, the two
    independent noise draws remain (2 × the pixel-noise share)."""
    cov, groups = _split(T_CAM_WORLD)
    p = T_WORLD_AGV[:3, 3]
    C = unc.difference_covariance(cov, groups, p, cov, groups, p)
    noise = unc.covariance_world_agv(unc.covariance(T_CAM_WORLD, _points_F(MARKERS), K, SIGMA_PX), se3.inverse(T_CAM_WORLD))
    J = np.eye(6)
    J[:3, 3:] = -so3.hat(p)
    np.testing.assert_allclose(C, 2 * J @ noise @ J.T, rtol=1e-8, atol=1e-14)
