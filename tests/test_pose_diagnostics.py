"""Pose diagnostics in the replay and the run .rrd: covariance, CRLB, NEES, ambiguity ratio,
ghost pose, flips, planar solver, odometry-based resolution — end to end on rendered frames,
then read back from the .rrd with Rerun's chunk API."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agvviz.geometry import se3
from agvviz.replay.graph import replay
from agvviz.model.messages import PoseMsg
from agvviz.settings import RunSettings, SettingsError, apply_overrides
from agvviz.viz import paths
from agvviz.viz.readback import read_rrd, scalar_series, text_logs
from agvviz.viz.run_logger import RunLogger
from test_pipeline import GOOD_CODE, _frame, _msg, _render, _static_messages


@pytest.fixture(scope="module")
def messages():
    """Two frames of the same view (different sensor noise), each with odometry."""
    out = _static_messages()
    for k, t_ns in enumerate((1_000, 2_000)):
        out.append(_msg("/agv/odometry", t_ns, PoseMsg("odom", np.eye(4))))
        out += _frame(t_ns, _render(GOOD_CODE, seed=k))
    return out


def test_solved_frames_carry_covariance_bound_nees_and_ambiguity(messages):
    # covariance=pixel: pixel noise alone, the CRLB's model (the full covariance adds the
    # systematic sources: tests/test_uncertainty_systematic.py, and below).
    frames = list(replay(messages, RunSettings(sigma_px="0.05", covariance="pixel")))
    full = list(replay(messages, RunSettings(sigma_px="0.05")))
    for f, g in zip(frames, full):
        assert np.all(np.linalg.eigvalsh(g.cov_world_agv - f.cov_world_agv) > 0)
    assert [f.rejected for f in frames] == [None, None]
    for f in frames:
        assert f.n_points == 4 and f.sigma_px == 0.05
        assert f.cov_world_agv.shape == (6, 6) and np.all(np.linalg.eigvalsh(f.cov_world_agv) > 0)
        # Position σ from the covariance and the CRLB at truth: the same geometry, so within
        # a few % of each other (estimate vs true pose differ by < 1 mm).
        assert f.position_sigma_m == pytest.approx(f.crlb_position_m, rel=0.05)
        assert f.position_over_crlb == pytest.approx(f.position_error_m / f.crlb_position_m)
        assert np.isfinite(f.nees) and f.nees_dof == 6
        assert f.ambiguity_ratio > 1.0  # a 330 px code at 1.8 m: clearly not ambiguous
        assert f.T_world_agv_ghost is not None and se3.is_rigid(f.T_world_agv_ghost)
        assert not f.flipped
    assert frames[0].ambiguity_rule == "lowest_error"


def test_odometry_policy_uses_the_odometry_on_the_second_frame(messages):
    frames = list(replay(messages, RunSettings(ambiguity="odometry")))
    assert [f.ambiguity_rule for f in frames] == ["lowest_error", "odometry"]
    # The vehicle did not move and odometry says so: the same branch both times, no flip.
    assert not frames[1].flipped
    assert frames[1].position_error_m < 2e-3


def test_planar_solver_in_the_replay(messages):
    lm = list(replay(messages, RunSettings()))
    planar = list(replay(messages, RunSettings(solver="planar")))
    assert all(f.solved for f in planar), [f.reject_detail for f in planar]
    for f_lm, f_pl in zip(lm, planar):
        assert f_pl.nees_dof == 3 and f_pl.ambiguity_rule.startswith("planar solver")
        # Height and tilt come from the mounting: the planar model's bound is below the 6-DoF one.
        assert f_pl.crlb_position_m < f_lm.crlb_position_m


def test_sigma_px_setting_is_validated():
    assert apply_overrides(RunSettings(), ["sigma_px=0.3"]).sigma_px_value == 0.3
    assert RunSettings().sigma_px_value is None
    for bad in ("sigma_px=-1", "sigma_px=abc", "ambiguity=vote"):
        with pytest.raises(SettingsError):
            apply_overrides(RunSettings(), [bad])


def test_new_entities_read_back_from_the_rrd(messages, tmp_path):
    frames = list(replay(messages, RunSettings()))
    frames[1] = dataclasses.replace(frames[1], flipped=True)  # as the pipeline would mark a branch switch
    out = tmp_path / "run.rrd"
    with RunLogger(out, recording_name="diag", recording_id="diag") as logger:
        for f in frames:
            logger.log_frame(f)
    contents = read_rrd(out)
    for entity, attribute in (
        (paths.ERROR_NEES, "nees"),
        (paths.ERROR_POSITION_OVER_CRLB, "position_over_crlb"),
        (paths.ERROR_CRLB_POSITION_M, "crlb_position_m"),
        (paths.ERROR_POSITION_SIGMA_M, "position_sigma_m"),
    ):
        index, values = scalar_series(contents, entity)
        assert list(index) == [0, 1]
        np.testing.assert_array_equal(values, [getattr(f, attribute) for f in frames])
    # The NEES view's lines: χ²₆'s mean and 99 % quantile on every frame with a NEES.
    _, expected = scalar_series(contents, paths.ERROR_NEES_EXPECTED)
    _, bound = scalar_series(contents, paths.ERROR_NEES_BOUND_99)
    np.testing.assert_array_equal(expected, [6.0, 6.0])
    np.testing.assert_allclose(bound, [16.811894, 16.811894])  # scipy.stats.chi2.ppf(0.99, 6)
    _, ratios = scalar_series(contents, paths.SOLVER_AMBIGUITY_RATIO)
    np.testing.assert_array_equal(ratios, [min(f.ambiguity_ratio, 100.0) for f in frames])
    logs = text_logs(contents, paths.EVENTS_FLIPS)
    assert [(frame, level) for frame, level, _ in logs] == [(1, "WARN")] and "flipped" in logs[0][2]
    assert paths.AGV_CAMERA_POSITION_COV in contents.entity_paths
    # The mirror pose is drawn only on frames where it is a real contender.
    from agvviz.viz.log_uncertainty import GHOST_MAX_AMBIGUITY_RATIO

    contenders = [f for f in frames if f.ambiguity_ratio is not None and f.ambiguity_ratio < GHOST_MAX_AMBIGUITY_RATIO
                  and f.T_world_agv_ghost is not None]
    assert (paths.AGV_GHOST in contents.entity_paths) == bool(contenders)
