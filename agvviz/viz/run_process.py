"""A run's ``.rrd`` written by a process of its own (issue 27): the replay solves while another
core logs.

:class:`RrdWriter` starts a child process that owns the run's
:class:`~agvviz.viz.run_logger.RunLogger` and :class:`~agvviz.viz.run_sinks.RrdSink`; the run
process hands it, through a pipe, the sink callbacks the ``.rrd`` acts on (:data:`SINK_CALLS`)
and the logger calls :func:`agvviz.app.run.run_recording` makes (:data:`LOGGER_CALLS`), in the
order it makes them. The child logs exactly what an in-process logger would: the same calls with
equal values (pickled), so the file is the same. What the run process saves is the logging
itself and ``import rerun`` (≈0.4 s, done in the fork server meanwhile); it pays pickling (≈0.05
s for 200 frames of images).

- The child is forked from the detection workers' fork server
  (:func:`agvviz.replay.detect.workers.pool_context`; spawned where there is none), which
  imports the logging modules beside the run's own start-up
  (:data:`~agvviz.replay.detect.workers.WRITER_MODULES`).
- :meth:`RrdWriter.close` asks the child to finish the file (blueprint, footer) and waits; the
  child writes under the run process's temporary name, which the run process then moves into
  place itself — an interruption before that removes it, as with a logger in process. An error
  the child met — a write failure, a value it refused — is raised there, with its own type when
  it is one of :mod:`agvviz.errors` (or of the modules it came from).
- :meth:`RrdWriter.discard` (an error or an interruption in the run process) makes the child
  remove its unfinished file. The child ignores Ctrl-C and SIGTERM (the run process handles them
  and tells it); if the run process dies without a word, the child sees its pipe close and
  removes its file.
- The pipe holds a few callbacks: a child slower than the replay slows the replay, memory does
  not grow.

This module imports nothing of Rerun: the run process never needs it.
"""

from __future__ import annotations

import importlib
import os
import pickle
import signal
import threading
from collections import deque
from pathlib import Path
from types import MappingProxyType

from agvviz.replay.detect.workers import pool_context

#: Sink callbacks :class:`~agvviz.viz.run_sinks.RrdSink` acts on; the others are not sent.
SINK_CALLS = ("cameras_changed", "frame", "fused", "corrected", "finished")
#: What the run process calls on the logger itself.
LOGGER_CALLS = ("log_manifest", "log_world_static", "log_summary", "log_error_budget")
#: How long :meth:`RrdWriter.discard` waits for the child to remove its file (seconds).
DISCARD_WAIT_S = 10.0
#: Pickled calls waiting for the child at most, in bytes and in calls: the run goes on meanwhile
#: (while the child starts — the fork server may still be importing — or logs a burst); beyond
#: either, the run waits. A few seconds of frames either way, the same on a long recording as
#: on a short one.
QUEUED_BYTES = 32 * 1024 * 1024
QUEUED_CALLS = 256

_CALL, _CLOSE, _DISCARD = "call", "close", "discard"

def rrd_writer(
    out_path: str | os.PathLike, settings, in_process: bool = False, **logger_kwargs,
) -> "RrdWriter | InProcessWriter":
    """The writer of a run's ``.rrd``: :class:`RrdWriter` (a child process), or
    :class:`InProcessWriter` when asked (``in_process``) or in a process that may not start one
    (a daemonic process: a Dask worker's)."""
    import multiprocessing

    if in_process or multiprocessing.current_process().daemon:
        return InProcessWriter(out_path, settings, **logger_kwargs)
    return RrdWriter(out_path, settings, **logger_kwargs)


class InProcessWriter:
    """:class:`RrdWriter`'s interface over a logger in this process."""

    def __init__(self, out_path: str | os.PathLike, settings, **logger_kwargs):
        from agvviz.viz.run_logger import RunLogger
        from agvviz.viz.run_sinks import RrdSink

        self.logger = RunLogger(Path(out_path), **logger_kwargs)
        self.sink = RrdSink(self.logger, settings)

    @property
    def recording_start_ns(self) -> int | None:
        return self.logger.recording_start_ns

    def close(self) -> None:
        self.logger.close()

    def discard(self) -> None:
        self.logger.discard()

    def __enter__(self) -> "InProcessWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.logger.__exit__(exc_type, exc, tb)


