"""A sweep on an existing Dask cluster (``agvviz sweep --scheduler ADDRESS``).

:func:`connect` gives a :class:`DaskEngine` on the cluster at a scheduler's address; it runs
every run of the sweep as a task on the cluster's workers, under the same loop as a local
sweep (:func:`agvviz.app.cluster.run_sweep_tasks`). A group's lead gets its share of the
cluster's threads to detect on (:func:`run_task`: processes of its own, or in process in a
daemonic worker); the others only solve, from the detection cache, which must be a folder every
worker sees. Workers report frames done through Dask's event log (``Worker.log_event``, at most
every :data:`PROGRESS_EVERY_S` per task); the stop is a Dask ``Event`` each running task checks
between frames. The cluster is the caller's: it is left running.

Dask is an optional dependency (``pip install 'agvviz[distributed]'``); without it the sweep
fails at once with :data:`DASK_MISSING`. Only this module imports Dask, and only inside
functions.
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

from agvviz.app.cluster import (
    STOP_CHECK_EVERY_S, RunTask, SweepStopped, TaskResult, _run, detection_groups, ended_futures,
)
from agvviz.errors import InputError

if TYPE_CHECKING:
    from agvviz.settings import RunSettings

#: The one-line error of a sweep on a Dask cluster (``--scheduler``) without Dask installed.
DASK_MISSING = (
    "agvviz sweep --scheduler runs on Dask distributed, which is not installed: pip install 'agvviz[distributed]'"
)
#: A worker reports its task's frames done at most this often (seconds).
PROGRESS_EVERY_S = 0.25
#: How long to wait for an existing cluster's scheduler to answer (seconds).
CONNECT_TIMEOUT_S = 10.0


def require_distributed() -> None:
    """:class:`InputError` (:data:`DASK_MISSING`) unless ``distributed`` can be imported; does
    not import it (≈0.7 s: checked before anything is written, imported once connecting)."""
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


# -- the worker side ------------------------------------------------------------------------------
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


def run_task(
    recording: str, settings: "RunSettings", out_path: str, cache_dir: str | None, topic: str, stop_name: str,
    unit: int, images: bool = True, share: int = 1, scratch: bool = False,
) -> TaskResult:
    """Worker: replay one setting. A group's lead (``share`` > 1: its share of the cluster's
    threads) detects on that many processes (in-process in a daemonic worker) and fills the
    cache; the others read their group's detections from it and only solve."""
    import cv2

    cv2.setNumThreads(1)  # one thread per worker: the workers already fill the CPUs
    reporter = _Reporter(topic, stop_name, unit)
    task = RunTask(Path(recording), settings, Path(out_path), images, scratch)
    return _run(task, _detect_jobs(share), reporter, Path(cache_dir) if cache_dir is not None else None)



class DaskEngine:
    """A sweep on an existing Dask cluster (``--scheduler``): every run is a task. A lead gets
    its share of the cluster's threads to detect on (:func:`run_task`); progress comes through
    Dask's event log and the stop through a Dask ``Event``."""

    def __init__(self, client, tasks: list[RunTask], cache_dir: Path | None):
        self.client, self.tasks = client, tasks
        self.cache = str(Path(cache_dir).resolve()) if cache_dir is not None else None
        token = uuid.uuid4().hex[:12]
        self.topic, self.stop_name, self.token = f"agvviz-sweep-progress-{token}", f"agvviz-sweep-stop-{token}", token
        self.share = max(1, sum(client.nthreads().values()) // max(1, len(detection_groups(tasks))))
        self._frames: dict[int, int] = {}
        self._lock = threading.Lock()
        self._pending: dict[object, int] = {}
        client.subscribe_topic(self.topic, self._on_event)

    def _on_event(self, event) -> None:  # in the client's event-loop thread
        _, (unit, count) = event
        with self._lock:
            self._frames[unit] = max(self._frames.get(unit, 0), int(count))

    def _submit(self, index: int, share: int) -> None:
        task = self.tasks[index]
        future = self.client.submit(
            run_task, str(task.recording.resolve()), task.settings, str(task.out_path.resolve()), self.cache,
            self.topic, self.stop_name, index, task.images, share, task.scratch, key=f"agvviz-run-{self.token}-{index}",
            pure=False,
        )
        self._pending[future] = index

    def start_lead(self, index: int) -> None:
        self._submit(index, self.share)

    def start_followers(self, indices: list[int]) -> None:
        # Submitted now rather than as the lead's dependents, which Dask would all place on the
        # one worker holding its result.
        for index in indices:
            self._submit(index, 1)

    def busy(self) -> bool:
        return bool(self._pending)

    def detected(self) -> list[int]:
        """A lead's group starts when the lead ends (its detections are then in the cache)."""
        return []

    def frames_done(self, index: int) -> int:
        with self._lock:
            return self._frames.get(index, 0)

    def ended(self) -> list[tuple[int, TaskResult]]:
        return ended_futures(self._pending)

    def stop(self) -> None:
        from distributed import Event

        try:
            Event(self.stop_name, client=self.client).set()
            self.client.cancel(list(self._pending))
        except Exception:  # noqa: BLE001 — the cluster may be gone already; closing follows
            pass


@contextmanager
def connect(scheduler: str, tasks: list[RunTask], cache_dir: Path | None,
            before_start: Callable[[], None] | None = None) -> Iterator[DaskEngine]:
    """A :class:`DaskEngine` for ``tasks`` on the cluster at ``scheduler``;
    :class:`~agvviz.errors.InputError` when Dask is missing or the scheduler cannot be reached.
    ``before_start`` is called once it answered, before any run starts."""
    distributed = import_distributed()
    try:
        distributed.comm.resolve_address(scheduler)  # a malformed address or unknown host: at once
        client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {' '.join(str(exc).split())}") from None
    try:
        if before_start is not None:
            before_start()
        yield DaskEngine(client, tasks, cache_dir)
    finally:
        client.close()
