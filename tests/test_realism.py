"""The non-image error sources (agvviz.sim.realism): each recording differs from the truth by
exactly its recorded draws, the sources are independent, ``ideal`` is today's world."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from agvviz import scenarios as scenario_registry
from agvviz.geometry import se3
from agvviz.geometry.euler import hpr_from_matrix
from agvviz.model import topics
from agvviz.recording.mcap_stream import iter_raw
from agvviz.recording.raw import RawMessage
from agvviz.recording.reader import iter_messages
from agvviz.recording.mcap_stream import realism_draws
from agvviz.sim import realism as rl
from agvviz.sim.trajectory import forward_camera_mount, track_pose
from agvviz.scenarios import qr_floor
from agvviz.scenarios import uwb_room

# Small worlds: 3 frames of a 320×256 qr_floor, 2 time stamps of a 320×256 uwb_room.
QR_SMALL = ["duration_s=0.3", "width_px=320", "height_px=256", "focal_px=250", "supersample=2"]
UWB_SMALL = ["duration_s=0.2", "width_px=320", "height_px=256", "supersample=1"]
UWB_GRID = ["variant=static_grid", "static_point_m=2.4,2.4", "fixes_per_point=2", "width_px=320",
            "height_px=256", "supersample=1"]
#: sha256 over (topic, log time, bytes) of every message, of recordings made with the code
#: before the error sources existed (seed 0): ``ideal`` must reproduce them exactly.
GOLDEN = {
    "qr_floor": (QR_SMALL + ["realism=ideal"], "24d3f12b1d513e68fe540ca21097f88b8c11bf6bda4c574ef30c9edf8d2e16e6", 12),
    "uwb_room": (UWB_SMALL + ["realism=ideal"], "1ade08cfb0d5c5478633e4ba93b707e3390d00bbdedc0cd017657a30394b1058", 33),
    "uwb_room_grid": (UWB_GRID + ["realism=ideal"], "0b37dfb431fac6587e34619303f63695cedc631b51c4a2b8895f16d6f5b15345", 33),
}
ONLY = {s: ",".join(x for x in rl.SOURCES if x != s) for s in rl.SOURCES}  # realism_off leaving s on


def _record(tmp_path, name: str, scenario: str, overrides: list[str], seed: int = 0):
    path = tmp_path / f"{name}.mcap"
    scenario_registry.record(scenario, path, seed=seed, overrides=overrides)
    return path


def _digest(path) -> tuple[str, int]:
    h, n = hashlib.sha256(), 0
    for item in iter_raw(path):
        if isinstance(item, RawMessage):
            h.update(item.topic.encode())
            h.update(str(item.log_time_ns).encode())
            h.update(item.data)
            n += 1
    return h.hexdigest(), n


def _raw(path, topic: str) -> list[tuple[int, bytes]]:
    """(log time, bytes) of every message on ``topic``, in file order."""
    return [(m.log_time_ns, m.data) for m in iter_raw(path, {topic}) if isinstance(m, RawMessage)]


def _messages(path, topic: str) -> list:
    return [m for m in iter_messages(path, {topic})]


# -- profiles and options ----------------------------------------------------------------------
def test_ideal_profile_draws_nothing_and_every_parameter_is_settable():
    ideal = rl.PROFILES["ideal"]
    assert all(v == 0.0 for s in ("calibration", "map", "timing", "slip") for v in ideal.parameters()[s].values())
    assert ideal.bumps.pitch_sigma_deg == ideal.bumps.roll_sigma_deg == 0.0
    custom = rl.make_realism("typical", "map,slip", "calibration.fx_sigma_px=0.7,timing.latency_s=-0.001")
    assert custom.calibration.fx_sigma_px == 0.7 and custom.timing.latency_s == -0.001
    assert custom.map == rl.MapErrors() and custom.slip == rl.SlipErrors()
    assert custom.timing.jitter_sigma_s == rl.PROFILES["typical"].timing.jitter_sigma_s
    assert custom.name == "typical*"


def test_scenarios_default_to_typical_and_studies_to_ideal():
    """Issue 14: a recording is as imperfect as a real one unless asked otherwise; the solver
    studies keep the ideal world (their noise is the study's own)."""
    for name in ("qr_floor", "uwb_room", "auv_under_ice"):
        assert scenario_registry.build_options(name, []).realism == "typical", name
    assert scenario_registry.build_options("p4p_monte_carlo", []).realism == "ideal"
    assert scenario_registry.build_options("auv_under_ice", ["mode=grid", "realism=ideal"]).mode == "grid"
    with pytest.raises(scenario_registry.ScenarioError, match="add --set realism=ideal"):
        scenario_registry.build_options("auv_under_ice", ["mode=grid"])


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["realism=sloppy"], "is not one of: ideal, typical, harsh"),
        (["realism_off=lens"], "realism_off: 'lens' is not one of"),
        (["realism_set=calibration.fx=1"], "is not name=value with a name among"),
        (["realism_set=map.tilt_sigma_deg=x"], "is not a number"),
        (["realism_set=calibration.fx_sigma_px=-1"], "must lie in 0..100"),
        (["realism_set=timing.latency_s=0.06"], "must be < half the frame period"),
    ],
)
def test_bad_realism_options_fail_with_one_line(overrides, message):
    with pytest.raises(scenario_registry.ScenarioError, match=message) as info:
        scenario_registry.build_options("qr_floor", overrides)
    assert "\n" not in str(info.value)


