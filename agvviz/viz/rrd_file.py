"""One way to write an ``.rrd`` atomically, reproducibly and safely.

:class:`AtomicRrd` opens a data-only :class:`rerun.RecordingStream` (pinned recording id, no
log time or tick, no properties, chunks cut by size only) whose bytes end up in a temporary
file beside the target (:func:`agvviz.recording.outputs.temp_path`), so memory stays flat;
:meth:`AtomicRrd.commit` sends the layout (active and default, so the file opens in it), writes
the footer, checks the file is complete and renames it into place; :meth:`AtomicRrd.discard`
deletes it. Used as a context manager, an exception discards.

Why a pipe: Rerun's file sink writes on a background thread and only *logs* a write error
(``Failed to write … No space left on device``); a flush or disconnect after such an error can
wait forever (seen on a full disk), and so can the interpreter's exit. So Rerun writes into a
named pipe (FIFO) that never fails, and a thread of ours copies the pipe into the temporary file
with ordinary ``os.write`` calls: a write error is caught there, the temporary file is deleted at
once (giving the space back), the rest of the stream is drained and dropped so Rerun never
blocks, and :meth:`AtomicRrd.check` / :meth:`AtomicRrd.commit` raise
:class:`~agvviz.errors.OutputError`. Where named pipes do not exist (Windows) Rerun writes the
file itself and commit flushes with a time limit.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Iterable

import rerun as rr
import rerun.blueprint as rrb

from agvviz.recording import outputs
from agvviz.errors import OutputError

#: The chunk batcher never cuts a chunk on a wall-clock tick (a day is "never" here), so the
#: same data gives the same chunks and `rerun rrd compare --unordered` finds two runs equal.
BATCHER_FLUSH_TICK_S = 86_400.0
#: ... and cuts one whenever this much payload has accumulated, a size small enough that what
#: the batcher holds does not grow with the run (with Rerun's default, peak memory of a run of
#: 600 frames was 75 MB above one of 200).
BATCHER_FLUSH_NUM_BYTES = 256 * 1024
#: First and last bytes of a complete ``.rrd`` (Rerun 0.41: header FourCC, footer FourCC).
RRD_MAGIC = b"RRF2"
RRD_FOOTER_MAGIC = b"RRF2FOOT"
#: Bytes moved per read from the pipe, and the pipe's buffer size asked of Linux.
_CHUNK = 1 << 20
_F_SETPIPE_SZ = 1031
#: Without a pipe: the longest a flush may make no progress before the write counts as failed.
_STALL_S = 60.0


def looks_complete(path: str | os.PathLike) -> bool:
    """Whether ``path`` starts with the ``.rrd`` header and ends with a footer."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(RRD_MAGIC))
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - 32))
            tail = f.read()
    except OSError:
        return False
    return head == RRD_MAGIC and RRD_FOOTER_MAGIC in tail


class _Pump(threading.Thread):
    """Copies the named pipe Rerun writes into the temporary file; records a write error."""

    def __init__(self, fifo: Path, fd: int, tmp: Path):
        super().__init__(name=f"agvviz-rrd-pump {tmp.name}", daemon=True)
        self.fifo, self.fd, self.tmp = fifo, fd, tmp
        self.error: OSError | None = None
        self.written = 0
        self.opened = threading.Event()

    def run(self) -> None:
        try:
            src = os.open(self.fifo, os.O_RDONLY)  # returns once Rerun opened the write end
        except OSError as exc:
            self._fail(exc)
            self.opened.set()
            return
        self.opened.set()
        _remove_fifo(self.fifo)  # both ends are open: the name is no longer needed
        try:
            fcntl = __import__("fcntl")
            fcntl.fcntl(src, _F_SETPIPE_SZ, _CHUNK)
        except (ImportError, OSError):
            pass
        try:
            if self._splice(src):
                return
            while True:
                try:
                    data = os.read(src, _CHUNK)
                except OSError as exc:
                    self._fail(exc)
                    break
                if not data:
                    break
                if self.error is None:
                    try:
                        view = memoryview(data)
                        while view:
                            view = view[os.write(self.fd, view):]
                        self.written += len(data)
                    except OSError as exc:
                        self._fail(exc)  # keep draining so Rerun never blocks
        finally:
            os.close(src)

    def _splice(self, src: int) -> bool:
        """Move the pipe into the file inside the kernel (Linux ``splice``: no copy through
        Python bytes, the GIL released meanwhile — a run's .rrd is tens of MB, issue 27). True
        when the stream ended; False when there is no splice, or after a write error (the
        caller then drains the rest with reads)."""
        splice = getattr(os, "splice", None)
        if splice is None:
            return False
        while True:
            try:
                moved = splice(src, self.fd, _CHUNK)
            except OSError as exc:
                if self.written == 0 and exc.errno in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
                    return False  # a file system without splice: copy with reads and writes
                self._fail(exc)  # keep draining so Rerun never blocks
                return False
            if moved == 0:
                return True
            self.written += moved

    def _fail(self, exc: OSError) -> None:
        if self.error is None:
            self.error = exc
            _close_quietly(self.fd)
            self.fd = -1
            _unlink_quietly(self.tmp)  # give the space back now


