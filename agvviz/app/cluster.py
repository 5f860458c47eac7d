"""The engine of ``agvviz sweep``: Dask distributed runs the sweep's replays.

:func:`open_client` gives a Dask client of a new ``distributed.LocalCluster`` (worker processes
on this machine, one thread each) or of an existing cluster given by its scheduler's address;
:func:`run_sweep_tasks` runs a sweep's runs (recording, settings, output ``.rrd``) on it. It
groups them by recording and detection settings (:func:`agvviz.replay.detect.stage.detection_settings`)
and detects each group once first (:func:`agvviz.replay.run.detect_recording`, which fills the
detection cache): on a local cluster in the sweep process itself while the cluster starts
(:class:`LocalDetections`), on an existing cluster as a task; the group's runs start when it is
done (a failed detection fails them, with its message) and only solve. A task's failure — an error of agvviz, a worker process
that died — comes back as that run's one-line message; the other runs go on.

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


class LocalDetections:
    """A local sweep's detections, run in the sweep process itself while its cluster starts.

    With a local cluster every process is on this machine, so nothing is gained by sending a
    detection to a worker — and much is lost: the cluster must first start and the worker then
    starts its own detection pool. Here the detections start at once, in a thread, on the
    detect stage's own pool of ``jobs`` processes (as ``agvviz run`` detects), one group after
    the other (:func:`detection_groups`, each from its first task); :func:`run_sweep_tasks`
    submits a group's runs when its detection is done. ``results[g]`` is None until group g is
    done, then a :class:`TaskResult` (``error``: the detection failed, its runs fail with it);
    ``frames[g]`` counts its frames detected. :meth:`close` stops the thread at its next frame.
    """

    def __init__(self, tasks: list[RunTask], cache_dir: Path | None, jobs: int):
        self.first_tasks = [tasks[members[0]] for members in detection_groups(tasks).values()]
        self.cache_dir, self.jobs = cache_dir, max(1, jobs)
        self.results: list[TaskResult | None] = [None] * len(self.first_tasks)
        self.frames = [0] * len(self.first_tasks)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._detect_all, name="agvviz sweep detection", daemon=True)

    def start(self) -> "LocalDetections":
        # Imported here, in the calling thread: two threads importing one module at once can
        # deadlock on its import lock (the sweep counts frames in another thread meanwhile).
        import agvviz.replay.run  # noqa: F401

        _start_method()  # the fork server (signals ignored) that the detection pool and the workers share
        self._thread.start()
        return self

    def _detect_all(self) -> None:
        for g, task in enumerate(self.first_tasks):

            def progress(frames_done: int, g: int = g) -> None:
                self.frames[g] = frames_done
                if self._stop.is_set():
                    raise SweepStopped("the sweep was interrupted")

            result = _detect_group(task.recording, task.settings, self.jobs, progress, self.cache_dir)
            if self._stop.is_set():  # interrupted: nobody waits for the result
                return
            self.results[g] = result

    def close(self) -> None:
        """Stop (at the next frame) and wait for the detection thread."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()


def _detect_group(
    recording: Path, settings: "RunSettings", jobs: int, progress: Callable[[int], None], cache_dir: Path | None,
) -> TaskResult:
    """Detect ``recording`` once for a group of runs (fills the detection cache); a failure,
    an interruption (:class:`SweepStopped` from ``progress``) included, is the result's error."""
    from agvviz.replay.run import detect_recording

    extra = {"cache_dir": cache_dir} if cache_dir is not None else {}
    try:
        detect_recording(recording, settings, jobs=jobs, progress=progress, **extra)
    except Exception as exc:  # noqa: BLE001 — reported as every dependent run's failure
        return TaskResult(error=one_line(exc))
    return TaskResult()


def detect_task(
    recording: str, settings: "RunSettings", cache_dir: str | None, share: int, topic: str, stop_name: str, unit: int,
) -> TaskResult:
    """Worker: :func:`_detect_group` on the cluster."""
    reporter = _Reporter(topic, stop_name, unit)
    return _detect_group(
        Path(recording), settings, _detect_jobs(share), reporter, Path(cache_dir) if cache_dir is not None else None,
    )


def run_task(
    recording: str, settings: "RunSettings", out_path: str, cache_dir: str | None, topic: str, stop_name: str,
    unit: int, images: bool = True,
) -> TaskResult:
    """Worker: replay one setting, reusing its group's detections (from the cache)."""
    import cv2

    from agvviz.app.run import run_recording

    cv2.setNumThreads(1)  # one thread per worker: the workers already fill the CPUs
    reporter = _Reporter(topic, stop_name, unit)
    extra = {"cache_dir": Path(cache_dir)} if cache_dir is not None else {}
    try:
        outcome = run_recording(Path(recording), settings, Path(out_path), progress=reporter, jobs=1, images=images,
                                **extra)
    except Exception as exc:  # noqa: BLE001 — any failure of one setting is reported, not raised
        return TaskResult(error=one_line(exc))
    return TaskResult(timing=dict(outcome.timing))


