"""Bounds of scenario options and run settings (issue 10): absurd values fail at once with an
InputError naming the allowed range, before anything is allocated or written."""

from __future__ import annotations

import dataclasses
import time
import tracemalloc

import pytest
from typer.testing import CliRunner

from agvviz import scenarios as scenario_registry
from agvviz.cli.main import app
from agvviz.errors import InputError
from agvviz.settings import (
    MAX_FRAMES,
    RunSettings,
    SettingsError,
    apply_overrides,
    describe,
    field_types,
    validate,
)

SCENARIOS = sorted(scenario_registry.available())


def _numeric_fields(cls):
    return [f for f in dataclasses.fields(cls) if field_types(cls)[f.name] in (int, float)]


@pytest.mark.parametrize(
    "override, message",
    [
        ("duration_s=1e9", r"duration_s .* must lie in 0\.01\.\.3600, got 1e\+09"),
        ("rate_hz=1e9", r"rate_hz .* must lie in 0\.1\.\.200, got 1e\+09"),
        ("width_px=100000", r"width_px .* must lie in 16\.\.8192, got 100000"),
    ],
)
def test_absurd_options_fail_fast_without_allocating(tmp_path, override, message):
    """These three used to end in MemoryError or the OOM killer after a minute, leaving a
    0-byte temporary file: now an InputError within milliseconds, no file, no allocation."""
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(InputError, match=message):
            scenario_registry.record("qr_floor", tmp_path / "r.mcap", overrides=[override])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - start < 2.0
    assert peak < 20e6, f"{peak / 1e6:.0f} MB allocated before refusing {override}"
    assert list(tmp_path.iterdir()) == []

    result = CliRunner().invoke(app, ["record", "qr_floor", "--set", override, "--out", str(tmp_path / "c.mcap")])
    assert result.exit_code == 2, result.output
    assert "must lie in" in result.output
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["duration_s=3600", "rate_hz=200"], f"frames = duration_s × rate_hz = 720000 exceeds the limit {MAX_FRAMES}"),
        (["width_px=8192", "height_px=8192"], "samples per image"),
        (["supersample=16", "width_px=4096", "height_px=2048"], "samples per image"),
        (["track_length_m=100", "track_width_m=100", "grid_spacing_m=0.02", "code_size_m=0.01"], "floor codes"),
    ],
)
def test_total_work_is_capped(overrides, message):
    with pytest.raises(InputError, match=message):
        scenario_registry.build_options("qr_floor", overrides)


@pytest.mark.parametrize(
    "scenario, overrides, message",
    [
        ("uwb_room", ["duration_s=3600", "uwb_rate_hz=1000"], "UWB rounds"),
        ("uwb_room", ["variant=static_grid", "fixes_per_point=10000"], "frames per camera"),
        ("auv_under_ice", ["images=true", "supersample=16"], "samples per image"),
        ("auv_under_ice", ["duration_s=3600", "frame_rate_hz=200"], "frames = duration_s × frame_rate_hz"),
        ("p4p_monte_carlo", ["trials=1000000"], r"trials .* must lie in 1\.\.100000"),
    ],
)
def test_other_scenarios_are_capped(scenario, overrides, message):
    with pytest.raises(InputError, match=message):
        scenario_registry.build_options(scenario, overrides)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_every_numeric_option_is_bounded_and_its_default_inside(scenario):
    options = scenario_registry.get(scenario).Options
    for f in _numeric_fields(options):
        assert "min" in f.metadata and "max" in f.metadata, f"{scenario}.{f.name} has no bounds"
        assert f.metadata["min"] <= f.default <= f.metadata["max"], f"{scenario}.{f.name}"
    scenario_registry.build_options(scenario, [])  # the defaults validate


def test_every_numeric_run_setting_is_bounded():
    for f in _numeric_fields(RunSettings):
        assert "min" in f.metadata and "max" in f.metadata, f"RunSettings.{f.name} has no bounds"
        assert f.metadata["min"] <= f.default <= f.metadata["max"], f.name
    validate(RunSettings())


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_just_outside_each_bound_is_refused_and_on_it_accepted(scenario):
    module = scenario_registry.get(scenario)
    base = module.Options()
    for f in _numeric_fields(module.Options):
        kind = field_types(module.Options)[f.name]
        lo, hi = f.metadata["min"], f.metadata["max"]
        step = 1 if kind is int else max(abs(lo), abs(hi), 1.0) * 1e-6
        for bad in (lo - step, hi + step):
            with pytest.raises(SettingsError, match=f"{f.name} .*must lie in"):
                validate(dataclasses.replace(base, **{f.name: kind(bad)}))
        for good in (lo, hi):
            validate(dataclasses.replace(base, **{f.name: kind(good)}))  # the field check alone


