"""The error budget (agvviz.app.budget and agvviz.evaluation.error_budget, `agvviz budget`): shares against independent
re-runs, a source without effect, the .rrd, and the errors on bad input."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.writer import Writer
from typer.testing import CliRunner

from agvviz import scenarios as scenario_registry
from agvviz.cli.main import app
from agvviz.errors import InputError
from agvviz.app.budget import error_budget, sources_on
from agvviz.evaluation.error_budget import INTERACTION
from agvviz.recording.writer import RecordingWriter
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings
from agvviz.viz import log_budget, paths
from agvviz.viz.readback import document_json, read_rrd, scalar_series, text_document

#: A tiny qr_floor: 5 frames, small images every one of which is solved under typical.
TINY = ["duration_s=0.5", "width_px=480", "height_px=384", "focal_px=375.0"]
SEED = 1
#: Without tracking the odometry does not steer detection, so slip changes nothing a camera
#: fix sees (with tracking on, odometry predicts the corners the tracker refines).
SETTINGS = RunSettings(tracking=False)

@pytest.fixture(scope="module")
def typical(tmp_path_factory):
    path = tmp_path_factory.mktemp("budget") / "typical.mcap"
    scenario_registry.record("qr_floor", path, seed=SEED, overrides=TINY + ["realism=typical"])
    return path

#: The sources the shares are checked for (the others cost time and check nothing more).
CHECKED = ["calibration", "bumps", "slip"]

@pytest.fixture(scope="module")
def budget(typical, tmp_path_factory):
    return error_budget(typical, SETTINGS, work_dir=tmp_path_factory.mktemp("work"), sources=CHECKED)

def _independent(tmp_path, off: str) -> dict:
    """Record and replay the counterfactual with ``off`` switched off, without the budget's code."""
    path = tmp_path / f"off_{off}.mcap"
    scenario_registry.record("qr_floor", path, seed=SEED, overrides=TINY + ["realism=typical", f"realism_off={off}"])
    return run_recording(path, SETTINGS, tmp_path / f"off_{off}.rrd", jobs=1, cache_dir=False).summary

def test_sources_on():
    assert sources_on({"realism": "ideal"}) == []
    assert sources_on({"realism": "typical", "realism_off": "slip,imaging"}) == ["calibration", "map", "timing", "bumps"]
    # Only the sources a scenario applies: no slip without odometry, no bumps or slip under water,
    # no image formation in a corner-only recording.
    assert sources_on({"realism": "typical"}, "qr_floor") == ["calibration", "map", "timing", "bumps", "slip", "imaging"]
    assert "slip" not in sources_on({"realism": "typical"}, "uwb_room")
    assert sources_on({"realism": "typical", "images": False}, "auv_under_ice") == ["calibration", "map", "timing"]
    assert sources_on({"realism": "typical", "images": True}, "auv_under_ice")[-1] == "imaging"

def test_shares_match_independent_reruns(budget, typical, tmp_path):
    assert [s.source for s in budget.sources] == CHECKED
    assert not budget.warnings  # this version re-records the recording byte for byte
    all_on = run_recording(typical, SETTINGS, tmp_path / "all.rrd", jobs=1, cache_dir=False).summary
    rmse_all = all_on["position_error_mm"]["rmse"]
    assert budget.rmse_all_mm == rmse_all
    assert budget.solved_all == all_on["solved"] == 5
    for off in ("calibration", "bumps"):
        rmse_off = _independent(tmp_path, off)["position_error_mm"]["rmse"]
        entry = next(s for s in budget.sources if s.source == off)
        assert entry.rmse_off_mm == rmse_off
        assert entry.share == pytest.approx((rmse_all**2 - rmse_off**2) / rmse_all**2, abs=1e-12)
    floor = _independent(tmp_path, ",".join(sources_on({"realism": "typical"})))
    assert budget.floor_rmse_mm == floor["position_error_mm"]["rmse"]
    assert budget.interaction == pytest.approx(1.0 - sum(s.share for s in budget.sources), abs=1e-12)

def test_per_frame_differences(budget):
    calibration = next(s for s in budget.sources if s.source == "calibration")
    assert calibration.delta_mm.shape == budget.time_ns.shape
    both = np.isfinite(calibration.delta_mm)
    assert both.sum() >= 4
    # the same frames' errors: all on − calibration off, matched by stamp
    where = {int(t): k for k, t in enumerate(calibration.time_ns)}
    for k in np.flatnonzero(both):
        j = where[int(budget.time_ns[k])]
        assert calibration.delta_mm[k] == budget.position_error_all_mm[k] - calibration.position_error_off_mm[j]

