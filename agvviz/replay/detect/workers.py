"""How detection worker processes start: forked from a fork server that has imported what they
need, started early so that its imports overlap the run's own start-up.

A detection worker (:mod:`agvviz.replay.detect.pool`) runs
:func:`agvviz.replay.detect.stage.detect_segment`; importing what that needs (OpenCV, NumPy,
zxing-cpp, and through the settings SciPy) takes ≈0.5 s of CPU, and a worker started afresh
does it before its first frame, while the run waits for that frame. Here the fork server does
it once (:data:`WORKER_MODULES`, its *preload*) and every worker is a fork of it, ready in
milliseconds. :func:`start_fork_server` starts the server in the background; ``agvviz run``
calls it before it imports Rerun and reads the recording, so the server's imports run on the
other core meanwhile. Where there is no fork server (macOS, Windows), workers are spawned and
import on their own.

This module imports nothing heavy itself: the command line calls it first thing.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Iterator
from types import MappingProxyType

#: The modules a detection worker needs (the functions and values it unpickles, and what they
#: import), imported once by the fork server.
WORKER_MODULES = ("agvviz.replay.detect.stage", "agvviz.markers.qr", "agvviz.markers.tracking")


def has_fork_server() -> bool:
    return "forkserver" in multiprocessing.get_all_start_methods()


#: The modules of the ``.rrd`` writer (:mod:`agvviz.viz.run_process`), which a run forks from
#: the same server; imported by it first. Named here, not registered by the writer's module, so
#: that the server can start before anything heavy is imported (:mod:`agvviz.cli.early`).
WRITER_MODULES = ("agvviz.viz.run_sinks",)

#: Imported after the preload: freezes the fork server's objects (:mod:`agvviz.replay.detect.gc_freeze`).
GC_FREEZE_MODULE = "agvviz.replay.detect.gc_freeze"

#: mimalloc — the allocator of Rerun's extension (and of pyarrow) — gives the memory a thread
#: freed back to the system at once, not after a delay (:func:`writer_allocator_settings`).
MIMALLOC_SETTINGS = MappingProxyType({"MIMALLOC_PURGE_DELAY": "0"})


def writer_allocator_settings() -> None:
    """Set :data:`MIMALLOC_SETTINGS` in this process's environment (a value the user set is
    kept), for the processes started after it: ``agvviz run`` calls it before it starts the
    fork server its ``.rrd`` writer is forked from. With mimalloc's default delay, what the
    writer freed while it logged (a frame's buffers, the encoded chunks) stayed with the
    process and grew with the run's length: at 2000 frames Rerun's arena held 29.5 MiB, 13.4 MiB
    with the delay at 0 (issue 27, docs/performance.md). mimalloc reads it once, when it starts.
    The writer then returns and takes pages more often: a 200-frame warm run waits ≈0.05 s more
    on it. ``agvviz sweep``, whose runs log in their own processes and whose memory did not
    grow this way, does not set it: there it cost ≈0.2 s of a 6.3 s sweep."""
    for name, value in MIMALLOC_SETTINGS.items():
        os.environ.setdefault(name, value)


def start_fork_server(
    preload: tuple[str, ...] = (*WRITER_MODULES, *WORKER_MODULES), ignored: tuple[int, ...] = (signal.SIGINT,),
) -> None:
    """Start this process's fork server now, without waiting for it: it imports ``preload``
    while this process goes on, and keeps ignoring ``ignored``. By default a run's: the
    :data:`WRITER_MODULES` first (what every run needs), then the :data:`WORKER_MODULES` (the
    writer's import them anyway: ≈0.65 s of CPU with or without them), Ctrl-C ignored (the
    server ignores SIGINT only after its imports, and a Ctrl-C during them — it goes to the
    whole process group — printed a KeyboardInterrupt traceback). A local sweep's pool asks
    for its own (:func:`agvviz.app.cluster.start_fork_server`). A no-op where there is no fork
    server, or when this process runs one already (then it is used as it is, and its children
    import what it lacks on their own)."""
    if not has_fork_server():
        return
    import multiprocessing.forkserver as forkserver

    # gc_freeze last: what the server imported stays shared with its processes (its docstring)
    forkserver.set_forkserver_preload([*preload, GC_FREEZE_MODULE])  # no effect once it runs
    with signals_ignored(*ignored):
        forkserver.ensure_running()


@contextlib.contextmanager
def signals_ignored(*signums: int) -> Iterator[None]:
    """Ignore ``signums`` meanwhile: a process started now keeps ignoring them (an ignored signal
    stays ignored across exec and fork, and Python then installs no handler of its own). Only
    in the main thread (elsewhere a no-op); a signal that comes meanwhile is lost, so keep it to
    starting a process."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in signums}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def pool_context():
    """forkserver where there is one (no fork of a process that already runs Rerun's threads),
    with :data:`WORKER_MODULES` preloaded; else spawn."""
    if has_fork_server():
        start_fork_server()
        return multiprocessing.get_context("forkserver")
    return multiprocessing.get_context("spawn")


def init_worker() -> None:
    """Worker set-up: Ctrl-C is the parent's to handle (it cancels the pool); die with the
    parent; one OpenCV thread (the workers already fill the CPUs)."""
    _exit_with_starter()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # A fork server started by a process that ignores SIGTERM (a sweep's Dask worker) passes
    # that on; the parent-death signal below must be able to end this worker.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            # PR_SET_PDEATHSIG: SIGTERM when the parent dies (the fork server, or the run for a
            # spawned worker); the run itself is watched by _exit_with_starter.
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError):
            pass
    import cv2

    cv2.setNumThreads(1)


def _exit_with_starter() -> None:
    """End this worker as soon as the process that started it (the run or the sweep, not the
    fork server) has ended, in whatever way — SIGKILL included.

    The parent-death signal alone does not do it: a worker forked from the fork server is the
    server's child, and holds (as every child of it does) the pipe end whose closing would end
    the server; so after a SIGKILL of the run, the server and its idle workers waited for each
    other for ever. A daemon thread waits on the starter's sentinel instead (which
    :func:`multiprocessing.parent_process` gives a forked or spawned worker) and exits the
    process; an unfinished output it leaves is a temporary that the next run, or a sweep's
    reaper, removes."""
    starter = multiprocessing.parent_process()
    if starter is None:
        return

    def wait_then_exit() -> None:
        starter.join()
        os._exit(1)

    threading.Thread(target=wait_then_exit, name="agvviz exit with starter", daemon=True).start()
