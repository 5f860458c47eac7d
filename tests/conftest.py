"""Shared pytest configuration.

The ``campaign`` marker (issue 10's long robustness campaign) is deselected unless the
``-m`` expression names it: ``pytest -q`` skips it, ``pytest -q -m campaign`` runs it.
"""

from __future__ import annotations


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "campaign: the long robustness campaign (deselected unless -m names 'campaign')"
    )


def pytest_collection_modifyitems(config, items):
    if "campaign" in (config.getoption("markexpr", "") or ""):
        return
    keep, drop = [], []
    for item in items:
        (drop if item.get_closest_marker("campaign") else keep).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


import pytest


@pytest.fixture(autouse=True, scope="session")
def _detection_cache_in_tmp(tmp_path_factory):
    """Runs store detections in a cache folder (agvviz.graph.detect_cache): the suite's go to a
    temporary folder, never the user's ~/.cache (subprocesses inherit the variable)."""
    import os

    folder = tmp_path_factory.mktemp("detection-cache")
    old = os.environ.get("AGVVIZ_CACHE_DIR")
    os.environ["AGVVIZ_CACHE_DIR"] = str(folder)
    yield folder
    if old is None:
        os.environ.pop("AGVVIZ_CACHE_DIR", None)
    else:
        os.environ["AGVVIZ_CACHE_DIR"] = old


#: uwb_room, 3 s at 5 Hz (15 time stamps × 4 wall cameras), the cameras blocked from 1.0 s to
#: 2.0 s, ideal world, seed 4. tests/test_uwb_room.py and tests/test_fusion_views.py both check
#: this one recording and its mean-compensation run, so it is recorded and replayed once.
UWB_ROOM_SMALL = ["duration_s=3", "rate_hz=5", "block_start_s=1.0", "block_end_s=2.0", "realism=ideal"]


@pytest.fixture(scope="session")
def uwb_room_small_run(tmp_path_factory):
    """(recording, outcome) of ``UWB_ROOM_SMALL`` (seed 4) replayed with fusion=mean_compensation.
    Read only: tests must not modify the recording or the run's .rrd."""
    from agvviz import scenario_registry
    from agvviz.runner import run_recording
    from agvviz.settings import RunSettings

    tmp = tmp_path_factory.mktemp("uwb_room_small")
    recording = tmp / "uwb_room.mcap"
    scenario_registry.record("uwb_room", recording, seed=4, overrides=UWB_ROOM_SMALL)
    outcome = run_recording(recording, RunSettings(fusion="mean_compensation"), tmp / "run.rrd")
    return recording, outcome
