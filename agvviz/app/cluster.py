"""The engine of ``agvviz sweep``: Dask distributed runs the sweep's replays.

:func:`open_client` gives a Dask client of a new ``distributed.LocalCluster`` (worker processes
on this machine, one thread each) or of an existing cluster given by its scheduler's address;
:func:`run_sweep_tasks` runs a sweep's runs (recording, settings, output ``.rrd``) on it. It
groups them by recording and detection settings (:func:`agvviz.replay.detect.stage.detection_settings`);
each group's first setting, its *lead*, runs first and alone: it detects the recording on both
cores and solves meanwhile, in one pass, as ``agvviz run`` does, and fills the detection cache.
On a local cluster the leads run in the sweep process itself while the cluster starts
(:class:`LocalRuns`), on an existing cluster as tasks. When a lead is done, its group's other
settings go to the workers, which have imported agvviz meanwhile, and only solve (from the
cache); a local sweep keeps one of them in its own process, which has imported everything too
and would otherwise wait. A lead that failed hands the lead to the next setting of its group.
A task's failure — an error of agvviz, a worker process that died — comes back as that run's
one-line message; the other runs go on.

Progress: workers report frames done through Dask's event log (``Worker.log_event``, at most
every :data:`PROGRESS_EVERY_S` per task); a task that finishes counts all its frames.

Interruption (Ctrl-C, SIGTERM): the sweep sets a Dask ``Event`` that every running task checks
between frames (it then stops, and its unfinished ``.rrd`` is removed), cancels the futures and
closes the cluster. The local cluster's worker processes ignore SIGINT and SIGTERM (see
:func:`_start_method`, :func:`dask_setup`), so a Ctrl-C at the terminal, which reaches the whole
process group, is handled by the sweep process alone. They end when the sweep process ends,
even by SIGKILL (Dask's own parent watch); a small reaper process then removes the temporary
files they leave.
On an existing cluster (``--scheduler``) the stop event ends the running tasks the same way.

Dask is an optional dependency (``pip install 'agvviz[distributed]'``); without it a sweep
fails at once with :data:`DASK_MISSING` — there is no second, serial engine.

Only this module imports Dask, and only inside functions (the reaper starts without it).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

from agvviz.recording import outputs
from agvviz.replay.detect.workers import signals_ignored
from agvviz.errors import InputError

if TYPE_CHECKING:
    from agvviz.settings import RunSettings

#: The one-line error of a sweep without Dask.
DASK_MISSING = "agvviz sweep runs on Dask distributed, which is not installed: pip install 'agvviz[distributed]'"
#: A worker reports its task's frames done at most this often (seconds).
PROGRESS_EVERY_S = 0.25
#: A running task looks at the sweep's stop event at most this often (seconds).
STOP_CHECK_EVERY_S = 0.5
#: How long to wait for an existing cluster's scheduler to answer (seconds).
CONNECT_TIMEOUT_S = 10.0
#: How long the local cluster's workers get to stop before they are killed (seconds): at the
#: end of a sweep, and when it was interrupted (a task stops at its next frame, and a worker
#: killed instead leaves temporary files that the sweep removes).
CLOSE_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class RunTask:
    """One run of a sweep: replay ``recording`` under ``settings`` into ``out_path``
    (``images=False``: the layers only, what a sweep ``.rrd`` takes of a setting)."""

    recording: Path
    settings: "RunSettings"
    out_path: Path
    images: bool = True


@dataclass(frozen=True)
class TaskResult:
    """How a task went: the run's wall-clock ``timing``, or ``error`` (one line) when it failed."""

    timing: dict = field(default_factory=dict)
    error: str | None = None


class SweepStopped(Exception):
    """Raised inside a task when the sweep was interrupted (its stop event is set)."""


def require_distributed() -> None:
    """:class:`InputError` (:data:`DASK_MISSING`) unless ``distributed`` can be imported; does
    not import it (≈0.7 s: a local sweep imports it while its first runs have started)."""
    import importlib.util

    try:
        found = importlib.util.find_spec("distributed") is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        raise InputError(DASK_MISSING)


def import_distributed():
    """The ``distributed`` package, or :class:`InputError` (:data:`DASK_MISSING`)."""
    try:
        import distributed
    except ImportError:
        raise InputError(DASK_MISSING) from None
    return distributed


def one_line(exc: BaseException) -> str:
    """``Type: message`` on one line; a worker that died is said so plainly."""
    name = type(exc).__name__
    if name == "KilledWorker":
        return "KilledWorker: the worker process running it died (crashed, ran out of memory or was killed)"
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


# -- worker side -------------------------------------------------------------------------------
class _Reporter:
    """A task's ``progress(frames_done)``: sends its count to the sweep's event topic (throttled)
    and raises :class:`SweepStopped` once the sweep's stop event is set."""

    def __init__(self, topic: str, stop_name: str, unit: int):
        from distributed import Event, get_worker

        self.worker = get_worker()
        self.topic, self.unit = topic, unit
        self.stop = Event(stop_name)
        self.last_sent = self.last_check = time.monotonic()

    def __call__(self, frames_done: int) -> None:
        now = time.monotonic()
        if now - self.last_sent >= PROGRESS_EVERY_S:
            self.last_sent = now
            self.worker.log_event(self.topic, [self.unit, int(frames_done)])
        if now - self.last_check >= STOP_CHECK_EVERY_S:
            self.last_check = now
            if self.stop.is_set():
                raise SweepStopped("the sweep was interrupted")


def _detect_jobs(share: int) -> int:
    """Detection processes of one detection task: its share of the cluster's threads, at most
    this machine's CPUs; 1 (in-process) in a daemonic worker, which may not start processes."""
    import multiprocessing

    if multiprocessing.current_process().daemon:
        return 1
    return max(1, min(share, os.cpu_count() or 1))


class LocalRuns:
    """The runs a local sweep makes in its own process: each detection group's lead, at once,
    while the cluster starts, and then some of the groups' other settings, beside the workers.

    The lead of a detection group (:func:`detection_groups`) is its first setting: it detects
    the recording on the detect stage's own pool of ``jobs`` processes and solves meanwhile, in
    one pass, as ``agvviz run`` does (which fills the detection cache). With a local cluster
    every process is on this machine, so nothing is gained by sending a lead to a worker — and
    much is lost: the cluster must first start and the worker then starts its own detection
    pool. Once the leads are done this process has imported everything a run needs, as the
    workers have, and would only wait: :func:`run_sweep_tasks` hands it one more setting of each
    group (:meth:`add`) while the workers solve the others. The runs go one after the other, in a
    thread; ``results[i]`` is task i's :class:`TaskResult` once it is done, ``frames[i]`` counts
    its frames done. :meth:`close` stops the thread at its next frame.
    """

    def __init__(self, tasks: list[RunTask], cache_dir: Path | None, jobs: int):
        self.tasks = tasks
        self.leads = [members[0] for members in detection_groups(tasks).values()]
        self.cache_dir, self.jobs = cache_dir, max(1, jobs)
        self.results: dict[int, TaskResult] = {}
        self.frames: dict[int, int] = {}
        self._queue = list(self.leads)
        self._wake = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run_all, name="agvviz sweep local runs", daemon=True)

    def start(self) -> "LocalRuns":
        # Imported here, in the calling thread: two threads importing one module at once can
        # deadlock on its import lock (the sweep counts frames in another thread meanwhile and
        # then imports Dask); so is what a run imports on its way (the detection cache's Parquet).
        import pyarrow.parquet  # noqa: F401

        import agvviz.app.run  # noqa: F401

        _start_method()  # the fork server (signals ignored) that the detection pool and the workers share
        self._thread.start()
        return self

    def add(self, index: int) -> None:
        """Run task ``index`` here too, after those already given (it reads its detections from
        the cache: one process)."""
        with self._wake:
            self._queue.append(index)
            self._wake.notify()

    def _run_all(self) -> None:
        while True:
            with self._wake:
                while not self._queue and not self._stop.is_set():
                    self._wake.wait()
                if self._stop.is_set():
                    return
                index = self._queue.pop(0)

            def progress(frames_done: int, index: int = index) -> None:
                self.frames[index] = frames_done
                if self._stop.is_set():
                    raise SweepStopped("the sweep was interrupted")

            jobs = self.jobs if index in self.leads else 1
            result = _run(self.tasks[index], jobs, progress, self.cache_dir)
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


def _run(task: RunTask, jobs: int, progress: Callable[[int], None], cache_dir: Path | None) -> TaskResult:
    """Replay one setting (:func:`agvviz.app.run.run_recording`) with ``jobs`` detection
    processes (its group's detections come from the cache when they are there); a failure, an
    interruption (:class:`SweepStopped` from ``progress``) included, is the result's error."""
    from agvviz.app.run import run_recording

    extra = {"cache_dir": cache_dir} if cache_dir is not None else {}
    try:
        # The .rrd in this process: a sweep keeps every core busy already.
        outcome = run_recording(task.recording, task.settings, task.out_path, progress=progress, jobs=jobs,
                                images=task.images, writer_process=False, **extra)
    except Exception as exc:  # noqa: BLE001 — any failure of one setting is reported, not raised
        return TaskResult(error=one_line(exc))
    return TaskResult(timing=dict(outcome.timing))


def run_task(
    recording: str, settings: "RunSettings", out_path: str, cache_dir: str | None, topic: str, stop_name: str,
    unit: int, images: bool = True, share: int = 1,
) -> TaskResult:
    """Worker: replay one setting. A group's lead (``share`` > 1: its share of the cluster's
    threads) detects on that many processes (in-process in a daemonic worker) and fills the
    cache; the others read their group's detections from it and only solve."""
    import cv2

    cv2.setNumThreads(1)  # one thread per worker: the workers already fill the CPUs
    reporter = _Reporter(topic, stop_name, unit)
    task = RunTask(Path(recording), settings, Path(out_path), images)
    return _run(task, _detect_jobs(share), reporter, Path(cache_dir) if cache_dir is not None else None)


# -- the cluster -------------------------------------------------------------------------------
def _start_method() -> str:
    """Dask's way to start the local workers: forked from the fork server, which this starts
    with SIGINT and SIGTERM ignored, where there is one; else spawned.

    A Ctrl-C at the terminal, or a SIGTERM to the process group, reaches every process of the
    sweep: the fork server must outlive it (the workers' exit is watched through it), and the
    workers ignore it too (they inherit SIGINT ignored; :func:`dask_setup` for SIGTERM) — the
    sweep process alone handles it, stopping the tasks and closing the cluster. A fork server
    already running in this process (a library user's) is used as it is."""
    import multiprocessing
    import multiprocessing.forkserver

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return "spawn"
    multiprocessing.forkserver.set_forkserver_preload(["distributed", "agvviz.app.run"])  # no effect once it runs
    with signals_ignored(signal.SIGINT, signal.SIGTERM):
        multiprocessing.forkserver.ensure_running()
    return "forkserver"


def start_fork_server() -> None:
    """Start the local cluster's fork server now (:func:`_start_method`), so that its imports run
    beside the caller's own."""
    _start_method()


def _ignore_signal(signum, frame) -> None:
    """A do-nothing handler: unlike SIG_IGN, processes started by exec get the default back."""


def _import_replay() -> None:
    import agvviz.app.run  # noqa: F401


def dask_setup(worker) -> None:
    """Dask preload of the local cluster's workers (run in each worker's main thread).

    SIGTERM, inherited ignored from the fork server, stays without effect here (the sweep
    process handles it) but through a handler, so the processes a task starts by exec (detection
    pools) get the default SIGTERM back (their parent-death signal). The replay's modules are
    imported in the background meanwhile, so a worker whose first run waits for a detection does
    not import them then."""
    signal.signal(signal.SIGTERM, _ignore_signal)
    threading.Thread(target=_import_replay, name="agvviz import", daemon=True).start()


def _local_cluster(distributed, workers: int):
    import dask

    with dask.config.set({
        "distributed.worker.multiprocessing-method": _start_method(),
        # Workers may start processes (detection pools): not daemonic. They still end with the
        # sweep process (Dask's parent watch).
        "distributed.worker.daemon": False,
        # A task whose worker died fails at once (a replay that crashes a process would again).
        "distributed.scheduler.allowed-failures": 0,
    }):
        return distributed.LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, silence_logs=logging.CRITICAL, memory_limit=0,
            preload=[__name__],  # dask_setup
            # No dashboard; the scheduler's own HTTP routes on a free local port (its default,
            # 8787, warns when another cluster has it).
            dashboard_address=None, scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
        )


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
def open_client(
    scheduler: str | None, workers: int, temp_folders: list[Path], before_cluster: Callable[[], None] | None = None,
) -> Iterator[object]:
    """A Dask client: of the cluster at ``scheduler``, or of a new local cluster of ``workers``
    processes (closed on leaving, with the reaper for ``temp_folders``). ``before_cluster``: a
    local cluster calls it once its reaper runs, before its workers start (the sweep starts its
    own runs then, :class:`LocalRuns`)."""
    if scheduler is not None:
        distributed = import_distributed()
        try:
            distributed.comm.resolve_address(scheduler)  # a malformed address or unknown host: at once
            client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {' '.join(str(exc).split())}") from None
        try:
            yield client
        finally:
            client.close()
        return
    with signals_ignored(signal.SIGINT, signal.SIGTERM):  # the reaper outlives any signal to the group
        reaper = _start_reaper(temp_folders)
    cluster = client = None
    interrupted = False
    try:
        if before_cluster is not None:
            before_cluster()
        distributed = import_distributed()
        cluster = _local_cluster(distributed, workers)
        client = distributed.Client(cluster, set_as_default=False)
        yield client
    except BaseException:
        interrupted = True
        raise
    finally:
        try:
            if client is not None:
                client.close()
            if cluster is not None:  # a worker still busy after 0.8 × the timeout is killed
                cluster.close(timeout=STOP_TIMEOUT_S if interrupted else CLOSE_TIMEOUT_S)
        except Exception:  # noqa: BLE001 — a close that timed out: the workers end with this process
            pass
        finally:
            for folder in temp_folders:  # left by a worker that was killed
                outputs.remove_stale_temps(folder)
            if reaper is not None:
                process, write_fd = reaper
                os.close(write_fd)
                process.wait()


