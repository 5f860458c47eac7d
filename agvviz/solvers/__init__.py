"""Single-frame pose solvers: paper 000's P4P and SE(3) LM, and OpenCV peers. Numpy/OpenCV only.

Use :func:`solve` with a name from :data:`SOLVER_NAMES`; see :mod:`agvviz.solvers.registry`.
"""

from agvviz.solvers.registry import SOLVER_NAMES, SolveResult, SolverOptions, solve

__all__ = ["SOLVER_NAMES", "SolveResult", "SolverOptions", "solve"]
