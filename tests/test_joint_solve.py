"""The joint solve over every marker in view (:mod:`agvviz.solvers.joint`, setting ``markers``).

Against truth: corners are projected from a known camera pose and given seeded Gaussian noise
of a known σ, so the joint estimate's error can be held to the Cramér–Rao bound of *all*
corners, the χ² test's false-alarm rate to its nominal level, and a marker whose map entry is
wrong must be left out by name. Then the replay on rendered frames: several QR codes in one
image, one whose payload lies.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agvviz.geometry import euler, se3
from agvviz.markers.payload import QrPayload, encode_payload
from agvviz.solvers import SolverOptions, uncertainty
from agvviz.solvers.ambiguity import ippe_pair
from agvviz.solvers.joint import MarkerView, solve_joint

K = np.array([[800.0, 0.0, 640.0], [0.0, 800.0, 360.0], [0.0, 0.0, 1.0]])
SIDE_M = 0.16
SQUARE_M = np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], dtype=float) * SIDE_M / 2
OPTIONS = SolverOptions(objective="pixel")
# A camera 1.6 m above the floor looking down 40° from vertical at five floor markers.
T_WORLD_CAM = se3.make(euler.Rz(0.3) @ euler.Rx(np.radians(-140.0)), [0.1, -1.2, 1.6])
T_CAM_WORLD = se3.inverse(T_WORLD_CAM)
MARKER_CENTRES_M = [(0.0, 0.0), (0.5, 0.1), (-0.45, 0.2), (0.2, 0.6), (-0.2, -0.35)]


def _world_markers(turns=(0, 1, 2, 3, 1)) -> list[np.ndarray]:
    return [se3.make(euler.Rz(t * np.pi / 2), [x, y, 0.0]) for (x, y), t in zip(MARKER_CENTRES_M, turns)]


def _views(rng, sigma_px, T_map_markers, T_true_markers=None) -> list[MarkerView]:
    """Markers as the map says (``T_map_markers``) seen where they truly are (``T_true_markers``)."""
    T_true_markers = T_map_markers if T_true_markers is None else T_true_markers
    views = []
    for i, (T_map, T_true) in enumerate(zip(T_map_markers, T_true_markers)):
        w = se3.transform_points(T_CAM_WORLD @ T_true, SQUARE_M)
        px = (w @ K.T)[:, :2] / w[:, 2:3] + rng.normal(0.0, sigma_px, (4, 2))
        views.append(MarkerView(str(i), SQUARE_M, T_map, px))
    return views


def _largest_start(views) -> tuple[np.ndarray, int]:
    """The best IPPE pose of the marker with the largest image (what the replay starts from)."""
    d1 = [v.ideal_px[2] - v.ideal_px[0] for v in views]
    d2 = [v.ideal_px[3] - v.ideal_px[1] for v in views]
    areas = [abs(a[0] * b[1] - a[1] * b[0]) for a, b in zip(d1, d2)]
    i = int(np.argmax(areas))
    pair, _ = ippe_pair(views[i].points_marker_m, views[i].ideal_px, K)
    return pair.T_best_cam_marker @ se3.inverse(views[i].T_F_marker), i


def _camera_position_error_m(T_cam_world: np.ndarray) -> float:
    return float(np.linalg.norm(se3.inverse(T_cam_world)[:3, 3] - T_WORLD_CAM[:3, 3]))


def test_joint_pose_reaches_the_bound_of_all_corners_and_beats_the_largest_marker():
    """Over seeded trials at σ 0.5 px the joint camera-position RMSE is within 10 % of the
    Cramér–Rao bound of all 20 corners (RMSE over 300 trials estimates it to ≈ ±4 %, 1σ; LM
    converges to the ML estimate, which is efficient to first order), and below the largest
    marker's own pose error."""
    rng = np.random.default_rng(7)
    sigma = 0.5
    T_markers = _world_markers()
    points = np.vstack([se3.transform_points(T, SQUARE_M) for T in T_markers])
    crlb = uncertainty.crlb(T_CAM_WORLD, points, K, sigma)
    crlb_cam_position_m = uncertainty.position_bound_m(
        uncertainty.position_covariance(uncertainty.covariance_world_agv(crlb, T_WORLD_CAM), T_WORLD_CAM)
    )
    joint_err, single_err = [], []
    for _ in range(300):
        views = _views(rng, sigma, T_markers)
        start, _ = _largest_start(views)
        solution = solve_joint(views, K, start, sigma, OPTIONS, p_outlier=1e-6)
        assert solution.T_cam_F is not None, solution.reason
        assert len(solution.used) == 5
        joint_err.append(_camera_position_error_m(solution.T_cam_F))
        single_err.append(_camera_position_error_m(start))
    joint_rmse = float(np.sqrt(np.mean(np.square(joint_err))))
    single_rmse = float(np.sqrt(np.mean(np.square(single_err))))
    assert joint_rmse <= 1.10 * crlb_cam_position_m, (joint_rmse, crlb_cam_position_m)
    assert joint_rmse < 0.5 * single_rmse, (joint_rmse, single_rmse)


def test_consistent_markers_fail_the_chi2_test_at_its_nominal_rate():
    """σ known, p_outlier 0.05: each marker's χ² uses its leverage-corrected degrees of freedom,
    so a consistent marker is flagged 5 % of the time, and a frame of five loses one in
    1 − 0.95⁵ = 22.6 % of trials. 300 trials: the binomial 99.9 % band is 15–31 %."""
    rng = np.random.default_rng(11)
    trials = 300
    left_out = 0
    for _ in range(trials):
        views = _views(rng, 0.4, _world_markers())
        start, _ = _largest_start(views)
        solution = solve_joint(views, K, start, 0.4, OPTIONS, p_outlier=0.05)
        left_out += bool(solution.excluded)
    assert 0.15 < left_out / trials < 0.31, left_out / trials


def test_a_marker_whose_map_entry_is_wrong_is_left_out_and_named():
    """Marker 3 is mapped turned 90° about its centre (the injected map error of issue 25): its
    corners land ≈ 0.1 m from where the map says. It is left out, named in the note, and the
    pose from the other four stays at the bound's scale — also when the solve starts from the
    wrong marker's own pose (the consensus over hypotheses finds the majority)."""
    rng = np.random.default_rng(3)
    true_markers = _world_markers()
    mapped = list(true_markers)
    mapped[3] = true_markers[3] @ se3.make(euler.Rz(np.pi / 2), [0, 0, 0])
    for start_from_wrong in (False, True):
        views = _views(rng, 0.3, mapped, true_markers)
        if start_from_wrong:
            pair, _ = ippe_pair(views[3].points_marker_m, views[3].ideal_px, K)
            start = pair.T_best_cam_marker @ se3.inverse(views[3].T_F_marker)
        else:
            start, _ = _largest_start(views)
        solution = solve_joint(views, K, start, 0.3, OPTIONS)
        assert solution.excluded == ("3",), solution.note
        assert solution.used == ("0", "1", "2", "4")
        assert "left out 3" in solution.note and "0, 1, 2, 4" in solution.note
        check = next(c for c in solution.checks if c.marker_id == "3")
        assert check.chi2 > 100 * check.chi2_limit
        assert _camera_position_error_m(solution.T_cam_F) < 0.02


def test_a_marker_size_wrong_for_every_marker_is_a_group_disagreement_not_an_outlier():
    """Every marker printed 10 % larger than the map says: every marker's corners are off by
    ≈ 4 px at this range, no single marker is to blame, so none is left out and the note says
    the markers disagree as a group."""
    rng = np.random.default_rng(5)
    T_markers = _world_markers()
    views = []
    for view in _views(rng, 0.2, T_markers):
        w = se3.transform_points(T_CAM_WORLD @ view.T_F_marker, 1.1 * SQUARE_M)
        px = (w @ K.T)[:, :2] / w[:, 2:3] + rng.normal(0.0, 0.2, (4, 2))
        views.append(dataclasses.replace(view, ideal_px=px))
    start, _ = _largest_start(views)
    solution = solve_joint(views, K, start, 0.2, OPTIONS)
    assert solution.T_cam_F is not None
    assert solution.excluded == ()
    assert "disagree as a group" in solution.note