@pytest.mark.parametrize("text", ["nan", "inf", "-inf", "NaN", "1e999"])
def test_non_finite_numbers_are_refused(text):
    with pytest.raises(InputError, match="finite"):
        scenario_registry.build_options("qr_floor", [f"duration_s={text}"])
    with pytest.raises(SettingsError, match="finite"):
        apply_overrides(RunSettings(), [f"max_reproj_px={text}"])
    with pytest.raises(SettingsError):
        apply_overrides(RunSettings(), [f"sigma_px={text}"])
    with pytest.raises(SettingsError, match="finite"):
        validate(dataclasses.replace(scenario_registry.get("qr_floor").Options(), duration_s=float(text)))


@pytest.mark.parametrize(
    "override, message",
    [
        ("lm_max_iterations=100000", r"lm_max_iterations .* must lie in 1\.\.1000"),
        ("max_reproj_px=1e9", r"max_reproj_px .* must lie in"),
        ("gimbal_threshold=1", r"gimbal_threshold .* must lie in"),
        ("cycle_distance_m=0", r"cycle_distance_m .* must lie in"),
        ("sigma_px=1e9", r"sigma_px must be auto or lie in"),
    ],
)
def test_run_settings_are_bounded(override, message):
    with pytest.raises(SettingsError, match=message):
        apply_overrides(RunSettings(), [override])


def test_bounds_are_shown_in_listings_and_help():
    rows = {name: help_text for name, _, _, help_text in describe(scenario_registry.get("qr_floor").Options)}
    assert rows["duration_s"].endswith("[0.01..3600]")
    assert rows["width_px"].endswith("[16..8192]")
    runner = CliRunner()
    listing = runner.invoke(app, ["scenarios"], terminal_width=400)
    assert listing.exit_code == 0, listing.output
    assert "0.01..3600" in listing.output
    help_text = runner.invoke(app, ["run", "--help"], terminal_width=400)
    assert help_text.exit_code == 0, help_text.output
    assert "1..1000" in help_text.output  # lm_max_iterations


# -- settings that do not apply (issue 13) ------------------------------------------------------
def test_settings_without_their_data_do_not_apply():
    from agvviz.settings import inapplicable, without

    s = apply_overrides(RunSettings(), ["fusion=kalman", "kalman_gate_chi2=4", "uwb=centroid", "correction=cnoem",
                                        "cycle_distance_m=2", "camera_select=combine", "refine=subpix"])
    # No UWB, no odometry, one camera (qr_floor): all but refine are ignored, in field order.
    ignored = inapplicable(s, has_uwb=False, has_odometry=False, n_cameras=1)
    assert list(ignored) == ["camera_select", "uwb", "fusion", "kalman_gate_chi2", "correction", "cycle_distance_m"]
    assert ignored["fusion"] == "the recording has no UWB ranges (no uwb.range topic)"
    assert "no odometry" in ignored["correction"] and "1 camera image topic;" in ignored["camera_select"]
    assert without(s, ignored) == RunSettings(refine="subpix")
    assert without(s, ignored).label() == "lm-refine=subpix"
    # With every kind of data, everything applies.
    assert inapplicable(s, has_uwb=True, has_odometry=True, n_cameras=4) == {}


def test_settings_switched_off_by_other_settings_do_not_apply():
    from agvviz.settings import inapplicable

    everything = {"has_uwb": True, "has_odometry": True, "n_cameras": 4}
    s = apply_overrides(RunSettings(), ["kalman_gate_chi2=4", "camera_sigma_m=0.01", "cycle_distance_m=2"])
    assert inapplicable(s, **everything) == {
        "kalman_gate_chi2": "fusion is mean_compensation, not kalman",
        "camera_sigma_m": "fusion is mean_compensation, not kalman",
        "cycle_distance_m": "correction is none",
    }
    bundle = apply_overrides(RunSettings(), ["correction=bundle", "cnoem_update=paper"])
    assert inapplicable(bundle, **everything) == {"cnoem_update": "correction is bundle, not cnoem"}
    # Defaults are never reported, even where they would not apply.
    assert inapplicable(RunSettings(), has_uwb=False, has_odometry=False, n_cameras=0) == {}