class RrdWriter:
    """The run's ``.rrd`` (``out_path``) written by a child process: :attr:`sink` is the replay
    graph's sink, :attr:`logger` takes :data:`LOGGER_CALLS`. ``logger_kwargs`` are
    :class:`~agvviz.viz.run_logger.RunLogger`'s; ``settings`` the run's (for the sink). Use as a
    context manager: an exception discards the file, else :meth:`close` finishes it.

    The calls are pickled here and handed to a sender thread, which starts the child (the fork
    server may still be importing: the run does not wait for it) and sends them in order; at
    most :data:`QUEUED_BYTES` and :data:`QUEUED_CALLS` wait (then the run waits for the child).
    A child that cannot start or fails is raised as an error at the next call or at
    :meth:`close`."""

    def __init__(self, out_path: str | os.PathLike, settings, **logger_kwargs):
        from agvviz.recording import outputs

        # Absolute paths, whatever the child's working folder.
        self._out_path = Path(os.path.abspath(out_path))
        logger_kwargs["inputs"] = tuple(os.path.abspath(p) for p in logger_kwargs.get("inputs", ()))
        # The child writes the file under this process's temporary name, and this process moves it
        # into place (close): an interruption before that removes it here, as an in-process
        # logger's would be; after it, the output is complete.
        self._tmp_path = outputs.temp_path(self._out_path)
        outputs.register_temp(self._tmp_path)
        logger_kwargs["tmp_path"] = str(self._tmp_path)
        out_path = str(self._out_path)
        context = pool_context()
        self._conn, child_conn = context.Pipe(duplex=True)
        self._process = context.Process(
            target=_serve, args=(child_conn, out_path, settings, logger_kwargs), name="agvviz rrd writer",
            daemon=True,
        )
        self._sender = _Sender(self._process, self._conn, child_conn)
        self._sender.start()
        self._done = False
        #: What the child's logger knows at the end (``recording_start_ns``), after :meth:`close`.
        self.recording_start_ns: int | None = logger_kwargs.get("recording_start_ns")
        self.sink = _Calls(self, "sink", SINK_CALLS)
        self.logger = _Calls(self, "logger", LOGGER_CALLS)

    def _call(self, target: str, method: str, args: tuple) -> None:
        if self._sender.reply is not None:  # the child failed (or never started): stop the run now
            self._raise(self._sender.reply)
        self._sender.put(pickle.dumps((_CALL, target, method, args), protocol=pickle.HIGHEST_PROTOCOL))

    def _reply(self):
        """The child's answer to :data:`_CLOSE` or :data:`_DISCARD` (or what it said before)."""
        self._sender.join()
        if self._sender.reply is not None:
            return self._sender.reply
        try:
            return self._conn.recv()
        except (EOFError, OSError):
            code = self._process.exitcode if self._process.pid is not None and not self._process.is_alive() else None
            return _ended(f"the process writing the .rrd ended (exit {code})")

    def _raise(self, reply) -> None:
        self.discard()
        raise _error(reply)

    def close(self) -> None:
        """Finish the file (the child logs what is left, ships the layout, renames the file into
        place) and wait; raises the child's error, if it met one (no file is written then)."""
        if self._done:
            return
        from agvviz.recording import outputs

        self._sender.put(pickle.dumps((_CLOSE,)), last=True)
        reply = self._reply()
        self._finish()
        if reply[0] != "ok":
            self._remove_temp()
            raise _error(reply)
        self.recording_start_ns = reply[1]
        try:
            outputs.publish(self._tmp_path, self._out_path)
        except OSError as exc:
            self._remove_temp()
            raise outputs.output_error(exc, self._out_path) from exc

    def _remove_temp(self) -> None:
        from agvviz.recording import outputs

        try:
            os.unlink(self._tmp_path)
        except OSError:
            pass
        outputs.release_temp(self._tmp_path)

    def discard(self) -> None:
        """Have the child remove its unfinished file, and wait for it (at most
        :data:`DISCARD_WAIT_S`)."""
        if self._done:
            return
        self._done = True
        self._sender.put(pickle.dumps((_DISCARD,)), last=True, drop_queued=True)
        self._sender.join(DISCARD_WAIT_S)
        try:
            if self._sender.reply is None and self._process.pid is not None and self._conn.poll(DISCARD_WAIT_S):
                self._conn.recv()
        except (EOFError, OSError):
            pass
        self._finish()
        self._remove_temp()

    def _finish(self) -> None:
        self._done = True
        self._conn.close()
        if self._process.pid is None:  # never started
            return
        self._process.join(DISCARD_WAIT_S)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()

    def __enter__(self) -> "RrdWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.discard()
        else:
            self.close()


