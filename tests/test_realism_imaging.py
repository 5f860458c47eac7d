"""Image formation and print under the realism profile (issue 14): ``realism=typical`` renders
typical images, the imaging effects are one more independent source, ``ideal`` is unchanged."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agvviz import scenarios as scenario_registry
from agvviz.model import topics
from agvviz.sim import imaging as im
from agvviz.recording.mcap_stream import realism_draws
from agvviz.sim import realism as rl
from tests.test_realism import GOLDEN, QR_SMALL, UWB_SMALL, _digest, _raw, _record

NON_IMAGING = ",".join(s for s in rl.SOURCES if s != "imaging")
IMAGE = "/cam/front/image"


def _typical_as_overrides() -> str:
    """``realism_set`` putting every non-imaging parameter of ``typical`` on top of ``ideal``."""
    params = rl.PROFILES["typical"].parameters()
    return ",".join(f"{s}.{k}={v!r}" for s in rl.SOURCES if s != "imaging" for k, v in params[s].items())


# -- profiles and options -------------------------------------------------------------------------
def test_profiles_carry_the_imaging_profiles_with_whole_pixel_apertures():
    assert rl.PROFILES["ideal"].imaging == im.IDEAL_IMAGING
    assert rl.PROFILES["typical"].imaging == dataclasses.replace(im.TYPICAL_IMAGING, pixel_aperture=1.0, line_delay_s=0.0)
    assert rl.PROFILES["harsh"].imaging == dataclasses.replace(im.HARSH_IMAGING, pixel_aperture=1.0)
    assert "imaging.defocus_radius_px" in rl.parameter_names()


def test_imaging_overrides_and_switches():
    r = rl.make_realism("typical", "imaging.glare,imaging.motion_blur", "imaging.defocus_radius_px=1.0,imaging.jpeg_quality=80")
    assert r.imaging.defocus_radius_px == 1.0
    assert r.imaging.jpeg_quality == 80 and isinstance(r.imaging.jpeg_quality, int)
    assert r.imaging.glare_peak_dn == 0.0 and r.imaging.exposure_s == 0.0
    assert r.imaging.vignetting_strength == im.TYPICAL_IMAGING.vignetting_strength  # the others stay
    assert r.calibration == rl.PROFILES["typical"].calibration
    # Off = the ideal world's camera, not a camera without blur or noise.
    assert rl.make_realism("typical", "imaging").imaging == im.IDEAL_IMAGING
    assert rl.make_realism("harsh", "imaging.lens_blur").imaging.blur_sigma_px == im.IDEAL_IMAGING.blur_sigma_px
    assert rl.make_realism("ideal", "imaging").is_ideal


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["realism_set=imaging.defocus=1"], "is not name=value with a name among"),
        (["realism_set=imaging.defocus_radius_px=-1"], "imaging.defocus_radius_px: imaging error defocus_radius_px must be ≥ 0"),
        (["realism_set=imaging.pixel_aperture=0"], "pixel_aperture must lie in"),
        (["realism_set=imaging.jpeg_quality=90.5"], "imaging.jpeg_quality must be an integer"),
        (["realism_set=imaging.exposure_s=fast"], "is not a number"),
        (["realism_off=imaging.lens"], "realism_off: 'imaging.lens' is not one of"),
        (["time_samples=0"], "time_samples"),
    ],
)
def test_bad_imaging_options_fail_with_one_line(overrides, message):
    with pytest.raises(scenario_registry.ScenarioError, match=message) as info:
        scenario_registry.build_options("qr_floor", overrides)
    assert "\n" not in str(info.value)


def test_scenario_options_override_the_profile_only_when_set():
    typical = rl.make_realism("typical")
    errors, quality = rl.scenario_imaging(typical, scenario_registry.build_options("qr_floor", []))
    assert (errors.blur_sigma_px, errors.read_noise_dn, errors.jpeg_quality, quality) == (0.4, 2.0, 0, 90)
    set_ = scenario_registry.build_options("qr_floor", ["blur_sigma_px=1.5", "noise_sigma_dn=0", "jpeg_quality=60"])
    errors, quality = rl.scenario_imaging(typical, set_)
    assert (errors.blur_sigma_px, errors.read_noise_dn, quality) == (1.5, 0.0, 60)
    # Under ideal the options keep their meaning exactly (and the profile's JPEG is the option's).
    errors, quality = rl.scenario_imaging(rl.make_realism("ideal"), set_)
    assert errors == im.ImagingErrors(blur_sigma_px=1.5, read_noise_dn=0.0) and quality == 60
    errors, quality = rl.scenario_imaging(rl.make_realism("ideal"), scenario_registry.build_options("qr_floor", []))
    assert errors == im.ImagingErrors(blur_sigma_px=0.8, read_noise_dn=2.0) and quality == 95


def test_capture_instant_is_the_middle_of_the_middle_rows_exposure():
    e = im.ImagingErrors(exposure_s=0.002, line_delay_s=1e-5)
    assert rl.exposure_start_s(e, 1001, 5.0) == pytest.approx(5.0 - 500 * 1e-5 - 0.001, abs=1e-15)
    assert rl.exposure_start_s(im.IDEAL_IMAGING, 1001, 5.0) == 5.0


# -- recordings -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def qr(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("qr_imaging")
    return {
        "ideal": _record(tmp, "ideal", "qr_floor", QR_SMALL + ["realism=ideal"]),
        "imaging_only": _record(tmp, "imaging_only", "qr_floor", QR_SMALL + ["realism=typical", f"realism_off={NON_IMAGING}"]),
        "typical_no_imaging": _record(tmp, "typical_no_imaging", "qr_floor", QR_SMALL + ["realism=typical", "realism_off=imaging"]),
        "ideal_plus_others": _record(tmp, "ideal_plus_others", "qr_floor", QR_SMALL + ["realism=ideal", f"realism_set={_typical_as_overrides()}"]),
        "typical": _record(tmp, "typical", "qr_floor", QR_SMALL + ["realism=typical"]),
    }


def test_imaging_changes_the_images_and_nothing_else(qr):
    """Typical imaging alone: every image differs from ideal; truth, odometry, calibration,
    /tf_static and the map are ideal's byte for byte; the record says what was rendered."""
    a, b = qr["imaging_only"], qr["ideal"]
    images_a, images_b = _raw(a, IMAGE), _raw(b, IMAGE)
    assert [t for t, _ in images_a] == [t for t, _ in images_b]
    assert all(x != y for (_, x), (_, y) in zip(images_a, images_b))
    for topic in (topics.GROUND_TRUTH_TOPIC, topics.ODOMETRY_TOPIC, "/cam/front/calibration",
                  topics.TF_STATIC_TOPIC, topics.MARKER_MAP_TOPIC):
        assert _raw(a, topic) == _raw(b, topic), topic
    record = realism_draws(a)
    imaging = record["sources"]["imaging"]
    assert imaging["errors"]["jpeg_quality"] == 90 and imaging["errors"]["defocus_radius_px"] == 0.5
    assert imaging["time_samples"] == 2 and imaging["rows_per_band"] == 32
    assert record["parameters"]["imaging"]["pixel_aperture"] == 1.0


