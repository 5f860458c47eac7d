"""Everything that calls Rerun: entity paths, the run logger, the default blueprint, read-back.

Only this package imports ``rerun``.
"""

from agvviz.viz.blueprint import default_blueprint
from agvviz.viz.readback import RrdContents, RrdReadError, read_rrd
from agvviz.viz.run_logger import RunLogError, RunLogger

__all__ = ["RrdContents", "RrdReadError", "RunLogError", "RunLogger", "default_blueprint", "read_rrd"]
