"""agvviz diff / sweep / overlay on real replays of a small qr_floor recording, read back
through Rerun's API; and run determinism under `rerun rrd compare`.

One module-scoped sweep (lm with refine=ecc and refine=none, plus a setting made to fail; its
runs kept, ``keep_runs``) provides the runs most tests here use; the sweep tests of several recordings, of a missing Dask
and of an existing Dask cluster (--scheduler) use tiny recordings and one or two workers.
"""

from __future__ import annotations

import csv
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from agvviz import scenarios as scenario_registry
from agvviz.cli.main import app
from agvviz.app import dask_engine
from agvviz.app.diff import COMPACT_METRICS, CompareError, diff, diff_table, diff_table_title, diff_verdict, format_p
from agvviz.app.run_series import cameras_of, fixed_cameras_of, load_run
from agvviz.app.sweep import SweepEntry, parse_grid, sweep
from agvviz.app.sweep_report import ranking_markdown, sweep_verdict
from agvviz.errors import InputError
from agvviz.evaluation.comparison import DIRECT, RunSeries, compare_runs
from agvviz.evaluation.expression import ExpressionError
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings
from agvviz.viz import blueprints, overlay, paths
from agvviz.viz.readback import (
    encoded_images,
    points2d,
    read_rrd,
    scalar_series,
    text_document,
    transforms,
)

# 2 s at 10 Hz = 20 frames of the default paper 000 geometry.
SMALL = ["duration_s=2", "rate_hz=10", "realism=ideal"]
# 1 s at 5 Hz = 5 frames: the sweeps of several recordings and on an existing cluster.
TINY = ["duration_s=1", "rate_hz=5", "realism=ideal"]
CAM = "front"


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("compare")
    recording = tmp / "qr_floor.mcap"
    scenario_registry.record("qr_floor", recording, seed=11, overrides=SMALL)
    out_dir = tmp / "sweep"
    out_dir.mkdir()
    # A directory where the subpix run's .rrd must go: that run is refused (OutputError), the others not.
    (out_dir / "qr_floor-lm-refine=subpix.rrd").mkdir()
    outcome = sweep(recording, parse_grid(["refine=ecc,none,subpix"]), out_dir=out_dir, jobs=2, keep_runs=True)
    return recording, outcome


def _entry(outcome, label):
    return next(e for e in outcome.entries if e.label == label)


def test_sweep_ranks_reports_failure_and_writes_tables(swept):
    _, outcome = swept
    assert [e.label for e in outcome.entries] == ["lm", "lm-refine=none", "lm-refine=subpix"]
    ecc, none, subpix = outcome.entries
    assert ecc.rank == 1 and none.rank == 2 and subpix.rank is None
    assert not subpix.ok and "OutputError" in subpix.error and "existing folder" in subpix.error
    assert ecc.ok and ecc.metrics["frames"] == 20 and ecc.metrics["solved"] >= 18
    # ECC-refined corners (≈0.02 px) beat unrefined OpenCV corners (≈1 px, DESIGN §8) on every
    # frame, so 18+ paired frames give a Wilcoxon p of at most 2/2^18 ≈ 8e-6.
    assert none.p_vs_best < 0.01
    assert ecc.metrics["position_rmse_mm"] < none.metrics["position_rmse_mm"]
    with open(outcome.csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["setting"] for r in rows] == ["lm", "lm-refine=none", "lm-refine=subpix"]
    assert float(rows[0]["position_rmse_mm"]) == pytest.approx(ecc.metrics["position_rmse_mm"], rel=1e-3)
    assert rows[2]["status"].startswith("failed: OutputError")
    assert "| 1 | lm |" in outcome.markdown_path.read_text()