# -- the cluster -------------------------------------------------------------------------------
@contextmanager
def _signals_ignored(*signums: int) -> Iterator[None]:
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
    with _signals_ignored(signal.SIGINT, signal.SIGTERM):
        multiprocessing.forkserver.ensure_running()
    return "forkserver"


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
    sys.stdin.buffer.read()
    folders = sys.argv[1:]
    deadline = time.monotonic() + grace_s
    while True:
        for folder in folders:
            outputs.remove_stale_temps(folder)
        left = [n for f in folders if os.path.isdir(f) for n in os.listdir(f) if outputs.TEMP_RE.match(n)]
        if not left or time.monotonic() > deadline:
            return
        time.sleep(0.1)


@contextmanager
def open_client(scheduler: str | None, workers: int, temp_folders: list[Path]) -> Iterator[object]:
    """A Dask client: of the cluster at ``scheduler``, or of a new local cluster of ``workers``
    processes (closed on leaving, with the reaper for ``temp_folders``)."""
    distributed = import_distributed()
    if scheduler is not None:
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
    with _signals_ignored(signal.SIGINT, signal.SIGTERM):  # the reaper outlives any signal to the group
        reaper = _start_reaper(temp_folders)
    cluster = client = None
    interrupted = False
    try:
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
    local: LocalDetections | None = None,
) -> list[TaskResult]:
    """Run ``tasks`` on the Dask ``client``'s cluster (see :func:`open_client`), one detection
    per :func:`detection_groups` group first; the results in the order of ``tasks``.
    ``local``: the detections run in this process (:class:`LocalDetections`, already started
    for these ``tasks``) instead of as tasks on the cluster.

    ``frames``: frames per recording, for ``progress(frames_done, runs_finished)``, where the
    frames of a detection and of every run count (see :func:`progress_total`). Interrupted
    (Ctrl-C), it stops the running tasks (at their next frame) and cancels the others.
    """
    from distributed import Event

    if not tasks:
        return []
    frames = frames or {}
    groups = detection_groups(tasks)
    token = uuid.uuid4().hex[:12]
    topic, stop_name = f"agvviz-sweep-progress-{token}", f"agvviz-sweep-stop-{token}"
    # Progress units: the detections first, then the runs.
    expected = [frames.get(tasks[members[0]].recording, 0) for members in groups.values()]
    expected += [frames.get(t.recording, 0) for t in tasks]
    done_frames = [0] * len(expected)
    lock = threading.Lock()

    def on_event(event) -> None:  # in the client's event-loop thread
        _, (unit, count) = event
        with lock:  # frames of a recording that could not be counted are not shown
            done_frames[unit] = max(done_frames[unit], min(int(count), expected[unit]))

    results: list[TaskResult | None] = [None] * len(tasks)

    def finish(unit: int, result: TaskResult | None = None) -> None:
        """A detection (unit < len(groups)) or a run has ended: all its frames count."""
        with lock:
            done_frames[unit] = expected[unit]
        if unit >= len(groups):
            results[unit - len(groups)] = result

    client.subscribe_topic(topic, on_event)
    cache = str(Path(cache_dir).resolve()) if cache_dir is not None else None
    share = max(1, sum(client.nthreads().values()) // len(groups))
    pending: dict[object, int] = {}  # future -> its progress unit
    local_waiting = set(range(len(groups))) if local is not None else set()
    try:
        for g, members in enumerate(groups.values()):
            if local is not None:
                continue
            first = tasks[members[0]]
            future = client.submit(
                detect_task, str(first.recording.resolve()), first.settings, cache, share, topic, stop_name, g,
                key=f"agvviz-detect-{token}-{g}", pure=False,
            )
            pending[future] = g
        members_of = list(groups.values())
        while pending or local_waiting:
            ended = []
            for future in [f for f in pending if f.done()]:
                unit = pending.pop(future)
                try:
                    result = future.result()
                except Exception as exc:  # noqa: BLE001 — a worker that died, a cancelled task
                    result = TaskResult(error=one_line(exc))
                ended.append((unit, result))
            for g in sorted(local_waiting):
                with lock:
                    done_frames[g] = max(done_frames[g], min(local.frames[g], expected[g]))
                if local.results[g] is not None:
                    local_waiting.discard(g)
                    ended.append((g, local.results[g]))
            for unit, result in ended:
                finish(unit, result)
                if unit >= len(groups):
                    continue
                # A detection: its group's detections are in the cache, its runs only solve.
                # They are submitted now rather than as the detection task's dependents, which
                # Dask would all place on the one worker holding its (tiny) result.
                for i in members_of[unit]:
                    if result.error is not None:  # a failed detection fails its runs
                        finish(len(groups) + i, result)
                        continue
                    task = tasks[i]
                    run = client.submit(
                        run_task, str(task.recording.resolve()), task.settings, str(task.out_path.resolve()),
                        cache, topic, stop_name, len(groups) + i, task.images, key=f"agvviz-run-{token}-{i}", pure=False,
                    )
                    pending[run] = len(groups) + i
            if progress is not None:
                with lock:
                    total_done = sum(done_frames)
                progress(total_done, sum(r is not None for r in results))
            if pending or local_waiting:
                time.sleep(0.1)
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
    """Frames a sweep's progress counts up to: each detection's and each run's."""
    groups = detection_groups(tasks)
    return sum(frames.get(tasks[m[0]].recording, 0) for m in groups.values()) + sum(
        frames.get(t.recording, 0) for t in tasks
    )
