"""The sweep .rrd (issue 27): one file per sweep with the frames once and each setting's layers
under ``settings/<key>/``; the layers carry the same values as a standalone run of that setting
(read back with :mod:`agvviz.viz.readback`); ``FILE#SETTING`` for diff and export; two sweeps of
the same grid compare equal under ``rerun rrd compare --unordered``; ``run --images none`` and
the frames ``agvviz view`` adds to it. One small recording (3 s at 10 Hz, 640×512), two solvers.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from agvviz import scenarios as scenario_registry
from agvviz.app.diff import diff
from agvviz.app.export import export_run
from agvviz.app.run import layers_only_frames, run_recording
from agvviz.app.run_series import load_run
from agvviz.app.sweep import parse_grid, sweep
from agvviz.cli.main import app
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz.readback import (
    RrdReadError,
    encoded_images,
    read_rrd,
    scalar_series,
    sweep_index,
    text_document,
    text_logs,
)

SMALL = ["duration_s=3", "rate_hz=10", "width_px=640", "height_px=512", "focal_px=500", "realism=typical"]
CAM = "front"
SOLVERS = ("lm", "ippe")


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """A sweep of two solvers and the standalone run of each."""
    tmp = tmp_path_factory.mktemp("sweep_file")
    recording = tmp / "qr.mcap"
    scenario_registry.record("qr_floor", recording, seed=4, overrides=SMALL)
    outcome = sweep(recording, parse_grid([f"solver={','.join(SOLVERS)}"]), out_dir=tmp / "sweep", jobs=2)
    standalone = {
        solver: run_recording(recording, RunSettings(solver=solver), tmp / f"{solver}.rrd", jobs=1).out_path
        for solver in SOLVERS
    }
    return recording, outcome, standalone


def test_a_sweep_writes_one_file_with_the_frames_once(swept):
    recording, outcome, standalone = swept
    folder = outcome.recordings[0].out_dir
    assert sorted(p.name for p in folder.iterdir()) == ["ranking.csv", "ranking.md", "sweep.rrd"]
    sweep_file = outcome.overlay_path
    assert sweep_file == folder / "sweep.rrd"
    contents = read_rrd(sweep_file)
    assert sorted(e["label"] for e in sweep_index(contents)) == sorted(SOLVERS)
    # The frames once, byte for byte a run's; no setting's subtree holds a camera image.
    assert encoded_images(contents, f"image/{CAM}") == encoded_images(standalone["lm"], paths.image(CAM))
    assert paths.camera_images(contents.entity_paths) == []
    # Two settings cost little more than one run: the layers are small beside the frames.
    assert sweep_file.stat().st_size < 1.5 * standalone["lm"].stat().st_size
    # The ranking document: verdict and p-value.
    report = text_document(contents, paths.COMPARE_REPORT)
    best, other = sorted(outcome.entries, key=lambda e: e.rank)
    assert f"| #1 | orange | {best.label} |" in report and "| best |" in report
    assert f"| #2 | magenta | {other.label} |" in report and "p vs best" in report


@pytest.mark.parametrize("solver", SOLVERS)
def test_each_settings_layers_carry_the_standalone_runs_values(swept, solver):
    _, outcome, standalone = swept
    ref = f"{outcome.overlay_path}#{solver}"
    inside, alone = load_run(ref), load_run(standalone[solver])
    np.testing.assert_array_equal(inside.frames, alone.frames)
    np.testing.assert_array_equal(inside.time_ns, alone.time_ns)
    np.testing.assert_array_equal(inside.T_est, alone.T_est)  # the same float32 values, not close ones
    for key in alone.errors:
        np.testing.assert_array_equal(inside.errors[key], alone.errors[key])
    assert inside.settings == alone.settings
    assert inside.summary["position_error_mm"] == alone.summary["position_error_mm"]  # the RMSE unchanged
    entry = next(e for e in outcome.entries if e.label == solver)
    assert entry.metrics["position_rmse_mm"] == pytest.approx(alone.summary["position_error_mm"]["rmse"], rel=1e-9)
    # LM iterations and suspects too: every layer, not only the errors.
    ours, theirs = read_rrd(ref), read_rrd(standalone[solver])
    for entity in (paths.LM_ITERATIONS, paths.ERROR_REPROJ_RMS_PX):
        if entity in theirs.entity_paths:
            for x, y in zip(scalar_series(ours, entity), scalar_series(theirs, entity)):
                np.testing.assert_array_equal(x, y)
    for entity in (paths.EVENTS_SUSPECTS, paths.EVENTS_REJECTIONS):
        assert (entity in ours.entity_paths) == (entity in theirs.entity_paths)
        if entity in theirs.entity_paths:
            assert text_logs(ours, entity) == text_logs(theirs, entity)
    assert ours.entity_paths == theirs.entity_paths - {paths.image(CAM)}


def test_diff_and_export_read_settings_of_a_sweep(swept, tmp_path):
    _, outcome, standalone = swept
    sweep_file = outcome.overlay_path
    inside = diff(f"{sweep_file}#solver=lm", f"{sweep_file}#ippe", overlay_path=tmp_path / "d.rrd")
    alone = diff(standalone["lm"], standalone["ippe"])
    assert inside.comparison.row("position_rmse_mm") == alone.comparison.row("position_rmse_mm")
    # diff --out is the two-run sweep file: its settings read back the same, its frames are the sweep's.
    again = diff(f"{tmp_path / 'd.rrd'}#a", f"{tmp_path / 'd.rrd'}#B")
    assert again.comparison.row("position_rmse_mm") == alone.comparison.row("position_rmse_mm")
    assert encoded_images(tmp_path / "d.rrd", f"image/{CAM}") == encoded_images(sweep_file, f"image/{CAM}")
    # A setting the file does not hold: one line naming the ones it does, exit 2.
    result = CliRunner().invoke(app, ["diff", f"{sweep_file}#p4p", f"{sweep_file}#lm"])
    assert result.exit_code == 2 and "has no setting 'p4p'; its settings: " in result.output
    assert len(result.output.strip().splitlines()) == 1
    with pytest.raises(RrdReadError, match="is a sweep .rrd of 2 settings"):
        load_run(sweep_file)
    # export: the setting's trajectory, named after it, equal to the standalone run's.
    written = export_run(f"{sweep_file}#ippe", "tum", tmp_path)
    mine = (tmp_path / "sweep-ippe.estimate.tum").read_text().splitlines()
    assert [w.path for w in written][0] == tmp_path / "sweep-ippe.estimate.tum"
    export_run(standalone["ippe"], "tum", tmp_path)
    theirs = (tmp_path / "ippe.estimate.tum").read_text().splitlines()
    assert mine[1:] == theirs[1:] and len(mine) > 10


def _rerun_cli() -> Path:
    cli = Path(sys.executable).parent / "rerun"
    if not cli.is_file():
        pytest.skip(f"rerun CLI not found next to {sys.executable}; needed for `rerun rrd compare`")
    return cli


def test_equal_sweeps_compare_equal_and_kept_runs_equal_standalone_runs(swept, tmp_path):
    recording, outcome, standalone = swept
    again = sweep(recording, parse_grid([f"solver={','.join(SOLVERS)}"]), out_dir=tmp_path / "again", jobs=2,
                  keep_runs=True)
    cli = _rerun_cli()

    def compare(x, y) -> subprocess.CompletedProcess:
        return subprocess.run([cli, "rrd", "compare", "--unordered", x, y], capture_output=True, text=True,
                              timeout=120, check=False)

    same = compare(outcome.overlay_path, again.overlay_path)
    assert same.returncode == 0, same.stdout + same.stderr
    kept = next(e for e in again.entries if e.label == "lm").out_path
    assert kept == tmp_path / "again" / "qr-lm.rrd"
    equal = compare(kept, standalone["lm"])
    assert equal.returncode == 0, equal.stdout + equal.stderr
    assert compare(kept, standalone["ippe"]).returncode != 0


def test_run_images_none_writes_the_layers_and_view_adds_the_frames(swept, tmp_path):
    recording, _, standalone = swept
    layers = run_recording(recording, RunSettings(), tmp_path / "layers.rrd", jobs=1, images=False)
    assert layers.manifest == run_recording(recording, RunSettings(), tmp_path / "full.rrd", jobs=1).manifest
    contents = read_rrd(layers.out_path)
    assert paths.camera_images(contents.entity_paths) == []
    assert layers.out_path.stat().st_size < standalone["lm"].stat().st_size / 2
    assert load_run(layers.out_path).errors["position"].tolist() == load_run(standalone["lm"]).errors["position"].tolist()
    frames = layers_only_frames(layers.out_path, recording, tmp_path)
    assert encoded_images(frames, paths.image(CAM)) == encoded_images(standalone["lm"], paths.image(CAM))
    assert layers_only_frames(standalone["lm"], None, tmp_path) is None  # a run with its frames needs none
    # Its recording not found: one line that says how to give it.
    result = CliRunner().invoke(app, ["view", str(layers.out_path), "--recording", str(tmp_path / "other.mcap")])
    assert result.exit_code == 2 and len(result.output.strip().splitlines()) == 1, result.output
    moved = tmp_path / "elsewhere" / "layers.rrd"
    moved.parent.mkdir()
    layers.out_path.rename(moved)
    result = CliRunner().invoke(app, ["view", str(moved), "--web", "--port", "0"])
    assert result.exit_code == 2 and "give it with --recording" in result.output, result.output


def test_the_elapsed_origin_is_read_without_pyarrow_compute(swept):
    """The sweep file's ``elapsed`` origin (its run's first per-frame row: time − elapsed) is read
    from the timeline buffers, not with ``Array.cast`` (which imports pyarrow.compute, ≈0.08 s of
    a sweep's last step): the value equals the cast's, in a process that never imports it."""
    import pyarrow as pa

    _, _, standalone = swept
    run = read_rrd(standalone["lm"])
    for chunk in run.store.stream().filter(is_static=False):
        if {paths.TIMELINE_TIME, paths.TIMELINE_ELAPSED} <= set(chunk.timeline_names) and chunk.num_rows:
            batch = chunk.to_record_batch()
            expected = (batch.column(paths.TIMELINE_TIME).cast(pa.int64())[0].as_py()
                        - batch.column(paths.TIMELINE_ELAPSED).cast(pa.int64())[0].as_py())
            break
    code = (
        "import sys; from agvviz.viz.overlay import _elapsed_origin_ns; from agvviz.viz.readback import read_rrd; "
        f"print(_elapsed_origin_ns(read_rrd({str(standalone['lm'])!r}).store, [], None), "
        "'pyarrow.compute' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == [str(expected), "False"]
