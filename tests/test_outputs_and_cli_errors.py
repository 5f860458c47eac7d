"""Issue 10, CLI and outputs: bad input and faults never crash, hang, lie or overwrite.

Every command ends a fault with one line ``error: …`` on stderr and the exit code of its kind
(2 bad input, 3 output not written, 130 interrupted), never writes over one of its inputs
(also through symbolic and hard links), never leaves a temporary file, and removes the
temporaries of killed processes on the next run into that folder.

Real faults where the machine allows them: a full disk and a read-only folder are tmpfs
mounts (those tests skip with the reason when ``mount`` is not permitted); signals go to real
subprocesses of the console script.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from agvviz.recording import outputs
from agvviz import scenarios as scenario_registry
from agvviz.cli.common import exit_for, handle_errors
from agvviz.cli.main import app
from agvviz.app.diff import CompareError
from agvviz.app.sweep import parse_grid, sweep
from agvviz.errors import OutputError
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings
from agvviz.viz.readback import RrdReadError, read_rrd
from agvviz.viz.rrd_file import AtomicRrd, looks_complete

TINY = ["duration_s=0.4", "rate_hz=5", "realism=ideal"]  # 2 frames
AGVVIZ = [sys.executable, "-m", "agvviz"]  # = the console script agvviz.__main__:main


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("faults")
    recording = tmp / "r.mcap"
    scenario_registry.record("qr_floor", recording, seed=5, overrides=TINY)
    a = run_recording(recording, RunSettings(solver="ippe"), tmp / "a.rrd").out_path
    b = run_recording(recording, RunSettings(solver="p4p"), tmp / "b.rrd").out_path
    return recording, a, b


def _invoke(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


def _one_error_line(result) -> str:
    lines = [line for line in result.output.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1, result.output
    assert "Traceback" not in result.output, result.output
    return errors[0]


def _temps(folder: Path) -> list[str]:
    return sorted(p.name for p in Path(folder).iterdir() if p.name.endswith(".tmp"))


def _mount_tmpfs(path: Path, options: str) -> None:
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a real full / read-only file system needs root and mount (tmpfs)")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"mount -t tmpfs is not permitted here: {done.stderr.strip()}")


@pytest.fixture
def full_disk(tmp_path):
    """A 2 MB tmpfs filled up to its last ~100 kB."""
    where = tmp_path / "full"
    _mount_tmpfs(where, "size=2m")
    try:
        with open(where / "filler", "wb") as f:
            f.write(b"\0" * (2 * 1024 * 1024 - 100 * 1024))
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


@pytest.fixture
def read_only(tmp_path):
    where = tmp_path / "ro"
    _mount_tmpfs(where, "ro,size=1m")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


# -- 2. never over an input -------------------------------------------------------------------
@pytest.mark.parametrize("how", ["same", "symlink", "hardlink"])
def test_diff_out_never_replaces_an_input(runs, tmp_path, how):
    _, a, b = runs
    before = a.read_bytes()
    target = {"same": a, "symlink": tmp_path / "link.rrd", "hardlink": tmp_path / "hard.rrd"}[how]
    if how == "symlink":
        target.symlink_to(a)
    elif how == "hardlink":
        os.link(a, target)
    result = _invoke("diff", a, b, "--out", target)
    assert result.exit_code == 3, result.output
    line = _one_error_line(result)
    assert "refusing to write over an input" in line and "choose another output name" in line
    assert a.read_bytes() == before
    assert not _temps(a.parent) and not _temps(tmp_path)


def test_run_export_sweep_never_replace_their_input(runs, tmp_path):
    recording, a, _ = runs
    # run --out a link named .rrd that points at the recording
    link = tmp_path / "rec.rrd"
    link.symlink_to(recording)
    before = recording.read_bytes()
    result = _invoke("run", recording, "--out", link)
    assert result.exit_code == 3 and "is the input" in _one_error_line(result)
    assert recording.read_bytes() == before
    # export: an output name that is a hard link of the run itself
    run_copy = tmp_path / "x.rrd"
    shutil.copy(a, run_copy)
    os.link(run_copy, tmp_path / "x.estimate.tum")
    result = _invoke("export", run_copy, "--format", "tum")
    assert result.exit_code == 3 and "is the input" in _one_error_line(result)
    assert run_copy.read_bytes() == a.read_bytes()
    # sweep: its sweep .rrd (or a kept run) a hard link of the recording; refused before any work
    out_dir = tmp_path / "sweep"
    out_dir.mkdir()
    os.link(recording, out_dir / "sweep.rrd")
    with pytest.raises(OutputError, match="refusing to write over an input"):
        sweep(recording, parse_grid(["solver=p4p,ippe"]), out_dir=out_dir, jobs=1)
    os.unlink(out_dir / "sweep.rrd")
    os.link(recording, out_dir / f"{recording.stem}-p4p.rrd")
    with pytest.raises(OutputError, match="refusing to write over an input"):
        sweep(recording, parse_grid(["solver=p4p,ippe"]), out_dir=out_dir, jobs=1, keep_runs=True)
    assert recording.read_bytes() == before


# -- 3. write failures: one line, exit 3, nothing left behind ---------------------------------
def test_out_under_a_regular_file_or_in_proc_is_one_line_exit_3(runs, tmp_path):
    recording, a, b = runs
    plain = tmp_path / "somefile.txt"
    plain.write_text("not a folder\n")
    folder_rrd = tmp_path / "folder.rrd"
    folder_rrd.mkdir()
    cases = [
        ("diff", a, b, "--out", plain / "x.rrd"),
        ("diff", a, b, "--out", "/proc/x/y.rrd"),
        ("run", recording, "--solver", "p4p", "--out", plain / "x.rrd"),
        ("record", "qr_floor", *sum((["--set", s] for s in TINY), []), "--out", plain / "x.mcap"),
        ("export", a, "--out-dir", plain),
        ("diff", a, b, "--out", folder_rrd),  # an existing folder
    ]
    for args in cases:
        result = _invoke(*args)
        assert result.exit_code == 3, (args, result.output)
        line = _one_error_line(result)
        assert line.startswith("error: cannot "), line
    assert plain.read_text() == "not a folder\n"
    assert not _temps(tmp_path)


def test_export_creates_a_missing_out_dir(runs, tmp_path):
    _, a, _ = runs
    out_dir = tmp_path / "new" / "deeper"
    result = _invoke("export", a, "--format", "tum", "--out-dir", out_dir)
    assert result.exit_code == 0, result.output
    assert "error" not in result.output
    assert sorted(p.name for p in out_dir.iterdir()) == ["a.estimate.tum", "a.truth.tum"]


def test_export_mcap_creates_its_folder(runs, tmp_path):
    pytest.importorskip("foxglove", reason="foxglove-sdk (the export extra) is not installed")
    _, a, _ = runs
    out_dir = tmp_path / "new" / "deeper"
    result = _invoke("export", a, "--format", "mcap", "--out-dir", out_dir)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out_dir.iterdir()) == ["a.poses.mcap"]
    assert f"estimate: 2 poses → {out_dir / 'a.poses.mcap'}" in result.output


def test_export_error_is_one_line_and_writes_nothing(runs, tmp_path):
    """An output that cannot be written is found before any is: one error line, exit 3, and
    not the estimate written while the truth fails."""
    _, a, _ = runs
    (tmp_path / "a.truth.tum").mkdir()
    result = _invoke("export", a, "--format", "tum", "--out-dir", tmp_path)
    assert result.exit_code == 3, result.output
    assert _one_error_line(result).startswith(f"error: cannot write {tmp_path / 'a.truth.tum'}: it is an existing folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.truth.tum"]


def test_read_only_folder_is_one_line_exit_3(runs, read_only):
    recording, a, b = runs
    for args in (("diff", a, b, "--out", read_only / "x.rrd"),
                 ("export", a, "--out-dir", read_only),
                 ("run", recording, "--solver", "p4p", "--out", read_only / "x.rrd")):
        result = _invoke(*args)
        assert result.exit_code == 3, (args, result.output)
        assert "read-only" in _one_error_line(result)
    assert not any(read_only.iterdir())


def test_read_only_folder_by_permission(runs, tmp_path, monkeypatch):
    """chmod does not stop root: the permission check is made to say no instead."""
    _, a, b = runs
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    real_access = os.access
    monkeypatch.setattr(outputs.os, "access",
                        lambda p, mode, **kw: False if Path(p) == locked else real_access(p, mode, **kw))
    try:
        result = _invoke("diff", a, b, "--out", locked / "x.rrd")
    finally:
        locked.chmod(0o755)
    assert result.exit_code == 3 and "permission" in _one_error_line(result)
    assert not any(locked.iterdir())


def test_full_disk_never_hangs_and_leaves_no_temporary(runs, full_disk):
    """diff --out onto a full disk hung in 2 of 8 tries before (Rerun's file sink); now each
    try ends in seconds with exit 3, and no .tmp is left filling the disk."""
    _, a, b = runs
    for attempt in range(4):
        t0 = time.monotonic()
        done = subprocess.run([*AGVVIZ, "diff", str(a), str(b), "--out", str(full_disk / "o.rrd")],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 3, done.stderr
        assert "No space left on device" in done.stderr and "Traceback" not in done.stderr
        assert [line for line in done.stderr.splitlines() if line.startswith("error:")], done.stderr
        assert sorted(p.name for p in full_disk.iterdir()) == ["filler"], attempt
        assert time.monotonic() - t0 < 100


def test_full_disk_for_run_and_record(runs, full_disk):
    recording, _, _ = runs
    result = _invoke("run", recording, "--solver", "p4p", "--out", full_disk / "x.rrd")
    assert result.exit_code == 3 and "disk is full" in _one_error_line(result)
    result = _invoke("record", "qr_floor", "--set", "duration_s=2", "--set", "rate_hz=5",
                     "--out", full_disk / "x.mcap")
    assert result.exit_code == 3 and "disk is full" in _one_error_line(result)
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]


def test_atomic_rrd_full_disk_raises_output_error_in_process(full_disk):
    import numpy as np
    import rerun as rr

    with pytest.raises(OutputError, match="No space left on device"):
        with AtomicRrd(full_disk / "x.rrd", recording_id="x", recording_name="x") as rrd:
            for i in range(200):
                rrd.rec.set_time("frame", sequence=i)
                rrd.rec.log("img", rr.Image(np.random.default_rng(i).integers(0, 255, (64, 64, 3), dtype=np.uint8)))
            rrd.commit()
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]



def test_atomic_writer_renames_on_success_and_leaves_the_target_on_failure(tmp_path):
    """outputs.atomic_writer (a detection cache entry is written through it a row group at a
    time): the target appears whole or not at all; an existing one is kept when writing fails."""
    target = tmp_path / "entry.bin"
    with outputs.atomic_writer(target) as file:
        file.write(b"first")
        assert not target.exists()
    assert target.read_bytes() == b"first"
    with pytest.raises(RuntimeError, match="stopped"):
        with outputs.atomic_writer(target) as file:
            file.write(b"second, half written")
            raise RuntimeError("stopped")
    assert target.read_bytes() == b"first" and sorted(p.name for p in tmp_path.iterdir()) == ["entry.bin"]


def test_atomic_writer_full_disk_is_output_error_and_leaves_nothing(full_disk):
    with pytest.raises(OutputError, match="No space left on device"):
        with outputs.atomic_writer(full_disk / "entry.bin") as file:
            file.write(bytes(4 << 20))
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]

# -- 5. stale temporaries and signals ---------------------------------------------------------
def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_stale_temporaries_of_dead_processes_are_removed(runs, tmp_path):
    _, a, _ = runs
    stale = tmp_path / f".a.estimate.tum.agvviz-{_dead_pid()}-0123456789ab.tmp"
    alive = tmp_path / f".a.truth.tum.agvviz-{os.getppid()}-0123456789ab.tmp"
    foreign = tmp_path / ".a.estimate.tum.0123456789abcdef.tmp"  # not agvviz's pattern: kept
    for p in (stale, alive, foreign):
        p.write_bytes(b"x")
    result = _invoke("export", a, "--format", "tum", "--out-dir", tmp_path)
    assert result.exit_code == 0, result.output
    assert not stale.exists() and alive.exists() and foreign.exists()


def _wait_for_temp(folder: Path, proc: subprocess.Popen, timeout: float = 120.0) -> list[str]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = [n for n in _temps(folder) if outputs.TEMP_RE.match(n)]
        if found:
            return found
        if proc.poll() is not None:
            pytest.fail(f"the command ended before writing: {proc.communicate()}")
        time.sleep(0.05)
    proc.kill()
    pytest.fail("no temporary file appeared")


@pytest.fixture(scope="module")
def longer_recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("long") / "long.mcap"
    scenario_registry.record("qr_floor", path, seed=1, overrides=["duration_s=4", "rate_hz=5", "realism=ideal"])
    return path


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_mid_run_removes_the_temporary_and_exits_130(longer_recording, tmp_path, sig):
    target = tmp_path / "run.rrd"
    proc = subprocess.Popen([*AGVVIZ, "run", str(longer_recording), "--solver", "lm", "--out", str(target)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for_temp(tmp_path, proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "error: interrupted" in err and "Traceback" not in err
    assert not target.exists() and not _temps(tmp_path)


@pytest.fixture
def console_handlers():
    """The console script's signal handlers (agvviz.cli.interrupts) for one test, then Python's."""
    from agvviz.cli import interrupts

    before = signal.signal(signal.SIGINT, interrupts._on_signal)
    try:
        yield interrupts
    finally:
        signal.signal(signal.SIGINT, before)
        interrupts.signalled = False


def _publish_with_a_signal_right_after_the_rename(tmp_path, monkeypatch) -> Path:
    target = tmp_path / "out.rrd"
    target.write_bytes(b"an earlier run")
    tmp = outputs.temp_path(target)
    tmp.write_bytes(b"this run")
    outputs.register_temp(tmp)
    real_replace = os.replace

    def replace_then_signal(src, dst):
        real_replace(src, dst)
        signal.raise_signal(signal.SIGINT)  # Ctrl-C lands between the rename and publish's return

    monkeypatch.setattr(os, "replace", replace_then_signal)
    try:
        outputs.publish(tmp, target)
    finally:
        monkeypatch.setattr(os, "replace", real_replace)
        assert target.read_bytes() == b"this run" and not tmp.exists()
        assert tmp not in outputs._live_temps  # nothing left for the interrupt's clean-up to remove
    return target


def test_a_signal_while_a_file_is_put_in_place_acts_once_it_is_there(console_handlers, tmp_path, monkeypatch):
    """The CI failure of the robustness case "SIGINT mid-run": the signal landed after the .rrd was
    renamed into place and before the run command knew, and the run exited 130 beside a complete
    output. A signal during outputs.publish now takes effect after it: the file is in place and
    forgotten as a temporary, and the interrupt follows."""
    with pytest.raises(KeyboardInterrupt):
        _publish_with_a_signal_right_after_the_rename(tmp_path, monkeypatch)
    assert console_handlers.signalled


def test_a_signal_while_a_commands_last_output_is_put_in_place_is_ignored(console_handlers, tmp_path, monkeypatch):
    """The run command's .rrd (on_published): the command is complete once it is in place, and a
    signal landing then is dropped — exit 0 with the output, never 130 beside it."""
    calls = []
    outputs.when_published(tmp_path / "out.rrd", lambda: calls.append("complete"))
    _publish_with_a_signal_right_after_the_rename(tmp_path, monkeypatch)
    assert calls == ["complete"] and not console_handlers.signalled
    # the registration was used up: the next file of that name is an ordinary one
    with pytest.raises(KeyboardInterrupt):
        _publish_with_a_signal_right_after_the_rename(tmp_path, monkeypatch)


def test_sigkill_of_a_run_leaves_no_temporary(longer_recording, runs, tmp_path):
    """SIGKILL mid-run: the process writing the .rrd (viz.run_process, a child of the fork
    server) sees its pipe close and removes the unfinished file; the folder is then as before and
    the next command writes into it."""
    _, a, b = runs
    proc = subprocess.Popen([*AGVVIZ, "run", str(longer_recording), "--solver", "p4p", "--out",
                             str(tmp_path / "run.rrd")], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    assert _wait_for_temp(tmp_path, proc)
    proc.kill()
    proc.wait(timeout=30)
    deadline = time.monotonic() + 20
    while _temps(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _temps(tmp_path) and not (tmp_path / "run.rrd").exists()
    result = _invoke("diff", a, b, "--out", tmp_path / "overlay.rrd", "--no-images")
    assert result.exit_code == 0, result.output
    assert not _temps(tmp_path)


def _catches_sigterm(pid: int) -> bool:
    """Whether ``pid`` has a SIGTERM handler yet: the first thing agvviz.__main__.main does."""
    try:
        with open(f"/proc/{pid}/status") as f:
            mask = next(int(line.split()[1], 16) for line in f if line.startswith("SigCgt:"))
    except (OSError, StopIteration):
        return False
    return bool(mask & (1 << (signal.SIGTERM - 1)))


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc to see the handlers")
def test_ctrl_c_during_start_up_is_not_a_traceback(tmp_path):
    """SIGINT while the command line is still importing (typer, numpy, Rerun, OpenCV), from the
    moment main() runs. (The interpreter's own start-up before any agvviz code, ~50 ms of
    `site` imports, is out of any program's reach.)"""
    for delay in (0.0, 0.1, 0.3, 0.8):
        proc = subprocess.Popen([*AGVVIZ, "diff", str(tmp_path / "a.rrd"), str(tmp_path / "b.rrd")],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 30
        while not _catches_sigterm(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.002)
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
        # Either interrupted, or it finished first (missing files: exit 2) — never a crash.
        assert proc.returncode in (130, 2), (proc.returncode, err)


# -- 6. garbage instead of a run ----------------------------------------------------------------
@pytest.fixture
def garbage(runs, tmp_path):
    _, a, _ = runs
    data = a.read_bytes()
    files = {
        "empty.rrd": b"",
        "random.rrd": os.urandom(5000),
        "text.rrd": b"hello, not a run\n",
        "truncated.rrd": data[: len(data) // 2],
        "no_footer.rrd": data[:-12],
        "header_only.rrd": data[:4] + bytes(3000),
        "run.txt": b"a text file\n",
    }
    for name, content in files.items():
        (tmp_path / name).write_bytes(content)
    return [tmp_path / name for name in files]


def test_diff_and_export_refuse_garbage_with_one_line(runs, garbage):
    _, a, _ = runs
    for bad in garbage:
        for args in (("diff", a, bad), ("diff", bad, a), ("export", bad, "--format", "tum")):
            result = _invoke(*args)
            assert result.exit_code == 2, (args, result.output)
            _one_error_line(result)
        with pytest.raises(RrdReadError):
            read_rrd(bad)
    assert not looks_complete(garbage[3])


def test_garbage_as_a_real_subprocess_has_no_traceback(runs, garbage):
    _, a, _ = runs
    done = subprocess.run([*AGVVIZ, "diff", str(a), str(garbage[3])], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().startswith("error:") and len(done.stderr.strip().splitlines()) == 1, done.stderr


# -- 7. sweep jobs and workers ------------------------------------------------------------------
def test_sweep_jobs_must_be_at_least_one(runs, tmp_path):
    recording, _, _ = runs
    for jobs in ("0", "-1"):
        result = _invoke("sweep", recording, "--set", "solver=p4p,ippe", "--jobs", jobs, "--out-dir", tmp_path / "s")
        assert result.exit_code == 2 and "--jobs must be ≥ 1" in _one_error_line(result)
    with pytest.raises(CompareError, match="--jobs"):
        sweep(recording, parse_grid(["solver=p4p,ippe"]), out_dir=tmp_path / "s", jobs=0)
    assert not (tmp_path / "s").exists()


def test_sweep_leaves_no_worker_behind(runs, tmp_path):
    recording, _, _ = runs
    outcome = sweep(recording, parse_grid(["solver=p4p,ippe"]), out_dir=tmp_path / "s", jobs=2, images=False)
    assert all(e.ok for e in outcome.entries)
    assert multiprocessing.active_children() == []
    assert not _temps(tmp_path / "s")


def _children(pid: int) -> set[int]:
    found = set()
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.add(int(entry))
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the workers")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_interrupted_sweep_stops_its_workers_and_removes_temporaries(longer_recording, tmp_path, sig):
    """SIGTERM: the sweep stops its workers and exits 130. SIGKILL of the sweep: the workers
    still end (Linux parent-death signal) and remove their temporaries."""
    out_dir = tmp_path / "sweep"
    proc = subprocess.Popen([*AGVVIZ, "sweep", str(longer_recording), "--set", "solver=lm,p4p", "--jobs", "2",
                             "--out-dir", str(out_dir)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out_dir.mkdir(exist_ok=True)
    _wait_for_temp(out_dir, proc, timeout=180)
    workers = _children(proc.pid)
    assert workers, "the sweep has no worker processes"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == (130 if sig == signal.SIGTERM else -signal.SIGKILL), err
    assert "Traceback" not in err, err
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and (
        [pid for pid in workers if outputs.pid_alive(pid) and _is_not_zombie(pid)] or _temps(out_dir)
    ):
        time.sleep(0.2)
    assert not [pid for pid in workers if outputs.pid_alive(pid) and _is_not_zombie(pid)]
    assert not _temps(out_dir)


def test_an_interrupted_command_leaves_no_semaphore_for_the_resource_tracker():
    """The hard exit of an interrupted command (agvviz.__main__._interrupted) unlinks the
    multiprocessing semaphores it made (a pool's queue, a sweep's stop event): the resource
    tracker printed "There appear to be 5 leaked semaphore objects" after the one-line error of a
    sweep stopped by SIGTERM."""
    code = (
        "import multiprocessing as mp, agvviz.__main__ as entry\n"
        "context = mp.get_context('spawn')\n"
        "queue, stop = context.Queue(), context.Event()\n"
        "entry._interrupted()\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 130
    assert done.stderr == "error: interrupted; unfinished outputs were removed\n", done.stderr


def _is_not_zombie(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


# -- 1. the one place errors become a line and a code ---------------------------------------
def test_error_kinds_map_to_exit_codes():
    import errno

    assert exit_for(OutputError("x"))[0] == 3
    assert exit_for(KeyboardInterrupt())[0] == 130
    assert exit_for(MemoryError())[0] == 2
    assert exit_for(OSError(errno.ENOSPC, "No space left on device", "/x"))[0] == 3
    assert exit_for(OSError(errno.ENOENT, "No such file or directory", "/x"))[0] == 2

    @handle_errors
    def boom() -> None:
        raise MemoryError

    import typer

    with pytest.raises(typer.Exit) as info:
        boom()
    assert info.value.exit_code == 2


def test_view_without_a_display_is_one_line(runs, monkeypatch):
    _, a, _ = runs
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is for Linux")
    result = _invoke("view", a)
    assert result.exit_code == 2 and "no display" in _one_error_line(result)


def test_markup_in_messages_is_printed_verbatim(tmp_path):
    result = _invoke("diff", tmp_path / "[bold]a.rrd", tmp_path / "b.rrd")
    assert result.exit_code == 2 and "[bold]a.rrd" in _one_error_line(result)


@pytest.mark.parametrize("durable", [True, False], ids=["an output", "a sweep's scratch run"])
def test_an_output_reaches_the_disk_before_its_rename_a_scratch_run_need_not(runs, tmp_path, monkeypatch, durable):
    """A run's .rrd is synced to the disk (fsync) before it is moved into place, so a crash never
    leaves a truncated file under its name; a sweep's layers-only run, which the sweep reads back
    and removes, is not (durable=False). Either way the file is complete."""
    synced = []
    fsync = os.fsync

    def recording_fsync(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    out = tmp_path / "run.rrd"
    run_recording(runs[0], RunSettings(), out, jobs=1, images=False, writer_process=False, durable=durable,
                  cache_dir=False)
    assert looks_complete(out)
    # (the run's .rrd, under its temporary name; the caches, written atomically too, are off)
    assert [Path(p).name.startswith(".run.rrd.agvviz-") for p in synced] == ([True] if durable else [])
