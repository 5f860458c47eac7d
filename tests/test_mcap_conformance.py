"""The streaming reader reads every file of the MCAP conformance suite (foxglove/mcap).

Each ``<name>.mcap`` has a ``<name>.json`` listing the records a streaming reader must see;
the reader has to yield exactly its ``Message`` records, without raising or reporting damage.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agvviz.recording.raw import ReadReport
from agvviz.recording.reader import iter_messages

SUITE = Path(__file__).resolve().parents[2] / "shared" / "data" / "mcap_conformance"
FILES = sorted(SUITE.glob("*/*.mcap")) if SUITE.is_dir() else []


@pytest.mark.skipif(not FILES, reason=f"MCAP conformance suite not found at {SUITE}")
@pytest.mark.parametrize("path", FILES, ids=[p.stem for p in FILES])
def test_reads_conformance_file(path):
    expected = json.loads(path.with_suffix(".json").read_text())
    expected_times = [
        int(dict(record["fields"])["log_time"])
        for record in expected["records"]
        if record["type"] == "Message"
    ]
    report = ReadReport()
    times = [m.log_time_ns for m in iter_messages(path, report=report)]
    assert report.problems == []
    assert len(times) == len(expected_times) and report.messages == len(expected_times)
    assert times == expected_times  # file order, as the streaming reader sees it
