"""The study stages' values: the trials of a study recording, each cell's figures, the outcome.

Two study kinds, each a recording without camera images that a run solves trial by trial
(:mod:`agvviz.replay.studies`):

* paper 000 §6 Monte-Carlo (``p4p_monte_carlo``): :class:`CellTrials` in, :class:`SolverStats` and
  :class:`CellResult` per cell, :class:`TrialsOutcome` for the run;
* paper 002 §3.1 CNOEM grid (``auv_under_ice`` ``mode=grid``): :class:`GridCell` and
  :class:`CycleTrial` (also drawn by :mod:`agvviz.sim.auv`), :class:`RecordedCell` in,
  :class:`CnoemCellResult` per cell, :class:`CnoemSummary` over cells,
  :class:`CnoemTrialsOutcome` for the run.

Read by the study logger (:mod:`agvviz.viz.log_studies`), the study reports
(the same module's report writers) and the benches.
Frozen: each is built complete.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from agvviz.solvers.cnoem import Sighting

# -- paper 000 §6 Monte-Carlo study ---------------------------------------------------------------


@dataclass(frozen=True)
class CellTrials:
    """All trials of one cell: pixels (T, N, 2), the marker points (N, 3), truth, σ."""

    cell_id: str
    points_marker_m: np.ndarray
    T_cam_marker_truth: np.ndarray
    sigma_px: float
    pixels_px: list = field(default_factory=list)


@dataclass(frozen=True)
class SolverStats:
    """One solver on one cell: solves that succeeded and failed, the statistics of t."""

    n_ok: int
    n_failed: int
    mean_t_m: np.ndarray  # (3,)
    var_t_m2: np.ndarray  # (3,) sample variance (ddof 1)
    rmse_t_m: float  # sqrt(mean ‖t̂ − t‖²)


@dataclass(frozen=True)
class CellResult:
    """One Monte-Carlo cell: its conditions, its CRLB and every solver's statistics."""

    cell_id: str
    sigma_px: float
    n_points: int
    tilt_deg: float
    code_side_px: float
    crlb_t_m: float  # sqrt(trace) of the CRLB position block
    crlb_var_t_m2: np.ndarray  # (3,) diagonal of the CRLB position block
    stats: dict[str, SolverStats]
    #: solver → (trials,) ‖t̂ − t‖ of every trial in recording order (m), NaN where it failed.
    errors_t_m: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class TrialsOutcome:
    """What the trials stage found. ``summary`` (``{"trials": {...}}``, JSON-ready, depends only
    on the recording) goes into the run summary; ``solve_s`` (wall clock) does not."""

    K: np.ndarray  # (3, 3) the study camera's matrix
    results: dict[str, CellResult]  # cell id → statistics, per-trial errors, CRLB; recording order
    trials_per_cell: int  # the largest number of trials of a cell (all equal unless messages were lost)
    solvers: tuple[str, ...]
    report_markdown: str  # the study report (paper comparison, every cell, the checks)
    checks: dict  # agvviz.replay.studies.monte_carlo_cells.checks(results)
    summary: dict
    warnings: tuple[str, ...]  # doubts about the numbers (unequal trial counts)
    solve_s: float  # wall time spent solving (s)

    @property
    def trials(self) -> int:
        """Trials solved (each by every solver)."""
        return self.summary["trials"]["trials"]


# -- paper 002 §3.1 CNOEM grid study --------------------------------------------------------------


@dataclass(frozen=True)
class GridCell:
    """One cell of the paper's Table 3 grid."""

    distance_m: float
    lateral_fraction: float
    vertical_fraction: float
    speed_mps: float
    sigma_px: float

    @property
    def cell_id(self) -> str:
        return (
            f"L{self.distance_m:g}_X{self.lateral_fraction:g}L_Y{self.vertical_fraction:g}L"
            f"_v{self.speed_mps:g}_s{self.sigma_px:g}"
        )

    @classmethod
    def from_id(cls, cell_id: str) -> "GridCell":
        """Inverse of :attr:`cell_id`; raises ValueError for text that is not a cell id."""
        m = re.fullmatch(r"L([\d.]+)_X([\d.]+)L_Y([\d.]+)L_v([\d.]+)_s([\d.]+)", cell_id)
        if m is None:
            raise ValueError(f"not a grid cell id: {cell_id!r} (expected e.g. L10_X0.2L_Y0.1L_v1_s1)")
        return cls(*(float(g) for g in m.groups()))

    @property
    def on_axis(self) -> bool:
        return self.lateral_fraction == 0.0 and self.vertical_fraction == 0.0


@dataclass(frozen=True)
class CycleTrial:
    """One Monte-Carlo trial: truth, the navigation's start, noisy sightings.

    T_world_F_truth, T_world_F_nav : (4, 4). sightings : noisy sightings (world corners).
    """

    T_world_F_truth: np.ndarray
    T_world_F_nav: np.ndarray
    sightings: list[Sighting]


@dataclass(frozen=True)
class RecordedCell:
    """One cell's trials read back from a recording; ``n_frames`` the frames (navigation poses)
    of its longest trial."""

    cell: GridCell
    trials: list[CycleTrial] = field(default_factory=list)
    n_frames: int = 0


@dataclass(frozen=True)
class CnoemCellResult:
    """Statistics of one cell. errors_m[method] : (trials,) position errors, NaN where failed."""

    cell: GridCell
    n_frames: int
    n_sightings: int
    crlb_position_m: float
    condition: float
    errors_m: dict[str, np.ndarray]
    converged_right: np.ndarray
    converged_right_multistart: np.ndarray
    cnoem_iterations: np.ndarray

    def mean_m(self, method: str) -> float:
        return float(np.nanmean(self.errors_m[method]))

    def rms_m(self, method: str) -> float:
        return float(np.sqrt(np.nanmean(self.errors_m[method] ** 2)))

    def failures(self, method: str) -> int:
        return int(np.sum(np.isnan(self.errors_m[method])))


@dataclass(frozen=True)
class CnoemSummary:
    """Grid-level figures (see :func:`agvviz.replay.studies.cnoem_cells.summarise`)."""

    ratio_of_means: dict[str, float] = field(default_factory=dict)
    mean_of_ratios: dict[str, float] = field(default_factory=dict)
    rms_over_crlb_well: dict[str, float] = field(default_factory=dict)
    rms_over_crlb_singular: dict[str, float] = field(default_factory=dict)
    converged_fraction: float = float("nan")
    converged_fraction_well: float = float("nan")
    converged_fraction_multistart: float = float("nan")
    cnoem_failures: int = 0


@dataclass(frozen=True)
class CnoemTrialsOutcome:
    """What the stage found. ``summary`` (``{"cnoem_study": {...}}``, JSON-ready, depends only on
    the recording and the run's correction settings) goes into the run summary; ``solve_s``
    (wall clock) does not."""

    results: dict[str, CnoemCellResult]  # cell id → per-trial errors, CRLB, convergence; recording order
    trials_per_cell: int  # the largest number of trials of a cell (all equal unless messages were lost)
    methods: tuple[str, ...]
    report_markdown: str  # the study report (paper comparison, every cell)
    summary: dict
    warnings: tuple[str, ...]  # doubts about the numbers (lost trials or sightings)
    solve_s: float  # wall time spent solving (s)

    @property
    def trials(self) -> int:
        """Trials solved (each by every method)."""
        return self.summary["cnoem_study"]["trials"]
