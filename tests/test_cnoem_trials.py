"""The CNOEM trials stage (agvviz.replay.studies.cnoem) on tiny auv_under_ice mode=grid recordings,
its sink (agvviz.viz.log_studies) and its rows of the summary table
(agvviz.evaluation.summary_table)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agvviz import scenarios as scenario_registry
from agvviz.errors import RecordingError
from agvviz.evaluation.summary_table import summary_rows
from agvviz.model.studies import GridCell
from agvviz.replay.studies import cnoem_cells
from agvviz.replay.studies.cnoem import is_cnoem_trials_recording, replay_cnoem_trials, study_method, trials_from_recording
from agvviz.replay.studies.cnoem_cells import METHODS
from agvviz.replay.studies.monte_carlo import trials_timing
from agvviz.model.messages import PoseMsg, RecordedMessage
from agvviz.recording.raw import ReadReport
from agvviz.recording.reader import iter_messages
from agvviz.recording.source import iter_role_messages, open_recording, resolve_roles, scan
from agvviz.model.topics import ROLE_CORNERS
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz.readback import document_json, read_rrd, scalar_series, text_document
from agvviz.viz.run_logger import RunLogger
from agvviz.viz.blueprints import cnoem_trials_blueprint
from agvviz.viz.log_studies import log_cnoem_trials
from agvviz.viz.paths import CNOEM_REPORT, cnoem_trial_errors

TRIALS = 3
CELL = "L10_X0.2L_Y0.1L_v1_s1"  # the scenario's default cell
#: A second, cheaper cell (11 frames per cycle at 1.5 m/s) with fewer trials.
CELL_2 = "L5_X0.4L_Y0.2L_v1.5_s0.5"
TRIALS_2 = 2


def _recording_and_roles(path):
    recording = open_recording(path)
    return recording, resolve_roles(scan(recording, ReadReport()))


def _messages(path):
    recording, roles = _recording_and_roles(path)
    return list(iter_role_messages(recording, roles, "log", ReadReport()))


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    """(recording path, its role-tagged messages) of a seeded TRIALS-trial grid recording."""
    out = tmp_path_factory.mktemp("cnoem") / "grid.mcap"
    scenario_registry.record("auv_under_ice", out, seed=4, overrides=["mode=grid", "realism=ideal", f"trials={TRIALS}"])
    return out, _messages(out)


@pytest.fixture(scope="module")
def grid_2(tmp_path_factory):
    out = tmp_path_factory.mktemp("cnoem") / "grid2.mcap"
    scenario_registry.record(
        "auv_under_ice", out, seed=6,
        overrides=["mode=grid", "realism=ideal", f"trials={TRIALS_2}", "grid_distance_m=5", "grid_lateral_fraction=0.4",
                   "grid_vertical_fraction=0.2", "speed_mps=1.5", "sigma_px=0.5"],
    )
    return out, _messages(out)


@pytest.fixture(scope="module")
def outcome(grid):
    return replay_cnoem_trials(grid[1], RunSettings(correction="cnoem"))


def test_every_trial_is_solved_and_agrees_with_evaluate_trials(grid, outcome):
    assert list(outcome.results) == [CELL] and outcome.methods == METHODS
    assert outcome.trials_per_cell == TRIALS and outcome.trials == TRIALS and not outcome.warnings
    # The same computation as the library on the same data, read back without the role map.
    (cell_id, trials), = trials_from_recording(iter_messages(grid[0])).items()
    direct = cnoem_cells.evaluate_trials(GridCell.from_id(cell_id), trials, len(trials), 16)
    result = outcome.results[CELL]
    assert (result.n_frames, result.n_sightings) == (16, 32)  # 1.5 m at 1 m/s, 10 Hz; both cameras see it
    assert result.crlb_position_m == pytest.approx(direct.crlb_position_m, rel=1e-12)
    for name in METHODS:
        errors_m = result.errors_m[name]
        assert errors_m.shape == (TRIALS,) and np.all(np.isfinite(errors_m)), name
        np.testing.assert_allclose(errors_m, direct.errors_m[name], rtol=1e-12, atol=0)
    # Against truth: the window methods are near-efficient in this cell (RMS ≈ the CRLB), so a
    # trial's error above 6× the RMS bound has probability < 1e-8; a wrong frame, unit or σ fails.
    for name in ("cnoem", "cnoem_multistart", "bundle"):
        assert np.all(result.errors_m[name] < 6.0 * result.crlb_position_m), name
    assert result.converged_right.all()


def test_summary_section(outcome):
    c = outcome.summary["cnoem_study"]
    json.dumps(outcome.summary, allow_nan=False)  # stored in the .rrd as JSON
    assert (c["cells"], c["cell_ids"], c["trials_per_cell"], c["trials"]) == (1, [CELL], TRIALS, TRIALS)
    assert c["methods"] == list(METHODS) and c["failed"] == 0
    assert c["run_setting"] == {"correction": "cnoem", "cnoem_update": "lm", "study_method": "cnoem_multistart"}
    result = outcome.results[CELL]
    for name in METHODS:
        m = c["per_method"][name]
        assert m["failed"] == 0
        assert m["error_m"]["mean"] == pytest.approx(np.mean(result.errors_m[name]), rel=1e-12)
        assert m["error_m"]["max"] == pytest.approx(np.max(result.errors_m[name]), rel=1e-12)
        assert m["rms_over_crlb"]["median"] == pytest.approx(result.rms_m(name) / result.crlb_position_m, rel=1e-12)
    ratio = c["cnoem_over_ippe"]
    assert ratio["ratio_of_means"] == pytest.approx(result.mean_m("cnoem") / result.mean_m("ippe_first"), rel=1e-12)
    assert (ratio["paper"], ratio["paper_scope"]) == (0.217, "the 243-cell grid")
    assert c["cnoem_right_minimum"]["all"] == 1.0 and c["well_conditioned_cells"] == 1


def test_two_cells_progress_and_lost_trials_warning(grid, grid_2):
    done = []
    both = replay_cnoem_trials(grid[1] + grid_2[1], RunSettings(correction="bundle"), progress=done.append)
    assert done == list(range(1, TRIALS + TRIALS_2 + 1))
    assert list(both.results) == [CELL, CELL_2] and both.results[CELL_2].n_frames == 11
    c = both.summary["cnoem_study"]
    assert (c["cells"], c["trials_per_cell"], c["trials"]) == (2, TRIALS, TRIALS + TRIALS_2)
    assert c["run_setting"]["study_method"] == "bundle"
    assert c["cnoem_over_ippe"]["paper"] == 0.217  # not every cell is a far-edge cell
    assert len(both.warnings) == 1 and "unequal numbers of trials (2..3)" in both.warnings[0]
    np.testing.assert_allclose(  # each cell solved on its own trials
        both.results[CELL].errors_m["cnoem"], replay_cnoem_trials(grid[1], RunSettings()).results[CELL].errors_m["cnoem"],
        rtol=1e-12,
    )
    assert "| X / L |" in both.report_markdown  # an attribute that varies gets its marginal table
    assert "| X / L |" not in replay_cnoem_trials(grid_2[1], RunSettings()).report_markdown


def test_lost_corner_message_is_a_warning(grid):
    corners = [i for i, m in enumerate(grid[1]) if m.role == ROLE_CORNERS]
    kept = grid[1][: corners[-1]] + grid[1][corners[-1] + 1 :]  # the last trial loses a sighting
    lost = replay_cnoem_trials(kept, RunSettings())
    assert len(lost.warnings) == 1 and f"cell {CELL}: its trials hold unequal numbers of sightings (31..32)" in lost.warnings[0]


def test_noise_free_cell_has_no_bound(tmp_path):
    # σ = 0: no CRLB (the information is infinite); the study says so instead of failing.
    path = tmp_path / "grid0.mcap"
    scenario_registry.record("auv_under_ice", path, seed=1, overrides=["mode=grid", "realism=ideal", "trials=1", "sigma_px=0"])
    noise_free = replay_cnoem_trials(_messages(path), RunSettings())
    c = noise_free.summary["cnoem_study"]
    json.dumps(noise_free.summary, allow_nan=False)
    assert c["crlb_position_m"] == {"min": None, "max": None} and c["per_method"]["cnoem"]["rms_over_crlb"]["median"] is None
    assert c["per_method"]["cnoem"]["error_m"]["max"] < 1e-6  # exact corners: the exact pose
    assert dict(summary_rows(noise_free.summary, {}))["cell / CRLB of F's position (m)"] == "L10_X0.2L_Y0.1L_v1_s0 / —"


def test_paper_ratio_of_the_far_edge_cells():
    far = GridCell(15.0, 0.4, 0.2, 1.0, 1.0)
    assert cnoem_cells.paper_ratio([far, GridCell(15.0, 0.4, 0.2, 0.5, 1.5)]) == (0.103, "cells L = 15 m, X = 0.4L, Y = 0.2L")
    assert cnoem_cells.paper_ratio([far, GridCell.from_id(CELL)])[0] == 0.217


def test_study_method_marks_the_run_setting():
    assert study_method(RunSettings(correction="cnoem")) == "cnoem_multistart"
    assert study_method(RunSettings(correction="bundle")) == "bundle"
    assert study_method(RunSettings(correction="cnoem", cnoem_update="paper")) is None
    assert study_method(RunSettings()) is None  # correction=none


def test_is_cnoem_trials_recording(grid, grid_2, tmp_path):
    recording, roles = _recording_and_roles(grid[0])
    assert is_cnoem_trials_recording(recording.scenario, roles)
    assert is_cnoem_trials_recording(recording.scenario, dict(roles.roles))
    assert not is_cnoem_trials_recording(recording.scenario, {})  # its corner topic not placed
    assert not is_cnoem_trials_recording(None, roles)  # no scenario record
    others = {
        "auv_under_ice": ["duration_s=0.3"],  # the route mode, corner-only: the correction replay's
        "qr_floor": ["duration_s=0.2", "width_px=160", "height_px=128", "supersample=1"],
        "p4p_monte_carlo": ["trials=1", "cells=crlb"],
    }
    for name, overrides in others.items():
        path = tmp_path / f"{name}.mcap"
        scenario_registry.record(name, path, overrides=overrides)
        recording, roles = _recording_and_roles(path)
        assert recording.scenario["name"] == name and not is_cnoem_trials_recording(recording.scenario, roles), name


def _replace_corners(message: RecordedMessage, edit) -> RecordedMessage:
    value = json.loads(json.dumps(message.value, default=lambda a: np.asarray(a).tolist()))
    edit(value)
    return RecordedMessage(message.topic, message.log_time_ns, message.schema_name, value, role=message.role)


def test_bad_grid_messages_give_one_line_errors(grid):
    messages = grid[1]
    first = next(i for i, m in enumerate(messages) if m.role == ROLE_CORNERS)
    head, corner, tail = messages[:first], messages[first], messages[first + 1 :]
    with pytest.raises(RecordingError, match="no corner messages .* not an auv_under_ice mode=grid recording"):
        replay_cnoem_trials([m for m in messages if m.role != ROLE_CORNERS], RunSettings())
    cases = {
        "missing 'cell'": lambda v: v.pop("cell"),
        "not a grid cell id: 'L10'": lambda v: v.update(cell="L10"),
        "marker 3 is not on the trial's marker map": lambda v: v["markers"][0].update(id="3"),
        r"corners_px must be 4 finite \(u, v\) pixels, got shape \(3, 2\)": lambda v: v["markers"][0].update(
            corners_px=v["markers"][0]["corners_px"][:3]
        ),
        "camera 'front' has no calibration or no /tf_static extrinsic": lambda v: v.update(cam_name="front"),
    }
    for detail, edit in cases.items():
        with pytest.raises(RecordingError, match=f"not an auv_under_ice grid trial: {detail}"):
            replay_cnoem_trials(head + [_replace_corners(corner, edit)] + tail, RunSettings())
    no_poses = [m for m in head if not isinstance(m.value, PoseMsg)]
    with pytest.raises(RecordingError, match="no navigation and ground-truth pose of its trial before it"):
        replay_cnoem_trials(no_poses + [corner], RunSettings())


def test_sink_logs_error_series_report_and_run_documents(outcome, tmp_path):
    out = tmp_path / "run.rrd"
    manifest = {"recording": "grid.mcap", "settings": {"correction": "cnoem"}}
    with RunLogger(out, recording_name="grid-cnoem", recording_id="test-cnoem-trials") as logger:
        logger.log_manifest(manifest)
        log_cnoem_trials(logger.stream, outcome)
        logger.blueprint = cnoem_trials_blueprint(outcome)
        logger.log_summary(outcome.summary)
    contents = read_rrd(out)
    assert text_document(contents, CNOEM_REPORT) == outcome.report_markdown
    assert document_json(contents, paths.RUN_SUMMARY) == json.loads(json.dumps(outcome.summary))
    assert document_json(contents, paths.RUN_MANIFEST) == manifest
    result = outcome.results[CELL]
    for name in METHODS:
        trials, errors_m = scalar_series(contents, f"{cnoem_trial_errors(CELL)}/{name}", timeline="trial")
        assert list(trials) == list(range(TRIALS))
        np.testing.assert_allclose(errors_m, result.errors_m[name], rtol=1e-12)
    trials, crlb_m = scalar_series(contents, f"{cnoem_trial_errors(CELL)}/crlb", timeline="trial")
    assert list(trials) == [0, TRIALS - 1]
    np.testing.assert_allclose(crlb_m, result.crlb_position_m, rtol=1e-12)


def test_summary_rows_cnoem_study(outcome):
    rows = summary_rows({**outcome.summary, "warnings": []}, trials_timing(outcome, 2.0))
    values = dict(rows)
    assert rows[:2] == [("study", "auv_under_ice grid"), ("cells × trials × methods", f"1 × {TRIALS} × {len(METHODS)}")]
    assert not any(label in ("frames", "solved", "wall time (s)") for label, _ in rows)
    header = rows.index(("per method: error of F", "mean / RMS (m), RMS ÷ CRLB, failed"))
    per_method = rows[header + 1 : header + 1 + len(METHODS)]
    assert [label.split()[0] for label, _ in per_method] == list(METHODS)
    assert [label for label, _ in per_method if "(the run setting)" in label] == ["  cnoem_multistart (the run setting)"]
    m = outcome.summary["cnoem_study"]["per_method"]["bundle"]
    assert values["  bundle"] == (
        f"{m['error_m']['mean']:.4f} / {m['error_m']['rmse']:.4f}, {m['rms_over_crlb']['median']:.3f}, 0"
    )
    ratio = outcome.summary["cnoem_study"]["cnoem_over_ippe"]["ratio_of_means"]
    assert values["cnoem ÷ ippe_first mean error (paper)"] == f"{ratio:.3f} (0.217, the 243-cell grid)"
    assert values["cell / CRLB of F's position (m)"].startswith(f"{CELL} / 0.1")
    assert values["time (s) / trials per s"] == f"2.0 / {TRIALS / 2.0:.1f}"


def test_run_on_a_grid_recording_solves_every_trial(grid, tmp_path):
    import subprocess
    import sys

    from agvviz.app.run import run_recording

    done, totals = [], []
    outcome = run_recording(
        grid[0], RunSettings(correction="bundle"), tmp_path / "grid.rrd", progress=done.append, on_total=totals.append
    )
    c = outcome.summary["cnoem_study"]
    assert (c["cells"], c["trials"], c["failed"]) == (1, TRIALS, 0) and c["run_setting"]["study_method"] == "bundle"
    assert "frames" not in outcome.summary and "correction" not in outcome.summary
    assert totals[-1] == TRIALS and done == list(range(1, TRIALS + 1))
    contents = read_rrd(outcome.out_path)
    assert document_json(contents, paths.RUN_SUMMARY)["cnoem_study"] == json.loads(json.dumps(c))
    assert document_json(contents, paths.RUN_MANIFEST)["scenario"]["options"]["mode"] == "grid"
    assert text_document(contents, CNOEM_REPORT).startswith("# Paper 002 §3.1 simulation study")
    trials, errors_m = scalar_series(contents, f"{cnoem_trial_errors(CELL)}/bundle", timeline="trial")
    assert list(trials) == list(range(TRIALS))
    np.testing.assert_allclose(
        errors_m, replay_cnoem_trials(grid[1], RunSettings()).results[CELL].errors_m["bundle"], rtol=1e-12
    )
    # The CLI needs no --set (correction=none: no method is the run setting) and prints the study's table.
    cli = subprocess.run(
        [sys.executable, "-m", "agvviz", "run", str(grid[0]), "--out", str(tmp_path / "cli.rrd")],
        capture_output=True, text=True,
    )
    assert cli.returncode == 0, cli.stderr
    assert f"1 × {TRIALS} × 6" in cli.stdout and "run setting" not in cli.stdout and "frames" not in cli.stdout
