"""The one exception hierarchy of agvviz, and the CLI's exit codes.

Every error agvviz raises on purpose derives from :class:`AgvvizError` through one of four
kinds; the CLI turns any of them into one line ``error: <message>`` and the kind's exit code
(:data:`EXIT_CODES`). Anything else reaching the CLI is a bug.

================  =====================================================================  ====
kind              raised when                                                             exit
================  =====================================================================  ====
InputError        a setting, option, expression, payload or file given by the user is     2
                  wrong (a ``ValueError`` too, so numeric code may catch it as such)
RecordingError    a recording cannot be read or holds nothing a run can use                2
RunError          a run or a computation cannot go on (degenerate geometry, a solver      2
                  that cannot start, no usable frame)
OutputError       an output could not be written (folder missing or read-only, disk       3
                  full, the output would replace an input)
================  =====================================================================  ====

Exit codes of every command: 0 success, 1 a condition held (``diff``/``run --fail-if``) or a
contract was violated (``inspect``), 2 bad input, 3 output could not be written,
130 interrupted (Ctrl-C or SIGTERM).

This module imports nothing from agvviz, so the math modules may use it.
"""

from __future__ import annotations

#: Exit codes (README "Exit codes", docs/errors-and-outputs.md).
EXIT_OK = 0
EXIT_CONDITION = 1
EXIT_BAD_INPUT = 2
EXIT_OUTPUT = 3
EXIT_INTERRUPTED = 130


class AgvvizError(Exception):
    """Base of every error agvviz raises on purpose; ``exit_code`` is the CLI's exit code."""

    exit_code = EXIT_BAD_INPUT


class InputError(AgvvizError, ValueError):
    """Bad input given by the user: settings, options, expressions, payloads, files."""

    exit_code = EXIT_BAD_INPUT


class RecordingError(InputError):
    """A recording (or run file) cannot be read, or holds nothing a run can use."""

    exit_code = EXIT_BAD_INPUT


class RunError(AgvvizError, ValueError):
    """A run or a computation cannot go on (degenerate geometry, solver set-up, no frame)."""

    exit_code = EXIT_BAD_INPUT


class OutputError(AgvvizError, OSError):
    """An output could not be written; the temporary file was removed, the target untouched."""

    exit_code = EXIT_OUTPUT

    def __str__(self) -> str:  # OSError's own __str__ would show "[Errno …]" for 2 args
        return str(self.args[0]) if self.args else ""
