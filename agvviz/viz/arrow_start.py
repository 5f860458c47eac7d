"""Keep pandas out of a run's start-up (issue 27).

Rerun turns every logged numpy array into an Arrow array with ``pyarrow.array``. On its first
call pyarrow's pandas shim (``pyarrow.lib._pandas_api``) imports pandas only to ask whether the
value is a pandas Series, Index or Categorical — ≈0.3–0.5 s of every ``agvviz`` process that logs,
for a library no agvviz code uses. :func:`keep_pandas_unloaded` lets that first look-up find no
pandas: the shim then answers "not a pandas object" without importing it (numpy and list inputs
convert exactly as before). Whatever really needs pandas (``Table.to_pandas``) still imports it:
the shim retries the import for those calls.
"""

from __future__ import annotations

import sys


class _NoPandasFinder:
    """A meta-path finder under which ``import pandas`` fails (installed for one call only)."""

    @staticmethod
    def find_spec(name, path=None, target=None):
        if name == "pandas" or name.startswith("pandas."):
            raise ImportError("pandas is not imported at agvviz's start-up")
        return None


def keep_pandas_unloaded() -> None:
    """Let pyarrow's pandas shim make its one optional import attempt now, with pandas hidden."""
    if "pandas" in sys.modules:
        return  # already paid for (another library imported it): nothing to save
    import numpy as np
    import pyarrow as pa

    sys.meta_path.insert(0, _NoPandasFinder)
    try:
        pa.array(np.zeros(1, dtype=np.bool_))  # the shim's first, optional look-up
    finally:
        sys.meta_path.remove(_NoPandasFinder)