def test_imaging_off_is_ideal_imaging_with_the_other_sources_on(qr):
    """Independence: typical with imaging off renders exactly what ideal imaging renders in a
    world with typical's other sources — and those sources draw the same with imaging on."""
    off, reference = qr["typical_no_imaging"], qr["ideal_plus_others"]
    for topic in (IMAGE, topics.GROUND_TRUTH_TOPIC, topics.ODOMETRY_TOPIC, "/cam/front/calibration"):
        assert _raw(off, topic) == _raw(reference, topic), topic
    on = realism_draws(qr["typical"])["sources"]
    without = realism_draws(off)["sources"]
    for source in ("calibration", "map", "timing", "bumps", "slip"):
        assert on[source] == without[source], source
    for topic in (topics.GROUND_TRUTH_TOPIC, topics.ODOMETRY_TOPIC, "/cam/front/calibration"):
        assert _raw(qr["typical"], topic) == _raw(off, topic), topic
    assert _raw(qr["typical"], IMAGE) != _raw(off, IMAGE)


def test_one_imaging_effect_off_changes_only_its_share(tmp_path):
    """Motion blur and rolling shutter off on a standing AGV change nothing: every exposure
    sample is the capture pose (the other effects' draws are untouched by the switch)."""
    still = QR_SMALL + ["speed_mps=0", "realism=typical", f"realism_off={NON_IMAGING}"]
    moving = _record(tmp_path, "still", "qr_floor", still)
    frozen = _record(tmp_path, "frozen", "qr_floor", [*still[:-1], f"realism_off={NON_IMAGING},imaging.motion_blur,imaging.rolling_shutter"])
    assert _raw(moving, IMAGE) == _raw(frozen, IMAGE)
    no_glare = _record(tmp_path, "no_glare", "qr_floor", [*still[:-1], f"realism_off={NON_IMAGING},imaging.glare"])
    assert _raw(no_glare, IMAGE) != _raw(moving, IMAGE)


@pytest.mark.parametrize("key", ["qr_floor", "uwb_room"])
def test_ideal_with_imaging_switched_off_is_still_todays_world(tmp_path, key):
    overrides, digest, count = GOLDEN[key]
    path = _record(tmp_path, key, key, overrides + ["realism_off=imaging"])
    assert _digest(path) == (digest, count)
    assert realism_draws(path) is None


def test_uwb_room_renders_typical_images_of_the_moving_roof_code(tmp_path):
    typical = _record(tmp_path, "room", "uwb_room", UWB_SMALL + ["realism=typical", f"realism_off={NON_IMAGING}"])
    ideal = _record(tmp_path, "room_ideal", "uwb_room", UWB_SMALL + ["realism=ideal"])
    for wall in ("south", "east", "north", "west"):
        assert _raw(typical, f"/cam/{wall}/image") != _raw(ideal, f"/cam/{wall}/image")
    for topic in (topics.GROUND_TRUTH_TOPIC, topics.UWB_RANGE_TOPIC):
        assert _raw(typical, topic) == _raw(ideal, topic)
    assert realism_draws(typical)["sources"]["imaging"]["errors"]["exposure_s"] == im.TYPICAL_IMAGING.exposure_s


def test_a_standing_camera_exposes_the_static_frame_bit_for_bit():
    """What lets uwb_room's static grid render each frame once: with the pose constant over
    the exposure, motion blur and rolling shutter bands give the static irradiance exactly."""
    from agvviz.scenarios import qr_floor
    from agvviz.sim.trajectory import forward_camera_mount

    options = scenario_registry.build_options("qr_floor", QR_SMALL)
    scene = qr_floor.build_scene(options, np.random.default_rng(0))
    camera = qr_floor.make_camera(options)
    T = forward_camera_mount(options.cam_height_m, options.cam_lookahead_m)
    T[:2, 3] = [-3.0, -1.5]
    static = im.render_exposure(scene, camera, lambda t: T, 0.0, supersample=2)
    exposed = im.render_exposure(scene, camera, lambda t: T, 0.0, exposure_s=0.002, line_delay_s=1.5e-5,
                                 time_samples=2, rows_per_band=7, supersample=2)
    assert static.max() > static.min()  # a code is in view
    np.testing.assert_array_equal(static, exposed)
