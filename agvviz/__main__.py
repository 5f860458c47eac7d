"""The ``agvviz`` console script (also ``python -m agvviz``).

Kept tiny on purpose: :func:`main` installs the signal handlers (:mod:`agvviz.cli.interrupts`)
*before* the command line (typer, rich, numpy, Rerun, OpenCV, :mod:`agvviz.cli.main`) is
imported, so Ctrl-C during start-up, or SIGTERM at any time, ends the process with
``error: interrupted`` and exit code 130 — never a traceback — and the temporary files of
unfinished outputs are removed.
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading

from agvviz.cli import interrupts
from agvviz.errors import EXIT_INTERRUPTED


def _interrupted(message: bool = True) -> int:
    """End the process now with exit code 130 (after the temporaries were removed).

    ``os._exit`` rather than a return: under ``python -m agvviz`` a return after a caught
    KeyboardInterrupt sometimes still ended the process *by* SIGINT (exit -2) — measured in
    about 1 of 4 interrupts — and an interrupted process has nothing left to finish.
    """
    _release_semaphores()
    try:
        if message:
            sys.stderr.write("error: interrupted; unfinished outputs were removed\n")
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    os._exit(EXIT_INTERRUPTED)


def _release_semaphores() -> None:
    """Unlink this process's multiprocessing semaphores (the locks of a worker pool's queues, a
    sweep's stop event) before an interrupted command's hard exit, which skips the finalizers
    that do it at a normal exit: multiprocessing's resource tracker then printed "There appear
    to be 5 leaked semaphore objects to clean up at shutdown" after the one-line error. Only
    the finalizers of exit priority ≥ 0 run (the semaphores' unlinking, a queue's closing);
    those that join threads or processes (negative priority) do not."""
    util = sys.modules.get("multiprocessing.util")
    if util is None:
        return
    try:
        util._run_finalizers(0)
    except BaseException:  # noqa: BLE001 — best effort while exiting
        pass


def _remove_temps() -> None:
    try:
        from agvviz.recording.outputs import remove_live_temps

        remove_live_temps()
    except BaseException:  # noqa: BLE001 — best effort while exiting
        pass


def _exit_now(code: int) -> None:
    """End the process with ``code`` once the command is over and its exit functions ran,
    without the interpreter's teardown of every module and object (≈0.15-0.2 s of CPU after a
    run, issue 27: Rerun, pyarrow, OpenCV and numpy torn down only to exit). Only with no other
    Python thread alive (the interpreter would join it) and no profiler or tracer; the exit
    functions (atexit: Rerun's shutdown, multiprocessing's children, logging) run as at a normal
    exit."""
    if threading.active_count() > 1 or sys.getprofile() is not None or sys.gettrace() is not None:
        return  # another thread to join, or a profiler / coverage tracer that reports at the end
    try:
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
    except BaseException:  # noqa: BLE001 — let the normal exit report or retry it
        return
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    """Run the agvviz command line; returns the exit code. As the program (``argv`` None: the
    console script, ``python -m agvviz``) it ends the process itself when done (:func:`_exit_now`)."""
    interrupts.install()
    try:
        try:
            from agvviz.cli.early import start_fork_server_for

            start_fork_server_for(sys.argv[1:] if argv is None else list(argv))  # before the imports below
            from agvviz.cli.main import app

            app(args=argv, prog_name="agvviz")
            code = 0
        except SystemExit as exc:
            code = exc.code
            if code is None:
                code = 0
            elif not isinstance(code, int):
                sys.stderr.write(f"{code}\n")
                code = 1
        except BaseException:  # noqa: BLE001 — only when a signal caused it; otherwise a bug
            if not interrupts.signalled:
                raise
            _remove_temps()
            _interrupted()
        finally:
            _remove_temps()
        if code == EXIT_INTERRUPTED or interrupts.signalled:
            _interrupted(message=code != EXIT_INTERRUPTED)  # 130: the CLI printed its line
        # The command is over and its exit code decided: a signal landing while the interpreter
        # shuts down would otherwise end the process *by* that signal (exit -2).
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if interrupts.signalled:  # it landed between the check above and here
            _interrupted()
        if argv is None:
            _exit_now(code)
        return code
    except KeyboardInterrupt:  # a second Ctrl-C / SIGTERM while cleaning up
        _remove_temps()
        _interrupted()


if __name__ == "__main__":
    sys.exit(main())
