"""The check stage against a camera knocked mid-run (issue 25): the motion check's covariance of a
pose difference (common sources cancel), the planar odometry's noise (no drift in tilt or height)
and the stretch carried across changing codes as the camera's extrinsic. Unit tests on built
FrameResults, and a small qr_floor recording (seeded, 6 s, 640×512) with the camera knocked 1° /
2 cm at 3 s, replayed as if it had no truth."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from agvviz import scenarios as scenario_registry
from agvviz.geometry import se3, so3
from agvviz.geometry.euler import Rx
from agvviz.model.suspects import CAUSE_EXTRINSIC, CAUSE_MAP_ENTRY, CAUSE_UNKNOWN
from agvviz.replay.checks import CheckSettings, CheckStage
from agvviz.replay.checks.common import carried_difference_cov, is_planar_step, odometry_cov
from agvviz.replay.run import replay_frames
from agvviz.settings import RunSettings
from tests.test_checks import SMALL, frame, pose, straight_odometry

#: The knock: the AGV's pose as the camera sees it is off by a fixed body-frame transform.
KNOCK = se3.make(Rx(math.radians(1.0)), [0.0, 0.015, 0.025])


def test_planar_odometry_drifts_along_the_floor_only():
    cs = CheckSettings()
    step = pose(2.0, 0.0, math.radians(30))
    assert is_planar_step(step) and not is_planar_step(se3.make(Rx(0.01), [2.0, 0.0, 0.0]))
    C = odometry_cov(step, cs)
    sigma_rot = cs.odom_rad_per_m * 2.0 + cs.odom_rad_per_rad * math.radians(30)
    sigma_pos = cs.odom_m_per_m * 2.0 + 2.0 * sigma_rot
    np.testing.assert_allclose(np.sqrt(np.diag(C)), [sigma_pos, sigma_pos, cs.floor_height_m + 2.0 * cs.floor_tilt_rad,
                                                     cs.floor_tilt_rad, cs.floor_tilt_rad, sigma_rot])
    short = np.sqrt(np.diag(odometry_cov(pose(0.1), cs)))  # 0.1 m: a fifth of the floor's length
    np.testing.assert_allclose(short[2:5], [cs.floor_height_m / 5 + 0.1 * cs.floor_tilt_rad, cs.floor_tilt_rad / 5,
                                            cs.floor_tilt_rad / 5])
    # a 3-D odometry (an INS): every axis alike
    C3 = odometry_cov(se3.make(Rx(0.01), [2.0, 0.0, 0.0]), cs)
    assert np.allclose(np.diag(C3)[:3], np.diag(C3)[0]) and np.allclose(np.diag(C3)[3:], np.diag(C3)[3])


def test_carried_difference_cancels_what_two_poses_share():
    """Two frames with the same camera factor: the shared error cancels; with no factors the two
    covariances add (and the reference's rotation swings the carried position)."""
    S = np.zeros((6, 2))
    S[0, 0], S[4, 1] = 0.01, 0.02  # 10 mm along x, 20 mrad about y: large against the floors
    cov = S @ S.T
    a = replace(frame(0, pose(0.0)), cov_world_agv=cov, cov_common_factors={"camera": S})
    b = replace(frame(1, pose(0.0)), cov_world_agv=cov, cov_common_factors={"camera": S})
    cs = CheckSettings()
    shared = carried_difference_cov(a, a.T_world_agv, b, cs)
    np.testing.assert_allclose(shared, 2 * np.diag([cs.pose_floor_m**2] * 3 + [cs.pose_floor_rad**2] * 3), atol=1e-15)
    a, b = replace(a, cov_common_factors=None), replace(b, cov_common_factors=None)
    apart = carried_difference_cov(a, a.T_world_agv, b, cs)
    assert apart[0, 0] == pytest.approx(2 * 0.01**2 + 2 * cs.pose_floor_m**2)
    carried = carried_difference_cov(a, pose(1.0), b, cs)  # carried 1 m along x: rotation about y moves z
    assert carried[2, 2] == pytest.approx(apart[2, 2] + 0.02**2 + cs.pose_floor_rad**2)


def test_a_knocked_camera_stays_flagged_as_its_extrinsic_across_codes():
    """From frame 5 on every pose is off by the same body-frame offset (1°, 3 cm) while the codes
    change every 4 frames; 20 m of travel (the carried reference's σ grows far past the offset
    along the floor): the jump is unknown, every frame after it is the camera's extrinsic."""
    stage = CheckStage(CheckSettings(), straight_odometry(1.0))
    codes = [f"Q{n:03d}" for n in range(1, 60)]
    out = []
    for i in range(200):
        T = pose(0.1 * i)
        if i >= 5:
            T = T @ KNOCK
        out.append(stage.check(frame(i, T, markers=(codes[i // 4],))))
    assert all(f.suspect is None for f in out[:5])
    assert out[5].suspect is not None and out[5].suspect.cause == CAUSE_UNKNOWN
    for f in out[6:]:
        assert f.suspect is not None and f.suspect.cause == CAUSE_EXTRINSIC, (f.index, f.suspect)
        assert f.suspect.marker_id is None and f.suspect.cam_name == "front"
    assert "across codes" in out[-1].suspect.message and "extrinsic" in out[-1].suspect.message


def test_a_map_entry_stretch_ends_with_its_code():
    """A wrong map entry moves the pose only while its code is in view: the next code's frames are clean."""
    stage = CheckStage(CheckSettings(), straight_odometry(1.0), lambda: {"Q001": None, "Q002": None, "Q003": None})
    out = [stage.check(frame(i, pose(0.1 * i), markers=("Q001",))) for i in range(5)]
    out += [stage.check(frame(i, pose(0.1 * i, 0.05), markers=("Q002",))) for i in range(5, 10)]
    out += [stage.check(frame(i, pose(0.1 * i), markers=("Q003",))) for i in range(10, 15)]
    assert all(f.suspect is None for f in out[:5] + out[10:])
    assert all(f.suspect is not None and f.suspect.cause == CAUSE_MAP_ENTRY and f.suspect.marker_id == "Q002" for f in out[5:10])


@pytest.fixture(scope="module")
def knocked(tmp_path_factory):
    path = tmp_path_factory.mktemp("knock") / "knocked.mcap"
    scenario_registry.record("qr_floor", path, seed=1, overrides=SMALL + ["inject=camera:front:pitch_deg=1,dz_m=0.02,from_s=3"])
    return path


def test_frames_after_a_knock_are_flagged_as_the_extrinsic_without_truth(knocked):
    scored = list(replay_frames(knocked, RunSettings()))
    blind = list(replay_frames(knocked, RunSettings(truth="ignore")))
    assert [f.suspect for f in blind] == [f.suspect for f in scored]  # truth is never read
    solved = [f for f in scored if f.solved]
    t0 = solved[0].log_time_ns
    before = [f for f in solved if f.log_time_ns - t0 < 2.9e9]
    after = [f for f in solved if f.log_time_ns - t0 >= 3.0e9]
    assert len(before) >= 20 and len(after) >= 20
    assert all(f.position_error_m > 0.02 for f in after)  # truth only to judge: the knock is 3 cm at the AGV
    assert all(f.suspect is None for f in before)
    assert all(f.suspect is not None for f in after), [f.index for f in after if f.suspect is None]
    named = [f for f in after if f.suspect.cause == CAUSE_EXTRINSIC]
    assert len(named) >= 0.9 * len(after) and all(f.suspect.cam_name == "front" for f in named)
