"""uwb_room end to end: record a short path with a blocked stretch, run it, read the .rrd back
(ranges, gates, trajectories, switch events, camera used); the pose chain of world-fixed
cameras; the joint multi-camera LM."""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.geometry import euler, se3
from agvviz.replay.solve import agv_pose_from_marker
from agvviz.recording.contract import inspect_recording
from agvviz.solvers.multi_camera import RigView, refine_rig_pose
from agvviz.viz import paths
from agvviz.viz.readback import _rows, document_json, read_rrd, scalar_series, text_logs
from agvviz.viz.log_uwb import NO_CAMERA

# 3 s at 5 Hz (15 time stamps × 4 cameras), cameras blocked from 1.0 s to 2.0 s: recorded and
# replayed once per session by conftest.uwb_room_small_run (test_fusion_views uses it too).
@pytest.fixture(scope="module")
def room_run(uwb_room_small_run):
    return uwb_room_small_run


def test_recording_meets_contract(room_run):
    recording, _ = room_run
    report = inspect_recording(recording)
    assert report.ok, report.violations + report.damage
    assert sorted(report.cameras) == ["east", "north", "south", "west"]
    counts = {t.topic: t.count for t in report.topics}
    assert counts["/uwb/range"] == 3 * 10 * 4 and counts["/cam/south/image"] == 15


def test_camera_uwb_and_fusion_figures(room_run):
    _, outcome = room_run
    f = outcome.summary["fusion"]
    # 10 of 15 time stamps have the code in view; the best wall camera sees a 30–70 px code
    # with ~0.1 px ECC corners: a few mm (paper 003: 12.9 mm dynamic). 10 mm fails a wrong
    # transform chain (decimetres) without flaking.
    assert f["camera_xy_error_mm"]["n"] == 10
    assert f["camera_xy_error_mm"]["mean"] < 10.0
    # UWB fixes: centimetres (noise 3 cm, clock-drift biases, NLOS); 0.25 m fails a broken fix.
    assert 0 < f["uwb_xy_error_mm"]["mean"] < 250.0
    assert f["fused_blocked_xy_error_mm"]["n"] > 0
    assert f["switches"] == 2  # camera → UWB at the blockage, UWB → camera after it


def test_rrd_holds_ranges_gates_trajectories_and_switch_events(room_run):
    _, outcome = room_run
    contents = read_rrd(outcome.out_path)
    for entity in (
        paths.UWB_ANCHORS, paths.TRAJECTORY_UWB, paths.TRAJECTORY_FUSED, paths.TRAJECTORY_TRUTH,
        paths.FUSION_CAMERA_USED, paths.ERROR_UWB_POSITION_MM, paths.ERROR_FUSED_POSITION_MM, paths.UWB_GDOP,
        paths.image("south", fixed=True), paths.detected("north", fixed=True),
    ):
        assert entity in contents.entity_paths, entity
    for anchor in ("A_south", "A_east", "A_north", "A_west"):
        _, measured = scalar_series(contents, paths.uwb_range(anchor, "measured"), paths.TIMELINE_TIME)
        _, from_truth = scalar_series(contents, paths.uwb_range(anchor, "predicted_truth"), paths.TIMELINE_TIME)
        assert len(measured) == len(from_truth) == 30
        # Measured − true range: noise + drift bias + occasional NLOS, never metres.
        assert np.median(np.abs(measured - from_truth)) < 0.2
        _, gate = scalar_series(contents, paths.uwb_gate(anchor), paths.TIMELINE_TIME)
        assert set(np.unique(gate)) <= {0.0, 1.0}
    events = text_logs(contents, paths.EVENTS_FUSION)
    assert len(events) == 2
    assert events[0][2].startswith("camera → uwb: offset (δx, δy) = (") and " jump " in events[0][2]
    assert events[1][2].startswith("uwb → camera:")
    # The camera used is a category logged when it changes: a camera, none while blocked, a camera.
    used = [row["StateChange:state"][0] for row in _rows(contents, paths.FUSION_CAMERA_USED, "StateChange:state")]
    assert len(used) == 3 and used[1] == NO_CAMERA and NO_CAMERA not in (used[0], used[2])
    assert document_json(contents, paths.RUN_SUMMARY)["fusion"]["fusion"] == "mean_compensation"


def test_agv_pose_from_a_marker_on_the_agv_seen_by_a_wall_camera():
    rng = np.random.default_rng(5)
    T_world_agv = se3.make(euler.Rz(0.7), [3.1, 2.4, 0.0])
    T_agv_marker = se3.make(np.eye(3), [0.0, 0.0, 0.35])
    T_world_cam = se3.make(euler.Rx(-2.2), [4.0, 0.05, 2.8])
    T_cam_marker = se3.inverse(T_world_cam) @ T_world_agv @ T_agv_marker
    _, T = agv_pose_from_marker(T_cam_marker, "agv", T_agv_marker, None, T_world_cam)
    np.testing.assert_allclose(T, T_world_agv, atol=1e-12)
    # Paper 000's chain (marker in the world, camera on the AGV) through the same function.
    T_world_marker = se3.make(euler.Rz(rng.uniform(-3, 3)), [1.0, 2.0, 0.0])
    T_agv_cam = se3.make(euler.Rx(-2.0), [0.0, 0.0, 1.5])
    T_cam_marker = se3.inverse(T_world_agv @ T_agv_cam) @ T_world_marker
    _, T = agv_pose_from_marker(T_cam_marker, "world", T_world_marker, T_agv_cam, None)
    np.testing.assert_allclose(T, T_world_agv, atol=1e-12)
    with pytest.raises(ValueError, match="says nothing about the AGV"):
        agv_pose_from_marker(T_cam_marker, "world", T_world_marker, None, T_world_cam)


def test_joint_multi_camera_lm_recovers_the_pose_from_exact_corners():
    from agvviz.scenarios import uwb_room

    o = uwb_room.Options()
    camera = uwb_room.make_camera(o).without_distortion()
    T_world_agv = se3.make(euler.Rz(0.4), [3.6, 2.9, 0.0])
    corners_agv = uwb_room.marker_corners_agv(o)
    views = []
    for T_world_cam in uwb_room.camera_poses(o).values():
        T_cam_world = se3.inverse(T_world_cam)
        px = camera.project(se3.transform_points(T_cam_world @ T_world_agv, corners_agv))
        views.append(RigView(camera.K, T_cam_world, corners_agv, px))
    start = se3.exp(np.array([0.02, -0.01, 0.01, 0.01, -0.02, 0.01])) @ T_world_agv
    T, rms_px = refine_rig_pose(start, views)
    np.testing.assert_allclose(T, T_world_agv, atol=1e-8)
    assert rms_px < 1e-6
