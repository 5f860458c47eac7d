"""Paper 002's correction cycle (agvviz.replay.correct): window bookkeeping, latency compensation
through T_F_G, gates, and the replay + run integration on an auv_under_ice recording."""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.model.correction import FrameSighting
from agvviz.replay.correct import (
    CorrectionCycle,
    CorrectionError,
    CorrectionReplay,
    CorrectionSettings,
)
from agvviz.geometry import se3
from agvviz.geometry.euler import matrix_from_hpr
from agvviz.sim import auv


def _marker_world(T_world_F: np.ndarray, distance_m: float, lateral_m: float) -> np.ndarray:
    return se3.transform_points(T_world_F @ auv.T_F_marker_ahead(distance_m, lateral_m, 0.5), auv.marker_corners_marker())


def _drive(cycle: CorrectionCycle, T_world_F_true: np.ndarray, T_world_F_nav: np.ndarray, n_frames: int, step_m: float,
           markers: list[np.ndarray], rng=None, sigma_px: float = 0.0, t0_ns: int = 0):
    """Straight drive along F's +y; the navigation is the truth moved rigidly by the start error
    (so relative motion is exact). Returns the events."""
    cam, mounts = auv.camera(), auv.camera_mounts()
    events = []
    for k in range(n_frames):
        T_F_agv = se3.make(np.eye(3), [0.0, step_m * k, 0.0])
        T_world_agv = T_world_F_true @ T_F_agv
        sightings = []
        for name, T_agv_cam in mounts.items():
            T_cam_world = se3.inverse(T_world_agv @ T_agv_cam)
            for i, corners in enumerate(markers):
                P = se3.transform_points(T_cam_world, corners)
                if np.all(P[:, 2] > 0.5):
                    px = cam.project(P)
                    if rng is not None:
                        px = px + rng.normal(0.0, sigma_px, px.shape)
                    sightings.append(FrameSighting(str(i), name, corners, px, cam.K))
        event = cycle.add_frame(t0_ns + k * 100_000_000, T_world_F_nav @ T_F_agv, sightings)
        if event is not None:
            events.append(event)
    return events


def test_a_cycle_corrects_the_current_pose_through_the_motion_during_the_cycle():
    T_world_F = se3.make(matrix_from_hpr(0.4, 0.02, -0.01), [30.0, -12.0, -8.0])
    # The navigation is off by 4 m and 1°: the correction must remove it exactly (noise-free).
    T_world_F_nav = se3.make(matrix_from_hpr(0.4 + 0.0174, 0.02, -0.01), [33.0, -9.5, -8.5])
    markers = [_marker_world(T_world_F, 10.0, 2.0), _marker_world(T_world_F, 14.0, -2.5)]
    cycle = CorrectionCycle(CorrectionSettings(cycle_distance_m=2.0), auv.camera_mounts())
    events = _drive(cycle, T_world_F, T_world_F_nav, 22, 0.1, markers)
    assert len(events) == 1
    e = events[0]
    assert e.applied and e.n_frames == 21 and e.n_sightings > 40
    np.testing.assert_allclose(e.T_world_F_after, T_world_F, atol=1e-7)
    # G is 2 m ahead of F; the corrected current pose is the true pose there, not F's.
    T_world_G_true = T_world_F @ se3.make(np.eye(3), [0.0, 2.0, 0.0])
    np.testing.assert_allclose(e.T_world_G_after, T_world_G_true, atol=1e-7)
    assert e.jump_m == pytest.approx(np.linalg.norm(e.T_world_G_before[:3, 3] - T_world_G_true[:3, 3]))
    # The correction stays applied to later navigation poses.
    T_nav_later = T_world_F_nav @ se3.make(np.eye(3), [0.0, 2.1, 0.0])
    np.testing.assert_allclose(cycle.corrected(T_nav_later)[:3, 3], (T_world_F @ se3.make(np.eye(3), [0.0, 2.1, 0.0]))[:3, 3], atol=1e-6)
    # The closing frame G is frame 0 of the next cycle; the frame after it is frame 1.
    assert cycle.frame_times_ns == [e.log_time_ns, e.log_time_ns + 100_000_000]
    assert cycle.sightings and {s.frame_index for s in cycle.sightings} == {1}


def test_cycles_without_enough_information_leave_the_navigation_alone():
    T_world_F = se3.make(np.eye(3), [0.0, 0.0, -10.0])
    cycle = CorrectionCycle(CorrectionSettings(cycle_distance_m=1.0), auv.camera_mounts())
    events = _drive(cycle, T_world_F, T_world_F, 12, 0.1, [])
    assert len(events) == 1 and not events[0].applied
    assert "0 marker sighting(s)" in events[0].reason
    np.testing.assert_array_equal(cycle.T_correction, np.eye(4))
    # One far, on-axis marker with 1.5 px noise: F is poorly determined → gated by its σ.
    cycle = CorrectionCycle(CorrectionSettings(cycle_distance_m=1.0), auv.camera_mounts())
    far = [se3.transform_points(T_world_F @ auv.T_F_marker_ahead(15.0, 0.0, 0.0), auv.marker_corners_marker())]
    events = _drive(cycle, T_world_F, T_world_F, 12, 0.1, far, np.random.default_rng(3), 1.5)
    assert not events[0].applied and "position σ" in events[0].reason
    np.testing.assert_array_equal(cycle.T_correction, np.eye(4))


def test_settings_and_unknown_cameras_are_refused_clearly():
    with pytest.raises(CorrectionError, match="cycle_distance_m"):
        CorrectionSettings(cycle_distance_m=0.0)
    with pytest.raises(CorrectionError, match="cnoem or bundle"):
        CorrectionSettings(solver="ippe")
    cycle = CorrectionCycle(CorrectionSettings(), {})
    s = FrameSighting("0", "front", np.zeros((4, 3)), np.zeros((4, 2)), np.eye(3))
    with pytest.raises(CorrectionError, match="no extrinsic"):
        cycle.add_frame(0, np.eye(4), [s])


@pytest.fixture(scope="module")
def route_recording(tmp_path_factory):
    from agvviz import scenarios as scenario_registry

    path = tmp_path_factory.mktemp("auv") / "auv.mcap"
    scenario_registry.record("auv_under_ice", path, seed=4, overrides=["duration_s=24", "realism=ideal"])
    return path


@pytest.mark.parametrize("solver", ["cnoem", "bundle"])
def test_correction_replay_beats_the_drifting_navigation(route_recording, solver):
    from agvviz.replay.solve import Replay
    from agvviz.recording.reader import iter_messages
    from agvviz.settings import RunSettings

    replay = Replay(RunSettings())
    correction = CorrectionReplay(CorrectionSettings(solver=solver, cycle_distance_m=3.0), replay.ctx.cameras, replay.sync)
    steps = []
    for message in iter_messages(route_recording):
        steps += correction.feed(message, replay.feed(message))
    steps += correction.finish()
    assert len(steps) == 241  # 24 s at 10 Hz, one step per frame time
    events = [s.event for s in steps if s.event is not None]
    assert len(events) == 8 and sum(e.applied for e in events) >= 6
    nav = np.array([np.linalg.norm(s.T_world_agv_nav[:3, 3] - s.T_world_agv_truth[:3, 3]) for s in steps])
    corrected = np.array([np.linalg.norm(s.T_world_agv_corrected[:3, 3] - s.T_world_agv_truth[:3, 3]) for s in steps])
    # The INS/DVL drift grows to ≈0.3 m in 24 m; corrections hold the error at a few cm (the
    # navigation's own 1 % relative error over a 3 m cycle is 3 cm).
    assert nav[-1] > 0.2
    assert np.sqrt(np.mean(corrected[120:] ** 2)) < 0.5 * np.sqrt(np.mean(nav[120:] ** 2))


def test_agvviz_run_with_correction_writes_the_window_and_events(route_recording, tmp_path):
    from agvviz.app.run import run_recording
    from agvviz.settings import RunSettings
    from agvviz.viz import paths
    from agvviz.viz.readback import _rows, read_rrd, scalar_series, text_logs

    out = tmp_path / "run.rrd"
    outcome = run_recording(route_recording, RunSettings(correction="cnoem", cycle_distance_m=3.0), out)
    summary = outcome.summary["correction"]
    assert summary["cycles"] == 8 and summary["corrections_applied"] >= 6
    assert summary["corrected_rmse_m"] < summary["nav_rmse_m"]
    contents = read_rrd(out)
    for entity in (paths.CORRECTION_TRAJECTORY_TRUTH, paths.CORRECTION_TRAJECTORY_NAV, paths.CORRECTION_TRAJECTORY_CORRECTED, paths.CORRECTION_WINDOW_CAMERAS,
                   paths.correction_observed("left"), paths.correction_theoretical("right"), paths.CORRECTION_COST_PER_ITERATION):
        assert entity in contents.entity_paths, entity
    logs = text_logs(contents, paths.EVENTS_CORRECTIONS)
    assert len(logs) == 8 and sum(": jump " in text.splitlines()[0] for _, _, text in logs) == summary["corrections_applied"]
    iters, costs = scalar_series(contents, paths.CORRECTION_COST, timeline=paths.TIMELINE_CNOEM_ITER)
    assert iters.min() == 0 and np.all(np.isfinite(costs))
    # The iteration timeline must not leak onto per-frame data.
    assert all(row.get(paths.TIMELINE_CNOEM_ITER) is None for row in _rows(contents, paths.ERROR_CORRECTED_MM, "Scalars:scalars"))
    # Theoretical corners: one batch per iteration on cnoem_iter, the last on the observed ones.
    rows = _rows(contents, paths.correction_theoretical("left"), "Points2D:positions")
    assert rows and all(row.get(paths.TIMELINE_CNOEM_ITER) is not None for row in rows)
