"""UWB: TOF arithmetic (paper 003 eqs 1–2), simulated TWR, trilateration, the NLOS gate, GDOP,
the range tracker, and the real Labyrinth UWB data set."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agvviz.sim.uwb import UWB_TICK_S, DeviceClock, simulate_twr
from agvviz.uwb import (
    SPEED_OF_LIGHT_MPS,
    RangeRecord,
    UwbLocalizationError,
    UwbTracker,
    gdop,
    least_squares_fix,
    range_from_timestamps_m,
    time_of_flight_s,
    trilateral_centroid,
)
from agvviz.uwb.localize import gate_ranges

# Paper 003's room: an anchor on the middle of each wall of an 8 × 7 m room.
ANCHORS = np.array([[4.0, 0.02, 2.2], [7.98, 3.5, 2.2], [4.0, 6.98, 2.2], [0.02, 3.5, 2.2]])
TAG_Z = 0.45
LABYRINTH = Path(__file__).resolve().parents[2] / "shared" / "data" / "librsf_uwb" / "Indoor_UWB"


def test_tof_arithmetic_by_hand():
    # Poll sent at 1000 ns (tag clock), received at 5000.0 (anchor), reply sent 150 µs later,
    # back at the tag at 1000 + 2·20 + 150000 ns: the flight is 20 ns each way.
    t1, t2, t3, t4 = 1000.0, 5000.0, 155000.0, 1000.0 + 40.0 + 150000.0
    assert time_of_flight_s(t1, t2, t3, t4) == pytest.approx(20e-9, abs=1e-18)
    assert range_from_timestamps_m(t1, t2, t3, t4) == pytest.approx(20e-9 * SPEED_OF_LIGHT_MPS, abs=1e-9)


def test_simulated_twr_offsets_cancel_drift_biases_as_predicted():
    rng = np.random.default_rng(0)
    # Perfect clocks with different offsets: only the tick quantisation is left
    # (4 timestamps, each ≤ half a tick: ≤ c · 2 ticks / 2 ≈ 4.7 mm).
    ex = simulate_twr(5.0, 3.0, DeviceClock(1.0, 0.0), DeviceClock(7.5, 0.0), rng, timestamp_noise_s=0.0)
    assert abs(ex.range_m - 5.0) <= SPEED_OF_LIGHT_MPS * UWB_TICK_S + 1e-9
    assert ex.range_m == pytest.approx(range_from_timestamps_m(ex.t1_ns, ex.t2_ns, ex.t3_ns, ex.t4_ns))
    # Drift: bias c · (ε_tag − ε_anchor) · D / 2 = c · 4e-6 · 150e-6 / 2 ≈ 89.9 mm.
    ex = simulate_twr(5.0, 3.0, DeviceClock(1.0, 2.0), DeviceClock(7.5, -2.0), rng, timestamp_noise_s=0.0)
    expected_bias = SPEED_OF_LIGHT_MPS * 4e-6 * 150e-6 / 2
    assert ex.range_m - 5.0 == pytest.approx(expected_bias, abs=0.005)
    # NLOS adds its excess path.
    ex = simulate_twr(5.0, 3.0, DeviceClock(1.0, 0.0), DeviceClock(7.5, 0.0), rng, timestamp_noise_s=0.0, nlos_excess_m=0.4)
    assert ex.range_m == pytest.approx(5.4, abs=0.005)


@pytest.mark.parametrize("xy", [(2.3, 4.1), (4.0, 3.5), (1.2, 1.2), (7.2, 6.0)])
def test_trilateration_on_exact_ranges(xy):
    truth = np.array([xy[0], xy[1], TAG_Z])
    ranges = np.linalg.norm(ANCHORS - truth, axis=1)
    # Exact ranges: the three circle intersections coincide, so the centroid is exact too.
    for fix in (trilateral_centroid(ANCHORS, ranges, TAG_Z), least_squares_fix(ANCHORS, ranges, TAG_Z)):
        np.testing.assert_allclose(fix.position_m, truth, atol=1e-9)
        np.testing.assert_allclose(fix.residuals_m, 0.0, atol=1e-9)
    assert trilateral_centroid(ANCHORS, ranges, TAG_Z).used.sum() == 3


def test_gate_removes_a_planted_nlos_range():
    rng = np.random.default_rng(1)
    truth = np.array([2.7, 2.2, TAG_Z])
    ranges = np.linalg.norm(ANCHORS - truth, axis=1) + rng.normal(0.0, 0.02, 4)
    ranges[2] += 0.5  # NLOS on the north anchor
    use = gate_ranges(ANCHORS, ranges, TAG_Z, sigma_m=0.03)
    assert use.tolist() == [True, True, False, True]
    gated = least_squares_fix(ANCHORS, ranges, TAG_Z, use=use)
    plain = least_squares_fix(ANCHORS, ranges, TAG_Z)
    # 2 cm range noise through GDOP ~1.2: a few cm; the NLOS range pulls the ungated fix ~20 cm.
    assert np.linalg.norm(gated.position_m - truth) < 0.06
    assert np.linalg.norm(plain.position_m - truth) > 0.1
    # Clean ranges pass untouched.
    clean = np.linalg.norm(ANCHORS - truth, axis=1) + rng.normal(0.0, 0.02, 4)
    assert gate_ranges(ANCHORS, clean, TAG_Z, sigma_m=0.03).all()


def test_gdop_of_a_symmetric_square_and_of_collinear_anchors():
    # Tag in the anchors' plane at the centre of a square: H = (±1, 0), (0, ±1) → HᵀH = 2I → √(2·½) = 1.
    square = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert gdop(square, np.zeros(3)) == pytest.approx(1.0)
    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    assert gdop(line, np.array([5.0, 0.0, 0.0])) == float("inf")


def test_bad_input_raises_clear_errors():
    with pytest.raises(UwbLocalizationError, match="at least 3 anchors"):
        least_squares_fix(ANCHORS[:2], np.ones(2), TAG_Z)
    with pytest.raises(UwbLocalizationError, match="NaN"):
        trilateral_centroid(ANCHORS, np.array([1.0, np.nan, 1.0, 1.0]), TAG_Z)


def test_tracker_makes_one_fix_per_round_and_survives_a_missed_reply():
    anchors = {f"A{i}": a for i, a in enumerate(ANCHORS)}
    tracker = UwbTracker(anchors, TAG_Z, method="least_squares")
    truth = np.array([3.0, 3.0, TAG_Z])
    r = {a: float(np.linalg.norm(p - truth)) for a, p in anchors.items()}
    fixes = [tracker.add(RangeRecord(t, a, r[a])) for t, a in enumerate(["A0", "A1", "A2", "A3"])]
    assert fixes[:3] == [None, None, None] and fixes[3] is not None
    np.testing.assert_allclose(fixes[3].position_m, truth, atol=1e-9)
    # A2 does not answer: A0 again after A1, A3 → a fix from the three of the round.
    out = [tracker.add(RangeRecord(10 + t, a, r[a])) for t, a in enumerate(["A0", "A1", "A3", "A0"])]
    assert out[3] is not None and sorted(out[3].anchor_ids) == ["A0", "A1", "A3"]
    assert tracker.add(RangeRecord(20, "A9", 1.0)) is None and tracker.refused == 1


def _labyrinth_errors(method: str) -> np.ndarray:
    rows = [line.split() for line in (LABYRINTH / "Indoor_UWB_Input.txt").read_text().splitlines() if line.startswith("range2")]
    truth = {float(f[1]): (float(f[2]), float(f[3])) for f in (
        line.split() for line in (LABYRINTH / "Indoor_UWB_GT.txt").read_text().splitlines() if line.startswith("point2"))}
    anchors = {}
    for f in rows:
        anchors[f[6]] = np.array([float(f[4]), float(f[5]), 0.0])
    tracker = UwbTracker(anchors, 0.0, method=method, sigma_m=0.1)
    errors = []
    for f in rows:
        fix = tracker.add(RangeRecord(int(float(f[1]) * 1e9), f[6], float(f[2])))
        if fix is not None:
            gt = truth[float(f[1])]
            errors.append(np.hypot(fix.position_m[0] - gt[0], fix.position_m[1] - gt[1]))
    return np.array(errors)


@pytest.mark.parametrize("method", ["centroid", "least_squares"])
def test_real_labyrinth_uwb_against_ground_truth(method):
    if not LABYRINTH.is_dir():
        pytest.skip(f"real UWB data absent: {LABYRINTH} (see ../shared/data/MANIFEST.md)")
    errors = _labyrinth_errors(method)
    # 233 ranges round-robin over 4 anchors → ~58 fixes; the robot moves during a 0.5 s round,
    # so tens of cm are expected; 0.3 m mean fails a wrong anchor table or a wrong time match.
    assert len(errors) >= 50
    assert np.mean(errors) < 0.3, np.mean(errors)
