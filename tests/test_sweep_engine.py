"""The local sweep engine's pool (agvviz.app.cluster.LocalEngine): its processes end as soon as
nothing is left for them (issue 27: idle, they were alive at the sweep's peak of memory), and
not before — a lead still detecting, a setting still solving on the pool, or a task not yet
given out (a failed lead's successor detects on the pool) keeps it."""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future

from agvviz.app import cluster


class _Pool:
    def __init__(self):
        self.submitted: list[Future] = []
        self.shut_down = False
        self._processes = {}

    def submit(self, fn, *args):
        assert not self.shut_down, "a task went to the pool after it was let go"
        future = Future()
        self.submitted.append(future)
        return future

    def shutdown(self, wait=True, cancel_futures=False):
        self.shut_down = True


class _Here:
    def __init__(self, pool):
        self.executor = pool
        self.detected: deque[int] = deque()
        self.results: dict[int, cluster.TaskResult] = {}
        self.given: list[tuple[int, bool]] = []

    def add(self, index, lead=False):
        self.given.append((index, lead))


def _engine(tasks: int) -> cluster.LocalEngine:
    engine = object.__new__(cluster.LocalEngine)  # without its processes: a pool and a thread of stand-ins
    engine.tasks, engine.cache_dir = [object()] * tasks, None
    engine.pool = _Pool()
    engine.here = _Here(engine.pool)
    engine._pending, engine._here, engine._given, engine._detecting = {}, set(), set(), set()
    engine._pool_processes = None
    return engine


def _released(engine) -> bool:
    return engine.pool.shut_down and engine.here.executor is None


def test_two_settings_let_the_pool_go_once_the_lead_has_detected():
    engine = _engine(2)
    engine.start_lead(0)
    assert not _released(engine) and engine.ended() == []
    assert not _released(engine)  # the lead still detects on the pool
    engine.here.detected.append(0)
    assert engine.detected() == [0]
    engine.start_followers([1])  # the last setting runs in the sweep process
    assert _released(engine)


def test_four_settings_keep_the_pool_while_it_solves():
    engine = _engine(4)
    engine.start_lead(0)
    engine.here.detected.append(0)
    engine.detected()
    engine.start_followers([1, 2, 3])
    assert len(engine.pool.submitted) == 2 and not _released(engine)
    engine.pool.submitted[0].set_result(cluster.TaskResult())
    assert [i for i, _ in engine.ended()] == [1] and not _released(engine)
    engine.pool.submitted[1].set_result(cluster.TaskResult())
    assert [i for i, _ in engine.ended()] == [2] and _released(engine)


def test_a_failed_lead_keeps_the_pool_for_the_setting_that_leads_next():
    engine = _engine(3)
    engine.start_lead(0)
    engine.here.results[0] = cluster.TaskResult(error="RunError: boom")  # failed before it detected
    assert [i for i, _ in engine.ended()] == [0]
    assert not _released(engine)  # tasks 1 and 2 are not given out yet
    engine.start_lead(1)  # what run_sweep_tasks does next
    engine.here.detected.append(1)
    engine.detected()
    engine.start_followers([2])
    assert _released(engine)


def test_run_sweep_tasks_lets_the_pool_go_and_gives_every_task_out(monkeypatch):
    """The loop itself (run_sweep_tasks) on the stand-ins: two groups of two settings (two
    recordings); the pool is let go only after both leads detected."""
    import json
    from pathlib import Path

    engine = _engine(4)
    tasks = [cluster.RunTask(Path(f"r{i // 2}.mcap"), None, Path(f"o{i}.rrd")) for i in range(4)]
    engine.tasks = tasks
    keys = {id(t): (str(t.recording), json.dumps({})) for t in tasks}
    monkeypatch.setattr(cluster, "detection_key", lambda task: keys[id(task)])
    finished = []

    detected = set()

    def step():  # the sweep process's thread: a lead detects, then each task given to it ends
        for index, lead in list(engine.here.given):
            if lead and index not in detected:
                detected.add(index)
                engine.here.detected.append(index)
                return
            if index not in engine.here.results:
                engine.here.results[index] = cluster.TaskResult()
                return

    engine.busy = lambda: (step() or True) and bool(engine._pending or engine._here)
    results = cluster.run_sweep_tasks(engine, tasks, on_result=lambda i, r: finished.append(i))
    assert detected == {0, 2}  # each recording's lead, once
    assert sorted(finished) == [0, 1, 2, 3] and all(r.error is None for r in results)
    assert _released(engine) and engine.pool.submitted == []
