"""Everything that calls Rerun: entity paths, the run logger and its modality loggers, the blueprints, read-back.

Only this package imports ``rerun``.
"""

from agvviz.viz.arrow_start import keep_pandas_unloaded

keep_pandas_unloaded()  # before rerun's first Arrow conversion (arrow_start's docstring)


from agvviz.viz.blueprints import default_blueprint
from agvviz.viz.log_frames import RunLogError
from agvviz.viz.readback import RrdContents, RrdReadError, read_rrd
from agvviz.viz.run_logger import RunLogger

__all__ = ["RrdContents", "RrdReadError", "RunLogError", "RunLogger", "default_blueprint", "read_rrd"]
