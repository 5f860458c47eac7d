"""How ``agvviz sweep`` runs its runs: the loop, and the local engine (a pool of processes).

:func:`run_sweep_tasks` runs a sweep's runs (recording, settings, output ``.rrd``) on an engine,
:func:`local_engine` or a Dask cluster's (:mod:`agvviz.app.dask_engine`). It groups them by
recording and detection settings (:func:`agvviz.replay.detect.stage.detection_settings`); each
group's first setting, its *lead*, runs first: it detects the recording on every core and solves meanwhile, in one pass, as
``agvviz run`` does, and fills the detection cache. When a lead is done, its group's other
settings only solve, from the cache. A lead that failed hands the lead to the next setting of
its group. A run's failure — an error of agvviz, a process that died — comes back as that run's
one-line message; the other runs go on.

**Local** (:class:`LocalEngine`, the default): one pool of ``--jobs`` processes, forked from the
fork server, which imports a run's modules while the sweep starts. The leads run in the sweep
process (:class:`LocalRuns`) and detect on the pool; the other settings then solve on the same
processes — no process starts after the work is known, and none imports anything then — and the
last setting of each group in the sweep process, which would otherwise wait. (Issue 27: a local
Dask cluster cost about 1 s of CPU — importing Dask in the sweep process and the fork server,
starting its scheduler and workers — while the lead detected, and its workers were processes of
their own beside the detection pool's.) Progress comes through an array shared with the pool,
the stop through a shared event.

**Dask** (``--scheduler ADDRESS``, :mod:`agvviz.app.dask_engine`): every run is a task on that
cluster's workers, under the same loop.

Interruption (Ctrl-C, SIGTERM): the sweep sets the stop event, which every running run checks
between frames (it then stops, and its unfinished ``.rrd`` is removed), and drops the runs not
started. The pool's processes and the fork server ignore SIGINT (see :func:`_start_method`), so
a Ctrl-C at the terminal, which reaches the whole process group, is handled by the sweep
process alone. They end when the sweep process ends, even by SIGKILL (each waits on its
starter's sentinel, :func:`agvviz.replay.detect.workers.init_worker`); a small reaper process
then removes the temporary files they leave.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

from agvviz.recording import outputs
from agvviz.replay.detect.workers import init_worker, signals_ignored

if TYPE_CHECKING:
    from agvviz.settings import RunSettings

#: A running task looks at the sweep's stop event at most this often (seconds).
STOP_CHECK_EVERY_S = 0.5
#: How long the local pool's processes get to stop before they are killed (seconds): at the
#: end of a sweep, and when it was interrupted (a run stops at its next frame, and a process
#: killed instead leaves temporary files that the sweep removes).
CLOSE_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class RunTask:
    """One run of a sweep: replay ``recording`` under ``settings`` into ``out_path``
    (``images=False``: the layers only, what a sweep ``.rrd`` takes of a setting; ``scratch``:
    a file the sweep reads back and removes, not synced to the disk)."""

    recording: Path
    settings: "RunSettings"
    out_path: Path
    images: bool = True
    scratch: bool = False


@dataclass(frozen=True)
class TaskResult:
    """How a task went: the run's wall-clock ``timing``, or ``error`` (one line) when it failed."""

    timing: dict = field(default_factory=dict)
    error: str | None = None


class SweepStopped(Exception):
    """Raised inside a task when the sweep was interrupted (its stop event is set)."""


def one_line(exc: BaseException) -> str:
    """``Type: message`` on one line; a worker that died is said so plainly."""
    name = type(exc).__name__
    if name == "KilledWorker":
        return "KilledWorker: the worker process running it died (crashed, ran out of memory or was killed)"
    if name == "BrokenProcessPool":
        return "BrokenProcessPool: a process of the sweep's pool died (crashed, ran out of memory or was killed)"
    if name == "CancelledError":
        return "cancelled: the task was cancelled on the cluster"
    return " ".join(f"{name}: {exc}".split())


def detection_key(task: RunTask) -> tuple[str, str]:
    """(recording, detection settings): runs with equal keys share one detection."""
    from agvviz.replay.detect.stage import detection_settings

    return str(task.recording), json.dumps(detection_settings(task.settings), sort_keys=True, default=str)


def detection_groups(tasks: list[RunTask]) -> dict[tuple[str, str], list[int]]:
    """Indices of ``tasks`` by :func:`detection_key`, in first-seen order."""
    groups: dict[tuple[str, str], list[int]] = {}
    for index, task in enumerate(tasks):
        groups.setdefault(detection_key(task), []).append(index)
    return groups


# -- the local sweep ------------------------------------------------------------------------------
class LocalRuns:
    """The runs a local sweep makes in its own process, one after the other, in a thread: each
    detection group's lead at once, and then one more setting of each group beside the pool.

    A lead (the first setting of a :func:`detection_groups` group) detects the recording on the
    sweep's process pool (``executor``, ``jobs`` processes) and solves meanwhile, in one pass, as
    ``agvviz run`` does (which fills the detection cache). Once the leads are done this process
    has imported everything a run needs and would only wait: :func:`run_sweep_tasks` hands it
    one more setting of each group (:meth:`add`) while the pool solves the others.
    ``results[i]`` is task i's :class:`TaskResult` once it is done, ``frames[i]`` counts its
    frames done. :meth:`close` stops the thread at its next frame.
    """

    def __init__(self, tasks: list[RunTask], cache_dir: Path | None, jobs: int, executor=None):
        self.tasks = tasks
        self.cache_dir, self.jobs, self.executor = cache_dir, max(1, jobs), executor
        self.results: dict[int, TaskResult] = {}
        self.frames: dict[int, int] = {}
        self.detected: deque[int] = deque()  # leads whose detections are in the cache (they may still solve)
        self._queue: list[tuple[int, bool]] = []  # (task, whether it leads: detects on the pool)
        self._wake = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run_all, name="agvviz sweep local runs", daemon=True)

    def start(self) -> "LocalRuns":
        # Imported here, in the calling thread: two threads importing one module at once can
        # deadlock on its import lock (the sweep counts frames in another thread meanwhile);
        # so is what a run imports on its way (the detection cache's Parquet).
        import pyarrow.parquet  # noqa: F401

        import agvviz.app.run  # noqa: F401

        self._thread.start()
        return self

    def add(self, index: int, lead: bool = False) -> None:
        """Run task ``index`` here too, after those already given: a lead detects on the pool,
        the others read their detections from the cache (one process)."""
        with self._wake:
            self._queue.append((index, lead))
            self._wake.notify()

    def _run_all(self) -> None:
        while True:
            with self._wake:
                while not self._queue and not self._stop.is_set():
                    self._wake.wait()
                if self._stop.is_set():
                    return
                index, lead = self._queue.pop(0)

            def progress(frames_done: int, index: int = index) -> None:
                self.frames[index] = frames_done
                if self._stop.is_set():
                    raise SweepStopped("the sweep was interrupted")

            if lead:
                result = _run(self.tasks[index], self.jobs, progress, self.cache_dir, executor=self.executor,
                              on_detected=lambda index=index: self.detected.append(index))
            else:
                result = _run(self.tasks[index], 1, progress, self.cache_dir)
            if self._stop.is_set():  # interrupted: nobody waits for the result
                return
            self.results[index] = result

    def close(self) -> None:
        """Stop (at the next frame) and wait for the thread."""
        with self._wake:
            self._stop.set()
            self._wake.notify()
        if self._thread.is_alive():
            self._thread.join()


def _run(
    task: RunTask, jobs: int, progress: Callable[[int], None], cache_dir: Path | None, executor=None,
    on_detected: Callable[[], None] | None = None,
) -> TaskResult:
    """Replay one setting (:func:`agvviz.app.run.run_recording`) with ``jobs`` detection
    processes (``executor``: the sweep's pool; its group's detections come from the cache when
    they are there; ``on_detected()`` once it stored them); a failure, an interruption
    (:class:`SweepStopped` from ``progress``) included, is the result's error."""
    from agvviz.app.run import run_recording

    extra = {"cache_dir": cache_dir} if cache_dir is not None else {}
    try:
        # The .rrd in this process: a sweep keeps every core busy already.
        outcome = run_recording(task.recording, task.settings, task.out_path, progress=progress, jobs=jobs,
                                images=task.images, writer_process=False, executor=executor,
                                on_detected=on_detected, durable=not task.scratch, **extra)
    except Exception as exc:  # noqa: BLE001 — any failure of one setting is reported, not raised
        return TaskResult(error=one_line(exc))
    return TaskResult(timing=dict(outcome.timing))


# -- the local pool's worker side -----------------------------------------------------------------
#: In a process of a local sweep's pool: the frames done of every task (shared with the sweep
#: process) and the sweep's stop event (:func:`_init_pool_worker`).
_POOL_SHARED: dict[str, object] = {}


def _init_pool_worker(frames_done, stop) -> None:
    """A local sweep's pool process: a detection worker's set-up (Ctrl-C is the sweep process's
    to handle, die with it, one OpenCV thread) and the sweep's shared progress and stop event."""
    init_worker()
    _POOL_SHARED.update(frames_done=frames_done, stop=stop)


def _pool_task(index: int, task: RunTask, cache_dir: Path | None) -> TaskResult:
    """In a local sweep's pool process: replay task ``index`` (its detections from the cache),
    counting its frames done in the shared array and stopping at the next frame once the
    sweep's stop event is set."""
    frames_done, stop = _POOL_SHARED["frames_done"], _POOL_SHARED["stop"]
    last_check = time.monotonic()

    def progress(done: int) -> None:
        nonlocal last_check
        frames_done[index] = done
        now = time.monotonic()
        if now - last_check >= STOP_CHECK_EVERY_S:
            last_check = now
            if stop.is_set():
                raise SweepStopped("the sweep was interrupted")

    if stop.is_set():
        return TaskResult(error="SweepStopped: the sweep was interrupted")
    return _run(task, 1, progress, cache_dir)


# -- the engines ----------------------------------------------------------------------------------
def ended_futures(pending: dict) -> list[tuple[int, TaskResult]]:
    """The futures of ``pending`` (future → task index) that are done, taken out of it, with
    their results; a future that raised (a process or worker that died, a cancelled task) gives
    a failed result."""
    done = []
    for future in [f for f in pending if f.done()]:
        index = pending.pop(future)
        try:
            result = future.result()
        except Exception as exc:  # noqa: BLE001 — reported as that run's failure
            result = TaskResult(error=one_line(exc))
        done.append((index, result))
    return done


class LocalEngine:
    """A local sweep: a pool of ``jobs`` processes, forked from the fork server (which has
    imported a run's modules: :func:`_start_method`) before any run starts, and this process.

    Each detection group's lead runs here (:class:`LocalRuns`) and detects on the pool; its
    group's other settings then solve on the same processes, which have imported everything
    and hold nothing else — no process starts after the work is known — and the last of them
    here. Progress and the stop come through a shared array and event.
    """

    def __init__(self, tasks: list[RunTask], cache_dir: Path | None, jobs: int):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        context = multiprocessing.get_context(_start_method())
        self.tasks, self.cache_dir = tasks, cache_dir
        self._frames_done = context.RawArray("q", max(1, len(tasks)))
        self._stop = context.Event()
        self.pool = ProcessPoolExecutor(
            max(1, jobs), mp_context=context, initializer=_init_pool_worker, initargs=(self._frames_done, self._stop),
        )
        self.here = LocalRuns(tasks, cache_dir, jobs, executor=self.pool)
        self._pending: dict[object, int] = {}  # a pool future → its task
        self._here: set[int] = set()  # tasks given to this process, not yet ended
        self._given: set[int] = set()  # tasks given to the pool or to this process
        self._detecting: set[int] = set()  # leads given that have neither detected nor ended
        self._pool_processes: list | None = None  # the pool's processes once it was let go (joined at close)

    def start(self) -> "LocalEngine":
        self.here.start()
        return self

    def start_lead(self, index: int) -> None:
        self.here.add(index, lead=True)
        self._here.add(index)
        self._given.add(index)
        self._detecting.add(index)

    def start_followers(self, indices: list[int]) -> None:
        """The pool solves these, this process the last of them (it would otherwise wait)."""
        if indices:
            self.here.add(indices[-1])
            self._here.add(indices[-1])
            for index in indices[:-1]:
                future = self.pool.submit(_pool_task, index, self.tasks[index], self.cache_dir)
                self._pending[future] = index
            self._given.update(indices)
        self._let_pool_go()

    def _let_pool_go(self) -> None:
        """End the pool's processes once nothing is left for them: every task given out, every
        lead done detecting, no setting solving on the pool. What is left runs in this process
        (the last settings, the read-back, the sweep file): the pool's idle processes (≈75 MiB
        each) would otherwise be alive at the sweep's peak of memory (issue 27)."""
        if self._pool_processes is not None or len(self._given) < len(self.tasks) or self._detecting or self._pending:
            return
        self._pool_processes = list((getattr(self.pool, "_processes", None) or {}).values())
        self.here.executor = None
        self.pool.shutdown(wait=False)

    def busy(self) -> bool:
        return bool(self._pending or self._here)

    def detected(self) -> list[int]:
        """Leads whose detections went into the cache since the last call: their groups' other
        settings can start, on the pool that has just finished detecting, while they finish."""
        done = []
        while self.here.detected:  # (appended to by the thread of this process's runs)
            done.append(self.here.detected.popleft())
        self._detecting.difference_update(done)
        return done

    def frames_done(self, index: int) -> int:
        return max(self.here.frames.get(index, 0), int(self._frames_done[index]))

    def ended(self) -> list[tuple[int, TaskResult]]:
        done = ended_futures(self._pending)
        for index in sorted(self._here):
            if index in self.here.results:
                self._here.discard(index)
                done.append((index, self.here.results[index]))
        self._detecting.difference_update(index for index, _ in done)
        self._let_pool_go()
        return done

    def stop(self) -> None:
        """Interrupted: every run stops at its next frame; tasks not started are dropped."""
        self._stop.set()
        for future in self._pending:
            future.cancel()
        self.here.close()

    def close(self, timeout_s: float) -> None:
        """Stop the thread and the pool; processes still busy after ``timeout_s`` are killed."""
        self.here.close()
        processes = self._pool_processes
        if processes is None:
            processes = list((getattr(self.pool, "_processes", None) or {}).values())
        self.pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + timeout_s
        for process in processes:
            process.join(timeout=max(0.0, deadline - time.monotonic()))
        for process in processes:
            if process.is_alive():
                process.kill()
                process.join(timeout=1.0)


# -- the local pool's processes -------------------------------------------------------------------
def _start_method() -> str:
    """How a local sweep's pool starts: forked from the fork server, which this starts with
    SIGINT and SIGTERM ignored and :mod:`agvviz.app.run` and the ``.rrd`` logger's modules
    imported (a setting's layers are written by the process that solves it: Rerun's import cost
    each pool process ≈0.3 s of CPU at its first setting), where there is one; else spawned.

    A Ctrl-C at the terminal, or a SIGTERM to the process group, reaches every process of the
    sweep: the fork server must outlive it (the pool's processes are its children), and the
    pool's processes ignore SIGINT (:func:`agvviz.replay.detect.workers.init_worker`) — the
    sweep process alone handles it, stopping the runs. A fork server already running in this
    process (a library user's) is used as it is."""
    from agvviz.replay.detect import workers

    if not workers.has_fork_server():
        return "spawn"
    # pyarrow.parquet: every setting reads its detections from the cache (≈0.02 s a process
    # otherwise, at its first setting).
    workers.start_fork_server(
        ("agvviz.app.run", *workers.WRITER_MODULES, "pyarrow.parquet"), ignored=(signal.SIGINT, signal.SIGTERM),
    )
    return "forkserver"


def start_fork_server() -> None:
    """Start the local pool's fork server now (:func:`_start_method`), so that its imports run
    beside the caller's own."""
    _start_method()


def _start_reaper(folders: list[Path]) -> tuple[subprocess.Popen, int] | None:
    """A process that, once this one has ended (in any way), removes the temporary files that
    dead processes left in ``folders`` (see :func:`reap`). Returns it and the pipe end to close."""
    read_fd, write_fd = os.pipe()
    try:
        process = subprocess.Popen(
            [sys.executable, "-c", "from agvviz.app.cluster import reap; reap()", *map(str, folders)],
            stdin=read_fd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True,
        )
    except OSError:
        os.close(write_fd)
        return None
    finally:
        os.close(read_fd)
    return process, write_fd


def reap(grace_s: float = 5.0) -> None:
    """Reaper process: wait for the sweep process to end (end of standard input), then remove
    agvviz temporaries of dead processes in the folders named on the command line, retrying for
    ``grace_s`` while the workers finish dying."""
    sweep_pid = os.getppid()
    sys.stdin.buffer.read()
    folders = sys.argv[1:]
    # The sweep process has ended, though it may linger as a zombie until whoever started it
    # waits for it, and so still look alive: its own temporaries (its local runs') go at once.
    for folder in folders:
        for name in os.listdir(folder) if os.path.isdir(folder) else []:
            match = outputs.TEMP_RE.match(name)
            if match and int(match["pid"]) == sweep_pid:
                try:
                    os.unlink(os.path.join(folder, name))
                except OSError:
                    pass
    deadline = time.monotonic() + grace_s
    while True:
        for folder in folders:
            outputs.remove_stale_temps(folder)
        left = [n for f in folders if os.path.isdir(f) for n in os.listdir(f) if outputs.TEMP_RE.match(n)]
        if not left or time.monotonic() > deadline:
            return
        time.sleep(0.1)