def test_sweep_overlay_holds_every_successful_run(swept):
    _, outcome = swept
    assert outcome.overlay_path.name == "sweep.rrd"
    contents = read_rrd(outcome.overlay_path)
    ok = [e for e in outcome.entries if e.ok]
    for entry in ok:
        key = entry.key
        assert key.endswith("_" + entry.label.replace("=", "_"))
        run = read_rrd(entry.out_path)
        # its layers in the sweep file: the kept run's values
        inside = read_rrd(f"{outcome.overlay_path}#{entry.label}")
        np.testing.assert_array_equal(scalar_series(inside, paths.ERROR_POSITION_MM)[1],
                                      scalar_series(run, paths.ERROR_POSITION_MM)[1])
        frames, values = scalar_series(contents, f"errors/position_mm/{key}")
        run_frames, run_values = scalar_series(run, paths.ERROR_POSITION_MM)
        np.testing.assert_array_equal(frames, run_frames)
        np.testing.assert_allclose(values, run_values, rtol=1e-12)
        assert f"world/trajectory/{key}" in contents.entity_paths
    report = text_document(contents, paths.COMPARE_REPORT)
    assert "settings/s3_" not in " ".join(contents.entity_paths)  # a failed setting has no layers
    table, failed = report.split("Failed settings:")
    assert "lm-refine=subpix" not in table and "lm-refine=subpix" in failed  # no row for a failed run
    # the ranking, the run's colour in the overlay and the verdict vs the best, in the viewer
    none = _entry(outcome, "lm-refine=none")
    assert "| #1 | orange | lm |" in table and "| best |" in table
    assert f"| #2 | magenta | lm-refine=none |" in table
    assert f"| {format_p(none.p_vs_best)} | worse than #1 (p" in table


def test_sweep_verdicts():
    """The viewer's verdict per setting: worse below α, not told apart at or above it."""
    def entry(label, rank, p):
        e = SweepEntry(label, RunSettings(), Path(f"{label}.rrd"), metrics={"position_rmse_mm": float(rank)})
        e.rank, e.p_vs_best = rank, p
        return e

    best, worse, same, untested = entry("a", 1, None), entry("b", 2, 0.0004), entry("c", 3, 0.2), entry("d", 4, None)
    assert sweep_verdict(best, best) == "best"
    assert sweep_verdict(worse, best) == "worse than #1 (p <0.001)"
    assert sweep_verdict(same, best) == "not told apart from #1 (p = 0.2 ≥ 0.05)"
    assert sweep_verdict(entry("e", 2, 0.049), best).startswith("worse")
    assert sweep_verdict(entry("e", 2, 0.05), best).startswith("not told apart")
    assert sweep_verdict(untested, best).startswith("no paired test")
    failed = SweepEntry("f", RunSettings(), Path("f.rrd"), error="OutputError: x")
    report = ranking_markdown("rec.mcap", [best, worse, same, untested, failed], "position_rmse_mm")
    assert report.count("\n| #") == 4 and "- f: OutputError: x" in report
    assert "| #3 | yellow | c | 3 |" in report


def test_diff_of_a_run_with_itself_is_zero_and_not_significant(swept):
    _, outcome = swept
    path = outcome.entries[0].out_path
    result = diff(path, path)
    for row in result.comparison.rows:
        assert row.diff == 0, row
        assert row.p_value in (None, 1.0)
    assert result.comparison.largest == []
    assert not result.failed


def test_worse_setting_is_detected(swept):
    _, outcome = swept
    ecc, none = outcome.entries[0].out_path, outcome.entries[1].out_path
    result = diff(ecc, none, fail_if="B.position_rmse_mm > 1.05*A.position_rmse_mm")
    row = result.comparison.row("position_rmse_mm")
    assert row.diff > 0 and row.p_value < 0.01 and row.ci_low > 0
    assert result.failed
    assert result.comparison.settings_changed == {"refine": ("ecc", "none")}
    assert not diff(ecc, none, fail_if="B.position_rmse_mm < A.position_rmse_mm").failed
    # The table's A column equals the run's own summary when both solved the same frames.
    run = load_run(ecc)
    if run.solved.all() and load_run(none).solved.all():
        from agvviz.viz.readback import document_json

        summary = document_json(read_rrd(ecc), paths.RUN_SUMMARY)
        assert row.a == pytest.approx(summary["position_error_mm"]["rmse"], rel=1e-12)