def test_source_generators_are_stable_and_distinct():
    a = rl.source_rng(3, "map").standard_normal(4)
    assert np.array_equal(a, rl.source_rng(3, "map").standard_normal(4))
    assert not np.array_equal(a, rl.source_rng(3, "calibration").standard_normal(4))
    assert not np.array_equal(a, rl.source_rng(4, "map").standard_normal(4))
    assert not np.array_equal(a, np.random.default_rng(3).standard_normal(4))


def test_bump_field_has_its_sigma_and_correlation_length():
    """Random Fourier features of σ²·exp(−Δ²/2ℓ²): over many fields, the angle at a point has
    std σ and two points ℓ apart correlate by e^(−1/2) ≈ 0.61. 400 fields: the std of a
    sample std is σ/√800 ≈ 3.5 %, of a correlation ≈ 0.03; bounds are ≈4 of those."""
    errors = rl.BumpErrors(pitch_sigma_deg=0.2, roll_sigma_deg=0.0, correlation_m=0.5)
    a, b = [], []
    for seed in range(400):
        field = rl.draw_bumps(errors, rl.source_rng(seed, "bumps"))
        a.append(field.angles_rad([1.0, 2.0])[0])
        b.append(field.angles_rad([1.5, 2.0])[0])
        assert field.angles_rad([1.0, 2.0])[1] == 0.0
    assert np.std(a) == pytest.approx(np.radians(0.2), rel=0.15)
    assert np.corrcoef(a, b)[0, 1] == pytest.approx(np.exp(-0.5), abs=0.12)


# -- ideal is today's world -----------------------------------------------------------------------
@pytest.mark.parametrize("key", sorted(GOLDEN))
def test_ideal_recordings_are_todays_message_for_message(tmp_path, key):
    overrides, digest, count = GOLDEN[key]
    path = _record(tmp_path, key, key.removesuffix("_grid"), overrides)
    assert _digest(path) == (digest, count)
    assert realism_draws(path) is None  # no source, no record


# -- each source: the recording differs from the truth by exactly the draws ------------------------
@pytest.fixture(scope="module")
def qr_sources(tmp_path_factory):
    """qr_floor under typical with only calibration, only map, only timing (strong), all on,
    and all on but calibration off."""
    tmp = tmp_path_factory.mktemp("qr_sources")
    strong_timing = "timing.latency_s=0.004,timing.jitter_sigma_s=0.001,timing.drop_probability=0.4"
    return {
        "calibration": _record(tmp, "calibration", "qr_floor", QR_SMALL + ["realism=typical", f"realism_off={ONLY['calibration']}"]),
        "map": _record(tmp, "map", "qr_floor", QR_SMALL + ["realism=typical", f"realism_off={ONLY['map']}"]),
        "timing": _record(tmp, "timing", "qr_floor", QR_SMALL + [
            "duration_s=1", "realism=typical", f"realism_off={ONLY['timing']}", f"realism_set={strong_timing}"]),
        "all": _record(tmp, "all", "qr_floor", QR_SMALL + ["realism=typical"]),
        "no_calibration": _record(tmp, "no_calibration", "qr_floor", QR_SMALL + ["realism=typical", "realism_off=calibration"]),
        "ideal": _record(tmp, "ideal", "qr_floor", QR_SMALL + ["realism=ideal"]),
    }