@contextmanager
def local_engine(
    tasks: list[RunTask], *, jobs: int, cache_dir: Path | None, temp_folders: list[Path],
    before_start: Callable[[], None] | None = None,
) -> Iterator[LocalEngine]:
    """A :class:`LocalEngine` of ``jobs`` processes for ``tasks``, closed on leaving, with the
    reaper for ``temp_folders``. ``before_start`` is called once the reaper runs, before any run
    starts (the sweep prepares its folders then)."""
    with signals_ignored(signal.SIGINT, signal.SIGTERM):  # the reaper outlives any signal to the group
        reaper = _start_reaper(temp_folders)
    engine = None
    interrupted = False
    try:
        if before_start is not None:
            before_start()
        engine = LocalEngine(tasks, cache_dir, jobs).start()
        yield engine
    except BaseException:
        interrupted = True
        raise
    finally:
        try:
            if engine is not None:
                engine.close(timeout_s=STOP_TIMEOUT_S if interrupted else CLOSE_TIMEOUT_S)
        finally:
            for folder in temp_folders:  # left by a process that was killed
                outputs.remove_stale_temps(folder)
            if reaper is not None:
                process, write_fd = reaper
                os.close(write_fd)
                process.wait()


def run_sweep_tasks(
    engine,
    tasks: list[RunTask],
    *,
    frames: Callable[[], dict[Path, int]] | None = None,
    progress: Callable[[int, int], None] | None = None,
    on_result: Callable[[int, TaskResult], None] | None = None,
) -> list[TaskResult]:
    """Run ``tasks`` on ``engine`` (a :class:`LocalEngine`, or a Dask cluster's
    :class:`agvviz.app.dask_engine.DaskEngine`: ``start_lead``, ``start_followers``, ``busy``,
    ``detected``, ``ended``, ``frames_done``, ``stop``): each :func:`detection_groups`
    group's lead (its first task) first, which detects and fills the cache, then the group's
    other tasks, which only solve — as soon as the lead's detections are stored where the engine
    says so (a local lead, while it finishes its own solve), else when it ends; the results in
    the order of ``tasks``. A lead that failed may not have detected (its output, its solver):
    the next task of its group leads instead.

    ``on_result(index, result)`` is called in this thread as each task ends (the sweep reads
    the run back meanwhile, while the others solve). ``frames()``: frames per recording (asked
    once the leads have started: the sweep counts them meanwhile), for
    ``progress(frames_done, runs_finished)`` (see :func:`progress_total`). Interrupted
    (Ctrl-C), it stops the running tasks (at their next frame) and drops the others.
    """
    if not tasks:
        return []
    results: list[TaskResult | None] = [None] * len(tasks)
    groups = list(detection_groups(tasks).values())
    waiting = {members[0]: members[1:] for members in groups}  # a running lead → its group's other tasks
    try:
        for members in groups:
            engine.start_lead(members[0])
        counts = frames() if frames is not None else {}
        expected = [counts.get(t.recording, 0) for t in tasks]  # progress: each task's frames
        while engine.busy():
            for i in engine.detected():  # its detections are in the cache: the others start now
                engine.start_followers(waiting.pop(i, []))
            ended = engine.ended()
            for i, result in ended:
                results[i] = result
                rest = waiting.pop(i, [])
                if rest and result.error is not None:
                    waiting[rest[0]] = rest[1:]
                    engine.start_lead(rest[0])
                else:
                    engine.start_followers(rest)
            for i, result in ended:  # after the submissions: the others go on meanwhile
                if on_result is not None:
                    on_result(i, result)
            if progress is not None:  # frames of a recording that could not be counted are not shown
                done = sum(expected[i] if results[i] is not None else min(engine.frames_done(i), expected[i])
                           for i in range(len(tasks)))
                progress(done, sum(r is not None for r in results))
            if engine.busy():
                time.sleep(0.05)
    except BaseException:  # interrupted: stop the running tasks, drop the others
        engine.stop()
        raise
    return results


def progress_total(tasks: list[RunTask], frames: dict[Path, int]) -> int:
    """Frames a sweep's progress counts up to: each run's (a lead's detection is its run's)."""
    return sum(frames.get(t.recording, 0) for t in tasks)