class _Sender(threading.Thread):
    """Starts the writer's process and sends it the pickled calls in order. ``reply`` is set
    when the child answered early (its error) or could not be started or reached."""

    def __init__(self, process, conn, child_conn):
        super().__init__(name="agvviz rrd writer sender", daemon=True)
        self._process, self._conn, self._child_conn = process, conn, child_conn
        self._queue: deque[bytes] = deque()
        self._queued_bytes = 0
        self._last = False
        self._wake = threading.Condition()
        self.reply = None

    def put(self, data: bytes, *, last: bool = False, drop_queued: bool = False) -> None:
        with self._wake:
            if self._last:
                return
            if drop_queued:
                self._queue.clear()
                self._queued_bytes = 0
            while (
                (self._queued_bytes > QUEUED_BYTES or len(self._queue) >= QUEUED_CALLS)
                and self.reply is None and self.is_alive()
            ):
                self._wake.wait(0.1)
            self._queue.append(data)
            self._queued_bytes += len(data)
            self._last = last
            self._wake.notify_all()

    def run(self) -> None:
        try:
            self._process.start()
        except OSError as exc:
            self.reply = _ended(f"cannot start the process that writes the .rrd ({exc}); free some memory or processes")
            return
        finally:
            self._child_conn.close()
        while True:
            with self._wake:
                while not self._queue:
                    self._wake.wait()
                data = self._queue.popleft()
                self._queued_bytes -= len(data)
                last = self._last and not self._queue
                self._wake.notify_all()
            try:
                if self._conn.poll():  # the child answers early only to say it failed
                    self.reply = self._conn.recv()
                    return
                self._conn.send_bytes(data)
            except (EOFError, OSError):
                code = self._process.exitcode if not self._process.is_alive() else None
                self.reply = _ended(f"the process writing the .rrd ended (exit {code})")
                return
            if last:
                return


def _ended(message: str) -> tuple:
    return ("error", "RunError", "agvviz.errors", message)


class _Calls:
    """Stands for the child's sink or logger: each of ``methods`` is sent; any other sink
    callback does nothing (the ``.rrd`` does not act on it)."""

    def __init__(self, writer: RrdWriter, target: str, methods: tuple[str, ...]):
        self._writer, self._target, self._methods = writer, target, methods

    def __getattr__(self, name: str):
        if name in self._methods:
            return lambda *args: self._writer._call(self._target, name, _plain(args))
        if name.startswith("_"):
            raise AttributeError(name)
        return _ignored


def _ignored(*args, **kwargs) -> None:
    return None


def _plain(args: tuple) -> tuple:
    """Arguments as they pickle: a read-only mapping (a camera snapshot) as a dict."""
    return tuple(dict(a) if isinstance(a, MappingProxyType) else a for a in args)


def _error(reply) -> BaseException:
    """The exception a child's ``("error", type name, module, message)`` stands for: its own
    type when that takes a message alone, else :class:`~agvviz.errors.RunError`."""
    from agvviz.errors import RunError

    _, name, module, message = reply
    try:
        cls = getattr(importlib.import_module(module), name)
        if isinstance(cls, type) and issubclass(cls, Exception):
            return cls(message)
    except Exception:  # noqa: BLE001 — a type that cannot be rebuilt from its message
        pass
    return RunError(f"{name}: {message}")


def _serve(conn, out_path: str, settings, logger_kwargs: dict) -> None:
    """The child: log every call it is handed, then finish or remove the file."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the run process handles Ctrl-C and SIGTERM
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logger = None
    error = None
    try:
        from agvviz.viz.run_logger import RunLogger
        from agvviz.viz.run_sinks import RrdSink

        logger = RunLogger(Path(out_path), **logger_kwargs)
        targets = {"logger": logger, "sink": RrdSink(logger, settings)}
    except Exception as exc:  # noqa: BLE001 — reported to the run process
        error = exc
    while True:
        try:
            message = pickle.loads(conn.recv_bytes())
        except Exception:  # noqa: BLE001 — the run process is gone (or died mid-message)
            if logger is not None:
                logger.discard()
            return
        kind = message[0]
        if kind == _CALL:
            if error is None:
                _, target, method, args = message
                try:
                    getattr(targets[target], method)(*args)
                except Exception as exc:  # noqa: BLE001 — reported to the run process
                    error = exc
                    if logger is not None:
                        logger.discard()
                    _send(conn, _describe(error))
            continue
        if kind == _CLOSE and error is None:
            try:
                logger.close(publish=False)  # the run process moves it into place
            except Exception as exc:  # noqa: BLE001
                error = exc
            else:
                _send(conn, ("ok", logger.recording_start_ns))
                return
        if logger is not None:
            logger.discard()
        _send(conn, _describe(error) if error is not None else ("ok", None))
        return


def _describe(exc: BaseException) -> tuple:
    return ("error", type(exc).__name__, type(exc).__module__, str(exc))


def _send(conn, reply) -> None:
    try:
        conn.send(reply)
    except (BrokenPipeError, ConnectionResetError, EOFError, OSError):
        pass
