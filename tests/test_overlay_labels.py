"""Labels and legends of the diff / sweep overlay (issue 26): nothing on screen can collide or
cover the data.

A small synthetic overlay of three runs whose estimates agree on some frames (their error arrows
then end at one point) is written and read back: no entity shows a label in the 3D views, no
arrow carries the magnification, the colour key names every run with its colour and the factor,
the 3D view titles say the factor once each, and every time-series plot has its legend off.
Seconds: no recording, no replay, no images.
"""

from __future__ import annotations

import numpy as np
import rerun.blueprint as rrb

from agvviz.viz import blueprints, overlay, paths
from agvviz.viz.readback import read_rrd, text_document
from agvviz.viz.style import color_name
from agvviz.viz.blueprints import views_in as _views

N_FRAMES = 20
LABELS = ("#1 lm", "#2 ippe", "#3 p4p")


def _runs() -> tuple[list[overlay.OverlayRun], overlay.OverlayTruth]:
    rng = np.random.default_rng(26)
    frames = np.arange(N_FRAMES, dtype=np.int64)
    time_ns = 1_000_000_000 + frames * 100_000_000
    T_truth = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    T_truth[:, 0, 3] = 0.1 * frames  # 1 m/s along x at 10 Hz
    runs = []
    for i, label in enumerate(LABELS):
        T_est = T_truth.copy()
        T_est[:, :3, 3] += rng.normal(0.0, 0.002 * (i + 1), (N_FRAMES, 3))
        T_est[::4, :3, 3] = T_truth[::4, :3, 3] + 0.001  # every 4th frame: all runs agree exactly
        T_est[7] = np.nan  # one frame the run did not solve
        errors = {"position_mm": np.linalg.norm(T_est[:, :3, 3] - T_truth[:, :3, 3], axis=1) * 1000.0}
        runs.append(overlay.OverlayRun(f"s{i + 1}", label, frames, time_ns, T_est, errors, T_truth=T_truth,
                                       short_label=label.split()[0]))
    return runs, overlay.OverlayTruth(frames, time_ns, T_truth)


def _label_columns(contents) -> dict[str, list]:
    """Entity → every value of its ``*:show_labels`` columns, and the ``*:labels`` it logged."""
    found: dict[str, list] = {}
    for chunk in contents.store.stream():
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.endswith(":show_labels") or name.endswith(":labels"):
                values = [v for v in batch.column(name).to_pylist() if v is not None]
                found.setdefault(chunk.entity_path.lstrip("/"), []).extend((name, v) for v in values)
    return found


def test_overlay_shows_no_label_in_3d_and_states_the_magnification_once(tmp_path):
    runs, truth = _runs()
    out = overlay.write_overlay(tmp_path / "o.rrd", recording_name="labels test", runs=runs, truth=truth,
                                source=None, cam_names=[], report_markdown="# report")
    contents = read_rrd(out)
    factor = overlay.error_magnification([overlay.position_errors_m(r)[1] for r in runs])
    assert factor > 1
    shown = blueprints.format_magnification(factor)

    # The runs' arrows meet where they agree (every 4th frame): a label at a tip would collide.
    tips = [r.T_truth[0, :3, 3] + overlay.position_errors_m(r)[1][0] * factor for r in runs]
    assert np.allclose(tips[0], tips[1]) and np.allclose(tips[1], tips[2])
    labels = _label_columns(contents)
    for entity, values in labels.items():
        for name, value in values:
            if name.endswith(":show_labels"):
                assert value == [False] or value is False, f"{entity} shows its labels on screen"
            else:
                assert not any("×" in str(v) for v in value), f"{entity} carries the magnification: {value}"
    for run in runs:
        arrows = [v for n, v in labels[paths.overlay_error_vector(run.key)] if n.endswith(":labels")]
        assert arrows == [[run.label]]  # its name on hover, no factor
    assert not any(e.startswith(f"{paths.overlay_error_vector('s1')}/") for e in labels), "no tip labels"

    # One key for every view: each run's label with its colour, and the factor.
    key = text_document(contents, paths.COMPARE_KEY)
    for i, label in enumerate(LABELS):
        assert f"**{label}** {color_name(i)}" in key
    assert key.count(shown) == 1 and "truth green" in key

    blueprint = blueprints.overlay_blueprint(runs, [], [], truth, factor)
    views = _views(blueprint.root_container)
    spatial = [v for v in views if isinstance(v, rrb.Spatial3DView)]
    assert len(spatial) == 2 and all(str(v.name).count(shown) == 1 for v in spatial)
    assert any(isinstance(v, rrb.TextDocumentView) and v.origin == paths.COMPARE_KEY for v in views)


def test_overlay_plots_have_no_legend_on_the_data():
    """Every time-series plot of a sweep's and a diff's layout: legend off (Rerun 0.41 draws a
    legend inside the plot; the colour key names the series)."""
    runs, truth = _runs()
    layouts = [
        blueprints.overlay_blueprint(runs, [], [], truth, 20.0,
                                     layer_entities={r.key: {paths.LM_ITERATIONS} for r in runs}),
        blueprints.overlay_blueprint(runs[:2], [], list(blueprints.ERROR_LABELS), truth, 20.0),
    ]
    for blueprint in layouts:
        plots = [v for v in _views(blueprint.root_container) if isinstance(v, rrb.TimeSeriesView)]
        assert len(plots) >= len(blueprints.ERROR_LABELS)
        for plot in plots:
            legend = plot.properties.get("PlotLegend")
            assert legend is not None and legend.visible.as_arrow_array().to_pylist() == [False], plot.name
            assert "/" not in str(plot.name).split("[")[0], f"title names an entity path: {plot.name}"
