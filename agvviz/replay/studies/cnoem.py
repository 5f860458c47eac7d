"""CNOEM trials stage: solve every trial of a paper 002 grid-study recording (``auv_under_ice``
``mode=grid``) — the second study kind beside the Monte-Carlo one (:mod:`agvviz.replay.studies.monte_carlo`),
in the same shape.

A grid recording holds no camera image: calibrations and extrinsics, then per trial (one
correction cycle of a Table 3 cell) a marker map, the navigation and true poses of every frame
and the noisy corners of every sighting. The stage reads the cycles back
(:func:`agvviz.evaluation.cnoem_study.read_grid_recording`), solves each with the study's whole
method set (:data:`~agvviz.evaluation.cnoem_study.METHODS`: CNOEM from the navigation, CNOEM
multi-start, the window bundle adjustment and the single-frame IPPE baselines — a study
recording exists to compare them, so a run does not solve ``settings.correction`` alone) and
scores the position of each cycle's start frame F against truth and the multi-frame CRLB
(:func:`~agvviz.evaluation.cnoem_study.evaluate_trials`). The summary names the method the run's
correction settings correspond to (:func:`study_method`). No file I/O, no Rerun, no printing.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from agvviz.evaluation.statistics import describe
from agvviz.model.messages import RecordedMessage
from agvviz.recording.roles import RoleMap
from agvviz.model.topics import ROLE_CORNERS
from agvviz.settings import RunSettings

if TYPE_CHECKING:
    from agvviz.evaluation.cnoem_study import CellResult

#: The scenario, and its mode, whose recordings are CNOEM grid studies for this stage.
CNOEM_TRIALS_SCENARIO = ("auv_under_ice", "grid")


def is_cnoem_trials_recording(scenario: dict | None, roles: RoleMap | Mapping[str, str]) -> bool:
    """Whether a recording goes to this stage instead of the correction replay: its scenario
    record (:attr:`agvviz.recording.source.Recording.scenario`) is ``auv_under_ice`` with option
    ``mode=grid`` and its role map (a :class:`RoleMap` or role → topic) places corner
    observations. A route recording of the same scenario is not one (it goes to the correction
    replay), nor is a grid file that lost its scenario record or its corner topic."""
    if not isinstance(scenario, dict) or scenario.get("name") != CNOEM_TRIALS_SCENARIO[0]:
        return False
    options = scenario.get("options")
    if not isinstance(options, dict) or options.get("mode") != CNOEM_TRIALS_SCENARIO[1]:
        return False
    placed = roles.roles if isinstance(roles, RoleMap) else roles
    return ROLE_CORNERS in placed


def study_method(settings: RunSettings) -> str | None:
    """The study method that the run's correction settings correspond to, ``None`` when the
    study has none like it: ``correction=cnoem`` → ``cnoem_multistart`` (the correction cycle
    solves with :func:`~agvviz.solvers.cnoem.solve_cnoem_multistart` from the navigation and
    the IPPE pair, :class:`agvviz.replay.correct.CorrectionCycle`); ``correction=bundle`` →
    ``bundle`` (the same, then the window bundle adjustment). The study solves with
    ``cnoem_update=lm``, so ``cnoem_update=paper`` has no row (``bench/bench_cnoem.py``
    compares the two updates), nor has ``correction=none``."""
    if settings.cnoem_update != "lm":
        return None
    return {"cnoem": "cnoem_multistart", "bundle": "bundle"}.get(settings.correction)


@dataclass(frozen=True)
class CnoemTrialsOutcome:
    """What the stage found. ``summary`` (``{"cnoem_study": {...}}``, JSON-ready, depends only on
    the recording and the run's correction settings) goes into the run summary; ``solve_s``
    (wall clock) does not."""

    results: dict[str, CellResult]  # cell id → per-trial errors, CRLB, convergence; recording order
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


def replay_cnoem_trials(
    messages: Iterable[RecordedMessage],
    settings: RunSettings,
    progress: Callable[[int], None] | None = None,
) -> CnoemTrialsOutcome:
    """Solve every trial of a grid recording's ``messages`` (role-tagged, in file order) with
    every study method and score them.

    ``progress(trials_done)`` is called after each trial. Raises
    :class:`~agvviz.errors.RecordingError` when the messages hold no trial or a malformed one.
    """
    from agvviz.evaluation import cnoem_study  # (the solvers and agvviz.sim: only when needed)

    cells = cnoem_study.read_grid_recording(messages)
    t0 = time.perf_counter()
    results: dict[str, CellResult] = {}
    done = 0
    for cell_id, recorded in cells.items():
        offset = done
        on_trial = None if progress is None else (lambda k, offset=offset: progress(offset + k))
        results[cell_id] = cnoem_study.evaluate_trials(
            recorded.cell, recorded.trials, len(recorded.trials), recorded.n_frames, progress=on_trial
        )
        done += len(recorded.trials)
    solve_s = time.perf_counter() - t0
    counts = sorted({len(recorded.trials) for recorded in cells.values()})
    warnings = []
    if len(counts) > 1:
        warnings.append(
            f"the study's cells hold unequal numbers of trials ({counts[0]}..{counts[-1]}): the recording "
            "lost trial messages; each cell's statistics use the trials it has"
        )
    for cell_id, recorded in cells.items():
        sightings = sorted({len(trial.sightings) for trial in recorded.trials})
        if len(sightings) > 1:
            warnings.append(
                f"cell {cell_id}: its trials hold unequal numbers of sightings ({sightings[0]}..{sightings[-1]}): the "
                "recording lost corner messages; the cell's CRLB is its first trial's"
            )
    trials_per_cell = counts[-1]
    n_trials = f"{counts[0]}..{counts[-1]}" if len(counts) > 1 else str(counts[0])
    heading = (
        f"# Paper 002 §3.1 simulation study (Table 3) from the recording: {len(results)} "
        f"cell{'s' if len(results) > 1 else ''} × {n_trials} trials"
    )
    report = cnoem_study.report_markdown(list(results.values()), heading)
    return CnoemTrialsOutcome(
        results=results,
        trials_per_cell=trials_per_cell,
        methods=cnoem_study.METHODS,
        report_markdown=report,
        summary={"cnoem_study": _summary(results, settings, trials_per_cell, done)},
        warnings=tuple(warnings),
        solve_s=solve_s,
    )


def _number(value: float | None) -> float | None:
    """A JSON-ready float: ``None`` for NaN, infinity or no value."""
    return float(value) if value is not None and np.isfinite(value) else None


def _summary(results: dict[str, CellResult], settings: RunSettings, trials_per_cell: int, trials: int) -> dict:
    from agvviz.evaluation import cnoem_study
    from agvviz.evaluation.cnoem_study import METHODS, PAPER_BASELINE

    cells = list(results.values())
    s = cnoem_study.summarise(cells)
    per_method = {}
    for name in METHODS:
        errors_m = np.concatenate([r.errors_m[name] for r in cells])
        ok = errors_m[np.isfinite(errors_m)]
        ratios = np.array([r.rms_m(name) / r.crlb_position_m for r in cells], dtype=float) if len(ok) else np.array([])
        ratios = ratios[np.isfinite(ratios)]
        error_m = {"mean": float(np.mean(ok)) if len(ok) else None, **describe(ok)}
        per_method[name] = {
            "failed": int(sum(r.failures(name) for r in cells)),
            "error_m": {k: _number(v) for k, v in error_m.items()},
            "rms_over_crlb": {
                "median": _number(np.median(ratios)) if len(ratios) else None,
                "max": _number(np.max(ratios)) if len(ratios) else None,
            },
        }
    paper, scope = cnoem_study.paper_ratio(r.cell for r in cells)
    bounds_m = [r.crlb_position_m for r in cells]
    return {
        "study": "auv_under_ice grid",
        "cells": len(cells),
        "cell_ids": list(results),
        "trials_per_cell": trials_per_cell,
        "trials": trials,
        "methods": list(METHODS),
        "run_setting": {
            "correction": settings.correction,
            "cnoem_update": settings.cnoem_update,
            "study_method": study_method(settings),
        },
        "failed": int(sum(m["failed"] for m in per_method.values())),
        "per_method": per_method,
        "crlb_position_m": {  # None where no cell has a bound (σ = 0)
            "min": _number(np.nanmin(bounds_m)) if np.isfinite(bounds_m).any() else None,
            "max": _number(np.nanmax(bounds_m)) if np.isfinite(bounds_m).any() else None,
        },
        "cnoem_over_ippe": {
            "baseline": PAPER_BASELINE,
            "ratio_of_means": _number(s.ratio_of_means[PAPER_BASELINE]),
            "paper": paper,
            "paper_scope": scope,
        },
        "cnoem_right_minimum": {
            "all": _number(s.converged_fraction),
            "well_conditioned": _number(s.converged_fraction_well),
            "multistart": _number(s.converged_fraction_multistart),
        },
        "well_conditioned_cells": sum(cnoem_study.well_conditioned(r.cell) for r in cells),
    }
