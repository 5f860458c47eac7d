"""The fork server of `agvviz run` and of a local `agvviz sweep` starts before the command line is
imported (agvviz.cli.early, issue 27): which commands start which server, and that the hook runs
before `agvviz.cli.main` is imported."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import agvviz.app.cluster as cluster
import agvviz.cli.early as early

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def started(monkeypatch):
    calls: list[str] = []
    monkeypatch.setattr(early, "start_run_fork_server", lambda: calls.append("run"))
    monkeypatch.setattr(cluster, "start_fork_server", lambda: calls.append("sweep"))
    return calls


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["run", "rec.mcap", "--set", "solver=ippe"], ["run"]),
        (["sweep", "rec.mcap", "--set", "solver=lm,ippe"], ["sweep"]),
        (["sweep", "rec.mcap", "--scheduler", "tcp://host:8786"], []),  # forks nothing here
        (["sweep", "rec.mcap", "--scheduler=tcp://host:8786"], []),
        (["run", "--help"], []),
        (["sweep", "--help"], []),
        (["diff", "a.rrd", "b.rrd"], []),
        (["record", "qr_floor"], []),
        ([], []),
    ],
)
def test_which_commands_start_a_fork_server_early(started, argv, expected):
    early.start_fork_server_for(argv)
    assert started == expected


def test_a_fork_server_that_cannot_start_is_left_to_the_command(monkeypatch):
    def no_processes_left():
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(cluster, "start_fork_server", no_processes_left)
    early.start_fork_server_for(["sweep", "rec.mcap"])  # no exception: the sweep reports it itself


def test_the_console_script_starts_it_before_the_command_line_is_imported():
    code = (
        "import sys, agvviz.cli.early as early\n"
        "seen = []\n"
        "early.start_fork_server_for = lambda argv: seen.append(('agvviz.cli.main' in sys.modules, argv))\n"
        "import agvviz.__main__ as m\n"
        "m.main(['version'])\n"
        "print(seen)\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60, check=True)
    assert done.stdout.strip().splitlines()[-1] == "[(False, ['version'])]"


def test_a_run_sets_its_writers_allocator_even_without_a_fork_server(monkeypatch):
    """Where there is no fork server (macOS, Windows) the writer is spawned: it reads the
    allocator setting from the environment all the same."""
    from agvviz.replay.detect import workers

    monkeypatch.delenv("MIMALLOC_PURGE_DELAY", raising=False)
    monkeypatch.setattr(workers, "has_fork_server", lambda: False)
    early.start_run_fork_server()
    assert os.environ["MIMALLOC_PURGE_DELAY"] == workers.MIMALLOC_SETTINGS["MIMALLOC_PURGE_DELAY"]
