"""Planar ambiguity (agvviz.solvers.ambiguity): both IPPE poses, flip detection, policies."""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.geometry import se3
from agvviz.geometry.euler import Rx, Rz
from agvviz.geometry.plane import square_points_marker
from agvviz.solvers.ambiguity import POLICIES, choose, ippe_pair, is_flip, rotation_distance_rad

K = np.array([[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]])
POINTS = square_points_marker(0.2)
FACING = np.diag([1.0, -1.0, -1.0])


def view(tilt_deg: float, distance_m: float) -> np.ndarray:
    return se3.make(FACING @ Rx(np.radians(tilt_deg)) @ Rz(0.4), [0.05, 0.02, distance_m])


def project(T, points=POINTS):
    w = se3.transform_points(T, points)
    return (w @ K.T)[:, :2] / w[:, 2:3]


def test_both_ippe_solutions_exist_and_reproject():
    T_true = view(25.0, 3.0)  # a small code far away: weak perspective, a real ambiguity
    pair, reason = ippe_pair(POINTS, project(T_true), K)
    assert reason == ""
    # The best one is the truth (noise-free: round-off), the other is a different pose that
    # still reprojects within a pixel — that is what makes the ambiguity dangerous.
    assert rotation_distance_rad(pair.T_best_cam_marker, T_true) < 1e-8
    assert pair.rms_best_px < 1e-6
    assert rotation_distance_rad(pair.T_other_cam_marker, T_true) > np.radians(20.0)
    assert 0.0 < pair.rms_other_px < 1.0
    assert pair.ratio > 1.0
    for T in (pair.T_best_cam_marker, pair.T_other_cam_marker):
        assert np.all(se3.transform_points(T, POINTS)[:, 2] > 0)


def test_ratio_is_near_one_under_noise_on_an_ambiguous_view_and_large_on_a_clear_one():
    rng = np.random.default_rng(0)
    # 0.2 m code, 10° tilt, 4 m away (≈50 px): the median ratio over 21 noisy draws is ≈1.5;
    # a 0.5 m code tilted 50° at 1 m: every ratio is in the hundreds (measured 119–829).
    ambiguous = [ippe_pair(POINTS, project(view(10.0, 4.0)) + rng.normal(0, 0.5, (4, 2)), K)[0].ratio for _ in range(21)]
    big = square_points_marker(0.5)
    clear = [ippe_pair(big, project(view(50.0, 1.0), big) + rng.normal(0, 0.5, (4, 2)), K)[0].ratio for _ in range(21)]
    assert np.median(ambiguous) < 3.0 and min(clear) > 30.0, (np.median(ambiguous), min(clear))


def test_flip_is_flagged_when_the_chosen_branch_switches():
    T_a, T_b = view(25.0, 3.0), view(-25.0, 3.0)  # stand-ins for the two branches
    small_motion = se3.make(Rz(0.02), [0.01, 0.0, 0.0])
    assert is_flip(small_motion @ T_b, T_a, T_b)  # previous chose a, now b: flip
    assert not is_flip(small_motion @ T_a, T_a, T_b)  # stays on a
    assert not is_flip(T_b, None, None)  # no previous frame


def test_policies_pick_the_expected_candidate():
    T_a, T_b = view(25.0, 3.0), view(-25.0, 3.0)
    rms = (0.30, 0.25)  # b fits slightly better (noise)
    assert choose("lowest_error", rms, (T_a, T_b)) == (1, "lowest_error")
    # Continuity: the previous frame chose a (moved a little since): keep a despite the error.
    assert choose("continuity", rms, (T_a, T_b), T_world_previous=se3.make(Rz(0.01), [0, 0, 0]) @ T_a) == (0, "continuity")
    # Odometry: the previous pose was a, but the odometry predicts a motion that lands on b
    # (e.g. the vehicle really turned); the prediction decides.
    predicted = T_b
    assert choose("odometry", (0.25, 0.30), (T_a, T_b), T_a, predicted) == (1, "odometry")
    # Fallbacks: no odometry → continuity; nothing → lowest error.
    assert choose("odometry", rms, (T_a, T_b), T_a, None) == (0, "continuity")
    assert choose("continuity", rms, (T_a, T_b)) == (1, "lowest_error")
    with pytest.raises(ValueError, match=", ".join(POLICIES)):
        choose("vote", rms, (T_a, T_b))


def test_ippe_failure_is_a_reason_not_an_exception():
    pair, reason = ippe_pair(POINTS[:3], project(view(25.0, 3.0))[:3], K)
    assert pair is None and reason
