"""The detection workers' fork server ignores Ctrl-C from its first instruction.

A Ctrl-C at the terminal reaches the whole process group. multiprocessing's fork server ignores
SIGINT only once its preload imports are done, so an interrupt during them printed a
KeyboardInterrupt traceback beside agvviz's own one-line "interrupted" (found by the robustness
campaign's "SIGINT mid-run" case). :func:`agvviz.replay.detect.workers.start_fork_server` starts
it with SIGINT ignored, which an exec keeps.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from agvviz.replay.detect import workers

SIGINT_BIT = 1 << (2 - 1)  # /proc/PID/status SigIgn: bit (signum - 1)

PROBE = """
import multiprocessing.forkserver as fs, signal
from agvviz.replay.detect.workers import start_fork_server
start_fork_server()
pid = fs._forkserver._forkserver_pid
status = open(f"/proc/{pid}/status").read()
ignored = int(next(l for l in status.splitlines() if l.startswith("SigIgn:")).split()[1], 16)
print(ignored, signal.getsignal(signal.SIGINT) is signal.default_int_handler)
"""


@pytest.mark.skipif(not (workers.has_fork_server() and Path("/proc/self/status").exists()),
                    reason="needs a fork server and /proc (Linux)")
def test_the_fork_server_ignores_sigint_from_its_start_and_the_caller_keeps_its_handler():
    # The probe starts with Ctrl-C at its default, as from a terminal: a test run started as a
    # background job of a shell has it ignored, and the probe would inherit that.
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, check=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    ignored, caller_handler_back = out.stdout.split()
    assert int(ignored) & SIGINT_BIT, "the fork server was started with Ctrl-C live"
    assert caller_handler_back == "True", "the caller's own Ctrl-C handler was not restored"


FREEZE_PROBE = """
import gc, multiprocessing
from agvviz.replay.detect.workers import pool_context

def frozen():
    return gc.get_freeze_count()

if __name__ == "__main__":
    context = pool_context()
    print(context.get_start_method(), gc.get_freeze_count())
    with context.Pool(1) as pool:
        print(pool.apply(frozen))
"""


@pytest.mark.skipif(not workers.has_fork_server(), reason="needs a fork server")
def test_processes_of_the_fork_server_inherit_its_imports_frozen(tmp_path):
    """gc_freeze, the fork server's last preload: a forked process starts with the server's
    objects in the permanent generation (its collections then leave those shared pages alone),
    while the process that started the server is untouched."""
    probe = tmp_path / "probe.py"
    probe.write_text(FREEZE_PROBE)
    out = subprocess.run([sys.executable, str(probe)], capture_output=True, text=True, timeout=120, check=True)
    (method, caller_frozen), (child_frozen,) = [line.split() for line in out.stdout.splitlines()]
    assert method == "forkserver" and int(caller_frozen) == 0
    # numpy, OpenCV, Rerun and agvviz's replay: hundreds of thousands of objects; tens of
    # thousands at the very least, whatever the versions
    assert int(child_frozen) > 20_000, out.stdout
