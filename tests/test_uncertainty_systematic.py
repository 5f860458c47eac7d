"""The full pose covariance (agvviz.solvers.uncertainty.frame_covariance_full): each systematic
source against finite differences of re-solving, NEES consistency when the errors are drawn from
exactly the modelled distribution, the pixel-only mode as before, the settings' defaults against
the ``typical`` realism profile, and the ellipsoid's one magnification in its label."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from agvviz.geometry import se3, so3
from agvviz.geometry.camera import PinholeCamera
from agvviz.geometry.euler import Rx, Ry, Rz
from agvviz.geometry.plane import square_points_marker
from agvviz.settings import RunSettings
from agvviz.sim.realism import PROFILES
from agvviz.solvers import uncertainty as unc
from agvviz.solvers.lm_batch import refine_lm_batch

K = np.array([[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]])
CORNERS = square_points_marker(0.5)  # (4, 3), centred, z = 0
#: Two floor codes in the world (frame F = world) and a camera 1.5 m up looking ahead and down.
MARKERS = [
    (se3.make(Rz(0.2), [0.9, -0.3, 0.0]), CORNERS),
    (se3.make(Rz(-0.4), [1.8, 0.5, 0.0]), CORNERS),
]
T_WORLD_CAM = se3.make(Rz(0.1) @ np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) @ Rx(-0.6), [0.0, 0.0, 1.5])
T_CAM_WORLD = se3.inverse(T_WORLD_CAM)
#: Camera on the AGV: ahead of the AGV origin and up.
T_AGV_CAM = se3.make(T_WORLD_CAM[:3, :3], [0.4, 0.05, 1.5])
T_WORLD_AGV = T_WORLD_CAM @ se3.inverse(T_AGV_CAM)
#: Large enough that every source matters against the noise, small enough for first order.
SIGMAS = unc.SystematicSigmas(
    corner_bias_px=0.3, focal_px=2.0, principal_point_px=2.0, k1=1e-3, k2=5e-4, p1=2e-4, p2=2e-4,
    extrinsic_rotation_rad=math.radians(0.1), extrinsic_translation_m=1e-3,
    map_position_m=1e-3, map_height_m=1e-3, map_yaw_rad=math.radians(0.1), map_tilt_rad=math.radians(0.1),
    map_scale=1e-3,
)
SIGMA_PX = 0.2


def _points_F(markers):
    return np.vstack([se3.transform_points(T, x) for T, x in markers])


def _pixels(T_cam_F, points_F, Kmat=K):
    w = se3.transform_points(T_cam_F, points_F)
    return (w @ Kmat.T)[:, :2] / w[:, 2:3]


def _solve(points_F, pixels, objective, start=T_CAM_WORLD):
    """LM (the production batch solver) from ``start``, tolerances at machine precision."""
    result = refine_lm_batch(
        np.asarray(start)[None], points_F[None], pixels[None], K, objective=objective,
        max_iterations=200, step_tol=1e-15, cost_rel_tol=1e-18,
    )
    assert result.ok[0]
    return result.T_cam_marker[0]


def _outline_sigma(pixels_px):
    """σ of a marker's apparent scale about its centre: ``corner_bias_px`` ÷ the RMS distance of
    its pixels from their mean (the model's outline shift)."""
    return SIGMAS.corner_bias_px / np.sqrt(np.mean(np.sum((pixels_px - pixels_px.mean(0)) ** 2, axis=1)))


def _numeric_parts(objective):
    """Each source's covariance of T_cam_F by central differences of re-solving (the estimate
    at the true pose moved by ±step of one parameter), σ² g gᵀ summed over the source's parameters."""
    points_true = _points_F(MARKERS)
    px_true = _pixels(T_CAM_WORLD, points_true)
    parts = {name: np.zeros((6, 6)) for name in unc.SOURCES if name != "noise"}

    def add(name, sigma, step, solve_at):
        g = (unc.left_error(solve_at(step), T_CAM_WORLD) - unc.left_error(solve_at(-step), T_CAM_WORLD)) / (2 * step)
        parts[name] += sigma**2 * np.outer(g, g)

    # Intrinsics: the solver's K off by e (pixels made with the true K).
    for (i, j), sigma in (((0, 0), SIGMAS.focal_px), ((1, 1), SIGMAS.focal_px),
                          ((0, 2), SIGMAS.principal_point_px), ((1, 2), SIGMAS.principal_point_px)):
        def at(e, i=i, j=j):
            Kp = K.copy()
            Kp[i, j] += e
            result = refine_lm_batch(T_CAM_WORLD[None], points_true[None], px_true[None], Kp, objective=objective,
                                     max_iterations=200, step_tol=1e-15, cost_rel_tol=1e-18)
            return result.T_cam_marker[0]
        add("intrinsics", sigma, 1e-2, at)
    # Distortion: the ideal pixels undistorted with a coefficient off by e (true: none).
    for k, sigma in enumerate((SIGMAS.k1, SIGMAS.k2, SIGMAS.p1, SIGMAS.p2)):
        def at(e, k=k):
            dist = np.zeros(5)
            dist[k] = e
            return _solve(points_true, PinholeCamera(K, dist=dist).undistort_pixels(px_true), objective)
        add("distortion", sigma, 1e-5, at)
    # Map: one marker's mapped pose or scale off by e (pixels from the true markers).
    sigmas = (SIGMAS.map_position_m, SIGMAS.map_position_m, SIGMAS.map_height_m,
              SIGMAS.map_tilt_rad, SIGMAS.map_tilt_rad, SIGMAS.map_yaw_rad, SIGMAS.map_scale)
    for m in range(len(MARKERS)):
        for p, sigma in enumerate(sigmas):
            def at(e, m=m, p=p):
                moved = []
                for i, (T, x) in enumerate(MARKERS):
                    if i == m:
                        d = np.zeros(7)
                        d[p] = e
                        T = se3.make(T[:3, :3] @ so3.exp(d[3:6]), T[:3, 3] + d[:3])
                        x = x * (1.0 + d[6])
                    moved.append((T, x))
                return _solve(_points_F(moved), px_true, objective)
            add("map", sigma, 1e-5, at)
    # Corner bias: one marker's outline grown by a fraction e about its centre (the pixels show
    # the grown outline, the map keeps the printed one).
    for m, (T, x) in enumerate(MARKERS):
        sigma_s = _outline_sigma(_pixels(T_CAM_WORLD, se3.transform_points(T, x)))

        def at(e, m=m):
            moved = [(Ti, xi.mean(0) + (xi - xi.mean(0)) / (1.0 + e) if i == m else xi)
                     for i, (Ti, xi) in enumerate(MARKERS)]
            return _solve(_points_F(moved), px_true, objective)
        add("corner_bias", sigma_s, 1e-5, at)
    return parts


@pytest.mark.parametrize("objective", ["pixel", "depth"])
def test_each_systematic_source_matches_finite_differences_of_re_solving(objective):
    analytic = unc.frame_covariance_parts(T_CAM_WORLD, MARKERS, K, SIGMA_PX, SIGMAS, objective)
    numeric = _numeric_parts(objective)
    for name, cov in numeric.items():
        # Central differences of an exactly converged solve: error O(ε²) of the sensitivity
        # (ε moves a pixel by ≤ 0.05 px, its second-order effect is ~1e-4 relative).
        scale = np.max(np.abs(cov))
        assert scale > 0, name
        np.testing.assert_allclose(analytic[name], cov, atol=2e-3 * scale, err_msg=name)


def test_noise_part_is_the_pixel_only_covariance():
    for objective in ("pixel", "depth"):
        parts = unc.frame_covariance_parts(T_CAM_WORLD, MARKERS, K, SIGMA_PX, SIGMAS, objective)
        old = unc.covariance(T_CAM_WORLD, _points_F(MARKERS), K, SIGMA_PX, objective)
        np.testing.assert_allclose(parts["noise"], old, rtol=1e-9, atol=0)


@pytest.mark.parametrize("camera_on_agv", [True, False])
def test_extrinsic_part_matches_finite_differences(camera_on_agv):
    """Recorded extrinsic [Exp(δφ)·R, t + δt] against the true one, through the composition."""
    T_parent_cam = T_AGV_CAM if camera_on_agv else T_WORLD_CAM
    T_world_agv = T_WORLD_AGV if camera_on_agv else T_WORLD_CAM @ T_CAM_WORLD  # marker frame F = AGV: identity
    numeric = np.zeros((6, 6))
    variances = [SIGMAS.extrinsic_translation_m] * 3 + [SIGMAS.extrinsic_rotation_rad] * 3
    for p, sigma in enumerate(variances):
        g = np.zeros(6)
        for sign in (1, -1):
            d = np.zeros(6)
            d[p] = sign * 1e-6
            recorded = se3.make(so3.exp(d[3:]) @ T_parent_cam[:3, :3], T_parent_cam[:3, 3] + d[:3])
            if camera_on_agv:
                estimate = T_WORLD_CAM @ se3.inverse(recorded)
            else:
                estimate = recorded @ T_CAM_WORLD
            g += sign * unc.left_error(estimate, T_world_agv) / 2e-6
        numeric += sigma**2 * np.outer(g, g)
    analytic = unc.extrinsic_covariance_world(T_world_agv, T_parent_cam, camera_on_agv, SIGMAS)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-6 * np.max(np.abs(numeric)))


def test_nees_is_consistent_when_errors_follow_the_model():
    """400 seeded draws of every modelled error (noise, each marker's outline, intrinsics,
    distortion, map, extrinsic) on the two-marker frame, each solved by LM: NEES ~ χ²₆ to first
    order, so its
    mean is 6 with standard error sqrt(2·6/400) = 0.17; the band 6 ± 0.75 is ±4.4 standard
    errors (first-order and estimate-vs-truth effects are ≲ 1 % here)."""
    rng = np.random.default_rng(2025)
    trials = 400
    points_map = _points_F(MARKERS)
    estimates, truths_agv, recorded_ext = [], [], []
    pixels_all = []
    for _ in range(trials):
        moved = []
        for T, x in MARKERS:
            outline = _outline_sigma(_pixels(T_CAM_WORLD, se3.transform_points(T, x))) * rng.standard_normal()
            d = rng.standard_normal(7) * [SIGMAS.map_position_m, SIGMAS.map_position_m, SIGMAS.map_height_m,
                                          SIGMAS.map_tilt_rad, SIGMAS.map_tilt_rad, SIGMAS.map_yaw_rad, SIGMAS.map_scale]
            x_true = x * (1.0 + d[6]) * (1.0 + outline)  # CORNERS are centred on the marker's origin
            T_true = se3.make(T[:3, :3] @ Rz(d[5]) @ Rx(d[3]) @ Ry(d[4]), T[:3, 3] + d[:3])
            moved.append((T_true, x_true))
        K_true = K.copy()
        K_true[0, 0] += SIGMAS.focal_px * rng.standard_normal()
        K_true[1, 1] += SIGMAS.focal_px * rng.standard_normal()
        K_true[0, 2] += SIGMAS.principal_point_px * rng.standard_normal()
        K_true[1, 2] += SIGMAS.principal_point_px * rng.standard_normal()
        raw = _pixels(T_CAM_WORLD, _points_F(moved), K_true) + SIGMA_PX * rng.standard_normal((len(points_map), 2))
        dist = np.zeros(5)
        dist[:4] = rng.standard_normal(4) * [SIGMAS.k1, SIGMAS.k2, SIGMAS.p1, SIGMAS.p2]
        pixels_all.append(PinholeCamera(K, dist=dist).undistort_pixels(raw))
        dphi = rng.standard_normal(3) * SIGMAS.extrinsic_rotation_rad
        dt = rng.standard_normal(3) * SIGMAS.extrinsic_translation_m
        recorded_ext.append(se3.make(so3.exp(dphi) @ T_AGV_CAM[:3, :3], T_AGV_CAM[:3, 3] + dt))
    result = refine_lm_batch(
        np.broadcast_to(T_CAM_WORLD, (trials, 4, 4)).copy(), np.broadcast_to(points_map, (trials,) + points_map.shape),
        np.array(pixels_all), K, objective="pixel",
    )
    assert result.ok.all()
    nees_full, nees_pixel = [], []
    for T_cam_F, T_agv_cam in zip(result.T_cam_marker, recorded_ext):
        T_world_cam = se3.inverse(T_cam_F)
        T_world_agv = T_world_cam @ se3.inverse(T_agv_cam)
        cov, _ = unc.frame_covariance_full(T_cam_F, MARKERS, K, SIGMA_PX, SIGMAS, T_world_cam, T_world_agv,
                                           T_agv_cam, True, "pixel")
        nees_full.append(unc.nees(T_world_agv, T_WORLD_AGV, cov))
        pixel_only = unc.covariance_world_agv(unc.covariance(T_cam_F, points_map, K, SIGMA_PX), T_world_cam)
        nees_pixel.append(unc.nees(T_world_agv, T_WORLD_AGV, pixel_only))
    assert 5.25 <= np.mean(nees_full) <= 6.75, np.mean(nees_full)
    assert np.mean(nees_pixel) > 30.0  # pixel noise alone: far over-confident


def test_pixel_mode_has_no_systematic_sources_and_defaults_are_the_typical_profile():
    assert RunSettings(covariance="pixel").systematic_sigmas is None
    s = RunSettings().systematic_sigmas
    typical = PROFILES["typical"]
    cal, mp = typical.calibration, typical.map
    assert s.focal_px == cal.fx_sigma_px == cal.fy_sigma_px
    assert s.principal_point_px == cal.cx_sigma_px == cal.cy_sigma_px
    assert (s.k1, s.k2, s.p1, s.p2) == (cal.k1_sigma, cal.k2_sigma, cal.p1_sigma, cal.p2_sigma)
    assert s.extrinsic_rotation_rad == pytest.approx(math.radians(cal.extrinsic_rotation_sigma_deg))
    assert s.extrinsic_translation_m == cal.extrinsic_translation_sigma_m
    assert (s.map_position_m, s.map_height_m, s.map_scale) == (mp.position_sigma_m, mp.height_sigma_m, mp.print_scale_sigma)
    assert s.map_yaw_rad == pytest.approx(math.radians(mp.yaw_sigma_deg))
    assert s.map_tilt_rad == pytest.approx(math.radians(mp.tilt_sigma_deg))


def test_pixel_mode_diagnostics_reproduce_the_pixel_only_covariance():
    """PoseDiagnostics with no systematic sources gives exactly the pixel-noise covariance."""
    from agvviz.replay.diagnostics import PoseDiagnostics
    from agvviz.solvers.registry import SolverOptions

    points = _points_F(MARKERS)
    px = _pixels(T_CAM_WORLD, points) + 0.1 * np.random.default_rng(1).standard_normal((len(points), 2))
    T_est = _solve(points, px, "pixel")
    T_world_cam = se3.inverse(T_est)
    covs = {}
    for mode, systematic in (("pixel", None), ("full", SIGMAS)):
        diag = PoseDiagnostics("lm", "pixel", "lowest_error", 0.2, SolverOptions(objective="pixel"), systematic)
        result = SimpleNamespace(T_world_cam=T_world_cam, T_world_agv=T_world_cam @ se3.inverse(T_AGV_CAM),
                                 T_world_agv_truth=None, n_points=0, sigma_px=None, uncertainty_note="",
                                 cov_world_agv=None, position_cov_world_m2=None, position_sigma_m=None)
        diag.finish(result, T_est, points, px, K, T_AGV_CAM, True, MARKERS, np.eye(4))
        covs[mode] = result.cov_world_agv
    old = unc.covariance_world_agv(unc.covariance(T_est, points, K, 0.2, "pixel"), T_world_cam)
    assert np.array_equal(covs["pixel"], old)
    assert np.all(np.linalg.eigvalsh(covs["full"] - old) > 0)  # every source adds


def test_ellipsoid_label_names_the_one_magnification():
    from agvviz.viz.log_uncertainty import COV_MAGNIFICATION, _covariance_ellipsoid

    frame = SimpleNamespace(T_world_agv=np.eye(4), position_cov_world_m2=np.diag([4e-6, 1e-6, 1e-6]))
    half_sizes, _, _, label = _covariance_ellipsoid(frame, COV_MAGNIFICATION)
    assert f"×{COV_MAGNIFICATION:g}" in label
    assert max(half_sizes) == pytest.approx(3 * COV_MAGNIFICATION * 2e-3)


def test_planar_extrinsic_jacobian_matches_finite_differences():
    """The planar model's pixels through a recorded extrinsic [Exp(δφ)·R, t + δt]."""
    from agvviz.solvers import planar

    points = _points_F(MARKERS)

    def pixels(T_agv_cam):
        return _pixels(se3.inverse(T_WORLD_AGV @ T_agv_cam), points).ravel()

    numeric = np.empty((2 * len(points), 6))
    for p in range(6):
        cols = []
        for sign in (1, -1):
            d = np.zeros(6)
            d[p] = sign * 1e-7
            cols.append(pixels(se3.make(so3.exp(d[3:]) @ T_AGV_CAM[:3, :3], T_AGV_CAM[:3, 3] + d[:3])))
        numeric[:, p] = (cols[0] - cols[1]) / 2e-7
    analytic = planar.pixel_jacobian_planar_wrt_extrinsic(T_WORLD_AGV, T_AGV_CAM, points, K)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-3)


def test_planar_full_covariance_adds_to_the_pixel_one():
    from agvviz.solvers import planar

    points = _points_F(MARKERS)
    J3 = planar.pixel_jacobian_planar(T_WORLD_AGV, T_AGV_CAM, points, K)
    J_ext = planar.pixel_jacobian_planar_wrt_extrinsic(T_WORLD_AGV, T_AGV_CAM, points, K)
    full = unc.planar_covariance_full(J3, J_ext, T_CAM_WORLD, MARKERS, K, SIGMA_PX, SIGMAS)
    pixel = planar.covariance_planar(T_WORLD_AGV, T_AGV_CAM, points, K, SIGMA_PX)
    none = unc.planar_covariance_full(J3, J_ext, T_CAM_WORLD, MARKERS, K, SIGMA_PX, unc.SystematicSigmas())
    np.testing.assert_allclose(none, pixel, rtol=1e-9)
    assert np.all(np.linalg.eigvalsh(full - pixel) > 0)


def test_pooled_residual_sigma_already_holds_each_corners_own_fixed_offset():
    """Corner offsets fixed per marker but independent between corners are, within each frame,
    indistinguishable from noise: the dof-corrected pooled residual σ² estimates noise² +
    offset², and the noise covariance at that σ alone is consistent (so the model adds no
    separate per-corner term). 120 markers (one offset draw each, 0.25 px) seen in 5 frames
    each, noise 0.1 px: σ² = 0.0725 px²; the pooled estimate over 1200 dof has a relative
    standard error ≈ 8 % (the 960 offset draws dominate), the band ± 25 % is ± 3 SE. NEES mean
    6 over 600 frames, correlated in fives: standard error ≈ sqrt(2·6·5/600) ≈ 0.32, band 6 ± 1.3."""
    rng = np.random.default_rng(7)
    noise_px, offset_px = 0.1, 0.25
    T_marker = se3.make(Rz(0.3), [1.2, 0.1, 0.0])
    points = se3.transform_points(T_marker, CORNERS)
    starts, truths, pixels = [], [], []
    for _ in range(120):
        offsets = offset_px * rng.standard_normal((4, 2))
        for _ in range(5):
            T_true = se3.make(so3.exp(0.05 * rng.standard_normal(3)) @ T_CAM_WORLD[:3, :3],
                              T_CAM_WORLD[:3, 3] + 0.1 * rng.standard_normal(3))
            pixels.append(_pixels(T_true, points) + offsets + noise_px * rng.standard_normal((4, 2)))
            truths.append(T_true)
    n = len(truths)
    result = refine_lm_batch(np.array(truths), np.broadcast_to(points, (n,) + points.shape), np.array(pixels), K,
                             objective="pixel", max_iterations=100, step_tol=1e-14, cost_rel_tol=1e-16)
    assert result.ok.all()
    sums = [unc.residual_sum_sq_px2(T, points, px, K) for T, px in zip(result.T_cam_marker, pixels)]
    sigma = unc.residual_sigma_px(sum(s for s, _ in sums), sum(d for _, d in sums))
    assert sigma**2 == pytest.approx(noise_px**2 + offset_px**2, rel=0.25)
    nees = [unc.nees(T, T_true, unc.covariance(T, points, K, sigma)) for T, T_true in zip(result.T_cam_marker, truths)]
    assert 4.7 <= np.mean(nees) <= 7.3, np.mean(nees)


def test_qr_codes_take_their_own_outline_shift():
    """PoseDiagnostics gives a QR code (its observation carries a payload) ``qr_outline_px`` and
    any other marker ``corner_bias_px``; markers it cannot match keep ``corner_bias_px``."""
    from agvviz.replay.diagnostics import PoseDiagnostics
    from agvviz.solvers.registry import SolverOptions

    sigmas = unc.SystematicSigmas(corner_bias_px=0.3, qr_outline_px=0.07)
    diag = PoseDiagnostics("lm", "pixel", "lowest_error", None, SolverOptions(), sigmas)
    observations = [SimpleNamespace(marker_id="Q001", payload="x=1;y=2"), SimpleNamespace(marker_id="7", payload="")]
    result = SimpleNamespace(used_marker_ids=("Q001", "7"), observations=observations)
    outlines = [m[2] for m in diag._with_outlines(result, MARKERS)]
    assert outlines == [0.07, 0.3]
    unmatched = SimpleNamespace(used_marker_ids=("Q001",), observations=observations)
    assert diag._with_outlines(unmatched, MARKERS) == MARKERS
    assert RunSettings().systematic_sigmas.qr_outline_px == 0.07
    # Each marker's part scales as the square of its outline σ.
    parts = [unc.frame_covariance_parts(T_CAM_WORLD, [(T, x, b) for T, x in MARKERS], K, SIGMA_PX, sigmas)["corner_bias"]
             for b in (0.07, 0.3)]
    np.testing.assert_allclose(parts[0] * (0.3 / 0.07) ** 2, parts[1], rtol=1e-9)
