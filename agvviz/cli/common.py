"""What every agvviz command shares: the consoles, the one error handler (:func:`handle_errors`:
an :class:`~agvviz.errors.AgvvizError`, an ``OSError`` from writing, ``MemoryError`` or an
interrupt becomes one line ``error: <message>`` on stderr and the exit code of its kind,
:mod:`agvviz.errors`: 2 bad input, 3 output not written, 130 interrupted) and the progress bar.
"""

from __future__ import annotations

import errno
import functools

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.text import Text

from agvviz.errors import EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_OUTPUT, AgvvizError, InputError
from agvviz.recording import outputs

console = Console()
err_console = Console(stderr=True, soft_wrap=True)

#: errno values of an ``OSError`` that mean "could not write" (exit 3) rather than bad input.
WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG}


def error_line(message: str) -> None:
    """Print ``error: <message>`` as one line on stderr (no markup is interpreted)."""
    text = " ".join(str(message).split()) or "unknown error"
    err_console.print(Text.assemble(("error:", "bold red"), " ", text), soft_wrap=True, highlight=False)


def exit_for(exc: BaseException) -> tuple[int, str]:
    """The exit code and the one-line message for an exception reaching the CLI."""
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED, "interrupted; unfinished outputs were removed"
    if isinstance(exc, AgvvizError):
        return exc.exit_code, str(exc)
    if isinstance(exc, MemoryError):
        return EXIT_BAD_INPUT, "out of memory; try a shorter recording, fewer settings or --no-images"
    if isinstance(exc, OSError):
        target = exc.filename or "a file"
        if exc.errno in WRITE_ERRNOS:
            return EXIT_OUTPUT, str(outputs.output_error(exc, target))
        return EXIT_BAD_INPUT, f"cannot use {target}: {exc.strerror or exc}"
    raise TypeError(f"not an error the CLI reports: {type(exc).__name__}")


def handle_errors(command):
    """Decorator of every command: the one place that turns errors into a line and a code."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except BrokenPipeError:  # stdout closed by the reader (`agvviz diff … | head`): typer's to handle
            raise
        except (AgvvizError, OSError, MemoryError, KeyboardInterrupt) as exc:
            if isinstance(exc, KeyboardInterrupt):
                outputs.remove_live_temps()
            code, message = exit_for(exc)
            error_line(message)
            raise typer.Exit(code=code) from None

    return wrapper


def fail(message: str) -> None:
    """Refuse the command line: :class:`~agvviz.errors.InputError` (one line, exit 2)."""
    raise InputError(message)


def stop_progress(progress: Progress) -> None:
    """Stop a bar that was started (Rich prints a blank line when stopping on a non-terminal);
    a bar drawn only once work starts may never have been."""
    if progress.live.is_started:
        progress.stop()


def progress_bar() -> Progress:
    """The progress bar of every long command, on stderr."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeRemainingColumn(),
        console=err_console,
        transient=False,
    )