_NO_SCIPY_STATS = """
import sys
from pathlib import Path

from agvviz.app import run_series, sweep as sweep_module
from agvviz.cli.main import app
from agvviz.evaluation.comparison import run_metrics
from agvviz.settings import RunSettings

a, b = sys.argv[1:3]
app(["diff", a, b], standalone_mode=False)  # the command, as a user runs it
series = {0: run_series.load_run(a), 1: run_series.load_run(b)}  # the sweep's ranking
entries = [sweep_module.SweepEntry(label, RunSettings(), Path(path), metrics=run_metrics(series[i]))
           for i, (label, path) in enumerate((("a", a), ("b", b)))]
sweep_module._rank(entries, series, "position_rmse_mm", "none", 1)
print("RESULT", repr(entries[1].p_vs_best), "scipy.stats" in sys.modules)
"""


def test_diff_and_the_sweep_ranking_do_not_import_scipy_stats(swept):
    """scipy.stats costs ≈0.8 s of CPU (issue 27): `agvviz diff` and the sweep's ranking get their
    Wilcoxon p-values without it, the same p as the sweep's own ranking."""
    _, outcome = swept
    ecc, none = _entry(outcome, "lm"), _entry(outcome, "lm-refine=none")
    out = subprocess.run([sys.executable, "-c", _NO_SCIPY_STATS, str(ecc.out_path), str(none.out_path)],
                         capture_output=True, text=True, check=True).stdout
    marker, p_value, loaded = out.strip().splitlines()[-1].split()
    assert marker == "RESULT" and "position_rmse_mm" in out  # the diff printed its table
    assert float(p_value) == none.p_vs_best < 0.01
    assert loaded == "False"


def test_unknown_metric_fails_before_reading(swept, tmp_path):
    with pytest.raises(ExpressionError, match="unknown metric 'position_rms'.*position_rmse_mm"):
        diff(tmp_path / "missing_a.rrd", tmp_path / "missing_b.rrd", fail_if="B.position_rms > 1")


def test_diff_overlay_contents(swept, tmp_path):
    _, outcome = swept
    a_path, b_path = outcome.entries[0].out_path, outcome.entries[1].out_path
    out = tmp_path / "overlay.rrd"
    result = diff(a_path, b_path, overlay_path=out)
    assert result.overlay_path == out
    contents = read_rrd(out)
    a, b = read_rrd(a_path), read_rrd(b_path)
    # Both trajectories: the per-frame poses are the runs' own.
    for key, run in (("a", a), ("b", b)):
        frames, _, T = transforms(contents, f"world/agv/{key}")
        run_frames, _, run_T = transforms(run, paths.AGV_CAMERA)
        np.testing.assert_array_equal(frames, run_frames)
        np.testing.assert_allclose(T, run_T, atol=1e-6)  # float32 storage on both sides
        corners = points2d(contents, f"image/{CAM}/{key}")
        run_corners = points2d(run, paths.reprojected(CAM))
        for frame, pts in run_corners.items():
            np.testing.assert_array_equal(corners[frame], pts)
    # Δ position error = |error B| − |error A| on frames both solved.
    fa, ea = scalar_series(a, paths.ERROR_POSITION_MM)
    fb, eb = scalar_series(b, paths.ERROR_POSITION_MM)
    common = sorted(set(fa) & set(fb))
    frames, delta = scalar_series(contents, "delta/position_mm")
    np.testing.assert_array_equal(frames, common)
    expected = [abs(eb[list(fb).index(f)]) - abs(ea[list(fa).index(f)]) for f in common]
    np.testing.assert_allclose(delta, expected, rtol=1e-9, atol=1e-12)
    # The Δ plot's zero line spans it, and its title gives the sign convention.
    zero_frames, zero = scalar_series(contents, "delta/position_mm/zero")
    assert zero_frames.tolist() == [common[0], common[-1]] and zero.tolist() == [0.0, 0.0]
    assert blueprints.delta_view_name("position_mm") == "Δ |position error| = B − A [mm]: positive = B worse"
    # Each run's position error, magnified by the stated factor, drawn from the truth position
    # (both runs solved every matched frame here: B's frames are A's).
    run_a, run_b = load_run(a_path), load_run(b_path)
    # The factor is said once, in the colour key (and the 3D view titles), not on the arrows.
    key_text = text_document(contents, paths.COMPARE_KEY)
    assert key_text.count("×") == 1, key_text
    factor = float(key_text.split("×")[1].split()[0])
    for key, run in (("a", run_a), ("b", run_b)):
        frames, origins, vectors, labels = _arrows(contents, f"world/error/{key}")
        assert len(labels) == 1 and labels[0].startswith(f"{key.upper()} ") and "×" not in labels[0], labels
        rows = np.searchsorted(run.frames, frames)
        np.testing.assert_array_equal(run.frames[rows], frames)
        # float32 storage of the poses (≈1 µm at 10 m, then × factor) and of the arrows.
        np.testing.assert_allclose(origins, run.T_truth[rows, :3, 3], atol=1e-5)
        np.testing.assert_allclose(vectors, (run.T_est[rows, :3, 3] - run.T_truth[rows, :3, 3]) * factor,
                                   atol=1e-5 * factor)
    assert factor > 1  # one factor for both, so the arrows compare; sub-mm errors are magnified
    # A's images, byte for byte, on the same frames; the report is the diff table.
    images = encoded_images(contents, f"image/{CAM}")
    assert images == encoded_images(a, paths.image(CAM))
    assert "position_rmse_mm" in text_document(contents, paths.COMPARE_REPORT)
    # Without images the overlay is a fraction of the size.
    small = diff(a_path, b_path, overlay_path=tmp_path / "small.rrd", images=False).overlay_path
    assert small.stat().st_size < out.stat().st_size / 5


