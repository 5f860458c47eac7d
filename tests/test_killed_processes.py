"""A run or a sweep killed outright (SIGKILL) leaves no process of its own behind.

Its detection workers (a sweep's pool) are children of the fork server, not of the run; every
child of the fork server holds the pipe whose closing ends the server, so after a SIGKILL the
server and its idle workers used to wait for each other for ever. Each worker now waits on its
starter's sentinel and ends with it (``agvviz.replay.detect.workers._exit_with_starter``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agvviz.scenarios import record

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads sessions from /proc (Linux)")

#: 60 frames, detected without tracking (4 frames a segment): both workers get work.
RECORDING = ["duration_s=6", "rate_hz=10", "width_px=640", "height_px=512", "focal_px=500", "realism=ideal"]


def _session(sid: int) -> list[int]:
    """Processes of session ``sid`` (from /proc/<pid>/stat: the fields after the command name
    are state, ppid, pgrp, session, …)."""
    pids = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            pids.append(int(entry))
    return pids


def _kill_mid_work(argv: list[str], folder: Path, cwd: Path) -> tuple[int, int]:
    """Start ``agvviz argv`` in a session of its own, SIGKILL it once it writes into ``folder``
    and has worker processes; returns (processes of its session then, left 30 s later)."""
    env = dict(os.environ, AGVVIZ_CACHE_DIR=str(cwd / "cache"))
    proc = subprocess.Popen([sys.executable, "-m", "agvviz", *argv], cwd=cwd, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            writing = folder.is_dir() and any(n.endswith(".tmp") for n in os.listdir(folder))
            if writing and len(_session(proc.pid)) >= 4:  # the command, the fork server, two workers
                break
            time.sleep(0.02)
        if proc.poll() is not None:
            pytest.skip(f"agvviz {argv[0]} ended (exit {proc.returncode}) before it could be killed mid-work")
        at_kill = len(_session(proc.pid))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 30
        while _session(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        return at_kill, len(_session(proc.pid))
    finally:
        for pid in _session(proc.pid):  # do not leave them to other tests
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass


def test_a_killed_run_leaves_no_process(tmp_path):
    record("qr_floor", tmp_path / "r.mcap", seed=2, overrides=RECORDING)
    at_kill, left = _kill_mid_work(["run", "r.mcap", "--out", "out/x.rrd", "--jobs", "2", "--set", "tracking=false"],
                                   tmp_path / "out", tmp_path)
    assert at_kill >= 4 and left == 0, (at_kill, left)


def test_a_killed_sweep_leaves_no_process(tmp_path):
    record("qr_floor", tmp_path / "r.mcap", seed=2, overrides=RECORDING)
    at_kill, left = _kill_mid_work(["sweep", "r.mcap", "--set", "solver=lm,p4p,ippe", "--set", "tracking=false",
                                    "--jobs", "2", "--out-dir", "out", "--no-images"], tmp_path / "out", tmp_path)
    assert at_kill >= 4 and left == 0, (at_kill, left)
