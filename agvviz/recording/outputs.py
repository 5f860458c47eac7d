"""Output-path safety for every file agvviz writes.

One set of rules, used by the run writer, the overlays, ``export``, ``sweep`` and ``record``:

* **Never over an input.** :func:`check_not_input` refuses an output that is one of the
  command's inputs — by resolved path, and when the output exists also by device and inode
  (:func:`os.path.samefile`), so symbolic and hard links are caught too.
* **Folders are made, faults are one clear error.** :func:`prepare_output` creates the output
  folder and turns every ``OSError`` (a path under a regular file, no permission, a read-only or
  full file system, ``/proc``) into :class:`~agvviz.errors.OutputError` with a message that says
  what to do (:func:`output_error`).
* **Temporary files have one name pattern** (:func:`temp_path`):
  ``.<target name>.agvviz-<pid>-<token>.tmp`` beside the target. Writers register them
  (:func:`register_temp`) so an interrupted process removes them (:func:`remove_live_temps`);
  a file of that pattern whose process is gone (killed with SIGKILL, power loss) is removed by
  the next agvviz command writing into that folder (:func:`remove_stale_temps`).
* **A finished file is put in place by one call** (:func:`publish`): the rename and the
  forgetting of its temporary name. The console script's signal handler
  (:mod:`agvviz.cli.interrupts`) holds a Ctrl-C or SIGTERM that lands meanwhile until the file
  is in place (:func:`hold_while_publishing`); a command whose output is then complete
  (:func:`when_published`) ignores it rather than exiting 130 beside a complete output.

This module imports nothing from agvviz but :mod:`agvviz.errors`.
"""

from __future__ import annotations

import errno
import os
import re
import threading
import uuid
from pathlib import Path
from contextlib import contextmanager
from typing import BinaryIO, Callable, Iterable, Iterator

from agvviz.errors import OutputError

#: ``.<target name>.agvviz-<pid>-<token>.tmp`` — the only temporary files agvviz removes.
TEMP_RE = re.compile(r"^\.(?P<name>.+)\.agvviz-(?P<pid>[0-9]+)-(?P<token>[0-9a-f]{12})\.tmp$")

_live_lock = threading.Lock()
_live_temps: set[Path] = set()

#: While the main thread is in :func:`publish`: the signal handler's actions it holds.
_publishing = False
_held: list[Callable[[], None]] = []
#: Outputs whose being in place completes the command, with what to call then (:func:`when_published`).
_on_published: dict[Path, Callable[[], None]] = {}


# -- temporary files ---------------------------------------------------------------------------
def temp_path(target: str | os.PathLike) -> Path:
    """A fresh temporary name beside ``target`` carrying this process id (not created)."""
    target = Path(target)
    return target.with_name(f".{target.name}.agvviz-{os.getpid()}-{uuid.uuid4().hex[:12]}.tmp")


def register_temp(path: str | os.PathLike) -> None:
    """Remember ``path`` as an unfinished file of this process (removed when interrupted)."""
    with _live_lock:
        _live_temps.add(Path(path))


def release_temp(path: str | os.PathLike) -> None:
    """``path`` was renamed into place or deleted: forget it."""
    with _live_lock:
        _live_temps.discard(Path(path))


def remove_live_temps() -> list[Path]:
    """Delete every registered unfinished file of this process; returns those deleted."""
    with _live_lock:
        paths = list(_live_temps)
        _live_temps.clear()
    removed = []
    for path in paths:
        try:
            path.unlink()
            removed.append(path)
        except OSError:
            pass
    return removed


