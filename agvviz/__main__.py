"""The ``agvviz`` console script (also ``python -m agvviz``).

Kept tiny on purpose: :func:`main` installs the signal handlers *before* the command line
(typer, rich, numpy, Rerun, OpenCV) is imported, so Ctrl-C during start-up, or SIGTERM at any
time, ends the process with ``error: interrupted`` and exit code 130 — never a traceback — and
the temporary files of unfinished outputs are removed.
"""

from __future__ import annotations

import signal
import sys

EXIT_INTERRUPTED = 130  # = agvviz.errors.EXIT_INTERRUPTED (not imported: start-up stays minimal)


def _sigterm(signum, frame) -> None:
    """SIGTERM is handled like Ctrl-C: unwind, remove temporaries, exit 130."""
    raise KeyboardInterrupt


def _interrupted() -> int:
    try:
        sys.stderr.write("error: interrupted; unfinished outputs were removed\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    return EXIT_INTERRUPTED


def _remove_temps() -> None:
    try:
        from agvviz.outputs import remove_live_temps

        remove_live_temps()
    except BaseException:  # noqa: BLE001 — best effort while exiting
        pass


def main(argv: list[str] | None = None) -> int:
    """Run the agvviz command line; returns the exit code."""
    signal.signal(signal.SIGTERM, _sigterm)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:  # keep "ignore" (nohup, `&`)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        try:
            from agvviz.cli import app

            app(args=argv, prog_name="agvviz")
            return 0
        except SystemExit as exc:
            code = exc.code
            if code is None:
                return 0
            if isinstance(code, int):
                return code
            sys.stderr.write(f"{code}\n")
            return 1
        except KeyboardInterrupt:
            return _interrupted()
        finally:
            _remove_temps()
    except KeyboardInterrupt:  # a second Ctrl-C / SIGTERM while cleaning up
        _remove_temps()
        return _interrupted()


if __name__ == "__main__":
    sys.exit(main())
