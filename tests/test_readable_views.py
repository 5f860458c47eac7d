"""Issue 26, views a user reads without the README: the audit's, the budget's, the study's and
the correction run's layouts open on a timeline of the recording, their plots carry no legend
(in Rerun 0.41 it sits on the data; the titles name the colours), a sweep's LM-steps series has
no value at a frame without LM steps, and the budget's share chart keeps its labels and grid
inside the chart. Fast: blueprints and loggers on small synthetic inputs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import rerun.blueprint as rrb

from agvviz.evaluation.error_budget import INTERACTION, ShareInterval
from agvviz.viz import blueprints, log_budget, paths, style
from agvviz.viz.log_lm import LmLogger
from agvviz.viz.blueprints import views_in as _views


def _legend_hidden(view) -> bool:
    legend = view.properties.get("PlotLegend")
    return legend is not None and not bool(legend.visible.pa_array[0].as_py())


def _budget(sources=("calibration", "map")):
    return SimpleNamespace(sources=[SimpleNamespace(source=s) for s in sources])


def test_audit_and_budget_open_on_elapsed_with_no_legend():
    """Before: no time panel, so the viewer opened on wall-clock ``time`` ("22:13:21")."""
    markers = [SimpleNamespace(corners_world_mapped=np.zeros((4, 3)))]
    audit = SimpleNamespace(estimate=SimpleNamespace(markers=markers, T_world_agv=np.tile(np.eye(4), (3, 1, 1))))
    axis = blueprints.PlotAxis(low=-0.07, high=0.07, marker_y=0.06)
    for bp in (blueprints.audit_blueprint(audit, {paths.AUDIT_ODOMETRY_HEADING_DEG: axis}),
               blueprints.budget_blueprint(_budget())):
        assert bp.time_panel.timeline == paths.TIMELINE_ELAPSED
        series = [v for v in _views(bp.root_container) if isinstance(v, rrb.TimeSeriesView)]
        assert series and all(_legend_hidden(v) for v in series)
    heading = next(v for v in _views(blueprints.audit_blueprint(audit, {paths.AUDIT_ODOMETRY_HEADING_DEG: axis}).root_container)
                   if v.origin == paths.AUDIT_ODOMETRY_HEADING_DEG)
    assert heading.properties["ScalarAxis"].range.pa_array[0].as_py() == [-0.07, 0.07]


def test_budget_titles_name_each_source_colour_and_run_budget_has_its_own_tab():
    bp = blueprints.budget_blueprint(_budget())
    titles = [v.name for v in _views(bp.root_container) if isinstance(v, rrb.TimeSeriesView)]
    assert all("calibration red" in t and "map blue" in t for t in titles)
    assert style.budget_source_color("calibration") == style.BUDGET_SOURCE_COLORS["calibration"]
    run = blueprints.default_blueprint(["front"], budget_sources=["calibration"])
    assert isinstance(run.root_container, rrb.Tabs)
    assert [c.name for c in run.root_container.contents] == ["run", blueprints.BUDGET_TAB]
    shares = [v for v in _views(run.root_container.contents[1]) if v.origin == paths.BUDGET_SHARES]
    assert len(shares) == 1


def test_study_and_correction_plots_have_no_legend_and_the_crlb_colour_is_named_right():
    from agvviz.model.studies import CellResult

    results = {cid: CellResult(cid, s, 4, 0.0, 208.0, 1e-3, np.zeros(3), {}, errors_t_m={})
               for cid, s in (("paper_h0.2667_z2_snr15_n4", 0.0377), ("paper_h0.2667_z2_snr24_n4", 0.0134))}
    bp = blueprints.study_blueprint(results)
    series = [v for v in _views(bp.root_container) if isinstance(v, rrb.TimeSeriesView)]
    assert series and all(_legend_hidden(v) for v in series)
    assert all("vs σ [mpx]" in v.name for v in series)
    crlb = style.SOLVER_COLORS["crlb"]
    assert min(crlb) > 200 and style.solver_color_name("crlb") == "white"  # the title says what it is drawn in
    assert any("CRLB white" in v.name for v in series)
    correction = blueprints.correction_blueprint(["left"], {paths.CORRECTION_CYCLE_REPROJ_RMS_PX: 2.0})
    plots = [v for v in _views(correction.root_container) if isinstance(v, rrb.TimeSeriesView)]
    assert plots and all(_legend_hidden(v) for v in plots)
    rms = next(v for v in plots if f"/{paths.CORRECTION_CYCLE_REPROJ_RMS_PX}" in str(v.contents))
    low, high = rms.properties["ScalarAxis"].range.pa_array[0].as_py()
    assert low == 0.0 and high >= 2.0  # 0 and the limit in sight (before: auto range 1.5–2)


class _Columns:
    """Records what LmLogger puts in its columns."""

    def __init__(self):
        self.calls = []

    def scalar(self, entity, stamp, value):
        self.calls.append(("scalar", entity, stamp, value))

    def gap(self, entity, stamp):
        self.calls.append(("gap", entity, stamp, None))

    def row(self, *args):
        pass

    def iterations(self, *args):
        pass

    def iteration_points(self, *args):
        pass


def _frame(index, iterations):
    its = [SimpleNamespace(cost=1.0 / (k + 1), damping=1e-3, step_norm=0.1, reproj_rms_px=0.5, accepted=True)
           for k in range(iterations)]
    return SimpleNamespace(index=index, cam_name="front", solved=True, lm_iterations=its, lm_iteration_px=(),
                           used_marker_ids=("Q1",), excluded_marker_ids=(), marker_note=None, suspect=None,
                           rejected=None, reproj_rms_px=0.2)


def test_lm_steps_are_a_gap_on_a_frame_without_lm():
    """A solver that iterates on frames 0 and 3 only (ippe falling back to LM): frames 1 and 2 are
    gaps in the steps series, not a line drawn from frame 0 to 3 (the sweep's 13 → 32)."""
    columns = _Columns()
    lm = LmLogger(SimpleNamespace(log=lambda *a, **k: None), columns)
    for index, iterations in ((0, 5), (1, 0), (2, 0), (3, 8)):
        lm.log(_frame(index, iterations), index, fixed=False)
    steps = [(kind, stamp, value) for kind, entity, stamp, value in columns.calls if entity == paths.LM_ITERATIONS]
    assert steps == [("scalar", 0, 4), ("gap", 1, None), ("gap", 2, None), ("scalar", 3, 7)]


def test_sweep_lm_steps_view_draws_points_and_names_colours_in_key_order():
    runs = [SimpleNamespace(key=k, label=f"#{i + 1} {k}") for i, k in enumerate(("ippe", "sqpnp", "lm"))]
    layers = {r.key: {paths.LM_ITERATIONS} for r in runs}
    (view,) = blueprints._layer_views(runs, layers)
    assert "key above" in view.name and "gap" in view.name and _legend_hidden(view)
    for i, r in enumerate(runs):  # lines and points in the key's colour; a sparse series shows as points
        lines, points = view.visualizer_overrides[paths.sweep_layer(r.key, paths.LM_ITERATIONS)]
        for visualizer in (lines, points):
            color = visualizer.colors.as_arrow_array().to_pylist()[0]
            assert color == int.from_bytes(bytes([*style.color_of(i), 255]), "big")


def test_share_chart_grid_is_round_and_sparse_and_labels_sit_inside():
    """The budget of the docs' picture: shares −34 … 103 %, CIs −120 … 255 %: at most 7 grid lines
    (before: 17, their labels overlapping), every label and tick inside the chart's width."""
    grid = log_budget.share_grid(np.array([-120.2, -34.1, 68.0, 103.3, 255.4]))
    assert len(grid) <= log_budget.MAX_GRID_LINES and grid[0] <= -120.2 and grid[-1] >= 255.4
    assert np.all(np.diff(grid) == grid[1] - grid[0]) and 0.0 in grid

    logged = {}
    rec = SimpleNamespace(log=lambda entity, value, static=False: logged.setdefault(entity, value))
    log_budget.log_share_chart(rec, [ShareInterval("calibration", 0.68, 0.591, 0.82),
                                     ShareInterval("imaging", -0.341, -1.202, 0.046),
                                     ShareInterval(INTERACTION, 1.033, 0.387, 2.554)])
    labels = logged[paths.BUDGET_SHARE_LABELS]
    xy = labels.positions.as_arrow_array().to_pylist()
    assert all(x == pytest.approx(log_budget.CHART_WIDTH / 2) for x, _ in xy)  # centred above each bar
    ticks = logged[paths.BUDGET_SHARE_TICKS].positions.as_arrow_array().to_pylist()
    assert all(-1e-9 <= x <= log_budget.CHART_WIDTH + 1e-9 for x, _ in ticks) and len(ticks) <= log_budget.MAX_GRID_LINES + 1
