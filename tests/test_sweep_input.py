"""`agvviz sweep` given something that is no recording (issue 27): refused up front with the one
line `agvviz run` gives for it and the same exit code, before any setting starts and before
anything is written (no out dir, no ranking of failed settings)."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from agvviz.app.sweep import parse_grid, sweep
from agvviz.cli.main import app
from agvviz.errors import RecordingError
from agvviz.viz.rrd_file import AtomicRrd


def _invoke(*args) -> tuple[int, list[str]]:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert "Traceback" not in result.output, result.output
    assert "sweeping" not in result.output, result.output  # no progress bar for a refused input
    return result.exit_code, [line for line in result.output.splitlines() if line.startswith("error:")]


@pytest.fixture(scope="module")
def not_recordings(tmp_path_factory):
    """Paths that are no recording: an .rrd, a text file named .mcap, a missing path, a folder
    that is no rosbag2 bag."""
    tmp = tmp_path_factory.mktemp("not_recordings")
    rrd = tmp / "run.rrd"
    with AtomicRrd(rrd, recording_id="x", recording_name="x") as out:
        out.commit()
    text = tmp / "notes.mcap"
    text.write_text("this is not an MCAP recording\n")
    folder = tmp / "folder"
    folder.mkdir()
    return {"rrd": rrd, "text": text, "missing": tmp / "missing.mcap", "folder": folder}


@pytest.mark.parametrize("kind", ["rrd", "text", "missing", "folder"])
def test_sweep_refuses_what_is_no_recording_as_run_does(not_recordings, tmp_path, kind):
    path = not_recordings[kind]
    run_code, run_errors = _invoke("run", path, "--out", tmp_path / "run.rrd")
    out_dir = tmp_path / "sweep"
    code, errors = _invoke("sweep", path, "--set", "solver=lm,ippe", "--jobs", "2", "--out-dir", out_dir)
    assert len(run_errors) == 1 and run_code == 2, run_errors
    assert errors == run_errors and code == run_code
    assert str(path) in errors[0]
    assert not out_dir.exists() and not (tmp_path / "run.rrd").exists()


def test_one_bad_recording_among_several_refuses_the_sweep_before_it_starts(not_recordings, qr_small, tmp_path):
    good = qr_small  # a recording (tests/conftest.py), given first: it does not start either
    out_dir = tmp_path / "sweep"
    code, errors = _invoke("sweep", good, not_recordings["rrd"], "--set", "solver=lm,ippe", "--out-dir", out_dir)
    assert code == 2 and len(errors) == 1 and "not an MCAP file" in errors[0], errors
    assert not out_dir.exists()
    # The library says the same, as a RecordingError.
    with pytest.raises(RecordingError, match="not an MCAP file"):
        sweep([good, not_recordings["text"]], parse_grid(["solver=lm,ippe"]), out_dir=out_dir, jobs=1)
    assert not out_dir.exists()
