"""Several runs of one recording in one pass (issue 27, :mod:`agvviz.replay.detect.lockstep`):
followers get the lead's messages and detections in order, and whatever ends early — the lead,
a follower — never leaves another waiting."""

from __future__ import annotations

import threading

import pytest

from agvviz.model.messages import RecordedMessage
from agvviz.recording.reader import ReadReport
from agvviz.replay.detect.lockstep import MAX_QUEUED, LeadFailed, Lockstep, LockstepMismatch

ROLES = {"camera/image": "/cam/image"}


class _Detections:
    def __init__(self, keyframe: bool):
        self.keyframe = keyframe


class _Feed:
    """A stand-in detect-stage feed: ``n`` messages, every other one with detections."""

    def __init__(self, n: int, fail_at: int | None = None):
        self.n, self.fail_at = n, fail_at
        self.entered = self.exited = False
        self.params = "params"

    def __enter__(self):
        self.entered = True
        return self

    def __exit__(self, *exc):
        self.exited = True

    def annotate(self, messages):
        for i in range(self.n):
            if i == self.fail_at:
                raise RuntimeError("the lead's own failure")
            message = RecordedMessage(topic="/cam/image", log_time_ns=i, schema_name="", value=None, role="camera/image")
            yield message, (_Detections(i % 4 == 0) if i % 2 == 0 else None)


def _lead(lockstep: Lockstep, feed: _Feed, report: ReadReport) -> list:
    tee = lockstep.tee(feed, ROLES, "log", report)
    try:
        with tee as f:
            return list(f.annotate(iter(())))
    finally:
        lockstep.lead_done()


def _follow(lockstep: Lockstep, index: int, out: dict, roles=ROLES, time_source="log") -> threading.Thread:
    def run():
        feed = lockstep.follower(index, "params", roles, time_source)
        try:
            with feed as f:
                out[index] = (list(f.annotate(iter(()))), feed)
        except Exception as exc:  # noqa: BLE001 — the test looks at it
            out[index] = exc
        finally:
            lockstep.close(index)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_followers_get_the_leads_messages_in_order_and_its_read_report():
    n = 5 * MAX_QUEUED  # more than a queue holds: the lead waits for the followers
    lockstep, out = Lockstep(2), {}
    threads = [_follow(lockstep, k, out) for k in range(2)]
    report = ReadReport(messages=7, chunks_ok=1, chunks_lost=0, problems=["a problem"])
    lead = _lead(lockstep, _Feed(n), report)
    for thread in threads:
        thread.join(timeout=30)
    assert len(lead) == n
    for k in range(2):
        items, feed = out[k]
        assert [m.time_ns for m, _ in items] == list(range(n))
        assert all(a is b for (_, a), (_, b) in zip(items, lead))  # shared, not copied
        assert feed.read_report is report
        assert (feed.keyframes, feed.tracked_frames) == (n // 4, n // 2 - n // 4)


def test_a_lead_that_fails_part_way_ends_its_followers():
    lockstep, out = Lockstep(1), {}
    thread = _follow(lockstep, 0, out)
    with pytest.raises(RuntimeError, match="own failure"):
        _lead(lockstep, _Feed(3 * MAX_QUEUED, fail_at=2 * MAX_QUEUED), ReadReport())
    thread.join(timeout=30)
    assert isinstance(out[0], LeadFailed)


def test_a_lead_that_fails_before_reading_ends_its_followers():
    lockstep, out = Lockstep(2), {}
    threads = [_follow(lockstep, k, out) for k in range(2)]
    lockstep.lead_done()  # e.g. its output could not be written: it never reached its messages
    for thread in threads:
        thread.join(timeout=30)
    assert all(isinstance(out[k], LeadFailed) for k in range(2))


def test_a_follower_that_stops_does_not_hold_the_lead_or_the_others():
    lockstep, out = Lockstep(2), {}
    lockstep.close(0)  # follower 0 failed before it read anything (it never will)
    thread = _follow(lockstep, 1, out)
    n = 4 * MAX_QUEUED
    done = []
    lead = threading.Thread(target=lambda: done.append(_lead(lockstep, _Feed(n), ReadReport())), daemon=True)
    lead.start()
    lead.join(timeout=30)
    thread.join(timeout=30)
    assert not lead.is_alive() and len(done[0]) == n
    assert len(out[1][0]) == n


def test_a_follower_that_reads_other_topics_is_refused():
    lockstep, out = Lockstep(1), {}
    thread = _follow(lockstep, 0, out, time_source="header")
    lead = _lead(lockstep, _Feed(3), ReadReport())
    thread.join(timeout=30)
    assert len(lead) == 3
    assert isinstance(out[0], LockstepMismatch)
