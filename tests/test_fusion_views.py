"""The correction (auv_under_ice, correction=cnoem) and UWB (uwb_room) views, read back from
the .rrd: time relative to the recording's start, named series, categories as categories, and
every view of the layout with something to show."""

from __future__ import annotations

import numpy as np
import pytest
import rerun.blueprint as rrb

from agvviz import scenarios as scenario_registry
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings
from agvviz.viz import blueprints, paths
from agvviz.viz.blueprints import uwb_blueprint
from agvviz.viz.readback import _rows, read_rrd, scalar_series
from agvviz.viz.blueprints import views_in as _views


@pytest.fixture(scope="module")
def correction_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("auv_views")
    recording = tmp / "auv.mcap"
    scenario_registry.record("auv_under_ice", recording, seed=4, overrides=["duration_s=7", "realism=ideal"])
    run_recording(recording, RunSettings(correction="cnoem", cycle_distance_m=3.0), tmp / "run.rrd")
    return read_rrd(tmp / "run.rrd")


@pytest.fixture(scope="module")
def uwb_run(uwb_room_small_run):
    # uwb_room, 3 s at 5 Hz, blocked 1.0–2.0 s, ideal, seed 4, fusion=mean_compensation: the
    # same recording and run as tests/test_uwb_room.py, made once (conftest.uwb_room_small_run).
    _, outcome = uwb_room_small_run
    return read_rrd(outcome.out_path)


def _elapsed_and_time(contents, entity: str) -> tuple[np.ndarray, np.ndarray]:
    rows = _rows(contents, entity, "Scalars:scalars")
    assert all(row.get(paths.TIMELINE_ELAPSED) is not None for row in rows), f"{entity} lacks {paths.TIMELINE_ELAPSED}"
    return (
        np.array([row[paths.TIMELINE_ELAPSED] for row in rows], dtype=np.int64),
        np.array([row[paths.TIMELINE_TIME] for row in rows], dtype=np.int64),
    )


def _check_elapsed(contents, entities: tuple[str, ...]) -> None:
    """elapsed = time − the recording's first stamp: one origin for every entity, and the
    first per-frame log (``entities[0]``) within a second of it."""
    starts = set()
    for k, entity in enumerate(entities):
        elapsed_ns, time_ns = _elapsed_and_time(contents, entity)
        starts |= set((time_ns - elapsed_ns).tolist())
        if k == 0:
            assert 0 <= elapsed_ns.min() < 1_000_000_000
    assert len(starts) == 1, "elapsed must count from one origin"


def _series_name(contents, entity: str, archetype: str) -> str:
    return _rows(contents, entity, f"{archetype}:names")[0][f"{archetype}:names"][0]


def _shows_something(view, entity_paths: set[str]) -> bool:
    """Whether an entity of the run matches one of the view's inclusions."""
    origin = str(view.origin).strip("/")
    exprs = view.contents if isinstance(view.contents, list) else [view.contents]
    for expr in exprs:
        expr = str(expr).strip()
        if expr.startswith("-"):
            continue
        expr = expr.lstrip("+ ").replace("$origin", "/" + origin).strip("/")
        if expr.endswith("**"):
            prefix = expr[:-2].rstrip("/")
            if any(p == prefix or p.startswith(prefix + "/") or not prefix for p in entity_paths):
                return True
        elif expr in entity_paths:
            return True
    return False


def test_correction_series_are_on_elapsed_named_and_in_mm(correction_run):
    c = correction_run
    _check_elapsed(c, (paths.ERROR_NAV_MM, paths.ERROR_CORRECTED_MM, paths.CORRECTION_CYCLE_REPROJ_RMS_PX))
    assert _series_name(c, paths.ERROR_CORRECTED_MM, "SeriesLines") == "corrected [mm]"
    assert _series_name(c, paths.ERROR_NAV_MM, "SeriesLines") == "navigation (uncorrected) [mm]"
    assert "max_reproj_px" in _series_name(c, paths.CORRECTION_CYCLE_MAX_REPROJ_PX, "SeriesLines")
    assert _series_name(c, paths.CORRECTION_COST, "SeriesLines") != _series_name(c, paths.CORRECTION_REPROJ_RMS_PX, "SeriesLines")
    # Errors in mm: the drift of a few seconds is tens of mm, not hundredths.
    _, nav_mm = scalar_series(c, paths.ERROR_NAV_MM)
    assert 1.0 < nav_mm.max() < 1000.0


def test_correction_layout_rides_on_the_vehicle_and_every_view_has_content(correction_run):
    blueprint = blueprints.correction_blueprint(["left", "right"])
    views = _views(blueprint)
    assert len(views) >= 10
    for view in views:
        assert _shows_something(view, correction_run.entity_paths), view.name
    world = next(v for v in views if str(v.name).startswith("3D"))
    assert str(world.origin).strip("/") == paths.CORRECTION_AGV_CORRECTED
    # The solver's iterations are in a tab of their own: the run's views never need cnoem_iter.
    tabs = blueprint.root_container
    assert [str(t.name) for t in tabs.contents] == ["correction run", f"solver iterations (timeline {paths.TIMELINE_CNOEM_ITER})"]


def test_uwb_series_are_on_elapsed_named_and_categories_are_states(uwb_run):
    c = uwb_run
    _check_elapsed(c, (paths.uwb_range("A_east", "measured"), paths.ERROR_UWB_POSITION_MM, paths.ERROR_FUSED_POSITION_MM))
    assert _series_name(c, paths.uwb_range("A_east", "measured"), "SeriesLines") == "measured"
    assert _series_name(c, paths.uwb_range("A_east", "predicted_truth"), "SeriesLines") == "expected from truth"
    assert _series_name(c, paths.ERROR_FUSED_POSITION_MM, "SeriesLines") == "fused [mm]"
    # Categories: state changes (camera name / none; fused source), not a numeric index series.
    with pytest.raises(Exception, match="no 'Scalars:scalars'"):
        _rows(c, paths.FUSION_CAMERA_USED, "Scalars:scalars")
    sources = [row["StateChange:state"][0] for row in _rows(c, paths.FUSION_SOURCE, "StateChange:state")]
    assert sources == ["camera", "uwb", "camera"]  # the blocked stretch switches to UWB and back
    _, fused_mm = scalar_series(c, paths.ERROR_FUSED_POSITION_MM)
    assert fused_mm.max() > 1.0  # mm, not m


def test_uwb_layout_views_all_have_content(uwb_run):
    entity_paths = uwb_run.entity_paths
    cams = ["east", "north", "south", "west"]
    zoom_cams = [c for c in cams if f"{paths.zoom(c)}/image" in entity_paths]
    assert zoom_cams, "the wall cameras see a small code: they get a zoomed view"
    blueprint = uwb_blueprint(cams, set(cams), ["A_east", "A_north", "A_south", "A_west"], zoom_cams)
    views = _views(blueprint)
    for view in views:
        assert _shows_something(view, entity_paths), view.name
    assert any(isinstance(v, rrb.StateTimelineView) for v in views)
    assert sum(isinstance(v, rrb.TimeSeriesView) and str(v.name).startswith("anchor ") for v in views) == 4
