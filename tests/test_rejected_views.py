"""A rejected frame is a gap in every value series of a run's ``.rrd``, marked by its own cross
(issue 26), and the run's plots' axes hold every value.

One small qr_floor recording (1.5 s at 10 Hz, 640×512, seed 0: 15 frames, reprojection RMS
0.03–0.19 px with the LM solver) replayed with ``max_reproj_px = 0.1``, so about half the frames
are rejected for their reprojection after LM iterated on them — the frames whose values were
plotted before (the RMS they broke the limit with, the LM steps, the ambiguity ratio).
"""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.app.run import run_recording
from agvviz.model.frames import REJECT_REPROJECTION
from agvviz.scenarios import record
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz.blueprints import clipped_axis, default_blueprint, plot_axis, run_plot_axes
from agvviz.viz.readback import read_rrd, scalar_entities, scalar_series, series_name, text_logs
from agvviz.viz.blueprints import views_in as _views

SMALL = ["duration_s=1.5", "width_px=640", "height_px=512", "focal_px=500"]
MAX_REPROJ_PX = 0.1


@pytest.fixture(scope="module")
def rejected_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("rejected_run")
    recording = tmp / "qr.mcap"
    record("qr_floor", recording, seed=0, overrides=SMALL)
    outcome = run_recording(recording, RunSettings(max_reproj_px=MAX_REPROJ_PX), tmp / "run.rrd")
    return read_rrd(tmp / "run.rrd"), outcome


def _rejected_frames(contents) -> dict[int, str]:
    """Frame → reason, from the rejections log (one line per rejected frame)."""
    return {frame: text.split("\n")[0].split(": ", 1)[1] for frame, _, text in text_logs(contents, paths.EVENTS_REJECTIONS)}


def test_the_recording_has_rejected_and_solved_frames(rejected_run):
    contents, outcome = rejected_run
    rejected = _rejected_frames(contents)
    assert 3 <= len(rejected), rejected  # the test means something only with rejections ...
    solved = scalar_series(contents, paths.ERROR_POSITION_MM)[0]
    assert len(solved) >= 3  # ... and solved frames beside them
    assert set(rejected.values()) == {REJECT_REPROJECTION}
    assert not set(rejected) & set(solved.tolist())


def test_no_value_series_has_a_value_at_a_rejected_frame(rejected_run):
    """Every Scalars entity on the frame timeline — errors, uncertainty, ambiguity ratio, LM steps
    per frame — is empty at every rejected frame; only the rejection crosses and the limit lines
    (a setting, drawn across the run) are there. The solver's per-iteration columns (timeline
    ``lm_iter``) index the iterations inside a frame, not the run's frames: they stay."""
    contents, _ = rejected_run
    rejected = set(_rejected_frames(contents))
    checked = []
    for entity, timelines in scalar_entities(contents).items():
        if paths.TIMELINE_FRAME not in timelines or paths.TIMELINE_LM_ITER in timelines:
            continue
        if entity.startswith(paths.ERROR_REJECTED + "/") or entity in paths.LIMIT_LINES:
            continue
        frames, _ = scalar_series(contents, entity)
        assert not rejected & set(frames.tolist()), f"{entity} has values at rejected frames {sorted(rejected & set(frames.tolist()))}"
        checked.append(entity)
    # The series that used to carry a rejected frame's value are among those checked.
    assert {paths.ERROR_REPROJ_RMS_PX, paths.ERROR_POSITION_MM, paths.SOLVER_AMBIGUITY_RATIO, paths.LM_ITERATIONS} <= set(checked)


def test_each_plot_marks_each_rejected_frame_at_its_limit_or_above_the_data(rejected_run):
    contents, _ = rejected_run
    rejected = sorted(_rejected_frames(contents))
    for entity in paths.REJECTION_MARKED:
        marker = paths.error_rejected(entity, REJECT_REPROJECTION)
        frames, y = scalar_series(contents, marker)
        np.testing.assert_array_equal(frames, rejected)
        if entity == paths.ERROR_REPROJ_RMS_PX:  # on the limit the frame broke
            np.testing.assert_allclose(y, MAX_REPROJ_PX)
        else:  # above every value of its plot, so no cross hides one
            _, values = scalar_series(contents, entity)
            assert np.all(y > values.max()), entity
        # Hovering a cross says why: its series name is the reason.
        assert "reprojection RMS above max_reproj_px 0.1 px" in series_name(contents, marker)


def test_run_axes_hold_every_value_and_the_crosses(rejected_run):
    contents, _ = rejected_run
    extents = {}
    for entity in (*paths.REJECTION_MARKED, paths.ERROR_NEES_EXPECTED, paths.ERROR_NEES_BOUND_99):
        if entity in contents.entity_paths:
            _, values = scalar_series(contents, entity)
            if len(values):
                extents[entity] = (float(values.min()), float(values.max()))
    axes = run_plot_axes(extents, max_reproj_px=MAX_REPROJ_PX, rejection_reasons=[REJECT_REPROJECTION])
    for entity, (low, high) in extents.items():
        if entity in axes:
            axis = axes[entity]
            assert axis.low <= min(low, 0.0) and axis.high > axis.marker_y > high, entity
    # Frames were rejected for their reprojection: the axis reaches the limit they broke.
    assert axes[paths.ERROR_REPROJ_RMS_PX].holds(MAX_REPROJ_PX)


def test_reprojection_axis_ranges_to_the_data_not_the_limit():
    """0.1 px data under a 2 px limit with no reprojection rejection: the axis ends near 0.1 px
    (not at 2 px, which would leave the data in its bottom 5 %), the limit line is left out and
    the title says where the limit is."""
    axes = run_plot_axes({paths.ERROR_REPROJ_RMS_PX: (0.05, 0.1)}, max_reproj_px=2.0, rejection_reasons=[])
    axis = axes[paths.ERROR_REPROJ_RMS_PX]
    assert 0.1 < axis.high < 0.15 and "max_reproj_px 2 above the axis" in axis.note
    blueprint = default_blueprint(["front"], has_threshold=True, max_reproj_px=2.0, axes=axes)
    views = _views(blueprint.root_container)
    reprojection = [v for v in views if str(v.name).startswith("reprojection RMS")]
    assert len(reprojection) == 1 and "above the axis" in str(reprojection[0].name)
    assert all(paths.ERROR_REPROJ_THRESHOLD_PX not in str(v.contents) for v in views)


def test_clipped_axis_says_where_it_clips():
    """A few metre-size outliers among ≈100 mm values: the axis clips at the 99th percentile and
    says so with the largest value; without outliers it holds the maximum."""
    rng = np.random.default_rng(3)
    values = list(rng.uniform(0.0, 100.0, 400)) + [900.0, 1200.0, 1500.0]  # p99 ≈ 100
    axis = clipped_axis(values, "mm")
    p99 = float(np.quantile(values, 0.99))
    assert axis.high > p99 and axis.high < 1200.0
    assert f"clipped at {p99:.0f} mm" in axis.note and "max 1500" in axis.note
    plain = clipped_axis(list(rng.uniform(0.0, 100.0, 400)) + [160.0, 280.0], "mm")  # under 3 × p99
    assert plain.note == "" and plain.high > 280.0
    assert plot_axis([(-0.2, 0.3)]).low < -0.2