def test_two_markers_that_disagree_keep_the_start_and_name_the_other():
    """Two markers, one mapped 0.3 m off: nothing tells which is right but the start (the
    largest marker, paper 000's choice); the other is left out by name."""
    rng = np.random.default_rng(9)
    true_markers = _world_markers()[:2]
    mapped = [true_markers[0], true_markers[1] @ se3.make(np.eye(3), [0.3, 0.0, 0.0])]
    views = _views(rng, 0.3, mapped, true_markers)
    pair, _ = ippe_pair(views[0].points_marker_m, views[0].ideal_px, K)
    solution = solve_joint(views, K, pair.T_best_cam_marker @ se3.inverse(views[0].T_F_marker), 0.3, OPTIONS)
    assert solution.used == ("0",) and solution.excluded == ("1",)
    assert solution.checks[1].own_offset_m == pytest.approx(0.3, abs=0.1)


def test_marker_checks_match_their_definitions_marker_by_marker():
    """Each MarkerCheck (computed for all markers at once: one projection, one Jacobian, OpenCV's
    IPPE unranked) against its definition computed marker by marker: χ² = Σ‖r‖²/σ², the RMS
    reprojection error, the χ² quantile at 2·n − leverage (leverage: trace of the marker's block
    of the hat matrix of the used markers; 0 when left out), and the own-pose offset from
    :func:`ippe_pair`'s two poses. Once with the start explaining every marker (the other
    markers' IPPE poses are then not hypotheses) and once from a wrong marker's pose (they are)."""
    from scipy.stats import chi2

    from agvviz.solvers.lm import reprojection_rms_px

    rng = np.random.default_rng(21)
    true_markers = _world_markers()
    mapped = list(true_markers)
    mapped[2] = true_markers[2] @ se3.make(np.eye(3), [0.12, 0.0, 0.0])
    sigma = 0.4
    for start_from_wrong in (False, True):
        views = _views(rng, sigma, mapped, true_markers)
        if start_from_wrong:
            pair, _ = ippe_pair(views[2].points_marker_m, views[2].ideal_px, K)
            start = pair.T_best_cam_marker @ se3.inverse(views[2].T_F_marker)
        else:
            start, _ = _largest_start(views)
        solution = solve_joint(views, K, start, sigma, OPTIONS)
        assert solution.excluded == ("2",), solution.note
        T = solution.T_cam_F
        used = [c.used for c in solution.checks]
        J_used = np.vstack([uncertainty.pixel_jacobian(T, v.points_F_m, K) for v, u in zip(views, used) if u])
        information_inv = np.linalg.inv(J_used.T @ J_used)
        p_joint = se3.inverse(T)[:3, 3]
        for view, check in zip(views, solution.checks):
            sum_sq, _ = uncertainty.residual_sum_sq_px2(T, view.points_F_m, view.ideal_px, K)
            assert check.chi2 == pytest.approx(sum_sq / sigma**2, rel=1e-9)
            assert check.rms_px == pytest.approx(reprojection_rms_px(T, view.points_F_m, view.ideal_px, K), rel=1e-9)
            J = uncertainty.pixel_jacobian(T, view.points_F_m, K)
            leverage = float(np.trace(J @ information_inv @ J.T)) if check.used else 0.0
            assert check.chi2_limit == pytest.approx(chi2.ppf(1 - 1e-3, 2 * len(view.ideal_px) - leverage), rel=1e-9)
            pair, _ = ippe_pair(view.points_marker_m, view.ideal_px, K)
            own = [se3.inverse(T_own @ se3.inverse(view.T_F_marker))[:3, 3]
                   for T_own in (pair.T_best_cam_marker, pair.T_other_cam_marker)]
            assert check.own_offset_m == pytest.approx(min(np.linalg.norm(p - p_joint) for p in own), rel=1e-9, abs=1e-12)


# -- the replay on rendered frames ---------------------------------------------------------------


def _replay_codes(codes, **settings):
    from agvviz.replay.graph import replay
    from agvviz.settings import RunSettings
    from agvviz.sim.render import FloorScene, encode_jpeg, render_frame
    from tests.test_pipeline import CAMERA, T_AGV_CAM, T_WORLD_AGV, _frame, _static_messages

    gray = render_frame(FloorScene(codes=tuple(codes)), CAMERA, T_WORLD_AGV @ T_AGV_CAM, np.random.default_rng(0))
    (result,) = replay(_static_messages() + _frame(1_000, encode_jpeg(gray, quality=95)), RunSettings(**settings))
    return result


