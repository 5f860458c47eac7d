"""Issue 27: `agvviz` ends its process once the command is over (agvviz.__main__._exit_now),
skipping the interpreter's teardown — yet its exit functions still run, its output is complete,
its exit code is the command's, and it does not cut short another thread, a profiler or a caller
that passes argv (a test calling main in-process)."""

from __future__ import annotations

import subprocess
import sys

PROGRAM = """
import atexit, sys, threading
import agvviz.__main__ as entry
atexit.register(lambda: print("exit function ran", flush=True))
sys.argv = ["agvviz", *{argv!r}]
{before}
code = entry.main({main_argv})
print("main returned", code, flush=True)
sys.exit(code)
"""


def _run(argv: list[str], before: str = "", main_argv: str = "") -> subprocess.CompletedProcess:
    code = PROGRAM.format(argv=argv, before=before, main_argv=main_argv)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_the_program_ends_itself_after_its_exit_functions():
    done = _run(["--help"])
    assert done.returncode == 0
    assert "Usage" in done.stdout and done.stdout.rstrip().endswith("exit function ran")
    assert "main returned" not in done.stdout  # the process ended inside main


def test_a_failing_command_keeps_its_exit_code_and_message():
    done = _run(["run", "/nonexistent/rec.mcap"])
    assert done.returncode == 2
    assert "no such file" in done.stderr
    assert "exit function ran" in done.stdout and "main returned" not in done.stdout


def test_main_with_argv_returns_to_its_caller():
    done = _run([], main_argv='["--help"]')
    assert done.returncode == 0
    assert "main returned 0" in done.stdout and done.stdout.rstrip().endswith("exit function ran")


def test_another_live_thread_is_left_to_the_normal_exit():
    before = ("threading.Thread(target=lambda: (__import__('time').sleep(3), print('thread done', flush=True)), "
              "daemon=False).start()")
    done = _run(["--help"], before=before)
    assert done.returncode == 0 and "main returned 0" in done.stdout and "thread done" in done.stdout


def test_a_profiler_is_left_to_the_normal_exit():
    done = _run(["--help"], before="sys.setprofile(lambda *a: None)")
    assert done.returncode == 0 and "main returned 0" in done.stdout
