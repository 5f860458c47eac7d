"""Trials stage: solve every trial of a Monte-Carlo study recording (``p4p_monte_carlo``).

A study recording holds no camera image: a calibration, then one corner-observation message
per noisy trial of each cell (a fixed true pose, code, point count and pixel σ). The stage
collects the cells (:func:`agvviz.evaluation.monte_carlo.collect`), solves every trial with
the study's whole solver set (:data:`~agvviz.evaluation.monte_carlo.SOLVERS`: a study
recording exists to compare them, so a run does not solve ``settings.solver`` alone) and scores
t against truth and the Cramér–Rao bound (:func:`~agvviz.evaluation.monte_carlo.evaluate_cell`,
LM budget :data:`~agvviz.evaluation.monte_carlo.MC_LM_MAX_ITERATIONS`, not the run's
``lm_max_iterations``). The summary names the study solver the run's pose-solver settings
correspond to (:func:`study_solver`). No file I/O, no Rerun, no printing.

The other study kind, paper 002's CNOEM grid (``auv_under_ice`` ``mode=grid``), has the same
shape in :mod:`agvviz.replay.studies.cnoem`; :func:`trials_timing` serves both.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from agvviz.evaluation import monte_carlo
from agvviz.evaluation.monte_carlo import LM_VARIANTS, MC_LM_MAX_ITERATIONS, SOLVERS, CellResult
from agvviz.evaluation.statistics import describe
from agvviz.model.messages import RecordedMessage
from agvviz.recording.roles import RoleMap
from agvviz.model.topics import ROLE_CORNERS
from agvviz.settings import RunSettings

if TYPE_CHECKING:
    from agvviz.replay.studies.cnoem import CnoemTrialsOutcome

#: Scenarios whose recordings are Monte-Carlo studies for this stage.
TRIALS_SCENARIOS = ("p4p_monte_carlo",)


def is_trials_recording(scenario: dict | None, roles: RoleMap | Mapping[str, str]) -> bool:
    """Whether a recording goes to the trials stage instead of the camera replay: its scenario
    record (:attr:`agvviz.recording.source.Recording.scenario`) names a study scenario and its
    role map (a :class:`RoleMap` or role → topic) places corner observations. A study file that
    lost its scenario record or its corner topic is not one (the run then finds nothing to
    replay and says so)."""
    if not isinstance(scenario, dict) or scenario.get("name") not in TRIALS_SCENARIOS:
        return False
    placed = roles.roles if isinstance(roles, RoleMap) else roles
    return ROLE_CORNERS in placed


def study_solver(settings: RunSettings) -> str | None:
    """The study solver that the run's pose-solver settings correspond to, ``None`` when the
    study has none like it: ``lm`` with ``objective=depth`` → ``lm`` (paper eq 23 from the P4P
    start); ``lm`` with ``objective=pixel`` → ``lm_amb`` under ``ambiguity=lowest_error``, else
    ``lm_pixel`` (continuity and odometry need a previous frame; trials are independent);
    ``p4p``, ``ippe``, ``sqpnp`` → themselves."""
    if settings.solver == "lm":
        if settings.objective == "depth":
            return "lm"
        return "lm_amb" if settings.ambiguity == "lowest_error" else "lm_pixel"
    return settings.solver if settings.solver in SOLVERS else None


@dataclass(frozen=True)
class TrialsOutcome:
    """What the trials stage found. ``summary`` (``{"trials": {...}}``, JSON-ready, depends only
    on the recording) goes into the run summary; ``solve_s`` (wall clock) does not."""

    K: np.ndarray  # (3, 3) the study camera's matrix
    results: dict[str, CellResult]  # cell id → statistics, per-trial errors, CRLB; recording order
    trials_per_cell: int  # the largest number of trials of a cell (all equal unless messages were lost)
    solvers: tuple[str, ...]
    report_markdown: str  # the study report (paper comparison, every cell, the checks)
    checks: dict  # monte_carlo.checks(results)
    summary: dict
    warnings: tuple[str, ...]  # doubts about the numbers (unequal trial counts)
    solve_s: float  # wall time spent solving (s)

    @property
    def trials(self) -> int:
        """Trials solved (each by every solver)."""
        return self.summary["trials"]["trials"]


def replay_trials(
    messages: Iterable[RecordedMessage],
    settings: RunSettings,
    progress: Callable[[int], None] | None = None,
) -> TrialsOutcome:
    """Solve every trial of a study recording's ``messages`` (its calibration and corner
    observations, role-tagged, in file order) with every study solver and score them.

    ``progress(trials_done)`` is called after each cell. Raises
    :class:`~agvviz.errors.RecordingError` when the messages hold no calibration, no trial or
    a malformed trial.
    """
    K, cells = monte_carlo.collect(messages)
    t0 = time.perf_counter()
    results: dict[str, CellResult] = {}
    done = 0
    for cell_id, cell in cells.items():
        results[cell_id] = monte_carlo.evaluate_cell(cell, K, SOLVERS)
        done += len(cell.pixels_px)
        if progress is not None:
            progress(done)
    solve_s = time.perf_counter() - t0
    counts = sorted({len(cell.pixels_px) for cell in cells.values()})
    warnings = []
    if len(counts) > 1:
        warnings.append(
            f"the study's cells hold unequal numbers of trials ({counts[0]}..{counts[-1]}): the recording "
            "lost trial messages; each cell's statistics use the trials it has"
        )
    trials_per_cell = counts[-1]
    checks = monte_carlo.checks(results)
    return TrialsOutcome(
        K=K,
        results=results,
        trials_per_cell=trials_per_cell,
        solvers=SOLVERS,
        report_markdown=monte_carlo.report_markdown(results, trials_per_cell),
        checks=checks,
        summary={"trials": _summary(results, checks, settings, trials_per_cell, done)},
        warnings=tuple(warnings),
        solve_s=solve_s,
    )


def trials_timing(outcome: TrialsOutcome | CnoemTrialsOutcome, wall_time_s: float) -> dict:
    """Wall-clock figures of a study run, either kind (printed, never stored): wall time and
    trials per second (each trial solved by every study solver or method)."""
    timing = {"wall_time_s": float(wall_time_s)}
    if wall_time_s > 0:
        timing["trials_per_s"] = outcome.trials / wall_time_s
    return timing


def _number(value: float) -> float | None:
    """A JSON-ready float: ``None`` for NaN or infinity (no estimate, or no bound)."""
    return float(value) if np.isfinite(value) else None


def _summary(results: dict[str, CellResult], checks: dict, settings: RunSettings, trials_per_cell: int, trials: int) -> dict:
    per_solver = {}
    for name in SOLVERS:
        errors_m = np.concatenate([r.errors_t_m[name] for r in results.values()])
        ratios = np.array([r.stats[name].rmse_t_m / r.crlb_t_m for r in results.values()], dtype=float)
        ratios = ratios[np.isfinite(ratios)]
        error_mm = describe(errors_m[np.isfinite(errors_m)] * 1000.0)
        per_solver[name] = {
            "failed": int(sum(r.stats[name].n_failed for r in results.values())),
            "error_mm": {k: _number(v) if v is not None else None for k, v in error_mm.items()},
            "rmse_over_crlb": {
                "median": _number(np.median(ratios)) if len(ratios) else None,
                "max": _number(np.max(ratios)) if len(ratios) else None,
            },
        }
    return {
        "study": "p4p_monte_carlo",
        "cells": len(results),
        "trials_per_cell": trials_per_cell,
        "trials": trials,
        "solvers": list(SOLVERS),
        "run_solver": {
            "solver": settings.solver,
            "objective": settings.objective,
            "ambiguity": settings.ambiguity,
            "study_solver": study_solver(settings),
        },
        "lm_max_iterations": MC_LM_MAX_ITERATIONS,
        "failed": int(sum(s["failed"] for s in per_solver.values())),
        "per_solver": per_solver,
        "well_conditioned_cells": checks["well_conditioned_cells"],
        "well_conditioned_max_rmse_over_crlb": {
            name: _number(checks["max_rmse_over_crlb"][name]) for name in LM_VARIANTS
        },
        "worse_than_peer": {name: len(checks["worse_than_peer"][name]) for name in LM_VARIANTS},
    }