def test_cli_diff_gates_and_exports(swept, tmp_path):
    _, outcome = swept
    a_path, b_path = str(outcome.entries[0].out_path), str(outcome.entries[1].out_path)
    runner = CliRunner()
    result = runner.invoke(app, ["diff", a_path, b_path, "--fail-if", "B.position_rmse_mm > 1.05*A.position_rmse_mm"])
    assert result.exit_code == 1, result.output
    assert "position_rmse_mm" in result.output and "--fail-if holds" in result.output
    result = runner.invoke(app, ["diff", a_path, a_path, "--fail-if", "B.position_rmse_mm > A.position_rmse_mm"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["diff", a_path, b_path, "--fail-if", "B.nope > 1"])
    assert result.exit_code == 2 and "unknown metric 'nope'" in result.output
    result = runner.invoke(app, ["export", a_path, "--format", "tum", "--out-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / f"{Path(a_path).stem}.estimate.tum").is_file()


def test_sweep_grid_errors_are_clear(tmp_path):
    assert parse_grid(["lm.max_iters=3,10,3", "solver=lm"]) == {"lm_max_iterations": ["3", "10"], "solver": ["lm"]}
    with pytest.raises(CompareError, match="unknown setting 'nope'"):
        parse_grid(["nope=1,2"])
    with pytest.raises(CompareError, match="given twice"):
        parse_grid(["solver=lm", "solver=p4p"])
    recording = tmp_path / "r.mcap"
    recording.write_bytes(b"")
    with pytest.raises(CompareError, match="lm_max_iterations=0"):
        sweep(recording, parse_grid(["lm_max_iterations=0,3"]), out_dir=tmp_path)
    with pytest.raises(CompareError, match="same settings more than once"):
        sweep(recording, parse_grid(["lm_max_iterations=3,03"]), out_dir=tmp_path)


def test_sweep_of_several_recordings_detects_once(tmp_path):
    """Two recordings × two solvers: each recording's runs, tables and overlay go to its own
    folder; every run of a recording reuses its one detection. Each recording is detected once:
    by its first setting's run (the lead), the other reads the cache. (A path that is no
    recording refuses the whole sweep before it starts: tests/test_sweep_input.py.)"""
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    scenario_registry.record("qr_floor", a, seed=1, overrides=TINY)
    scenario_registry.record("qr_floor", b, seed=2, overrides=TINY)
    out = tmp_path / "sweep"
    reports = []
    outcome = sweep([a, b], parse_grid(["solver=lm,p4p"]), out_dir=out, jobs=2, images=False,
                    progress=lambda frames, runs: reports.append((frames, runs)), on_total=reports.append)
    assert [r.recording for r in outcome.recordings] == [a, b]
    assert [e.recording for e in outcome.entries] == [a, a, b, b]
    for recording in (a, b):
        result = next(r for r in outcome.recordings if r.recording == recording)
        assert result.out_dir == out / recording.stem
        assert sorted(e.label for e in result.entries) == ["lm", "p4p"]
        assert [e.rank for e in result.entries] == [1, 2]
        for entry in result.entries:
            assert entry.ok and entry.recording == recording
            assert str(entry.out_path) == f"{out / recording.stem / 'sweep.rrd'}#{entry.label}"
            assert entry.metrics["frames"] == 5
        # the group's one detection, by its lead (lm, first in the grid), reused by p4p
        assert {e.label: e.timing["detection_source"] for e in result.entries} == {"lm": "detected", "p4p": "cache"}
        assert result.overlay_path == out / recording.stem / "sweep.rrd" and result.overlay_path.is_file()
        assert sorted(p.name for p in result.out_dir.iterdir()) == ["ranking.csv", "ranking.md", "sweep.rrd"]
        with open(result.csv_path, newline="") as f:
            assert [r["status"] for r in csv.DictReader(f)] == ["ok", "ok"]
    # The first recording's files are the outcome's own (as for a sweep of one recording).
    assert outcome.csv_path == out / "a" / "ranking.csv"
    # Progress: the total first (2 recordings × 2 runs × 5 frames), then counts that never go
    # down and end at the total, 4 runs done.
    assert reports[0] == 20
    counts = reports[1:]
    assert counts[-1] == (20, 4)
    assert all(x[0] <= y[0] and x[1] <= y[1] for x, y in zip(counts, counts[1:]))
    assert not [n for d in out.iterdir() for n in (p.name for p in d.iterdir()) if n.endswith(".tmp")]


def test_sweep_of_one_setting_detects_on_every_process(tmp_path):
    """A sweep's lead detects on the whole pool of --jobs processes, also when there are fewer
    settings than processes (the pool was sized to the settings: a sweep of one setting
    detected on one process, 1.5× the wall time of `agvviz run`)."""
    recording = tmp_path / "r.mcap"  # 40 frames, untracked: 10 segments, work for two processes (detection_plan)
    scenario_registry.record("qr_floor", recording, seed=6, overrides=[
        "duration_s=4", "rate_hz=10", "width_px=640", "height_px=512", "focal_px=500", "realism=ideal"])
    outcome = sweep(recording, parse_grid(["solver=lm"]), base=RunSettings(tracking=False), out_dir=tmp_path / "one",
                    jobs=2, images=False, cache_dir=tmp_path / "cache")
    (entry,) = outcome.entries
    assert entry.ok, entry.error
    assert entry.timing["detection_source"] == "detected" and entry.timing["detect_workers"] == 2


def test_sweep_lead_that_fails_hands_the_lead_on(tmp_path):
    """The first setting of a detection group (its lead) detects, the others read the cache. A
    lead that fails (here: its kept run's path is a folder) hands the lead to the next setting,
    which detects; the third reads the cache (in the sweep process: a local sweep solves one
    setting there beside the workers)."""
    recording = tmp_path / "r.mcap"
    scenario_registry.record("qr_floor", recording, seed=4, overrides=TINY)
    out = tmp_path / "sweep"
    out.mkdir()
    (out / "r-lm.rrd").mkdir()
    outcome = sweep(recording, parse_grid(["solver=lm,p4p,ippe"]), out_dir=out, jobs=2, images=False,
                    keep_runs=True, cache_dir=tmp_path / "cache")
    by_label = {e.label: e for e in outcome.entries}
    assert not by_label["lm"].ok and by_label["lm"].error.startswith("OutputError")
    assert by_label["p4p"].ok and by_label["p4p"].timing["detection_source"] == "detected"
    assert by_label["ippe"].ok and by_label["ippe"].timing["detection_source"] == "cache"
    assert by_label["ippe"].metrics["frames"] == by_label["p4p"].metrics["frames"] == 5
    assert sorted(p.name for p in out.iterdir()) == ["r-ippe.rrd", "r-lm.rrd", "r-p4p.rrd", "ranking.csv",
                                                      "ranking.md", "sweep.rrd"]


def test_sweep_without_dask_runs_locally_and_scheduler_is_one_line(tmp_path, monkeypatch, qr_small):
    """Dask is needed for --scheduler alone: a local sweep runs on its own pool without it, and
    a sweep on a cluster without Dask installed is refused in one line, before anything is
    written."""
    recording = qr_small  # a recording: what is none is refused before Dask is looked for
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` raises ImportError
    outcome = sweep(recording, parse_grid(["solver=lm,p4p"]), out_dir=tmp_path / "local", images=False,
                    cache_dir=tmp_path / "cache")
    assert all(e.ok for e in outcome.entries), [e.error for e in outcome.entries]
    with pytest.raises(InputError, match=r"pip install 'agvviz\[distributed\]'"):
        sweep(recording, parse_grid(["solver=lm,p4p"]), out_dir=tmp_path / "out", scheduler="tcp://127.0.0.1:1")
    assert not (tmp_path / "out").exists()
    result = CliRunner().invoke(app, ["sweep", str(recording), "--set", "solver=lm,p4p", "--out-dir",
                                      str(tmp_path / "out"), "--scheduler", "tcp://127.0.0.1:1"])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert lines[-1] == f"error: {dask_engine.DASK_MISSING}", result.output
    assert not (tmp_path / "out").exists()


def test_sweep_on_an_existing_cluster(tmp_path):
    """--scheduler ADDRESS: the sweep runs on that cluster's workers (here a local cluster of
    one daemonic worker process, which detects in-process), leaves the cluster running, and
    refuses --jobs with it."""
    distributed = pytest.importorskip("distributed")
    import logging

    recording = tmp_path / "r.mcap"
    scenario_registry.record("qr_floor", recording, seed=3, overrides=TINY)
    out = tmp_path / "sweep"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=logging.ERROR) as local:
        result = CliRunner().invoke(app, ["sweep", str(recording), "--set", "solver=lm,p4p", "--scheduler",
                                          local.scheduler_address, "--out-dir", str(out), "--no-images"])
        assert result.exit_code == 0, result.output
        assert "sweep of r.mcap" in result.output and "failed" not in result.output
        assert {p.name for p in out.iterdir()} == {"sweep.rrd", "ranking.csv", "ranking.md"}
        assert len(local.workers) == 1  # the cluster is the caller's: still there
        with pytest.raises(CompareError, match="--jobs .* --scheduler"):
            sweep(recording, parse_grid(["solver=lm"]), out_dir=out, jobs=1, scheduler=local.scheduler_address)


def _rerun_cli() -> Path:
    cli = Path(sys.executable).parent / "rerun"
    if not cli.is_file():
        pytest.skip(f"rerun CLI not found next to {sys.executable}; needed for `rerun rrd compare`")
    return cli


def test_same_recording_and_settings_give_equal_rrd(tmp_path):
    """Determinism: recording id, timestamps and chunking pinned, no wall-clock figures in the
    summary, the recording named by file name (not by the path it was given): two runs of the
    same recording — even from another folder — are equal under `rerun rrd compare`; another
    setting is not."""
    cli = _rerun_cli()
    recording = tmp_path / "qr_floor.mcap"
    scenario_registry.record("qr_floor", recording, seed=5, overrides=TINY)
    elsewhere = tmp_path / "copy" / "qr_floor.mcap"
    elsewhere.parent.mkdir()
    shutil.copy(recording, elsewhere)
    run_recording(recording, RunSettings(), tmp_path / "first.rrd")
    run_recording(elsewhere, RunSettings(), tmp_path / "second.rrd")
    run_recording(recording, RunSettings(refine="none"), tmp_path / "other.rrd")

    def compare(x: str, y: str) -> subprocess.CompletedProcess:
        return subprocess.run([cli, "rrd", "compare", "--unordered", tmp_path / x, tmp_path / y],
                              capture_output=True, text=True, timeout=120, check=False)

    same = compare("first.rrd", "second.rrd")
    assert same.returncode == 0, same.stdout + same.stderr
    assert compare("first.rrd", "other.rrd").returncode != 0


# -- the verdict and the table of `diff` ------------------------------------------------------
def _series(name: str, position_mm: np.ndarray) -> RunSeries:
    """A run of len(position_mm) frames at 10 Hz, all solved, with these position errors (the
    other quantities zero, no poses: only the direct error series are compared)."""
    n = len(position_mm)
    errors = {q.key: np.zeros(n) for q in DIRECT}
    errors["position"] = np.asarray(position_mm, dtype=float)
    return RunSeries(
        name=name, frames=np.arange(n), time_ns=np.arange(n) * 100_000_000, solved=np.ones(n, bool),
        errors=errors, T_truth=np.full((n, 4, 4), np.nan), T_est=np.full((n, 4, 4), np.nan),
    )


def _verdict_of(a_mm: np.ndarray, b_mm: np.ndarray):
    comparison = compare_runs(_series("a", a_mm), _series("b", b_mm), seed=0)
    return comparison, diff_verdict(comparison)


A_MM = np.abs(np.random.default_rng(7).normal(0.0, 0.3, 200))  # seeded: the same on every machine


def test_verdict_names_a_worse_b_with_metric_interval_and_p():
    comparison, verdict = _verdict_of(A_MM, 2.0 * A_MM)  # B's error twice A's on every frame
    row = comparison.row("position_rmse_mm")
    assert verdict.outcome == "worse" and verdict.metric == "position_rmse_mm"
    assert row.ci_low <= row.diff <= row.ci_high and row.ci_low > 0  # the interval holds what was seen
    # 200 frames all worse: Wilcoxon's p is far below 0.001.
    assert verdict.headline == (
        f"B worse in position RMSE by {row.diff:.2f} mm [{row.ci_low:.2f}, {row.ci_high:.2f}] "
        f"(A {row.a:.2f} → B {row.b:.2f} mm), p < 0.001"
    ), verdict.headline
    assert verdict.lines[1].startswith("position RMSE decides (the estimated AGV position against truth, over the 200")
    # The other way round B is better, by the same amount, its interval given as a size.
    _, better = _verdict_of(2.0 * A_MM, A_MM)
    assert better.outcome == "better"
    assert better.headline.startswith(
        f"B better in position RMSE by {row.diff:.2f} mm [{row.ci_low:.2f}, {row.ci_high:.2f}]"
    ), better.headline


def test_verdict_of_identical_and_of_indistinguishable_runs():
    _, same = _verdict_of(A_MM, A_MM.copy())
    assert same.outcome == "identical"
    assert same.headline.startswith("no difference in position RMSE: the two runs' errors are identical on the 200")
    # ±1 µm alternating on every frame: as many frames better as worse, no significant difference.
    wiggle = A_MM + np.where(np.arange(200) % 2 == 0, 0.001, -0.001)
    comparison, verdict = _verdict_of(A_MM, wiggle)
    assert verdict.outcome == "no significant difference"
    assert comparison.row("position_rmse_mm").p_value > 0.05
    assert verdict.headline.startswith("no significant difference in position RMSE: B − A = ")


def test_verdict_says_when_the_runs_solved_different_frames():
    a, b = _series("a", A_MM), _series("b", 2.0 * A_MM)
    b.solved[:10] = False
    b.errors["position"][:10] = np.nan
    verdict = diff_verdict(compare_runs(a, b))
    assert verdict.lines[-1].startswith("B solved 10 fewer frames than A (190 vs 200")


@pytest.mark.parametrize("p, text", [
    (None, "—"), (0.0, "<0.001"), (0.00099, "<0.001"), (0.001, "0.001"), (0.0042, "0.004"), (0.03, "0.03"),
    (0.031, "0.03"), (0.4, "0.4"), (0.449, "0.45"), (1.0, "1"),
])
def test_p_values_read_as_a_reader_wants(p, text):
    assert format_p(p) == text


def test_compact_table_and_all_metrics():
    comparison, _ = _verdict_of(A_MM, 2.0 * A_MM)
    header, rows = diff_table(comparison)
    present = {r.name for r in comparison.rows}
    assert header[-1] == "p" and [r[0] for r in rows] == [m for m in COMPACT_METRICS if m in present]
    position = next(r for r in rows if r[0] == "position_rmse_mm")
    assert position[3].startswith("+") and position[-1] == "<0.001"
    assert len(diff_table(comparison, all_metrics=True)[1]) == len(comparison.rows)
    assert "more metrics with --all" in diff_table_title(comparison)


def test_error_magnification_is_a_1_2_5_step_that_fits_the_target():
    rng = np.random.default_rng(3)
    small, large = rng.normal(0, 0.0003, (100, 3)), rng.normal(0, 0.001, (100, 3))  # metres
    factor = overlay.error_magnification([small, large], target_m=0.5)
    p95 = float(np.percentile(np.linalg.norm(large, axis=1), 95))
    steps = [m * 10.0 ** e for e in range(0, 6) for m in (1, 2, 5)]
    assert factor in steps and p95 * factor <= 0.5 < p95 * steps[steps.index(factor) + 1]
    assert overlay.error_magnification([np.full((5, 3), 2.0)]) == 1.0  # never shrinks
    assert overlay.error_magnification([np.zeros((5, 3))]) == 1.0


def _arrows(contents, entity: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Frames, origins and vectors (per frame, one arrow each) and the static labels of an
    Arrows3D entity of an overlay, read back through Rerun's chunk API."""
    frames, origins, vectors, labels = [], [], [], []
    for chunk in contents.store.stream().filter(content=f"/{entity}"):
        if chunk.entity_path.lstrip("/") != entity:
            continue
        for row in chunk.to_record_batch().to_pylist():
            if row.get("Arrows3D:vectors") and row.get(paths.TIMELINE_FRAME) is not None:  # empty: no arrow
                frames.append(row[paths.TIMELINE_FRAME])
                origins += row["Arrows3D:origins"]
                vectors += row["Arrows3D:vectors"]
            if row.get("Arrows3D:labels") is not None:
                labels += row["Arrows3D:labels"]
    order = np.argsort(frames, kind="stable")
    return np.array(frames)[order], np.array(origins)[order], np.array(vectors)[order], labels


# 2 s at 10 Hz of uwb_room (four wall cameras fixed in the world, UWB), small images, the
# cameras blocked for a stretch: frames no camera solved are on the clock, unsolved.
UWB_TINY = [
    "duration_s=2", "width_px=640", "height_px=512", "block_start_s=0.8", "block_end_s=1.3", "realism=ideal",
]


def test_diff_of_uwb_room_runs_reads_the_wall_cameras(tmp_path):
    """A camera–UWB run's cameras are fixed in the world (``world/cameras/cam_<name>``): diff
    reads its frames from them, its per-run errors are each run summary's, and the overlay
    shows the wall cameras' images and corners."""
    recording = tmp_path / "uwb.mcap"
    scenario_registry.record("uwb_room", recording, seed=1, overrides=UWB_TINY)
    a_path, b_path = tmp_path / "a.rrd", tmp_path / "b.rrd"
    summary_a = run_recording(recording, RunSettings(), a_path, jobs=1, cache_dir=False).summary
    summary_b = run_recording(recording, RunSettings(fusion="kalman"), b_path, jobs=1, cache_dir=False).summary
    run_a = load_run(a_path)
    assert len(run_a.frames) == summary_a["frames"] and int(run_a.solved.sum()) == summary_a["solved"]
    assert 0 < summary_a["solved"] < summary_a["frames"]  # the blocked stretch is on the clock
    out = tmp_path / "d.rrd"
    result = diff(a_path, b_path, overlay_path=out)
    c = result.comparison
    for label, summary in (("a", summary_a), ("b", summary_b)):
        row = c.row("position_rmse_mm")
        assert getattr(row, label) == pytest.approx(summary["position_error_mm"]["rmse"], rel=1e-9)
        assert getattr(c.row("solved"), label) == summary["solved"]
    assert any("camera–UWB" in note and "kalman" in note for note in c.notes)
    contents, a = read_rrd(out), read_rrd(a_path)
    cams = cameras_of(a)
    assert cams and fixed_cameras_of(a) == set(cams)  # uwb_room: wall cameras only
    for cam in cams:
        assert encoded_images(contents, f"image/{cam}") == encoded_images(a, paths.image(cam, fixed=True))
        corners = points2d(contents, f"image/{cam}/a")
        for frame, pts in points2d(a, paths.reprojected(cam, fixed=True)).items():
            np.testing.assert_array_equal(corners[frame], pts)
