"""A run's ``.rrd`` written by a child process (issue 27, :mod:`agvviz.viz.run_process`): the
same file as a logger in the run's own process writes, the child's errors raised in the run
process with their own type, and no file or temporary left behind when the run fails, is
discarded or dies."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from agvviz.app.run import run_recording
from agvviz import scenarios as scenario_registry
from agvviz.settings import RunSettings
from agvviz.viz import run_process

TINY = ["duration_s=1", "rate_hz=5", "realism=ideal"]
RERUN = Path(sys.executable).parent / "rerun"


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "r.mcap"
    scenario_registry.record("qr_floor", path, seed=5, overrides=TINY)
    return path


def test_the_child_writes_the_file_an_in_process_logger_writes(recording, tmp_path):
    child = run_recording(recording, RunSettings(), tmp_path / "child.rrd", jobs=1, cache_dir=False)
    here = run_recording(recording, RunSettings(), tmp_path / "here.rrd", jobs=1, cache_dir=False,
                         writer_process=False)
    assert child.summary == here.summary and child.recording_start_ns == here.recording_start_ns
    if not RERUN.exists():
        pytest.skip(f"the rerun CLI is not at {RERUN}")
    same = subprocess.run([str(RERUN), "rrd", "compare", "--unordered", str(tmp_path / "child.rrd"),
                           str(tmp_path / "here.rrd")], capture_output=True, text=True, timeout=120, check=False)
    assert same.returncode == 0, same.stdout + same.stderr


def test_an_error_in_the_child_is_raised_with_its_type_and_leaves_no_file(tmp_path):
    writer = run_process.RrdWriter(tmp_path / "x.rrd", RunSettings(), recording_name="x", recording_id="x")
    writer.logger.log_manifest({"recording": "x"})
    writer.sink.frame("not a frame")  # the child's logger refuses it
    with pytest.raises(AttributeError):
        writer.close()
    assert _files(tmp_path) == []


def test_a_discarded_file_is_removed(tmp_path):
    with pytest.raises(KeyError):
        with run_process.RrdWriter(tmp_path / "x.rrd", RunSettings(), recording_name="x", recording_id="x") as writer:
            writer.logger.log_manifest({"recording": "x"})
            raise KeyError("the run failed")
    assert _files(tmp_path) == []


def test_a_run_process_that_dies_leaves_no_temporary(tmp_path):
    """Killed without a word (os._exit), the run process leaves the child its pipe's end: the
    child removes its unfinished file."""
    script = textwrap.dedent(f"""
        import os
        from agvviz.settings import RunSettings
        from agvviz.viz.run_process import RrdWriter
        writer = RrdWriter({str(tmp_path / 'x.rrd')!r}, RunSettings(), recording_name="x", recording_id="x")
        writer.logger.log_manifest({{"recording": "x"}})
        import time
        deadline = time.monotonic() + 60  # the child opens its file once started (slow on a loaded machine)
        while not any(n.endswith(".tmp") for n in os.listdir({str(tmp_path)!r})) and time.monotonic() < deadline:
            time.sleep(0.05)
        print(sorted(os.listdir({str(tmp_path)!r})), flush=True)
        os._exit(3)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 3, done.stderr
    assert ".tmp" in done.stdout  # the child had its temporary file open
    deadline = time.monotonic() + 20
    while _files(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _files(tmp_path) == []



def _python(code: str, **env) -> str:
    """Run ``code`` in a fresh interpreter on this tree (the allocator settings are per process)."""
    environment = {k: v for k, v in os.environ.items() if not k.startswith("MIMALLOC_")} | env
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(Path(__file__).resolve().parents[1]),
                                                              environment.get("PYTHONPATH")]))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=environment,
                          timeout=60, check=True)
    return done.stdout.strip()


def test_agvviz_run_sets_mimalloc_to_give_freed_memory_back_before_the_fork_server_starts():
    """``agvviz run`` sets it before its fork server starts; a sweep, which imports the writer's
    module too, does not; a value the user set is kept."""
    code = ("import os, sys, agvviz.replay.detect.workers as w; print(os.environ.get('MIMALLOC_PURGE_DELAY')); "
            "w.writer_allocator_settings(); print(os.environ.get('MIMALLOC_PURGE_DELAY'))")
    assert _python(code).split() == ["None", "0"]
    assert _python(code, MIMALLOC_PURGE_DELAY="25").split() == ["25", "25"]  # the user's own value is kept
    import agvviz.cli.early as early
    import inspect

    source = inspect.getsource(early.start_run_fork_server)
    assert source.index("writer_allocator_settings()") < source.index("_started(start_fork_server)")