class AtomicRrd:
    """A recording stream writing ``out_path`` only once it is complete.

    Parameters
    ----------
    out_path : path
        The ``.rrd`` to write; its folder is created if needed.
    recording_id : str
        Pinned so identical inputs give comparable files.
    recording_name : str
        Shown in the viewer.
    inputs : paths
        Files the caller reads; ``out_path`` must not be one of them (also through links).
    durable : bool
        Make the file reach the disk (``fsync``) before it is moved into place, so a crash
        never leaves a truncated output under its name. False for a scratch file that the same
        program reads back and removes (a sweep's layers-only runs): ≈5–60 ms less per file.

    Raises
    ------
    OutputError
        The output would replace an input, its folder cannot be made or written, or (from
        :meth:`check` / :meth:`commit`) writing failed; the temporary file is removed then.
    """

    def __init__(
        self,
        out_path: str | os.PathLike,
        *,
        recording_id: str,
        recording_name: str,
        inputs: Iterable[str | os.PathLike] = (),
        tmp_path: str | os.PathLike | None = None,
        durable: bool = True,
    ):
        self.out_path = outputs.prepare_output(out_path, inputs=inputs)
        self.durable = durable
        # (another process's name for it: the process that will move it into place, see commit)
        self._tmp_path = Path(tmp_path) if tmp_path is not None else outputs.temp_path(self.out_path)
        self._pump: _Pump | None = None
        self._fd = -1
        self.closed = False
        outputs.register_temp(self._tmp_path)
        try:
            self._fd = os.open(self._tmp_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except OSError as exc:
            outputs.release_temp(self._tmp_path)
            raise outputs.output_error(exc, self.out_path) from exc
        try:
            self.rec = rr.RecordingStream(
                "agvviz",
                recording_id=recording_id,
                send_properties=False,
                batcher_config=rr.ChunkBatcherConfig(
                    flush_tick=BATCHER_FLUSH_TICK_S, flush_num_bytes=BATCHER_FLUSH_NUM_BYTES
                ),
            )
            self.rec.set_log_time_enabled(False)
            self.rec.set_log_tick_enabled(False)
            fifo = _make_fifo()
            if fifo is not None:
                self._pump = _Pump(fifo, self._fd, self._tmp_path)
                self._pump.start()
                try:
                    self.rec.save(fifo)
                except BaseException:
                    _unblock(fifo, self._pump)
                    raise
            else:  # no named pipes here: Rerun writes the file itself
                _close_quietly(self._fd)
                self._fd = -1
                self.rec.save(self._tmp_path)
            self.rec.send_recording_name(recording_name)
        except BaseException:
            self._cleanup()
            raise

    # -- state ---------------------------------------------------------------------------------
    def check(self) -> None:
        """Raise :class:`OutputError` (and discard) if writing the file has already failed."""
        if self._pump is not None and self._pump.error is not None and not self.closed:
            error = outputs.output_error(self._pump.error, self.out_path)
            self.discard()
            raise error

    def commit(self, blueprint: rrb.Blueprint | None = None, publish: bool = True) -> Path:
        """Send ``blueprint`` (the file's layout), finish the file and move it into place;
        returns ``out_path``. ``publish=False``: finish it but leave it at its temporary path
        (returned), for the process that named that path to move into place
        (:mod:`agvviz.viz.run_process`)."""
        if self.closed:
            raise RuntimeError(f"{self.out_path} was already committed or discarded")
        self.closed = True
        try:
            if blueprint is not None:
                rr.send_blueprint(blueprint, make_active=True, make_default=True, recording=self.rec)
            if self._pump is not None:
                self.rec.disconnect()  # writes the footer into the pipe; cannot block on the disk
                self._pump.join()
                if self._pump.error is not None:
                    raise outputs.output_error(self._pump.error, self.out_path)
                fd, self._pump.fd = self._pump.fd, -1
                try:
                    if self.durable:
                        os.fsync(fd)
                finally:
                    os.close(fd)
            else:
                self._flush_without_pipe()
                self.rec.disconnect()
            if not looks_complete(self._tmp_path):
                raise OutputError(
                    f"cannot write {self.out_path}: the file came out incomplete (no .rrd footer); "
                    "check the disk has space and try again"
                )
            if publish:
                try:
                    outputs.publish(self._tmp_path, self.out_path)
                except OSError as exc:
                    raise outputs.output_error(exc, self.out_path) from exc
        except BaseException:
            self._cleanup(disconnect=False)
            raise
        if not publish:  # publish forgot it; else it is the caller's to move into place now
            outputs.release_temp(self._tmp_path)
        return self.out_path if publish else self._tmp_path

    def discard(self) -> None:
        """Stop writing and delete the unfinished file; ``out_path`` is left untouched."""
        if self.closed:
            return
        self.closed = True
        self._cleanup()

    def __enter__(self) -> "AtomicRrd":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.discard()

    # -- helpers -------------------------------------------------------------------------------
    def _flush_without_pipe(self) -> None:
        """Flush while the file grows; a flush that makes no progress for a while failed."""
        size, stalled_s = -1, 0.0
        while True:
            try:
                self.rec.flush(timeout_sec=2.0)
                return
            except Exception as exc:  # noqa: BLE001 — Rerun raises RuntimeError on timeout/failure
                if "timed out" not in str(exc).lower():
                    raise OutputError(f"cannot write {self.out_path}: {exc}; check the disk") from exc
            now = self._tmp_path.stat().st_size if self._tmp_path.exists() else -1
            stalled_s = stalled_s + 2.0 if now == size else 0.0
            size = now
            if stalled_s >= _STALL_S:
                raise OutputError(f"cannot write {self.out_path}: writing stopped (disk full?)")

    def _cleanup(self, disconnect: bool = True) -> None:
        """Stop the stream (when it is safe) and the pump; delete the temporary file."""
        rec = getattr(self, "rec", None)
        # With the pipe a disconnect cannot block on the disk; without it, only before a failure.
        if rec is not None and (self._pump is not None or disconnect):
            try:
                rec.disconnect()  # the pipe is always drained, so this cannot block on the disk
            except Exception:  # noqa: BLE001
                pass
        if self._pump is not None:
            self._pump.join(timeout=30.0)
            _close_quietly(self._pump.fd)
            self._pump.fd = -1
        else:
            _close_quietly(self._fd)
        self._fd = -1
        _unlink_quietly(self._tmp_path)
        outputs.release_temp(self._tmp_path)


def _make_fifo() -> Path | None:
    """A fresh named pipe in a private temporary folder (None where there are none)."""
    if not hasattr(os, "mkfifo"):
        return None
    try:
        folder = Path(tempfile.mkdtemp(prefix="agvviz-pipe-"))
    except OSError:
        return None
    fifo = folder / "stream.rrd"
    try:
        os.mkfifo(fifo, 0o600)
    except OSError:
        shutil.rmtree(folder, ignore_errors=True)
        return None
    return fifo


def _remove_fifo(fifo: Path) -> None:
    _unlink_quietly(fifo)
    try:
        fifo.parent.rmdir()
    except OSError:
        pass


def _unblock(fifo: Path, pump: _Pump) -> None:
    """Rerun never opened the pipe: hold a write end until the pump's open returned, so the
    pump reads end-of-file and stops (O_RDWR on a pipe never blocks on Linux)."""
    try:
        fd = os.open(fifo, os.O_RDWR | os.O_NONBLOCK)
    except OSError:
        _remove_fifo(fifo)
        return
    try:
        pump.opened.wait(timeout=5.0)
    finally:
        os.close(fd)
    _remove_fifo(fifo)


def _close_quietly(fd: int) -> None:
    if fd is not None and fd >= 0:
        try:
            os.close(fd)
        except OSError:
            pass


def _unlink_quietly(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass
