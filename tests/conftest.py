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
