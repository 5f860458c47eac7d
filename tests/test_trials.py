"""The trials stage (agvviz.replay.studies.monte_carlo) on a tiny p4p_monte_carlo recording, its sink
(agvviz.viz.log_studies) and the kind-aware summary table (agvviz.evaluation.summary_table)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agvviz import scenarios as scenario_registry
from agvviz.errors import RecordingError
from agvviz.evaluation.summary import FrameScore, summarize, timing
from agvviz.evaluation.summary_table import summary_rows
from agvviz.replay.studies.monte_carlo import collect, is_trials_recording, replay_trials, study_solver, trials_timing
from agvviz.replay.studies.monte_carlo_cells import SOLVERS, evaluate_cell
from agvviz.recording.reader import ReadReport, RecordedMessage
from agvviz.recording.source import iter_role_messages, open_recording, resolve_roles, scan
from agvviz.model.topics import CORNERS_TOPIC, ROLE_CORNERS
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz.readback import document_json, read_rrd, scalar_series, text_document
from agvviz.viz.run_logger import RunLogger
from agvviz.viz.blueprints import trials_blueprint
from agvviz.viz.log_studies import log_trials

TRIALS = 3
#: Three well-conditioned CRLB cells (tilted 30°, code ≈ 417 px, σ ≤ 1 px), one with 8 points.
CELLS = ("crlb_tilt30_h0.2667_z2_s0.25_n4", "crlb_tilt30_h0.2667_z2_s0.5_n8", "crlb_tilt30_h0.2667_z2_s1_n4")
import subprocess
import sys
from agvviz.app.run import run_recording


def _roles_and_scenario(path):
    recording = open_recording(path)
    return recording, resolve_roles(scan(recording, ReadReport()))


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """(recording path, its role-tagged messages restricted to CELLS) of a seeded study."""
    out = tmp_path_factory.mktemp("trials") / "mc.mcap"
    scenario_registry.record("p4p_monte_carlo", out, seed=5, overrides=[f"trials={TRIALS}", "cells=crlb"])
    recording, roles = _roles_and_scenario(out)
    messages = [
        m for m in iter_role_messages(recording, roles, "log", ReadReport())
        if m.role != ROLE_CORNERS or m.value["cell"] in CELLS
    ]
    return out, messages


@pytest.fixture(scope="module")
def outcome(study):
    return replay_trials(study[1], RunSettings())


def test_every_trial_is_solved_and_agrees_with_evaluate_cell(study, outcome):
    assert list(outcome.results) == list(CELLS) and outcome.solvers == SOLVERS
    assert outcome.trials_per_cell == TRIALS and outcome.trials == TRIALS * len(CELLS) and not outcome.warnings
    K, cells = collect(study[1])
    np.testing.assert_array_equal(outcome.K, K)
    for cid, result in outcome.results.items():
        direct = evaluate_cell(cells[cid], K)
        bound_mm = result.crlb_t_m * 1000.0
        for name in SOLVERS:
            errors_m = result.errors_t_m[name]
            assert errors_m.shape == (TRIALS,) and np.all(np.isfinite(errors_m)), (cid, name)
            # The same computation as evaluate_cell on the same cells (both solve in this process).
            np.testing.assert_allclose(errors_m, direct.errors_t_m[name], rtol=1e-12, atol=0)
            assert result.stats[name].rmse_t_m == pytest.approx(direct.stats[name].rmse_t_m, rel=1e-12)
            # The per-trial series is what the statistics were made of.
            assert np.sqrt(np.mean(errors_m**2)) == pytest.approx(result.stats[name].rmse_t_m, rel=1e-12)
        # Against truth: lm_pixel is near-efficient in these cells, so a trial's ‖t̂ − t‖ above
        # 6× the RMS bound has probability ~1e-20 (χ²₃ > 108); a wrong unit, t or σ fails.
        assert np.all(result.errors_t_m["lm_pixel"] * 1000.0 < 6.0 * bound_mm), cid


def test_summary_section(outcome):
    t = outcome.summary["trials"]
    json.dumps(outcome.summary, allow_nan=False)  # stored in the .rrd as JSON
    assert (t["cells"], t["trials_per_cell"], t["trials"]) == (len(CELLS), TRIALS, len(CELLS) * TRIALS)
    assert t["solvers"] == list(SOLVERS) and t["failed"] == 0
    assert t["run_solver"]["study_solver"] == "lm_amb"  # default lm, pixel objective, lowest_error
    for name in SOLVERS:
        s = t["per_solver"][name]
        errors_mm = np.concatenate([r.errors_t_m[name] for r in outcome.results.values()]) * 1000.0
        assert s["failed"] == 0 and s["error_mm"]["max"] == pytest.approx(errors_mm.max(), rel=1e-12)
        ratios = [r.stats[name].rmse_t_m / r.crlb_t_m for r in outcome.results.values()]
        assert s["rmse_over_crlb"]["median"] == pytest.approx(np.median(ratios), rel=1e-12)
    assert t["well_conditioned_cells"] == len(CELLS)


def test_study_solver_marks_the_run_setting():
    assert study_solver(RunSettings(solver="lm", objective="depth")) == "lm"
    assert study_solver(RunSettings(solver="lm", ambiguity="continuity")) == "lm_pixel"
    assert study_solver(RunSettings(solver="sqpnp")) == "sqpnp"
    assert study_solver(RunSettings(solver="epnp")) is None


def test_progress_counts_trials(study):
    done = []
    replay_trials(study[1], RunSettings(), progress=done.append)
    assert done == [TRIALS, 2 * TRIALS, 3 * TRIALS]


def test_is_trials_recording(study, tmp_path):
    recording, roles = _roles_and_scenario(study[0])
    assert is_trials_recording(recording.scenario, roles)
    assert is_trials_recording(recording.scenario, dict(roles.roles))
    assert not is_trials_recording(recording.scenario, {})  # its corner topic not placed
    assert not is_trials_recording(None, roles)  # no scenario record
    qr = tmp_path / "qr.mcap"
    scenario_registry.record(
        "qr_floor", qr, overrides=["duration_s=0.2", "width_px=160", "height_px=128", "supersample=1"]
    )
    recording, roles = _roles_and_scenario(qr)
    assert recording.scenario["name"] == "qr_floor" and not is_trials_recording(recording.scenario, roles)


def test_bad_study_messages_give_one_line_errors(study):
    calibration = study[1][0]
    good = next(m for m in study[1] if m.role == ROLE_CORNERS)
    with pytest.raises(RecordingError, match="no camera calibration"):
        replay_trials([good], RunSettings())
    with pytest.raises(RecordingError, match="no corner messages"):
        replay_trials([calibration], RunSettings())
    value = json.loads(json.dumps(good.value))
    del value["markers"][0]["corners_px"]
    broken = RecordedMessage(CORNERS_TOPIC, good.log_time_ns, good.schema_name, value, role=ROLE_CORNERS)
    with pytest.raises(RecordingError, match="not a p4p_monte_carlo trial: missing 'corners_px'"):
        replay_trials([calibration, broken], RunSettings())
    value = json.loads(json.dumps(good.value))
    value["markers"][0]["corners_px"] = value["markers"][0]["corners_px"][:3]
    short = RecordedMessage(CORNERS_TOPIC, good.log_time_ns, good.schema_name, value, role=ROLE_CORNERS)
    with pytest.raises(RecordingError, match=r"corners_px has shape \(3, 2\)"):
        replay_trials([calibration, short], RunSettings())


def test_sink_logs_error_series_report_and_run_documents(outcome, tmp_path):
    out = tmp_path / "run.rrd"
    manifest = {"recording": "mc.mcap", "settings": {"solver": "lm"}}
    with RunLogger(out, recording_name="mc-lm", recording_id="test-trials") as logger:
        logger.log_manifest(manifest)
        log_trials(logger.stream, outcome)
        logger.blueprint = trials_blueprint(outcome)
        logger.log_summary(outcome.summary)
    contents = read_rrd(out)
    assert text_document(contents, "mc/report") == outcome.report_markdown
    assert document_json(contents, paths.RUN_SUMMARY) == json.loads(json.dumps(outcome.summary))
    assert document_json(contents, paths.RUN_MANIFEST) == manifest
    for cid, result in outcome.results.items():
        for name in ("p4p", "lm_amb"):
            trials, errors_mm = scalar_series(contents, f"mc/trials/{cid}/error_mm/{name}", timeline="trial")
            assert list(trials) == list(range(TRIALS))
            np.testing.assert_allclose(errors_mm, result.errors_t_m[name] * 1000.0, rtol=1e-12)
        trials, crlb_mm = scalar_series(contents, f"mc/trials/{cid}/error_mm/crlb", timeline="trial")
        assert list(trials) == [0, TRIALS - 1]
        np.testing.assert_allclose(crlb_mm, result.crlb_t_m * 1000.0, rtol=1e-12)


# -- the summary table fits the run's kind ----------------------------------------------------
def _frame(index: int, error_m: float | None, rejected: str | None = None) -> FrameScore:
    return FrameScore(index, rejected, error_m, 0.1 if error_m is not None else None, 0.3, 0.1, 0.08, 0.01)


CORRECTION = {
    "solver": "cnoem", "cycles": 6, "corrections_applied": 3, "cycles_without_correction": {},
    "mean_jump_m": 0.02031, "nav_rmse_m": 0.11142, "corrected_rmse_m": 0.07494,
    "nav_final_error_m": 0.19619, "corrected_final_error_m": 0.14516,
}


def test_summary_rows_camera_frames():
    scores = [_frame(0, 0.004), _frame(1, 0.002), _frame(2, None, "no_marker")]
    rows = dict(summary_rows(summarize(scores), timing(scores, 1.5)))
    assert rows["frames"] == "3" and rows["solved"] == "2" and rows["rejected: no_marker"] == "1"
    assert rows["position RMSE / median / p95 (mm)"].startswith("3.16 / 3.00")
    assert rows["throughput (frames/s, incl. logging)"] == "2.0"
    assert not any(k.startswith(("correction", "study")) for k in rows)


def test_summary_rows_failed_camera_run_still_shows_frames():
    scores = [_frame(0, None, "no_marker")]
    rows = dict(summary_rows(summarize(scores), timing(scores, 1.0)))
    assert rows["frames"] == "1" and rows["solved"] == "0" and rows["position RMSE / median / p95 (mm)"] == "— / — / —"


@pytest.mark.parametrize("with_frame_keys", [True, False])
def test_summary_rows_correction_only(with_frame_keys):
    # A corner-only auv_under_ice run: corrections, no camera frame (today's runner still writes
    # summarize([]) into the summary; the table must not show its empty rows either way).
    summary = {**(summarize([]) if with_frame_keys else {}), "correction": CORRECTION, "warnings": []}
    rows = summary_rows(summary, timing([], 2.0))
    labels = [label for label, _ in rows]
    assert not any(label in ("frames", "solved") or "RMSE / median" in label or "per frame" in label for label in labels)
    values = dict(rows)
    assert values["correction cycles / applied"] == "6 / 3"
    assert values["navigation RMSE raw → corrected (mm)"] == "111.42 → 74.94"
    assert values["final error raw → corrected (mm)"] == "196.19 → 145.16"
    assert values["wall time (s)"] == "2.0"


def test_summary_rows_camera_frames_with_fusion_and_correction():
    scores = [_frame(0, 0.004)]
    stats = {"mean": 5.0, "rmse": 6.0, "median": 5.0, "p95": 9.0, "max": 10.0, "n": 4}
    fusion = {
        "uwb": "least_squares", "fusion": "kalman", "camera_xy_error_mm": stats, "uwb_xy_error_mm": stats,
        "fused_xy_error_mm": stats, "fused_blocked_xy_error_mm": stats, "switches": 2,
        "switch_jump_mm": stats, "uwb_ranges": 40, "uwb_ranges_gated": 1, "kalman_ranges_gated": 0,
    }
    rows = dict(summary_rows({**summarize(scores), "fusion": fusion, "correction": CORRECTION}, timing(scores, 1.0)))
    assert rows["frames"] == "1" and rows["UWB ranges / fixes scored"] == "40 / 4"
    assert rows["fused (kalman) 2-D error mean / p95 (mm)"] == "5.00 / 9.00"
    assert rows["correction cycles / applied"] == "6 / 3" and "wall time (s)" not in rows


def test_summary_rows_trials(outcome):
    rows = summary_rows({**outcome.summary, "warnings": []}, trials_timing(outcome, 2.0))
    values = dict(rows)
    assert rows[:2] == [("study", "p4p_monte_carlo"), ("cells × trials × solvers", f"{len(CELLS)} × {TRIALS} × {len(SOLVERS)}")]
    assert "frames" not in values and "solved" not in values
    header = rows.index(("per solver", "RMSE ÷ CRLB median / max, failed"))
    per_solver = rows[header + 1 : header + 1 + len(SOLVERS)]
    assert [label.split()[0] for label, _ in per_solver] == list(SOLVERS)
    ratio = outcome.summary["trials"]["per_solver"]["lm_amb"]["rmse_over_crlb"]
    assert values["  lm_amb (the run setting)"] == f"{ratio['median']:.3f} / {ratio['max']:.3f}, 0"
    assert [label for label, _ in per_solver if "(the run setting)" in label] == ["  lm_amb (the run setting)"]
    assert values["time (s) / trials per s"] == f"2.0 / {len(CELLS) * TRIALS / 2.0:.1f}"


def test_run_on_a_study_recording_solves_every_trial(tmp_path):
    rec = tmp_path / "mc.mcap"
    scenario_registry.record("p4p_monte_carlo", rec, seed=2, overrides=["trials=2", "cells=crlb"])
    done, totals = [], []
    outcome = run_recording(rec, RunSettings(), tmp_path / "mc.rrd", progress=done.append, on_total=totals.append)
    t = outcome.summary["trials"]
    assert (t["cells"], t["trials_per_cell"], t["trials"]) == (48, 2, 96) and t["failed"] == 0
    assert "frames" not in outcome.summary and totals[-1] == 96 and done[-1] == 96
    contents = read_rrd(outcome.out_path)
    assert document_json(contents, paths.RUN_SUMMARY)["trials"] == json.loads(json.dumps(t))
    assert document_json(contents, paths.RUN_MANIFEST)["scenario"]["name"] == "p4p_monte_carlo"
    assert text_document(contents, "mc/report").startswith("# Paper 000 §6 Monte-Carlo study")
    trials, errors_mm = scalar_series(contents, "mc/trials/crlb_tilt30_h0.2667_z2_s0.5_n4/error_mm/lm_amb", timeline="trial")
    assert list(trials) == [0, 1] and np.all(np.isfinite(errors_mm))
    cli = subprocess.run([sys.executable, "-m", "agvviz", "run", str(rec), "--out", str(tmp_path / "cli.rrd")],
                         capture_output=True, text=True)
    assert cli.returncode == 0, cli.stderr
    assert "48 × 2 × 6" in cli.stdout and "lm_amb (the run setting)" in cli.stdout and "frames" not in cli.stdout