def test_recorded_calibration_and_extrinsic_are_true_plus_the_draws(qr_sources):
    path = qr_sources["calibration"]
    draw = realism_draws(path)["sources"]["calibration"]["front"]
    options = scenario_registry.build_options("qr_floor", QR_SMALL)
    true_camera = qr_floor.make_camera(options)
    np.testing.assert_array_equal(draw["true"]["K"], true_camera.K)
    (calibration,) = _messages(path, "/cam/front/calibration")
    K, D = calibration.value.camera.K, calibration.value.camera.dist
    d = draw["delta"]
    assert d["fx_px"] != 0.0 and d["k1"] != 0.0
    # Recorded − true = draw, to float64 rounding of the sum (values ≈ 100–1000).
    assert K[0, 0] - true_camera.K[0, 0] == pytest.approx(d["fx_px"], abs=1e-9)
    assert K[1, 1] - true_camera.K[1, 1] == pytest.approx(d["fy_px"], abs=1e-9)
    assert K[0, 2] - true_camera.K[0, 2] == pytest.approx(d["cx_px"], abs=1e-9)
    assert K[1, 2] - true_camera.K[1, 2] == pytest.approx(d["cy_px"], abs=1e-9)
    np.testing.assert_allclose(D[:4] - true_camera.dist[:4], [d["k1"], d["k2"], d["p1"], d["p2"]], atol=1e-15)
    (tf,) = _messages(path, topics.TF_STATIC_TOPIC)
    T_rec = tf.value[0].T_parent_child
    T_true = forward_camera_mount(options.cam_height_m, options.cam_lookahead_m)
    # Through the quaternion of /tf_static: 1e-12 (float64 quaternion round trip).
    np.testing.assert_allclose(T_rec[:3, 3] - T_true[:3, 3], d["translation_m"], atol=1e-12)
    from agvviz.geometry import so3

    np.testing.assert_allclose(np.degrees(so3.log(T_rec[:3, :3] @ T_true[:3, :3].T)), d["rotation_deg"], atol=1e-9)
    # Truth and images are those of the ideal world: the calibration is only what is believed.
    for topic in (topics.GROUND_TRUTH_TOPIC, "/cam/front/image"):
        assert _raw(path, topic) == _raw(qr_sources["ideal"], topic)


def test_map_holds_the_mapped_codes_and_the_draws_the_true_ones(qr_sources):
    path = qr_sources["map"]
    draws = realism_draws(path)["sources"]["map"]
    (map_message,) = _messages(path, topics.MARKER_MAP_TOPIC)
    recorded = {m["id"]: np.array(m["corners_world_m"]) for m in map_message.value["markers"]}
    ideal_map = _messages(qr_sources["ideal"], topics.MARKER_MAP_TOPIC)[0].value
    assert map_message.value == ideal_map  # the map (and the payloads) say where codes were meant to be
    assert len(draws) == len(recorded)
    for d in draws:
        T_map, T_true = np.array(d["mapped"]["T_parent_marker"]), np.array(d["true"]["T_parent_marker"])
        h = d["mapped"]["side_m"] / 2.0
        corners = se3.transform_points(T_map, np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0.0]]))
        np.testing.assert_allclose(corners, recorded[d["id"]], atol=1e-12)
        delta = d["delta"]
        np.testing.assert_allclose(T_true[:3, 3] - T_map[:3, 3], delta["position_m"], atol=1e-15)
        tilt = T_map[:3, :3].T @ T_true[:3, :3]  # Rz(yaw)·Rx(tilt_x)·Ry(tilt_y)
        heading, pitch, roll = np.degrees(hpr_from_matrix(tilt))
        assert (heading, pitch, roll) == pytest.approx((delta["yaw_deg"], delta["tilt_x_deg"], delta["tilt_y_deg"]), abs=1e-9)
        assert d["true"]["side_m"] == pytest.approx(d["mapped"]["side_m"] * (1 + delta["scale"]), rel=1e-15)
    assert any(d["delta"]["scale"] != 0 for d in draws)
    # The codes moved: the images are not the ideal ones, the truth is.
    assert _raw(path, "/cam/front/image") != _raw(qr_sources["ideal"], "/cam/front/image")
    assert _raw(path, topics.GROUND_TRUTH_TOPIC) == _raw(qr_sources["ideal"], topics.GROUND_TRUTH_TOPIC)


def test_latency_shifts_the_world_an_image_shows_and_dropped_frames_are_missing(qr_sources):
    path = qr_sources["timing"]
    timing = realism_draws(path)["sources"]["timing"]
    stamps = np.array(timing["stamp_ns"])
    delay = np.array(timing["cameras"]["front"]["delay_ns"])
    dropped = np.array(timing["cameras"]["front"]["dropped"])
    assert 0 < dropped.sum() < len(dropped)  # 10 frames at p = 0.4
    images = [t for t, _ in _raw(path, "/cam/front/image")]
    assert images == stamps[~dropped].tolist()
    # Delays are latency + jitter: 4 ms ± 1 ms, rounded to ns.
    assert np.all(np.abs(delay - 4_000_000) < 5_000_000) and len(set(delay.tolist())) == len(delay)
    # Truth at every stamp and at every capture time (stamp − delay), the pose of that instant.
    truth = {m.log_time_ns: m.value.T for m in _messages(path, topics.GROUND_TRUTH_TOPIC)}
    assert sorted(truth) == sorted(stamps.tolist() + (stamps - delay).tolist())
    options = scenario_registry.build_options("qr_floor", QR_SMALL + ["duration_s=1"])
    for t_ns in (stamps - delay).tolist():
        expected = track_pose(qr_floor.make_track(options), options.speed_mps, (t_ns - stamps[0]) * 1e-9)
        # Through the PoseInFrame quaternion: 1e-12.
        np.testing.assert_allclose(truth[t_ns], expected, atol=1e-12)
    # The AGV moves at 1 m/s: over a 4 ms delay it moves 4 mm.
    step = np.linalg.norm(truth[int(stamps[5])][:3, 3] - truth[int(stamps[5] - delay[5])][:3, 3])
    assert step == pytest.approx(delay[5] * 1e-9 * options.speed_mps, rel=1e-3)


def test_switching_a_source_off_leaves_every_other_draw_unchanged(qr_sources):
    everything = realism_draws(qr_sources["all"])["sources"]
    no_calibration = realism_draws(qr_sources["no_calibration"])["sources"]
    for source in ("map", "timing", "bumps", "slip"):
        assert no_calibration[source] == everything[source], source
    assert all(v == 0.0 or v == [0.0, 0.0, 0.0] for v in no_calibration["calibration"]["front"]["delta"].values())
    assert everything["calibration"]["front"]["delta"]["fx_px"] != 0.0
    # Calibration errors change only what is believed: images and truth stay the same.
    for topic in ("/cam/front/image", topics.GROUND_TRUTH_TOPIC, topics.ODOMETRY_TOPIC):
        assert _raw(qr_sources["all"], topic) == _raw(qr_sources["no_calibration"], topic), topic


def test_bumps_pitch_and_roll_the_true_agv_by_the_recorded_angles(tmp_path):
    path = _record(tmp_path, "bumps", "qr_floor", QR_SMALL + [
        "realism=harsh", f"realism_off={ONLY['bumps']}"])
    bumps = realism_draws(path)["sources"]["bumps"]
    truth = _messages(path, topics.GROUND_TRUTH_TOPIC)
    assert len(truth) == len(bumps["stamp_pitch_deg"]) == 3
    for message, pitch, roll in zip(truth, bumps["stamp_pitch_deg"], bumps["stamp_roll_deg"]):
        _, p, r = np.degrees(hpr_from_matrix(message.value.T[:3, :3]))
        assert (p, r) == pytest.approx((pitch, roll), abs=1e-9)
        assert abs(pitch) > 1e-4  # harsh: σ 0.5°
        assert message.value.T[2, 3] == 0.0  # the AGV origin stays on the floor


def test_wheel_slip_scales_each_odometry_step_by_the_drawn_fraction(tmp_path):
    quiet = ["odom_scale_error=0", "odom_heading_bias_deg_per_s=0", "odom_step_noise_m=0", "odom_heading_noise_deg=0"]
    path = _record(tmp_path, "slip", "qr_floor", QR_SMALL + quiet + ["realism=harsh", f"realism_off={ONLY['slip']}"])
    slip = np.array(realism_draws(path)["sources"]["slip"]["fraction"])
    truth = np.array([m.value.T[:3, 3] for m in _messages(path, topics.GROUND_TRUTH_TOPIC)])
    odom = np.array([m.value.T[:3, 3] for m in _messages(path, topics.ODOMETRY_TOPIC)])
    ratio = np.linalg.norm(np.diff(odom, axis=0), axis=1) / np.linalg.norm(np.diff(truth, axis=0), axis=1)
    assert len(slip) == 2 and np.all(slip != 0.0)
    np.testing.assert_allclose(ratio - 1.0, slip, atol=1e-9)  # through the quaternion-free position: 1e-9


# -- uwb_room ------------------------------------------------------------------------------------
def test_uwb_room_cameras_roof_code_and_timing_carry_their_draws(tmp_path):
    path = _record(tmp_path, "room", "uwb_room", UWB_SMALL + [
        "realism=harsh", "realism_set=timing.drop_probability=0.5"])
    draws = realism_draws(path)["sources"]
    assert draws["slip"] is None  # no odometry in the room
    options = scenario_registry.build_options("uwb_room", UWB_SMALL)
    poses = uwb_room.camera_poses(options)
    (tf,) = _messages(path, topics.TF_STATIC_TOPIC)
    recorded = {t.child_frame: t.T_parent_child for t in tf.value}
    for wall in ("south", "east", "north", "west"):
        d = draws["calibration"][wall]
        np.testing.assert_allclose(d["true"]["T_parent_cam"], poses[wall], atol=0)
        np.testing.assert_allclose(recorded[f"cam_{wall}"][:3, 3] - poses[wall][:3, 3], d["delta"]["translation_m"], atol=1e-12)
        (cal,) = _messages(path, f"/cam/{wall}/calibration")
        assert cal.value.camera.K[0, 0] - uwb_room.make_camera(options).K[0, 0] == pytest.approx(d["delta"]["fx_px"], abs=1e-9)
        stamps = np.array(draws["timing"]["stamp_ns"])
        dropped = np.array(draws["timing"]["cameras"][wall]["dropped"])
        assert [t for t, _ in _raw(path, f"/cam/{wall}/image")] == stamps[~dropped].tolist()
    # The map keeps the code where it was meant to be (a pure lift); the draw says where it is.
    (marker,) = draws["map"]
    np.testing.assert_array_equal(recorded["marker_7"], marker["mapped"]["T_parent_marker"])
    assert not np.array_equal(marker["true"]["T_parent_marker"], marker["mapped"]["T_parent_marker"])


def test_static_grid_capture_before_a_points_first_fix_sees_that_point(tmp_path):
    """With latency, the first fix of a grid point is captured before the point's dwell
    starts; the AGV must already stand there (it moves on in the middle of the 1 s gap)."""
    path = _record(tmp_path, "grid", "uwb_room", UWB_GRID + [
        "realism=typical", f"realism_off={ONLY['timing']}", "realism_set=timing.latency_s=0.01"])
    truth = [m.value.T[:3, 3] for m in _messages(path, topics.GROUND_TRUTH_TOPIC)]
    np.testing.assert_allclose(np.array(truth)[:, :2], 2.4, atol=1e-12)


# -- accuracy ------------------------------------------------------------------------------------
def test_typical_world_costs_millimetres_not_centimetres(tmp_path):
    """0.5 s of default qr_floor (5 frames, lm): ideal ≈ 0.3 mm; typical (seed 0: calibration
    and map biases of ≈1 mm, 0.1 ms latency at 1 m/s) must be worse, yet below 10 mm — a
    wrong sign or unit in any draw (a degree read as a radian, a px σ as a fraction) gives
    centimetres to metres.

    5 frames rather than 10 (the full-size images cost ≈0.5 s each to render): the typical
    error is dominated by the recording's systematic draws (calibration and map biases are one
    draw per recording, the latency a fixed offset), which more frames do not average away, so
    the separation does not depend on the frame count — seed 0 gives ideal 0.34 / typical
    2.5 mm at 5 frames and 0.25 / 2.2 mm at 10. Both bounds keep their margins (typical ≈7×
    ideal, 10 mm ≈4× typical); a wrong unit or sign is as wrong on 5 frames as on 10."""
    from agvviz.app.run import run_recording
    from agvviz.settings import RunSettings

    errors = {}
    for profile in ("ideal", "typical"):
        path = _record(tmp_path, profile, "qr_floor", ["duration_s=0.5", f"realism={profile}"])
        outcome = run_recording(path, RunSettings(), tmp_path / f"{profile}.rrd", jobs=1, cache_dir=False)
        assert outcome.summary["frames"] == outcome.summary["solved"] == 5, outcome.summary
        errors[profile] = outcome.summary["position_error_mm"]["rmse"]
    assert errors["ideal"] < errors["typical"] < 10.0, errors
