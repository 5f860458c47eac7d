"""Everything that calls Rerun: entity paths, the run logger and its modality loggers, the blueprints, read-back.

Only this package imports ``rerun`` — and not on import of the package itself: a run process
hands its logging to a child (:mod:`agvviz.viz.run_process`) and never needs Rerun. The names
below are loaded on first use.
"""

from agvviz.viz.arrow_start import keep_pandas_unloaded

keep_pandas_unloaded()  # before rerun's first Arrow conversion (arrow_start's docstring)

_LAZY = {
    "default_blueprint": "agvviz.viz.blueprints",
    "RunLogError": "agvviz.viz.log_frames",
    "RrdContents": "agvviz.viz.readback",
    "RrdReadError": "agvviz.viz.readback",
    "read_rrd": "agvviz.viz.readback",
    "RunLogger": "agvviz.viz.run_logger",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'agvviz.viz' has no attribute {name!r}")