def test_source_without_effect_has_no_share(budget):
    slip = next(s for s in budget.sources if s.source == "slip")
    assert slip.rmse_off_mm == budget.rmse_all_mm  # same images ⇒ identical errors
    assert slip.share == 0.0
    assert np.all(np.nan_to_num(slip.delta_mm) == 0.0)

def test_budget_rrd(budget, tmp_path):
    out = log_budget.write_budget_rrd(tmp_path / "budget.rrd", budget)
    contents = read_rrd(out)
    md = text_document(contents, paths.BUDGET_TABLE)
    assert "| calibration |" in md and INTERACTION in md
    frames, values = scalar_series(contents, paths.budget_series("calibration"))
    calibration = next(s for s in budget.sources if s.source == "calibration")
    assert np.allclose(np.sort(values), np.sort(calibration.position_error_off_mm[np.isfinite(calibration.position_error_off_mm)]))
    _, on = scalar_series(contents, paths.budget_series("all_on"))
    assert len(on) == budget.solved_all
    # the chart: one labelled bar per source and interaction/other, each with its interval
    from agvviz.viz.readback import _rows

    labels = _rows(contents, paths.BUDGET_SHARE_LABELS, "Points2D:labels")[0]["Points2D:labels"]
    assert [label.split(" ")[0] for label in labels] == [*CHECKED, INTERACTION]
    assert labels[0].startswith(f"calibration {100 * calibration.share:.1f} % [")
    assert paths.BUDGET_SHARE_CI in contents.entity_paths

@pytest.fixture(scope="module")
def one_source(tmp_path_factory):
    """One source on (calibration): a budget re-records the world three times, not eight."""
    path = tmp_path_factory.mktemp("one") / "one.mcap"
    scenario_registry.record("qr_floor", path, seed=SEED, overrides=TINY + [
        "realism=typical", "realism_off=map,timing,bumps,slip,imaging"])
    return path

def test_cli_budget(one_source, tmp_path):
    out = tmp_path / "b.rrd"
    result = CliRunner().invoke(app, ["budget", str(one_source), "--set", "tracking=false", "--out", str(out),
                                      "--work-dir", str(tmp_path / "w")])
    assert result.exit_code == 0, result.output
    assert "calibration" in result.output and INTERACTION in result.output and out.exists()
    assert "all_off.mcap" in {p.name for p in (tmp_path / "w").glob("*.mcap")}

def test_run_with_budget(one_source, tmp_path):
    """`agvviz run --budget`: the budget in the run's summary, its table and series in the run's .rrd."""
    out = tmp_path / "run.rrd"
    result = CliRunner().invoke(app, ["run", str(one_source), "--set", "tracking=false", "--out", str(out),
                                      "--budget", "--jobs", "1", "--no-cache"])
    assert result.exit_code == 0, result.output
    assert "error budget (typical)" in result.output
    contents = read_rrd(out)
    summary = document_json(contents, paths.RUN_SUMMARY)
    budget = summary["error_budget"]
    rmse_all = summary["position_error_mm"]["rmse"]
    assert budget["rmse_all_mm"] == rmse_all  # the budget's run is this run
    (calibration,) = budget["sources"]
    assert calibration["source"] == "calibration"
    # The only source on: switching it off is the all-off world, so its RMSE off is the floor.
    assert calibration["rmse_off_mm"] == budget["floor_rmse_mm"]
    assert calibration["share"] == pytest.approx((rmse_all**2 - calibration["rmse_off_mm"]**2) / rmse_all**2, abs=1e-12)
    assert "| calibration |" in text_document(contents, paths.BUDGET_TABLE)
    frames, on = scalar_series(contents, paths.budget_series("all_on"))
    run_frames, run_errors = scalar_series(contents, paths.ERROR_POSITION_MM)
    assert list(frames) == list(run_frames) and np.allclose(on, run_errors)
    # the chart: one labelled bar per source and interaction/other, each with its interval
    from agvviz.viz.readback import _rows

    labels = _rows(contents, paths.BUDGET_SHARE_LABELS, "Points2D:labels")[0]["Points2D:labels"]
    assert [label.split(" ")[0] for label in labels] == ["calibration", INTERACTION]
    assert labels[0].startswith(f"calibration {100 * calibration['share']:.1f} % [")
    assert paths.BUDGET_SHARE_CI in contents.entity_paths

def test_run_budget_refusals(one_source, tmp_path):
    ideal = tmp_path / "ideal.mcap"
    scenario_registry.record("qr_floor", ideal, seed=SEED, overrides=TINY + ["realism=ideal"])
    result = CliRunner().invoke(app, ["run", str(ideal), "--budget", "--out", str(tmp_path / "i.rrd")])
    assert result.exit_code != 0 and "nothing to budget" in result.output and not (tmp_path / "i.rrd").exists()
    result = CliRunner().invoke(app, ["run", str(one_source), "--budget", "--markers", str(ideal)])
    assert result.exit_code != 0 and "--budget re-records" in result.output

