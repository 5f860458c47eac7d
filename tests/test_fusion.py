"""Fusion: paper 003's switching with mean compensation (eqs 13–16) and the Kalman filter."""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.fusion import CameraOnly, KalmanFusion, KalmanSettings, MeanCompensation, make_fusion
from agvviz.uwb.localize import UwbFix

ANCHORS = {"A": np.array([4.0, 0.0, 2.2]), "B": np.array([8.0, 3.5, 2.2]), "C": np.array([4.0, 7.0, 2.2]), "D": np.array([0.0, 3.5, 2.2])}
TAG_Z = 0.45


def _uwb_fix(t_ns: int, xy) -> UwbFix:
    n = len(ANCHORS)
    return UwbFix(np.array([xy[0], xy[1], TAG_Z]), "least_squares", np.ones(n, bool), np.zeros(n, bool), np.zeros(n), 1.0, log_time_ns=t_ns)


def test_mean_compensation_switch_offset_and_jump():
    fusion = MeanCompensation()
    bias = np.array([0.06, -0.04])  # UWB reads 6 cm east, 4 cm south of the camera
    cam = [np.array([1.0 + 0.01 * k, 2.0]) for k in range(6)]
    for k in range(4):  # camera and UWB interleaved, camera visible
        step = fusion.camera(k * 100, cam[k])
        assert step.fused.source == "camera" and np.allclose(step.fused.position_xy_m, cam[k])
        assert fusion.uwb_fix(_uwb_fix(k * 100 + 50, cam[k] + bias)).fused is None
    # Cameras blocked: nothing yet; the next UWB fix switches with δ = mean(cam) − mean(uwb) = −bias.
    assert fusion.camera(400, None).fused is None
    step = fusion.uwb_fix(_uwb_fix(450, cam[4] + bias))
    assert len(step.events) == 1 and (step.events[0].from_source, step.events[0].to_source) == ("camera", "uwb")
    np.testing.assert_allclose(step.events[0].offset_m, -bias, atol=1e-12)  # eq 15
    np.testing.assert_allclose(step.fused.position_xy_m, cam[4], atol=1e-12)  # eq 16
    # Jump = distance from the last camera output (cam[3]) to the first compensated fix (cam[4]).
    assert step.events[0].jump_m == pytest.approx(0.01)
    assert "offset (δx, δy) = (-60.0, +40.0) mm" in step.events[0].text()
    # The camera returns: back to the camera at once, jump from the last fused output.
    step = fusion.camera(500, cam[5] + np.array([0.0, 0.003]))
    assert step.fused.source == "camera"
    assert [(e.from_source, e.to_source) for e in step.events] == [("uwb", "camera")]
    assert step.events[0].jump_m == pytest.approx(np.hypot(0.01, 0.003))


def test_camera_only_ignores_uwb():
    fusion = make_fusion("camera_only", ANCHORS, TAG_Z)
    assert isinstance(fusion, CameraOnly)
    assert fusion.camera(0, None).fused is None and fusion.uwb_fix(_uwb_fix(1, (1, 1))).fused is None
    with pytest.raises(ValueError, match="unknown fusion"):
        make_fusion("magic", ANCHORS, TAG_Z)


def _ranges(xy, biases, rng, sigma):
    p = np.array([xy[0], xy[1], TAG_Z])
    return {a: float(np.linalg.norm(p - ANCHORS[a]) + biases[a] + rng.normal(0.0, sigma)) for a in ANCHORS}


def test_kalman_learns_link_biases_then_holds_them_through_a_blockage_and_gates_nlos():
    rng = np.random.default_rng(2)
    biases = {"A": 0.08, "B": -0.05, "C": 0.03, "D": -0.07}
    kf = KalmanFusion(ANCHORS, TAG_Z, KalmanSettings(range_sigma_m=0.03))
    speed = np.array([0.2, 0.0])
    errors_blocked, gate_verdicts = [], []
    for k in range(300):  # 30 s at 10 Hz: camera for 15 s, then blocked
        t_ns = k * 100_000_000
        truth = np.array([2.0, 3.0]) + speed * k * 0.1
        blocked = k >= 150
        kf.camera(t_ns, None if blocked else truth + rng.normal(0.0, 0.002, 2))
        ranges = _ranges(truth, biases, rng, 0.03)
        if k == 200:
            ranges["C"] += 0.6  # planted NLOS range
        for i, (anchor, r) in enumerate(ranges.items()):
            step = kf.uwb_range(t_ns + (i + 1) * 20_000_000, anchor, r)
            if k == 200 and anchor == "C":
                gate_verdicts.append(step.range_gate["C"])
        if blocked:
            errors_blocked.append(np.linalg.norm(kf.state[:2] - truth))
    np.testing.assert_allclose(kf.state[4:], [biases[a] for a in sorted(ANCHORS)], atol=0.03)
    assert gate_verdicts == [False]
    # 15 s blocked, 3 cm range noise, 4 ranges per 0.1 s; the bias states slowly trade off
    # against the position with nothing but ranges (≈2.5 cm mean here). Without the bias states
    # the error would be the bias-driven UWB error of ≈8 cm; 4 cm separates the two.
    assert np.mean(errors_blocked) < 0.04, np.mean(errors_blocked)


def test_kalman_reports_camera_loss_and_return_with_the_jump():
    kf = KalmanFusion(ANCHORS, TAG_Z)
    kf.camera(0, np.array([1.0, 1.0]))
    lost = kf.camera(100_000_000, None)
    assert [(e.from_source, e.to_source) for e in lost.events] == [("camera", "uwb")]
    back = kf.camera(200_000_000, np.array([1.0, 1.01]))
    assert [(e.from_source, e.to_source) for e in back.events] == [("uwb", "camera")]
    assert 0.0 < back.events[0].jump_m < 0.011
