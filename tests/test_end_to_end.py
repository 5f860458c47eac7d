"""End to end: record a small qr_floor scenario, run it, read the .rrd back with Rerun's API."""

from __future__ import annotations


import numpy as np
import pytest
from typer.testing import CliRunner

from agvviz import scenarios as scenario_registry
from agvviz.cli.main import app
from agvviz.recording.contract import inspect_recording
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz.readback import document_json, points2d, read_rrd, scalar_series

# Small and fast: 2 s at 5 Hz = 10 frames of the default paper 000 geometry (1280x1024,
# camera 1.5 m high looking ~1 m ahead at 0.5 m codes).
SMALL = ["duration_s=2", "rate_hz=5", "realism=ideal"]


@pytest.fixture(scope="module")
def run_files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("e2e")
    recording = tmp / "qr_floor.mcap"
    scenario_registry.record("qr_floor", recording, seed=3, overrides=SMALL)
    outcome = run_recording(recording, RunSettings(solver="lm"), tmp / "run.rrd")
    return recording, outcome


def test_recording_meets_contract(run_files):
    recording, _ = run_files
    report = inspect_recording(recording)
    assert report.ok, report.violations + report.damage
    assert "front" in report.cameras
    image_topic = next(t for t in report.topics if t.topic == "/cam/front/image")
    assert image_topic.count == 10


def test_run_solves_frames_against_truth(run_files):
    _, outcome = run_files
    s = outcome.summary
    assert s["frames"] == 10
    assert s["solved"] >= 8, s["rejected"]
    # A 0.5 m code spans ~250 px; at σ = 0.3 px the CRLB on position is ≈6 mm (DESIGN §8),
    # and ECC-refined corners are far better than that. 20 mm fails any wrong link in the
    # transform chain (which gives errors of decimetres) without flaking on one hard frame.
    assert s["position_error_mm"]["max"] < 20.0
    assert s["heading_error_deg"]["max"] < 1.0


def test_rrd_holds_frames_corners_errors_and_manifest(run_files):
    recording, outcome = run_files
    contents = read_rrd(outcome.out_path)
    cam = "front"
    for entity in (
        paths.image(cam),
        paths.detected(cam),
        paths.reprojected(cam),
        paths.TRAJECTORY_TRUTH,
        paths.TRAJECTORY_CAMERA,
        paths.ERROR_POSITION_MM,
        paths.ERROR_HEADING_DEG,
        paths.RUN_MANIFEST,
        paths.RUN_SUMMARY,
    ):
        assert entity in contents.entity_paths, f"{entity} missing from the .rrd"

    # Reprojected corners within a pixel of the detected ones, on every solved frame.
    detected = points2d(contents, paths.detected(cam))
    reprojected = points2d(contents, paths.reprojected(cam))
    common = sorted(set(detected) & set(reprojected))
    assert len(common) >= 8
    for frame in common:
        d, r = detected[frame], reprojected[frame]
        assert d.shape == r.shape
        assert np.max(np.linalg.norm(d - r, axis=1)) < 1.0, frame

    # Position errors are logged in millimetres, one per solved frame, and match the summary.
    frames, pos_mm = scalar_series(contents, paths.ERROR_POSITION_MM)
    assert outcome.summary["solved"] >= 8  # 10 frames recorded; a run that solves none fails here
    assert len(frames) == outcome.summary["solved"]
    rmse_mm = float(np.sqrt(np.mean(pos_mm**2)))
    assert rmse_mm == pytest.approx(outcome.summary["position_error_mm"]["rmse"], rel=1e-6)

    manifest = document_json(contents, paths.RUN_MANIFEST)
    assert manifest["recording_sha256"] == outcome.manifest["recording_sha256"]
    assert manifest["settings"]["solver"] == "lm"
    summary = document_json(contents, paths.RUN_SUMMARY)
    assert summary["solved"] == outcome.summary["solved"] == len(frames)


def test_cli_record_inspect_run(tmp_path):
    runner = CliRunner()
    recording = tmp_path / "r.mcap"
    result = runner.invoke(app, ["record", "qr_floor", "--seed", "1", "--out", str(recording),
                                 *sum((["--set", s] for s in ["duration_s=0.4", "rate_hz=5"]), [])])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["inspect", str(recording)])
    assert result.exit_code == 0, result.output
    assert "/cam/front/image" in result.output
    out = tmp_path / "r.rrd"
    result = runner.invoke(app, ["run", str(recording), "--solver", "ippe", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert out.is_file() and "position RMSE" in result.output


def test_cli_rejects_bad_settings_with_clear_errors(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["run", str(tmp_path / "missing.mcap")])
    assert result.exit_code == 2 and "no such file" in result.output
    result = runner.invoke(app, ["record", "qr_floor", "--set", "nope=1", "--out", str(tmp_path / "x.mcap")])
    assert result.exit_code == 2 and "unknown setting 'nope'" in result.output
    assert not (tmp_path / "x.mcap").exists()
    result = runner.invoke(app, ["record", "no_such_scenario", "--out", str(tmp_path / "x.mcap")])
    assert result.exit_code == 2 and "unknown scenario" in result.output


def test_run_refuses_to_overwrite_its_input(run_files, tmp_path):
    from agvviz.replay.run import RunError

    recording, _ = run_files
    with pytest.raises(RunError):
        run_recording(recording, RunSettings(), recording.with_suffix(".mcap"))