# -- putting a finished file in place ----------------------------------------------------------
def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Rename the finished temporary ``tmp`` into place as ``path`` and forget ``tmp``. In the
    main thread, a signal that lands meanwhile acts once ``path`` is in place (raises ``OSError``
    as ``os.replace`` does; ``tmp`` stays registered then, for the caller to remove)."""
    global _publishing
    main = threading.current_thread() is threading.main_thread()
    if main:
        _publishing = True
    try:
        os.replace(tmp, path)
        release_temp(tmp)
        completed = _on_published.pop(Path(os.path.abspath(path)), None) if main else None
        if completed is not None:
            completed()
            _held.clear()  # the command's output is in place: the signal is ignored
    finally:
        if main:
            _publishing = False
            held = list(_held)
            _held.clear()
            for action in held:  # the signal acts now (on a failed rename too)
                action()


def hold_while_publishing(action: Callable[[], None]) -> bool:
    """For a signal handler: when the main thread is in :func:`publish`, keep ``action`` (the
    handler's own, e.g. raising ``KeyboardInterrupt``) for when the file is in place and return
    True; else return False (the handler acts now)."""
    if not _publishing:
        return False
    _held.append(action)
    return True


def when_published(path: str | os.PathLike, action: Callable[[], None]) -> None:
    """Call ``action`` as soon as :func:`publish` has put ``path`` in place, with no signal
    handled in between (a command whose outputs are then complete: ``run``)."""
    _on_published[Path(os.path.abspath(path))] = action


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (on this machine's process table)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True
    return True


def remove_stale_temps(folder: str | os.PathLike) -> list[Path]:
    """Delete agvviz temporaries in ``folder`` whose process is gone; returns those deleted.

    Only names matching :data:`TEMP_RE` are considered, never this process's own, never one
    whose process still exists. Errors (no permission, folder gone) are ignored.
    """
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    me = os.getpid()
    for entry in entries:
        match = TEMP_RE.match(entry.name)
        if not match:
            continue
        pid = int(match["pid"])
        if pid == me or pid_alive(pid):
            continue
        try:
            if entry.is_file(follow_symlinks=False):
                os.unlink(entry.path)
                removed.append(Path(entry.path))
        except OSError:
            pass
    return removed


# -- errors ------------------------------------------------------------------------------------
_ADVICE = {
    errno.ENOSPC: "the disk is full; free some space or write somewhere else",
    errno.EDQUOT: "the disk quota is used up; free some space or write somewhere else",
    errno.EROFS: "the file system is read-only; write somewhere else",
    errno.EACCES: "no permission to write there; choose a folder you can write to",
    errno.EPERM: "no permission to write there; choose a folder you can write to",
    errno.ENOTDIR: "a part of the path is a file, not a folder; choose another path",
    errno.EISDIR: "that is a folder; give a file name",
    errno.ENOENT: "a folder on the way does not exist and cannot be created; choose another path",
    errno.EFBIG: "the file is too large for that file system; write somewhere else",
    errno.ENAMETOOLONG: "the name is too long; choose a shorter path",
    errno.EXDEV: "the temporary file and the target are on different file systems",
}


def output_error(exc: OSError, path: str | os.PathLike, action: str = "write") -> OutputError:
    """``exc`` (an ``OSError`` from writing ``path``) as one :class:`OutputError` line."""
    if isinstance(exc, OutputError):
        return exc
    reason = exc.strerror or str(exc) or type(exc).__name__
    advice = _ADVICE.get(exc.errno or -1)
    message = f"cannot {action} {path}: {reason}" + (f" — {advice}" if advice else "")
    error = OutputError(message)
    error.__cause__ = exc
    return error


# -- never over an input -----------------------------------------------------------------------
def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether ``a`` and ``b`` name the same file: same resolved path, or (both existing) the
    same device and inode — symbolic links and hard links included."""
    a, b = Path(a), Path(b)
    try:
        if a.resolve() == b.resolve():
            return True
    except (OSError, RuntimeError):
        pass
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return False


def check_not_input(
    out: str | os.PathLike, inputs: Iterable[str | os.PathLike], *, option: str = "--out"
) -> None:
    """Raise :class:`OutputError` when ``out`` is (a link to) one of ``inputs``."""
    for source in inputs:
        if source is not None and same_file(out, source):
            raise OutputError(
                f"{option} {out} is the input {source}; refusing to write over an input — "
                "choose another output name"
            )


# -- folders -----------------------------------------------------------------------------------
def prepare_dir(folder: str | os.PathLike, *, option: str = "output folder") -> Path:
    """Create ``folder`` (and its parents) if needed and check it can be written into."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"cannot write into {folder}: {option} is a file, not a folder; choose a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError as exc:  # a path component is a file
        raise output_error(OSError(errno.ENOTDIR, "Not a directory"), folder, "create folder") from exc
    except OSError as exc:
        raise output_error(exc, folder, "create folder") from exc
    if not folder.is_dir():
        raise OutputError(f"cannot write into {folder}: it is not a folder; choose a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        code = errno.EROFS if _read_only(folder) else errno.EACCES
        raise output_error(OSError(code, os.strerror(code)), folder, "write into")
    remove_stale_temps(folder)
    return folder


def _read_only(folder: Path) -> bool:
    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


def prepare_output(
    path: str | os.PathLike,
    *,
    inputs: Iterable[str | os.PathLike] = (),
    option: str = "--out",
) -> Path:
    """Check ``path`` is a writable output that is not an input; create its folder.

    Raises :class:`OutputError` when it would replace an input, is an existing folder, lies
    under a regular file or in a folder that cannot be created or written.
    """
    path = Path(path)
    check_not_input(path, inputs, option=option)
    if path.is_dir():
        raise OutputError(f"cannot write {path}: it is an existing folder; give a file name or remove the folder")
    prepare_dir(path.parent if str(path.parent) else Path("."), option=f"the folder of {option}")
    return path


# -- small text files --------------------------------------------------------------------------
def atomic_write_text(path: str | os.PathLike, text: str, *, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically: :func:`atomic_write_bytes`."""
    return atomic_write_bytes(path, text.encode("utf-8"), inputs=inputs)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Write ``data`` to ``path`` through a temporary file renamed into place
    (:func:`atomic_writer`)."""
    with atomic_writer(path, inputs=inputs) as file:
        file.write(data)
    return Path(path)


@contextmanager
def atomic_writer(path: str | os.PathLike, *, inputs: Iterable[str | os.PathLike] = ()) -> Iterator[BinaryIO]:
    """A binary file to write ``path`` through: a temporary file beside it, synced and renamed
    into place when the block ends without an error, removed otherwise (``path`` is then left
    as it was). For what is written in pieces (a detection cache entry, a row group at a time).

    Every ``OSError`` becomes :class:`OutputError`.
    """
    path = Path(path)
    check_not_input(path, inputs)
    tmp = temp_path(path)
    register_temp(tmp)
    try:
        with open(tmp, "xb") as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        publish(tmp, path)
    except OSError as exc:
        _unlink_quietly(tmp)
        raise output_error(exc, path) from exc
    except BaseException:
        _unlink_quietly(tmp)
        raise
    finally:
        release_temp(tmp)


def _unlink_quietly(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass
