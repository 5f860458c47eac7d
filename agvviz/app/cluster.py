"""The engine of ``agvviz sweep``: each detection group's settings in one pass, in this process
or on a Dask cluster.

A sweep's runs (:class:`RunTask`: recording, settings, output ``.rrd``) are grouped by recording
and detection settings (:func:`detection_groups`, :func:`agvviz.replay.detect.stage.detection_settings`).
A group runs in one pass (:func:`run_group`): its first setting, the *lead*, reads the recording
and detects it on the detect stage's pool of processes, as ``agvviz run`` does (filling the
detection cache); the others *follow* it in lockstep, each in a thread of the same process,
taking every message with its detections and only solving
(:mod:`agvviz.replay.detect.lockstep`). A follower that could not follow (its lead failed) runs
again with the others like it, the first of them leading.

- A local sweep (:class:`LocalRuns`) runs its groups in its own process, one after the other:
  the lead's detection pool already fills every CPU, so more processes would gain nothing, and
  no worker has to start or import anything.
- On an existing Dask cluster (``--scheduler``, :func:`open_client`) each group is one task
  (:func:`run_group_task`).

A setting's failure comes back as that run's one-line message (:class:`TaskResult`); the other
runs go on.

Progress: a local sweep reads each run's frames done; on a cluster, tasks report them through
Dask's event log (``Worker.log_event``, at most every :data:`PROGRESS_EVERY_S` per run); a run
that finishes counts all its frames.

Interruption (Ctrl-C, SIGTERM): local runs stop at their next frame (their unfinished ``.rrd``
files are removed); on a cluster the sweep sets a Dask ``Event`` that every running task checks
between frames, and cancels the others.

Dask is an optional dependency (``pip install 'agvviz[distributed]'``), needed for
``--scheduler`` only; without it such a sweep fails at once with :data:`DASK_MISSING`. Only this
module imports Dask, and only inside functions.
"""

from __future__ import annotations

import json
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

from agvviz.errors import InputError
from agvviz.recording import outputs
from agvviz.replay.detect.workers import signals_ignored

if TYPE_CHECKING:
    from agvviz.settings import RunSettings

#: The one-line error of a sweep on a cluster (--scheduler) without Dask.
DASK_MISSING = (
    "agvviz sweep --scheduler runs on Dask distributed, which is not installed: pip install 'agvviz[distributed]'"
)
#: A worker reports its task's frames done at most this often (seconds).
PROGRESS_EVERY_S = 0.25
#: A running task looks at the sweep's stop event at most this often (seconds).
STOP_CHECK_EVERY_S = 0.5
#: How long to wait for an existing cluster's scheduler to answer (seconds).
CONNECT_TIMEOUT_S = 10.0


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
    #: It did not run for a reason of its group's, not its own (its lead stopped early, or it
    #: could not follow the lead): to be run again on its own.
    retry: bool = False


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
    """A local sweep's runs, in this process: each detection group (:func:`detection_groups`) in
    one pass (:func:`run_group`), one group after the other, in a thread.

    A group's lead detects the recording on the detect stage's own pool of ``jobs`` processes,
    which fills both cores; its other settings follow it in lockstep and only solve. Nothing is
    gained by more processes on one machine — the lead's pool already uses every CPU — so a
    local sweep starts no cluster. ``results[i]`` is task i's :class:`TaskResult` once its group
    is done, ``frames[i]`` counts its frames done. :meth:`close` stops the runs at their next
    frame.
    """

    def __init__(self, tasks: list[RunTask], cache_dir: Path | None, jobs: int):
        self.tasks = tasks
        self.groups = list(detection_groups(tasks).values())
        self.cache_dir, self.jobs = cache_dir, max(1, jobs)
        self.results: dict[int, TaskResult] = {}
        self.frames: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run_all, name="agvviz sweep local runs", daemon=True)

    def start(self) -> "LocalRuns":
        # Imported here, in the calling thread: two threads importing one module at once can
        # deadlock on its import lock (the sweep counts frames in another thread meanwhile);
        # so is what a run imports on its way (the detection cache's Parquet).
        import pyarrow.parquet  # noqa: F401

        import agvviz.app.run  # noqa: F401
        from agvviz.replay.detect.workers import start_fork_server
        from agvviz.viz import run_process  # noqa: F401 — its .rrd writer forks from the server too (preload_too)

        start_fork_server()  # the detection pool's and .rrd writers' (signals ignored)
        self._thread.start()
        return self

    def _progress(self, index: int) -> Callable[[int], None]:
        def progress(frames_done: int) -> None:
            self.frames[index] = frames_done
            if self._stop.is_set():
                raise SweepStopped("the sweep was interrupted")

        return progress

    def _run_all(self) -> None:
        for members in self.groups:
            if self._stop.is_set():
                return
            results = run_group(self.tasks, members, jobs=self.jobs, cache_dir=self.cache_dir,
                                progress_of=self._progress, stopped=self._stop.is_set)
            if self._stop.is_set():  # interrupted: nobody waits for the results
                return
            self.results.update(results)

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def close(self) -> None:
        """Stop (at the next frame) and wait for the thread."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()


def run_group(
    tasks: list[RunTask], members: list[int], *, jobs: int, cache_dir: Path | None,
    progress_of: Callable[[int], Callable[[int], None]], stopped: Callable[[], bool] = lambda: False,
) -> dict[int, TaskResult]:
    """Run one detection group's tasks (``members``, indices of ``tasks``) in one pass: the
    first leads — it reads the recording and detects it on ``jobs`` processes (from the cache
    when it is there) — and the others follow it, each in its own thread, taking its messages
    and detections (:mod:`agvviz.replay.detect.lockstep`). A follower that could not follow (its
    lead stopped early: it failed; other topics or clock) runs again with the others like it,
    the first of them leading. ``progress_of(i)`` is task i's ``progress(frames_done)``;
    ``stopped()`` says the sweep was interrupted (nothing is run again then). Returns each
    member's :class:`TaskResult`."""
    from agvviz.replay.detect.lockstep import Lockstep

    results: dict[int, TaskResult] = {}
    todo = list(members)
    while todo and not stopped():
        lead, followers = todo[0], todo[1:]
        lockstep = Lockstep(len(followers))

        def follow(k: int, index: int) -> None:
            try:
                results[index] = _run(tasks[index], 1, progress_of(index), cache_dir, follow=(lockstep, k))
            finally:
                lockstep.close(k)

        threads = [
            threading.Thread(target=follow, args=(k, index), name=f"agvviz sweep follower {index}", daemon=True)
            for k, index in enumerate(followers)
        ]
        for thread in threads:
            thread.start()
        try:
            results[lead] = _run(tasks[lead], jobs, progress_of(lead), cache_dir,
                                 lead_of=lockstep if followers else None)
        finally:
            lockstep.lead_done()
            for thread in threads:
                thread.join()
        todo = [i for i in followers if results[i].retry]
    return results


def _run(
    task: RunTask, jobs: int, progress: Callable[[int], None], cache_dir: Path | None, *, lead_of=None, follow=None,
) -> TaskResult:
    """Replay one setting (:func:`agvviz.app.run.run_recording`) with ``jobs`` detection
    processes (its group's detections come from the cache when they are there; ``lead_of`` /
    ``follow``: in lockstep, see :func:`run_group`); a failure, an interruption
    (:class:`SweepStopped` from ``progress``) included, is the result's error."""
    from agvviz.app.run import run_recording
    from agvviz.replay.detect.lockstep import LeadFailed, LockstepMismatch

    extra = {"cache_dir": cache_dir} if cache_dir is not None else {}
    try:
        outcome = run_recording(task.recording, task.settings, task.out_path, progress=progress, jobs=jobs,
                                images=task.images, lead_of=lead_of, follow=follow, **extra)
    except (LeadFailed, LockstepMismatch) as exc:
        return TaskResult(error=one_line(exc), retry=True)
    except Exception as exc:  # noqa: BLE001 — any failure of one setting is reported, not raised
        return TaskResult(error=one_line(exc))
    return TaskResult(timing=dict(outcome.timing))


def run_group_task(
    tasks: list[RunTask], members: list[int], cache_dir: str | None, topic: str, stop_name: str, share: int = 1,
) -> dict[int, TaskResult]:
    """Worker: one detection group's tasks in one pass (:func:`run_group`); the lead detects on
    ``share`` processes (its share of the cluster's threads; in-process in a daemonic worker)."""
    import cv2

    cv2.setNumThreads(1)  # one thread per worker: the workers already fill the CPUs
    reporters = {i: _Reporter(topic, stop_name, i) for i in members}
    stop = reporters[members[0]].stop
    return run_group(
        tasks, members, jobs=_detect_jobs(share), cache_dir=Path(cache_dir) if cache_dir is not None else None,
        progress_of=reporters.__getitem__, stopped=stop.is_set,
    )


# -- temporaries left behind -------------------------------------------------------------------
@contextmanager
def reaper(folders: list[Path]) -> Iterator[None]:
    """A local sweep's guard: a small process that, once this one has ended in any way (even by
    SIGKILL), removes the temporary files its runs left in ``folders`` (:func:`reap`)."""
    with signals_ignored(signal.SIGINT, signal.SIGTERM):  # the reaper outlives any signal to the group
        started = _start_reaper(folders)
    try:
        yield
    finally:
        for folder in folders:
            outputs.remove_stale_temps(folder)
        if started is not None:
            process, write_fd = started
            os.close(write_fd)
            process.wait()


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
    ``grace_s`` while its detection workers finish dying."""
    sweep_pid = os.getppid()
    sys.stdin.buffer.read()
    folders = sys.argv[1:]
    # The sweep process has ended, though it may linger as a zombie until whoever started it
    # waits for it, and so still look alive: its own temporaries (its runs') go at once.
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



# -- the cluster -------------------------------------------------------------------------------
@contextmanager
def open_client(scheduler: str) -> Iterator[object]:
    """A Dask client of the cluster at ``scheduler`` (``--scheduler``); the cluster is the
    caller's and stays as it is. :class:`InputError` when it cannot be reached."""
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
    """Run ``tasks``, each :func:`detection_groups` group in one pass (:func:`run_group`): in
    this process (``local``, a :class:`LocalRuns` already started for these ``tasks``), or as
    one task per group on the Dask ``client``'s cluster (:func:`open_client`). The results in
    the order of ``tasks``.

    ``on_result(index, result)`` is called in this thread as each group ends (the sweep reads
    its runs back meanwhile, while the next groups run). ``frames``: frames per recording, for
    ``progress(frames_done, runs_finished)`` (see :func:`progress_total`). Interrupted
    (Ctrl-C), it stops the running tasks (at their next frame) and cancels the others.
    """
    if not tasks:
        return []
    frames = frames or {}
    expected = [frames.get(t.recording, 0) for t in tasks]  # progress: each task's frames
    done_frames = [0] * len(tasks)
    lock = threading.Lock()
    results: list[TaskResult | None] = [None] * len(tasks)
    pending: dict[object, list[int]] = {}  # future -> its group
    stop_name = None
    if local is None:
        from distributed import Event

        groups = list(detection_groups(tasks).values())
        token = uuid.uuid4().hex[:12]
        topic, stop_name = f"agvviz-sweep-progress-{token}", f"agvviz-sweep-stop-{token}"

        def on_event(event) -> None:  # in the client's event-loop thread
            _, (unit, count) = event
            with lock:  # frames of a recording that could not be counted are not shown
                done_frames[unit] = max(done_frames[unit], min(int(count), expected[unit]))

        client.subscribe_topic(topic, on_event)
        cache = str(Path(cache_dir).resolve()) if cache_dir is not None else None
        share = max(1, sum(client.nthreads().values()) // len(groups))
        resolved = [RunTask(t.recording.resolve(), t.settings, t.out_path.resolve(), t.images) for t in tasks]
        for n, members in enumerate(groups):
            future = client.submit(run_group_task, resolved, members, cache, topic, stop_name, share,
                                   key=f"agvviz-group-{token}-{n}", pure=False)
            pending[future] = members
    try:
        while pending or (local is not None and not all(r is not None for r in results)):
            ended: list[tuple[int, TaskResult]] = []
            for future in [f for f in pending if f.done()]:
                members = pending.pop(future)
                try:
                    group_results = future.result()
                except Exception as exc:  # noqa: BLE001 — a worker that died, a cancelled task
                    group_results = {i: TaskResult(error=one_line(exc)) for i in members}
                ended += sorted(group_results.items())
            if local is not None:
                for i in range(len(tasks)):
                    if results[i] is None:
                        with lock:
                            done_frames[i] = max(done_frames[i], min(local.frames.get(i, 0), expected[i]))
                        if i in local.results:
                            ended.append((i, local.results[i]))
                if local.done and not ended and not all(r is not None for r in results):
                    raise RuntimeError("the sweep's local runs ended without a result for every setting")
            for i, result in ended:
                with lock:
                    done_frames[i] = expected[i]
                results[i] = result
            for i, result in ended:
                if on_result is not None:
                    on_result(i, result)
            if progress is not None:
                with lock:
                    total_done = sum(done_frames)
                progress(total_done, sum(r is not None for r in results))
            if pending or (local is not None and not all(r is not None for r in results)):
                time.sleep(0.05)
    except BaseException:  # interrupted: stop the running tasks, drop the others
        if local is not None:
            local.close()
        if stop_name is not None:
            try:
                Event(stop_name, client=client).set()
                client.cancel(list(pending))
            except Exception:  # noqa: BLE001 — the cluster may be gone already
                pass
        raise
    return results


def progress_total(tasks: list[RunTask], frames: dict[Path, int]) -> int:
    """Frames a sweep's progress counts up to: each run's (a lead's detection is its run's)."""
    return sum(frames.get(t.recording, 0) for t in tasks)
