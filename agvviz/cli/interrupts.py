"""Ctrl-C and SIGTERM in the console script: the handlers :func:`agvviz.__main__.main` installs
first (:func:`install`), and :func:`outputs_complete`, which a command calls once its outputs are
in place. Imports only the standard library, so the handlers are in place before the command line
(typer, rich, numpy, Rerun, OpenCV) is imported.
"""

from __future__ import annotations

import signal
import sys

#: Set by the signal handler. A KeyboardInterrupt raised inside an extension module's
#: initialisation comes out as ``ImportError: initialization failed`` (pybind11, seen with
#: scipy), so "was a signal received?" is asked of this flag, not of the exception's type.
signalled = False


def _on_signal(signum, frame) -> None:
    """SIGINT and SIGTERM alike: unwind, remove temporaries, exit 130 — once a file being put in
    place is there (:func:`agvviz.recording.outputs.hold_while_publishing`), so that the exit
    code and the outputs agree."""
    outputs = sys.modules.get("agvviz.recording.outputs")  # not imported yet: nothing is being put in place
    if outputs is not None and outputs.hold_while_publishing(_interrupt):
        return
    _interrupt()


def _interrupt() -> None:
    global signalled
    signalled = True
    raise KeyboardInterrupt


def _unraisable(unraisable) -> None:
    """After a signal, an object the interrupt left half-built (e.g. a Rerun RecordingStream
    interrupted in its constructor) may complain from its ``__del__`` while the process unwinds;
    that is not an error of the command, and must not print a traceback. Otherwise: Python's own
    report."""
    if signalled:
        return
    sys.__unraisablehook__(unraisable)


def install() -> None:
    """From now on SIGTERM, and SIGINT unless it is ignored (nohup, `&`), raise KeyboardInterrupt
    and set :data:`signalled`."""
    sys.unraisablehook = _unraisable
    signal.signal(signal.SIGTERM, _on_signal)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:  # keep "ignore" (nohup, `&`)
        signal.signal(signal.SIGINT, _on_signal)


def outputs_complete() -> None:
    """The command's outputs are complete and in place: from now on a signal is ignored rather
    than ending the process by exit 130 (which would say the outputs failed). Only in the
    console script; a program calling the CLI in-process keeps its own handlers."""
    if signal.getsignal(signal.SIGTERM) is _on_signal:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if signal.getsignal(signal.SIGINT) is _on_signal:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
