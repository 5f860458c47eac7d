"""Injected faults (agvviz/sim/inject.py, issue 25): a payload with wrong coordinates, a camera
knocked mid-run (``from_s``), a camera time offset, and the exact truth of each in the draws.

Every recording here is ``ideal`` (only the render's 0.8 px blur, 2 DN noise and JPEG remain), so
the replay's pose is the truth to the ideal world's accuracy and whatever else it shows is the
injected fault. Tolerances: :data:`IDEAL_MM` is that accuracy at this small camera (640×512,
f = 500 px, the codes ≈1.8 m away; qr_floor's marker-family test measures ≈2 mm, bounds 20 mm);
the faults are ≥ 30 mm, so each check separates "the fault as injected" from "no fault".
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agvviz import scenarios as scenario_registry
from agvviz.geometry import se3
from agvviz.markers.payload import parse_payload
from agvviz.recording.mcap_stream import realism_draws
from agvviz.replay.run import replay_frames
from agvviz.scenarios import ScenarioError
from agvviz.scenarios import qr_floor as q
from agvviz.settings import RunSettings
from agvviz.sim import inject as inj
from agvviz.sim import realism as rl
from agvviz.sim.trajectory import forward_camera_mount, sample_track, track_pose

# 15 frames of a half-size camera at 5 Hz: ≈1 s to record, ≈1 s to replay.
SMALL = ["duration_s=3", "rate_hz=5", "realism=ideal", "width_px=640", "height_px=512", "focal_px=500", "supersample=2"]
#: The ideal world's position accuracy here (see the module docstring), mm.
IDEAL_MM = 8.0
#: Rotation accuracy in the same world, degrees (≈0.1° measured; a 1° knock is 10×).
IDEAL_DEG = 0.3
#: One code per frame: the injected code's effect is that frame's pose, not a share of a joint one.
LARGEST = dataclasses.replace(RunSettings(), markers="largest", tracking=False)


def _options(extra=()):
    return scenario_registry.build_options("qr_floor", SMALL + list(extra))


def _truth(o, t_s: float) -> np.ndarray:
    """True ``T_world_agv`` (flat floor: ideal) ``t_s`` after the first stamp."""
    return track_pose(q.make_track(o), o.speed_mps, t_s)


def _code_in_view(o) -> str:
    """The code the camera sees whole in the most frames (from the scenario's own geometry)."""
    scene = q.build_scene(o, np.random.default_rng(SEED))
    trajectory = sample_track(q.make_track(o), o.speed_mps, o.rate_hz, o.duration_s)
    T_cam = [T @ forward_camera_mount(o.cam_height_m, o.cam_lookahead_m) for T in trajectory.T_world_agv]
    counts = {c.marker_id: len(inj.frames_in_view(q.make_camera(o), T_cam, c.points_world_m[:4], trajectory.log_time_ns))
              for c in scene.codes}
    return max(counts, key=counts.get)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


SEED = 4


# -- parsing, bounds, targets ----------------------------------------------------------------
def test_new_kinds_parse():
    spec = inj.parse_inject("payload:Q014:dx_m=0.2,dy_m=-0.0005;camera:front:pitch_deg=1,dz_m=0.02,from_s=10;"
                            "timing:front:offset_ms=30")
    assert spec.payloads()["Q014"].values == {"dx_m": 0.2, "dy_m": -0.0005}
    assert spec.cameras()["front"].from_s == 10.0
    assert spec.timings()["front"].values == {"offset_ms": 30.0}
    assert inj.parse_inject("camera:front:dz_m=0.02").cameras()["front"].from_s is None


@pytest.mark.parametrize("bad,words", [
    ("payload:Q1:yaw_deg=1", "payload key among: dx_m, dy_m, dz_m"),
    ("payload:Q1:dx_m=0.00005", "multiple of 0.0001 m"),
    ("payload:Q1:dx_m=11", "|dx_m| must be ≤ 10"),
    ("camera:front:dz_m=0.01,from_s=-1", "from_s must lie in 0..3600 s"),
    ("camera:front:from_s=2", "from_s alone moves nothing"),
    ("timing:front:offset_ms=1001", "|offset_ms| must be ≤ 1000"),
    ("timing:front:delay_ms=3", "timing key among: offset_ms"),
    ("lamp:Q1:dx_m=1", "kind 'lamp' is not one of: marker, payload, camera, timing"),
])
def test_bad_items_are_one_line_errors_naming_key_and_range(bad, words):
    with pytest.raises(ValueError) as info:
        inj.parse_inject(bad)
    assert words in str(info.value) and "\n" not in str(info.value), str(info.value)


@pytest.mark.parametrize("extra,words", [
    (["inject=timing:rear:offset_ms=30"], "timing: the scenario has no camera 'rear'"),
    (["inject=camera:rear:dz_m=0.01,from_s=1"], "camera: the scenario has no camera 'rear'"),
    (["inject=timing:front:offset_ms=120"], "|offset_ms| must be < 99.4 ms"),  # 100 ms less typical 0.1 ms + 5 · 0.1 ms
    (["inject=camera:front:dz_m=0.01,from_s=2.9"], "from_s must lie in 0..2.8 s (the last frame's time)"),
    (["marker_family=DICT_APRILTAG_36h11", "inject=payload:0:dx_m=0.1"], "payload needs QR codes"),
    (["marker_family=DICT_APRILTAG_36h11", "write_map=false"], "write_map=false needs marker_family=qr"),
])
def test_scenario_refuses_impossible_injections(extra, words):
    over = [s for s in SMALL if not s.startswith("realism=")] + extra
    with pytest.raises(ScenarioError) as info:
        scenario_registry.build_options("qr_floor", over)
    assert words in str(info.value), str(info.value)


def test_unknown_targets_are_refused_before_recording():
    for item, words in [("payload:Q999:dx_m=0.1", "no QR code 'Q999'"), ("marker:Q999:dx_m=0.1", "no marker 'Q999'")]:
        with pytest.raises(ScenarioError, match=None) as info:
            scenario_registry.build_options("qr_floor", SMALL + [f"inject={item}"])
        assert words in str(info.value), str(info.value)
    o = _options()  # the ids validate checks are the scene's
    ids = [c.marker_id for c in q.build_scene(o, np.random.default_rng(SEED)).codes]
    assert q.marker_ids(q.QR_FAMILY, len(ids)) == ids
    aruco = _options(["marker_family=DICT_APRILTAG_36h11"])
    assert q.marker_ids(aruco.marker_family, len(ids)) == [c.marker_id for c in q.build_scene(aruco, np.random.default_rng(SEED)).codes]


# -- the pieces, exactly -----------------------------------------------------------------------
def test_payload_text_carries_the_shift_and_the_map_does_not():
    o = _options()
    scene = q.build_scene(o, np.random.default_rng(SEED))
    code = scene.codes[7]
    shift = np.array([0.2, -0.0005, 0.0])
    moved = inj.apply_to_payload(code, inj.parse_inject(f"payload:{code.marker_id}:dx_m=0.2,dy_m=-0.0005").payloads()[code.marker_id])
    np.testing.assert_allclose(parse_payload(moved.payload).points_world_m, code.points_world_m + shift, atol=1e-12)
    assert moved.marker_id == code.marker_id and moved.side_m == code.side_m
    np.testing.assert_array_equal(moved.T_world_marker, code.T_world_marker)  # printed where it belongs
    assert not np.array_equal(moved.modules, code.modules)  # another text, another symbol
    mapped = next(m for m in q.marker_map(scene)["markers"] if m["id"] == code.marker_id)
    np.testing.assert_allclose(mapped["corners_world_m"], code.points_world_m[:4], atol=1e-12)
    np.testing.assert_allclose(parse_payload(mapped["payload"]).points_world_m, code.points_world_m, atol=1e-12)


def test_knocked_mount_and_offset_are_exact():
    T = forward_camera_mount(1.5, 1.0)
    item = inj.parse_inject("camera:front:pitch_deg=1,dz_m=0.02,from_s=1").cameras()["front"]
    after = inj.knocked_mount(T, item)
    phi = np.radians([1.0, 0.0, 0.0])
    # R_after·R_trueᵀ = Exp(φ) about the AGV's x: a 1° rotation, axis x
    delta = after[:3, :3] @ T[:3, :3].T
    assert abs(_angle_deg(delta) - 1.0) < 1e-9 and abs(delta[2, 1] - np.sin(phi[0])) < 1e-12
    np.testing.assert_allclose(after[:3, 3] - T[:3, 3], [0.0, 0.0, 0.02], atol=1e-15)
    assert inj.knocked_mount(T, None) is T
    assert not inj.knocked(item, 0.999) and inj.knocked(item, 1.0)
    # with from_s the recorded extrinsic stays as drawn (only the true mount moves)
    cam = rl.draw_calibration(rl.PROFILES["ideal"].calibration, rl.source_rng(0, "calibration"),
                              {"front": (q.make_camera(q.Options()), T)})["front"]
    kept = inj.apply_to_camera(cam, item)
    np.testing.assert_array_equal(kept.T_parent_cam_recorded, cam.T_parent_cam_recorded)
    assert kept.delta["injected"] == {"pitch_deg": 1.0, "dz_m": 0.02, "from_s": 1.0}
    timing = rl.CameraTiming(np.array([0, 100, -50], dtype=np.int64), np.zeros(3, bool))
    shifted = inj.apply_to_timing(timing, inj.parse_inject("timing:front:offset_ms=30").timings()["front"])
    np.testing.assert_array_equal(shifted.delay_ns, [30_000_000, 30_000_100, 29_999_950])


# -- recordings replayed against truth -----------------------------------------------------------
def test_payload_shift_moves_the_pose_without_a_map_and_is_refused_with_one(tmp_path):
    o = _options()
    target = _code_in_view(o)
    shift = np.array([0.15, -0.1, 0.0])
    item = f"inject=payload:{target}:dx_m=0.15,dy_m=-0.1"
    # Without /markers/map the payload is the only source of coordinates: the replay decodes the
    # shifted text and the AGV lands shifted by exactly that (a translation of the whole code).
    bare = tmp_path / "bare.mcap"
    scenario_registry.record("qr_floor", bare, seed=SEED, overrides=SMALL + [item, "write_map=false"])
    draws = realism_draws(bare)["sources"]["inject"][0]
    assert draws["kind"] == "payload" and draws["target"] == target and len(draws["frames_in_view_ns"]) >= 3
    used = 0
    for r in replay_frames(bare, LARGEST):
        if r.used_marker_id != target:
            if r.solved:
                assert r.position_error_m * 1000 < IDEAL_MM, (r.index, r.position_error_m)
            continue
        used += 1
        seen = next(ob for ob in r.observations if ob.marker_id == target)
        assert seen.payload == draws["payload"]
        decoded = parse_payload(seen.payload).points_world_m
        error = r.T_world_agv[:3, 3] - r.T_world_agv_truth[:3, 3]
        np.testing.assert_allclose(error, shift, atol=IDEAL_MM / 1000)
        assert r.log_time_ns in draws["frames_in_view_ns"]
    assert used >= 3
    np.testing.assert_allclose(decoded[:4] - shift, q.build_scene(o, np.random.default_rng(SEED)).codes[int(target[1:])].points_world_m[:4], atol=1e-9)
    # With the map the same code is refused (payload vs map beyond 10 mm): never used, poses right.
    mapped = tmp_path / "mapped.mcap"
    scenario_registry.record("qr_floor", mapped, seed=SEED, overrides=SMALL + [item])
    for r in replay_frames(mapped, dataclasses.replace(LARGEST, markers="all")):
        assert target not in r.used_marker_ids
        if r.solved:
            assert r.position_error_m * 1000 < IDEAL_MM, (r.index, r.position_error_m)


def test_camera_knocked_mid_run(tmp_path):
    """Frames captured before from_s are as without the fault; from then on the replay (which
    believes the recorded mount) puts the AGV at truth · T_after · T_mount⁻¹: here 1° of pitch
    and ≈33 mm (2 cm up plus 1.5 m · sin 1° forward), to first order what the camera moved."""
    o = _options()
    path = tmp_path / "knock.mcap"
    scenario_registry.record("qr_floor", path, seed=SEED, overrides=SMALL + ["inject=camera:front:pitch_deg=1,dz_m=0.02,from_s=1.5"])
    T_mount = forward_camera_mount(o.cam_height_m, o.cam_lookahead_m)
    item = realism_draws(path)["sources"]["inject"][0]
    E = np.array(item["T_parent_cam_true_after"]) @ se3.inverse(T_mount)  # AGV-frame error after the knock
    assert 0.030 < np.linalg.norm(E[:3, 3]) < 0.036 and abs(_angle_deg(E[:3, :3]) - 1.0) < 1e-9
    t0 = None
    before = after = 0
    for r in replay_frames(path, dataclasses.replace(RunSettings(), tracking=False)):
        t0 = r.log_time_ns if t0 is None else t0
        if not r.solved:
            continue
        knocked = r.log_time_ns in item["frames_ns"]
        assert knocked == ((r.log_time_ns - t0) * 1e-9 >= 1.5)
        expected = r.T_world_agv_truth @ E if knocked else r.T_world_agv_truth
        miss_mm = np.linalg.norm(r.T_world_agv[:3, 3] - expected[:3, 3]) * 1000
        assert miss_mm < IDEAL_MM, (r.index, knocked, miss_mm)
        assert _angle_deg(r.T_world_agv[:3, :3] @ expected[:3, :3].T) < IDEAL_DEG
        if knocked:
            after += 1
            assert r.position_error_m * 1000 > 30.0 - IDEAL_MM
        else:
            before += 1
            assert r.position_error_m * 1000 < IDEAL_MM
    assert before >= 5 and after >= 5


def test_timing_offset_shows_the_world_offset_earlier(tmp_path):
    """Stamped t + 30 ms, rendered at t: the pose solved from each image equals the truth at
    stamp − 30 ms (within the ideal accuracy) and misses the truth at the stamp by the 30 mm
    the AGV drives in 30 ms at 1 m/s."""
    o = _options()
    path = tmp_path / "late.mcap"
    scenario_registry.record("qr_floor", path, seed=SEED, overrides=SMALL + ["inject=timing:front:offset_ms=30"])
    draws = realism_draws(path)["sources"]
    assert draws["inject"][0]["offset_ns"] == 30_000_000
    assert draws["timing"]["cameras"]["front"]["delay_ns"] == [30_000_000] * 15  # ideal: the offset alone
    t0 = None
    solved = 0
    for r in replay_frames(path, dataclasses.replace(RunSettings(), tracking=False)):
        t0 = r.log_time_ns if t0 is None else t0
        if not r.solved:
            continue
        solved += 1
        t_s = (r.log_time_ns - t0) * 1e-9
        at_capture = _truth(o, t_s - 0.030)
        assert np.linalg.norm(r.T_world_agv[:2, 3] - at_capture[:2, 3]) * 1000 < IDEAL_MM, r.index
        stamp_miss_mm = np.linalg.norm(r.T_world_agv[:2, 3] - _truth(o, t_s)[:2, 3]) * 1000
        assert 30.0 - IDEAL_MM < stamp_miss_mm < 30.0 + IDEAL_MM, (r.index, stamp_miss_mm)
    assert solved >= 10


# -- ambiguity-prone geometry (options only) ---------------------------------------------------------
#: The recipe of docs/realism.md: 6 cm ArUco codes (≈19 px) seen from ≈3.2 m at ≈18° off their
#: normal, one code in view at a time — the mirror pose reprojects nearly as well as the true one.
AMBIGUOUS = ["marker_family=DICT_4X4_1000", "code_size_m=0.06", "cam_height_m=3", "cam_lookahead_m=1",
             "grid_spacing_m=2.5", "duration_s=3", "rate_hz=5", "supersample=1"]


def test_ambiguity_recipe_records_mirror_flips(tmp_path):
    """The typical world with the recipe: some solved frames take the IPPE mirror branch — tens
    of degrees and metres off the truth while the ambiguity ratio is near 1 — and their rejected
    candidate (the ghost) lies much nearer the truth (1–19° on the ideal 6 s run). Measured
    (seed 1): 2 such frames of 14 solved, ratios 1.03–3.8 over all, the mirrored ones 34° and
    58° off."""
    path = tmp_path / "ambiguous.mcap"
    scenario_registry.record("qr_floor", path, seed=1, overrides=AMBIGUOUS)
    mirrored = ratios = 0
    for r in replay_frames(path, dataclasses.replace(RunSettings(), tracking=False)):
        if not r.solved or r.ambiguity_ratio is None:
            continue
        ratios += r.ambiguity_ratio < 2.0
        off_deg = _angle_deg(r.T_world_agv[:3, :3] @ r.T_world_agv_truth[:3, :3].T)
        if off_deg > 20.0:
            mirrored += 1
            assert r.ambiguity_ratio < 2.0 and r.position_error_m > 0.3, (r.index, r.ambiguity_ratio, r.position_error_m)
            ghost_deg = _angle_deg(r.T_world_agv_ghost[:3, :3] @ r.T_world_agv_truth[:3, :3].T)
            assert ghost_deg < off_deg / 2.0, (r.index, off_deg, ghost_deg)  # the mirror of a noisy pose
    assert mirrored >= 2 and ratios >= 8, (mirrored, ratios)


# -- uwb_room: wall cameras ------------------------------------------------------------------------
def test_uwb_room_knock_offset_and_roof_marker_in_the_images(tmp_path):
    """uwb_room applies the same kinds to its wall cameras and roof code. The detected corners of
    every frame match the projection of the roof code — moved 5 cm along the AGV's x — through
    the true camera at the true capture time (south knocked 3 cm along x from 1.5 s on, east's
    images stamped 30 ms late) within 1 px (ECC corners of a ≈20 px code: ≤ 0.71 px measured),
    and miss by > 1.5 px with any one fault left out (≥ 2.0 px measured)."""
    from agvviz.scenarios import uwb_room as u

    over = ["duration_s=3", "rate_hz=5", "block_start_s=0", "block_end_s=0", "realism=ideal", "speed_mps=1",
            "width_px=640", "height_px=512", "supersample=2",
            "inject=camera:south:dx_m=0.03,from_s=1.5;timing:east:offset_ms=30;marker:7:dx_m=0.05"]
    path = tmp_path / "room.mcap"
    scenario_registry.record("uwb_room", path, seed=4, overrides=over)
    o = scenario_registry.build_options("uwb_room", over)
    draws = {(i["kind"], i["target"]): i for i in realism_draws(path)["sources"]["inject"]}
    knock = draws[("camera", "south")]
    after = np.array(knock["T_parent_cam_true_after"])
    np.testing.assert_allclose(after[:3, 3] - u.camera_poses(o)["south"][:3, 3], [0.03, 0.0, 0.0], atol=1e-12)
    assert len(knock["frames_ns"]) == 7  # 1.6 … 2.8 s
    assert draws[("timing", "east")]["offset_ns"] == 30_000_000
    assert draws[("marker", "7")]["frames_in_view_ns"]["south"]
    pose = u._schedule(o, 4, None).pose  # the path: the AGV's true pose at any time (flat: ideal)
    cams, camera = u.camera_poses(o), u.make_camera(o)
    moved, mapped = u.marker_corners_agv(o) + [0.05, 0.0, 0.0], u.marker_corners_agv(o)

    def miss_px(observation, T_world_cam, t_s, corners_agv):
        world = se3.transform_points(pose(t_s), corners_agv)
        return np.abs(observation.corners_px - camera.project(se3.transform_points(se3.inverse(T_world_cam), world))).max()

    t0, seen = None, {"south": 0, "east": 0, "knocked": 0}
    for r in replay_frames(path, dataclasses.replace(RunSettings(), tracking=False)):
        t0 = r.log_time_ns if t0 is None else t0
        t_s = (r.log_time_ns - t0) * 1e-9
        for ob in r.observations:
            knocked = r.cam_name == "south" and r.log_time_ns in knock["frames_ns"]
            T, t_capture = (after if knocked else cams[r.cam_name]), (t_s - 0.030 if r.cam_name == "east" else t_s)
            assert miss_px(ob, T, t_capture, moved) < 1.0, (r.index, r.cam_name)
            assert miss_px(ob, T, t_capture, mapped) > 1.5, (r.index, r.cam_name)
            if knocked:
                assert miss_px(ob, cams["south"], t_capture, moved) > 1.5, r.index
            if r.cam_name == "east":
                assert miss_px(ob, T, t_s, moved) > 1.5, r.index
            seen[r.cam_name] = seen.get(r.cam_name, 0) + 1
            seen["knocked"] += knocked
    assert seen["south"] >= 10 and seen["east"] >= 8 and seen["knocked"] >= 5, seen


def test_uwb_room_refuses_payload_and_unknown_walls():
    for item, words in [("payload:7:dx_m=0.1", "payload needs markers whose payload carries coordinates"),
                        ("camera:front:dz_m=0.01", "no camera 'front'"), ("marker:3:dx_m=0.1", "no marker '3'")]:
        with pytest.raises(ScenarioError, match=None) as info:
            scenario_registry.build_options("uwb_room", [f"inject={item}"])
        assert words in str(info.value), str(info.value)


# -- auv_under_ice: corner-only route ----------------------------------------------------------------
def test_auv_route_corners_follow_the_knock_the_offset_and_the_moved_marker():
    """auv_under_ice (route, corner-only, σ = 0: the corners are exact projections) applies the
    same kinds: left knocked 5 cm along the AUV's x from 4 s on, right stamped 20 ms late, marker 0
    hung 10 cm off along world x. Each written corner set equals the projection through the model
    with the fault (1e-6 px) and differs from it without that fault by > 0.1 px (20 ms at 1 m/s
    moves a marker 10 m away ≈0.4 px)."""
    import json
    import tempfile
    from pathlib import Path

    from agvviz.model.topics import CORNERS_TOPIC
    from agvviz.recording.mcap_stream import iter_raw
    from agvviz.recording.raw import RawMessage
    from agvviz.scenarios import auv_under_ice as a
    from agvviz.sim import auv

    over = ["duration_s=8", "realism=ideal", "sigma_px=0", "marker_spacing_m=6",
            "inject=camera:left:dx_m=0.05,from_s=4.05;timing:right:offset_ms=20;marker:0:dx_m=0.1"]
    o = scenario_registry.build_options("auv_under_ice", over)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "auv.mcap"
        scenario_registry.record("auv_under_ice", path, seed=2, overrides=over)
        draws = {(i["kind"], i["target"]): i for i in realism_draws(path)["sources"]["inject"]}
        messages = [(m.log_time_ns, json.loads(m.data)) for m in iter_raw(path, {CORNERS_TOPIC}) if isinstance(m, RawMessage)]
    knock = draws[("camera", "left")]
    assert len(knock["frames_ns"]) == 40  # 4.1 … 8.0 s at 10 Hz
    mounts, cam = auv.camera_mounts(), auv.camera()
    markers = dict(a.route_markers(o))

    def corners(name, t_s, mount, marker_id, moved):
        T_world_marker = markers[marker_id].copy()
        T_world_marker[0, 3] += 0.1 if (moved and marker_id == "0") else 0.0
        T_cam_world = se3.inverse(a.route_pose(o, o.speed_mps * t_s) @ mount)
        return auv.visible_pixels(cam, T_cam_world @ T_world_marker, auv.marker_corners_marker())

    checked = {"left": 0, "right": 0, "knocked": 0, "moved": 0}
    for t_ns, value in messages:
        name = value["cam_name"]
        t_s = (t_ns - a.START_TIME_NS) * 1e-9
        knocked = name == "left" and t_ns in knock["frames_ns"]
        mount = np.array(knock["T_parent_cam_true_after"]) if knocked else mounts[name]
        t_capture = t_s - 0.020 if name == "right" else t_s
        for seen in value["markers"]:
            got = np.array(seen["corners_px"])
            np.testing.assert_allclose(got, corners(name, t_capture, mount, seen["id"], True), atol=1e-6)
            alternatives = []
            if knocked:
                alternatives.append(corners(name, t_capture, mounts[name], seen["id"], True))
            if name == "right":
                alternatives.append(corners(name, t_s, mount, seen["id"], True))
            if seen["id"] == "0":
                alternatives.append(corners(name, t_capture, mount, seen["id"], False))
                checked["moved"] += 1
            for other in alternatives:
                assert other is None or np.abs(got - other).max() > 0.1, (t_s, name, seen["id"])
            checked[name] += 1
            checked["knocked"] += knocked
    assert checked["left"] and checked["right"] and checked["knocked"] and checked["moved"], checked