def run_sweep_tasks(
    client,
    tasks: list[RunTask],
    *,
    cache_dir: Path | None = None,
    frames: dict[Path, int] | None = None,
    progress: Callable[[int, int], None] | None = None,
    local: LocalRuns | None = None,
    on_result: Callable[[int, TaskResult], None] | None = None,
) -> list[TaskResult]:
    """Run ``tasks`` on the Dask ``client``'s cluster (see :func:`open_client`): each
    :func:`detection_groups` group's lead (its first task) first, which detects and fills the
    cache, then the group's other tasks, which only solve; the results in the order of
    ``tasks``. ``local``: the leads run in this process (:class:`LocalRuns`, already started
    for these ``tasks``) instead of as tasks on the cluster.

    ``on_result(index, result)`` is called in this thread as each task ends (the sweep reads
    the run back meanwhile, while the others solve). ``frames``: frames per recording, for
    ``progress(frames_done, runs_finished)`` (see :func:`progress_total`). Interrupted
    (Ctrl-C), it stops the running tasks (at their next frame) and cancels the others.
    """
    from distributed import Event

    if not tasks:
        return []
    frames = frames or {}
    groups = list(detection_groups(tasks).values())
    leads = [members[0] for members in groups]
    token = uuid.uuid4().hex[:12]
    topic, stop_name = f"agvviz-sweep-progress-{token}", f"agvviz-sweep-stop-{token}"
    expected = [frames.get(t.recording, 0) for t in tasks]  # progress: each task's frames
    done_frames = [0] * len(tasks)
    lock = threading.Lock()

    def on_event(event) -> None:  # in the client's event-loop thread
        _, (unit, count) = event
        with lock:  # frames of a recording that could not be counted are not shown
            done_frames[unit] = max(done_frames[unit], min(int(count), expected[unit]))

    results: list[TaskResult | None] = [None] * len(tasks)
    client.subscribe_topic(topic, on_event)
    cache = str(Path(cache_dir).resolve()) if cache_dir is not None else None
    share = max(1, sum(client.nthreads().values()) // len(groups))
    pending: dict[object, int] = {}  # future -> its task

    def submit(i: int, share: int = 1) -> None:
        task = tasks[i]
        future = client.submit(
            run_task, str(task.recording.resolve()), task.settings, str(task.out_path.resolve()), cache, topic,
            stop_name, i, task.images, share, key=f"agvviz-run-{token}-{i}", pure=False,
        )
        pending[future] = i

    waiting = {members[0]: members[1:] for members in groups}  # a running lead → its group's other tasks
    running_here = set(leads) if local is not None else set()  # tasks of `local`, not yet ended
    try:
        if local is None:
            for lead in leads:
                submit(lead, share)
        while pending or running_here:
            ended = []
            for future in [f for f in pending if f.done()]:
                i = pending.pop(future)
                try:
                    result = future.result()
                except Exception as exc:  # noqa: BLE001 — a worker that died, a cancelled task
                    result = TaskResult(error=one_line(exc))
                ended.append((i, result))
            for i in sorted(running_here):
                with lock:
                    done_frames[i] = max(done_frames[i], min(local.frames.get(i, 0), expected[i]))
                if i in local.results:
                    running_here.discard(i)
                    ended.append((i, local.results[i]))
            for i, result in ended:
                with lock:
                    done_frames[i] = expected[i]
                results[i] = result
                rest = waiting.pop(i, [])
                if rest and result.error is not None:
                    # A lead that failed may not have detected (its output, its solver): the
                    # next task of its group leads in its place, on the cluster.
                    waiting[rest[0]] = rest[1:]
                    submit(rest[0], share)
                    continue
                # A lead that ran: its group's detections are in the cache, the others only
                # solve. They are submitted now rather than as the lead's dependents, which
                # Dask would all place on the one worker holding its result. A local sweep
                # keeps the last of them in this process, which would otherwise only wait.
                if rest and local is not None:
                    local.add(rest[-1])
                    running_here.add(rest[-1])
                    rest = rest[:-1]
                for member in rest:
                    submit(member)
            for i, result in ended:  # after the submissions: the workers go on meanwhile
                if on_result is not None:
                    on_result(i, result)
            if progress is not None:
                with lock:
                    total_done = sum(done_frames)
                progress(total_done, sum(r is not None for r in results))
            if pending or running_here:
                time.sleep(0.05)
    except BaseException:  # interrupted: stop the running tasks, drop the others
        if local is not None:
            local.close()
        try:
            Event(stop_name, client=client).set()
            client.cancel(list(pending))
        except Exception:  # noqa: BLE001 — the cluster may be gone already; closing follows
            pass
        raise
    return results


def progress_total(tasks: list[RunTask], frames: dict[Path, int]) -> int:
    """Frames a sweep's progress counts up to: each run's (a lead's detection is its run's)."""
    return sum(frames.get(t.recording, 0) for t in tasks)