def _floor_codes():
    from agvviz.sim.qr_texture import make_floor_code

    return [
        make_floor_code("A", (-0.45, 1.0), 0, 0.3),
        make_floor_code("B", (0.0, 1.2), 1, 0.4),
        make_floor_code("C", (0.45, 1.0), 2, 0.3),
    ]


def test_replay_solves_from_every_code_in_view():
    """Three QR codes in one rendered frame: all three make the pose, and it is within 5 mm
    of truth (the rendered corners are ≈ 0.05 px accurate: the bound is ≈ 1 mm)."""
    result = _replay_codes(_floor_codes())
    assert result.solved, result.reject_detail
    assert result.used_marker_id == "B"
    assert sorted(result.used_marker_ids) == ["A", "B", "C"]
    assert result.excluded_marker_ids == ()
    assert result.position_error_m < 0.005
    assert result.n_points == 12
    largest = _replay_codes(_floor_codes(), markers="largest")
    assert largest.used_marker_ids == ("B",)


def test_replay_leaves_out_the_largest_code_when_its_payload_lies():
    """The largest code's payload puts it 0.25 m from where it is printed: markers=largest
    gives a pose 0.25 m off; markers=all leaves the code out by name and keeps the pose."""
    from agvviz.sim.qr_texture import qr_symbol_modules

    codes = _floor_codes()
    liar = codes[1]
    points = liar.points_world_m.copy()
    points[:, 0] += 0.25
    text = encode_payload(QrPayload("B", points))
    codes[1] = dataclasses.replace(liar, payload=text, modules=qr_symbol_modules(text))
    largest = _replay_codes(codes, markers="largest")
    assert largest.solved and largest.position_error_m > 0.2
    result = _replay_codes(codes)
    assert result.solved, result.reject_detail
    assert result.excluded_marker_ids == ("B",)
    assert "left out B" in result.marker_note
    assert result.position_error_m < 0.01


def test_replay_keeps_the_largest_code_when_the_markers_fit_no_common_pose():
    """The calibration given to the replay has k1 0.3 larger than the lens that made the image:
    each code on its own still fits (0.47 px RMS), but the three, spread over the image, fit no
    common pose within max_reproj_px = 1 px (they disagree as a group). The frame keeps the
    largest code's own pose — paper 000's answer — instead of losing the frame, and says why."""
    from agvviz.geometry import PinholeCamera
    from agvviz.replay.graph import replay
    from agvviz.model.messages import CalibrationMsg, FrameTransformMsg
    from agvviz.settings import RunSettings
    from agvviz.sim.render import FloorScene, encode_jpeg, render_frame
    from tests.test_pipeline import CAM, CAMERA, T_AGV_CAM, T_WORLD_AGV, _frame, _msg

    gray = render_frame(FloorScene(codes=tuple(_floor_codes())), CAMERA, T_WORLD_AGV @ T_AGV_CAM, np.random.default_rng(0))
    wrong = PinholeCamera(CAMERA.K.copy(), np.array([0.25, 0.01, 0, 0, 0]), CAMERA.width_px, CAMERA.height_px)
    static = [
        _msg(f"/cam/{CAM}/calibration", 0, CalibrationMsg(CAM, f"cam_{CAM}", wrong, "plumb_bob")),
        _msg("/tf_static", 0, [FrameTransformMsg("agv", f"cam_{CAM}", T_AGV_CAM)]),
    ]
    messages = static + _frame(1_000, encode_jpeg(gray, quality=95))
    (largest,) = replay(messages, RunSettings(markers="largest", max_reproj_px=1.0))
    (result,) = replay(messages, RunSettings(max_reproj_px=1.0))
    assert largest.solved and largest.reproj_rms_px < 1.0
    assert result.solved, result.reject_detail
    assert result.used_marker_ids == ("B",)
    assert "> max_reproj_px 1 px: the largest code B alone" in result.marker_note
    np.testing.assert_allclose(result.T_world_agv, largest.T_world_agv, atol=1e-12)
