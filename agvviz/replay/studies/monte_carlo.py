"""Trials stage: solve every trial of a Monte-Carlo study recording (``p4p_monte_carlo``).

A study recording holds no camera image: a calibration, then one corner-observation message
per noisy trial of each cell (a fixed true pose, code, point count and pixel σ). The stage
reads the cells from the messages (:func:`collect`), solves every trial with the study's whole
solver set (:data:`~agvviz.replay.studies.monte_carlo_cells.SOLVERS`: a study recording exists
to compare them, so a run does not solve ``settings.solver`` alone) and scores t against truth
and the Cramér–Rao bound (:func:`~agvviz.replay.studies.monte_carlo_cells.evaluate_cell`, LM
budget :data:`~agvviz.replay.studies.monte_carlo_cells.MC_LM_MAX_ITERATIONS`, not the run's
``lm_max_iterations``). The summary names the study solver the run's pose-solver settings
correspond to (:func:`study_solver`). No file I/O, no Rerun, no printing; the values it hands
on are in :mod:`agvviz.model.studies`.

The other study kind, paper 002's CNOEM grid (``auv_under_ice`` ``mode=grid``), has the same
shape in :mod:`agvviz.replay.studies.cnoem`; :func:`trials_timing` serves both.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping

import numpy as np

from agvviz.errors import RecordingError
from agvviz.model.studies import CellResult, CellTrials, CnoemTrialsOutcome, TrialsOutcome
from agvviz.model.messages import CalibrationMsg
from agvviz.recording.reader import RecordedMessage
from agvviz.recording.roles import RoleMap
from agvviz.model.topics import CORNERS_TOPIC, ROLE_CORNERS
from agvviz.replay.studies import monte_carlo_cells
from agvviz.replay.studies.monte_carlo_cells import LM_VARIANTS, MC_LM_MAX_ITERATIONS, SOLVERS
from agvviz.settings import RunSettings

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


def collect(messages: Iterable[RecordedMessage]) -> tuple[np.ndarray, dict[str, CellTrials]]:
    """(K, cells) from a p4p_monte_carlo recording's messages (file order): the calibration and
    every corner-observation message (role ``corners``) that carries a ``cell``. Raises
    :class:`RecordingError` when either is missing or a trial message is malformed."""
    K = None
    conditions: dict[str, tuple[np.ndarray, np.ndarray, float]] = {}  # cell id → points, truth, σ
    pixels: dict[str, list[np.ndarray]] = {}  # cell id → every trial's corners
    for message in messages:
        value = message.value
        if isinstance(value, CalibrationMsg):
            K = value.camera.K
        elif message.role == ROLE_CORNERS and isinstance(value, dict) and "cell" in value:
            try:
                marker = value["markers"][0]
                cell_id = str(value["cell"])
                if cell_id not in conditions:
                    conditions[cell_id] = (
                        np.asarray(marker["points_marker_m"], dtype=float),
                        np.asarray(marker["T_cam_marker_truth"], dtype=float),
                        float(value["noise_sigma_px"]),
                    )
                    pixels[cell_id] = []
                points_marker_m, T_cam_marker_truth, sigma_px = conditions[cell_id]
                corners_px = np.asarray(marker["corners_px"], dtype=float)
                n_points = len(points_marker_m)
                if n_points < 4 or points_marker_m.shape != (n_points, 3) or T_cam_marker_truth.shape != (4, 4):
                    raise ValueError("points_marker_m must be (N ≥ 4, 3) and T_cam_marker_truth (4, 4)")
                if not (sigma_px > 0 and np.isfinite(sigma_px)):
                    raise ValueError(f"noise_sigma_px must be a positive number, got {sigma_px}")
                if corners_px.shape != (n_points, 2):
                    raise ValueError(f"corners_px has shape {corners_px.shape}, the cell's points need ({n_points}, 2)")
            except (KeyError, IndexError, TypeError, ValueError) as exc:
                detail = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
                raise RecordingError(
                    f"{message.topic} message at {message.time_ns} ns is not a p4p_monte_carlo trial: {detail}"
                ) from None
            pixels[cell_id].append(corners_px)
    if K is None:
        raise RecordingError("the recording has no camera calibration; record it with the p4p_monte_carlo scenario")
    if not conditions:
        raise RecordingError(
            f"the recording has no corner messages ({CORNERS_TOPIC}) with a 'cell': not a p4p_monte_carlo recording"
        )
    return K, {cell_id: CellTrials(cell_id, *conditions[cell_id], pixels[cell_id]) for cell_id in conditions}


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
    K, cells = collect(messages)
    t0 = time.perf_counter()
    results: dict[str, CellResult] = {}
    done = 0
    for cell_id, cell in cells.items():
        results[cell_id] = monte_carlo_cells.evaluate_cell(cell, K, SOLVERS)
        done += len(cell.pixels_px)
        if progress is not None:
            progress(done)
    solve_s = time.perf_counter() - t0
    counts = sorted({len(cell.pixels_px) for cell in cells.values()})
    warnings = unequal_trials_warnings(counts)
    trials_per_cell = counts[-1]
    checks = monte_carlo_cells.checks(results)
    return TrialsOutcome(
        K=K,
        results=results,
        trials_per_cell=trials_per_cell,
        solvers=SOLVERS,
        report_markdown=monte_carlo_cells.report_markdown(results, trials_per_cell),
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


def unequal_trials_warnings(counts: list[int]) -> list[str]:
    """The study's warning when its cells hold unequal numbers of trials (``counts``: the sorted
    distinct trial counts per cell), for both studies: none when they are equal."""
    if len(counts) <= 1:
        return []
    return [
        f"the study's cells hold unequal numbers of trials ({counts[0]}..{counts[-1]}): the recording "
        "lost trial messages; each cell's statistics use the trials it has"
    ]


def error_statistics(values: np.ndarray) -> dict[str, float | None]:
    """RMSE, median, 95th percentile and maximum of ``values`` (N,) (already absolute), ``None``
    each when empty: the statistics a run summary reports (as
    :func:`agvviz.evaluation.statistics.describe`, which the replay cannot import)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {name: None for name in ("rmse", "median", "p95", "max")}
    return {
        "rmse": float(np.sqrt(np.mean(v**2, axis=-1))),
        "median": float(np.median(v, axis=-1)),
        "p95": float(np.percentile(v, 95, axis=-1)),
        "max": float(np.max(v, axis=-1)),
    }


def _number(value: float) -> float | None:
    """A JSON-ready float: ``None`` for NaN or infinity (no estimate, or no bound)."""
    return float(value) if np.isfinite(value) else None


def _summary(results: dict[str, CellResult], checks: dict, settings: RunSettings, trials_per_cell: int, trials: int) -> dict:
    per_solver = {}
    for name in SOLVERS:
        errors_m = np.concatenate([r.errors_t_m[name] for r in results.values()])
        ratios = np.array([r.stats[name].rmse_t_m / r.crlb_t_m for r in results.values()], dtype=float)
        ratios = ratios[np.isfinite(ratios)]
        error_mm = error_statistics(errors_m[np.isfinite(errors_m)] * 1000.0)
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