def _plain_mcap(path):
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="not agvviz")
        writer.finish()
    return path

def test_errors_on_bad_input(tmp_path):
    with pytest.raises(InputError, match="not an agvviz recording"):
        error_budget(_plain_mcap(tmp_path / "plain.mcap"), SETTINGS)
    unknown = tmp_path / "unknown.mcap"
    with RecordingWriter(unknown, scenario={"name": "no_such", "seed": 0, "options": {"realism": "typical"}}):
        pass
    with pytest.raises(InputError, match="unknown scenario 'no_such'"):
        error_budget(unknown, SETTINGS)
    ideal = tmp_path / "ideal.mcap"
    scenario_registry.record("qr_floor", ideal, seed=0, overrides=["duration_s=0.1", "width_px=64", "height_px=64", "focal_px=50.0", "realism=ideal"])
    with pytest.raises(InputError, match="nothing to budget"):
        error_budget(ideal, SETTINGS)
    with pytest.raises(InputError, match="no such file"):
        error_budget(tmp_path / "missing.mcap", SETTINGS)
    result = CliRunner().invoke(app, ["budget", str(ideal), "--out", str(tmp_path / "b.rrd")])
    assert result.exit_code == 2
    assert "nothing to budget" in result.output and not (tmp_path / "b.rrd").exists()


# -- issue 26: the shares' bootstrap intervals and the labelled chart --------------------------------
def _synthetic_budget(rng, n=300):
    """A budget of one source over n independent frames whose true share is 1/2: the error with the
    source off is |N(0, 1)|, with it on sqrt(off² + d²), d ~ N(0, 1) independent of it."""
    from pathlib import Path

    from agvviz.evaluation.error_budget import ErrorBudget, SourceBudget, share

    t = np.arange(n, dtype=np.int64) * 100_000_000
    off = np.abs(rng.normal(size=n))
    on = np.sqrt(off**2 + rng.normal(size=n) ** 2)
    rmse_on, rmse_off = float(np.sqrt(np.mean(on**2))), float(np.sqrt(np.mean(off**2)))
    source = SourceBudget("calibration", rmse_off, share(rmse_on, rmse_off), n, t, off, on - off)
    return ErrorBudget(Path("x.mcap"), "qr_floor", 0, "typical", "", {}, rmse_on, n, None, t, np.arange(n),
                       on, [source])


def test_share_interval_matches_a_seeded_reference():
    """The bootstrap interval of a share has the width of the share's sampling distribution (the
    reference: 2000 seeded independent budgets of the same world) within 20 %, covers the true
    share (1/2), is the same for the same seed, and interaction/other is 1 − Σ shares."""
    from agvviz.evaluation.error_budget import INTERACTION, share_intervals

    budget = _synthetic_budget(np.random.default_rng(7))
    source, interaction = share_intervals(budget)
    reference = [_synthetic_budget(np.random.default_rng(1000 + k)).sources[0].share for k in range(2000)]
    ref_low, ref_high = np.percentile(reference, [2.5, 97.5])
    assert source.name == "calibration" and source.share == budget.sources[0].share
    assert source.low < 0.5 < source.high and source.low < source.share < source.high
    assert (source.high - source.low) == pytest.approx(ref_high - ref_low, rel=0.2)
    assert share_intervals(budget) == [source, interaction]  # seeded
    assert share_intervals(budget, seed=1)[0] != source
    assert interaction.name == INTERACTION and interaction.share == pytest.approx(1 - source.share)
    assert interaction.low == pytest.approx(1 - source.high, abs=1e-9) and interaction.high == pytest.approx(1 - source.low, abs=1e-9)
    assert "95 % CI over frames" in budget.markdown() and "negative share" in budget.markdown().lower()


def test_share_chart_labels_and_colours():
    from agvviz.evaluation.error_budget import INTERACTION, ShareInterval
    from agvviz.viz import style

    rows = log_budget.share_chart_rows([ShareInterval("calibration", 0.613, 0.48, 0.721),
                                        ShareInterval("map", -0.285, -0.4, -0.1), ShareInterval(INTERACTION, 0.672, 0.5, 0.9)])
    assert [r[0] for r in rows] == ["calibration 61.3 % [48.0, 72.1]", "map -28.5 % [-40.0, -10.0]",
                                    f"{INTERACTION} 67.2 % [50.0, 90.0]"]
    assert [r[4] for r in rows] == [style.COLOR_BUDGET_SOURCE, style.COLOR_BUDGET_NEGATIVE, style.COLOR_BUDGET_INTERACTION]
