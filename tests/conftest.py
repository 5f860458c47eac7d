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
