"""CNOEM trials stage: solve every trial of a paper 002 grid-study recording (``auv_under_ice``
``mode=grid``) — the second study kind beside the Monte-Carlo one (:mod:`agvviz.replay.studies.monte_carlo`),
in the same shape.

A grid recording holds no camera image: calibrations and extrinsics, then per trial (one
correction cycle of a Table 3 cell) a marker map, the navigation and true poses of every frame
and the noisy corners of every sighting. The stage reads the cycles back
(:func:`read_grid_recording`), solves each with the study's whole method set
(:data:`~agvviz.replay.studies.cnoem_cells.METHODS`: CNOEM from the navigation, CNOEM
multi-start, the window bundle adjustment and the single-frame IPPE baselines — a study
recording exists to compare them, so a run does not solve ``settings.correction`` alone) and
scores the position of each cycle's start frame F against truth and the multi-frame CRLB
(:func:`~agvviz.replay.studies.cnoem_cells.evaluate_trials`). The summary names the method the
run's correction settings correspond to (:func:`study_method`). No file I/O, no Rerun, no
printing; the values it hands on are in :mod:`agvviz.model.studies`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping

import numpy as np

from agvviz.conventions import AGV_FRAME
from agvviz.errors import RecordingError
from agvviz.geometry import se3
from agvviz.model.studies import CnoemCellResult, CnoemTrialsOutcome, CycleTrial, GridCell, RecordedCell
from agvviz.model.messages import CalibrationMsg, PoseMsg
from agvviz.recording.reader import RecordedMessage
from agvviz.recording.roles import RoleMap
from agvviz.model.topics import ROLE_CORNERS, ROLE_MARKER_MAP, ROLE_ODOMETRY, ROLE_TF_STATIC, ROLE_TRUTH
from agvviz.replay.studies.monte_carlo import error_statistics, unequal_trials_warnings
from agvviz.settings import RunSettings
from agvviz.solvers.cnoem import Sighting

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
    from agvviz.replay.studies import cnoem_cells  # (the solvers and agvviz.sim: only when needed)

    cells = read_grid_recording(messages)
    t0 = time.perf_counter()
    results: dict[str, CnoemCellResult] = {}
    done = 0
    for cell_id, recorded in cells.items():
        offset = done
        on_trial = None if progress is None else (lambda k, offset=offset: progress(offset + k))
        results[cell_id] = cnoem_cells.evaluate_trials(
            recorded.cell, recorded.trials, len(recorded.trials), recorded.n_frames, progress=on_trial
        )
        done += len(recorded.trials)
    solve_s = time.perf_counter() - t0
    counts = sorted({len(recorded.trials) for recorded in cells.values()})
    warnings = unequal_trials_warnings(counts)
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
    report = cnoem_cells.report_markdown(list(results.values()), heading)
    return CnoemTrialsOutcome(
        results=results,
        trials_per_cell=trials_per_cell,
        methods=cnoem_cells.METHODS,
        report_markdown=report,
        summary={"cnoem_study": _summary(results, settings, trials_per_cell, done)},
        warnings=tuple(warnings),
        solve_s=solve_s,
    )


def _number(value: float | None) -> float | None:
    """A JSON-ready float: ``None`` for NaN, infinity or no value."""
    return float(value) if value is not None and np.isfinite(value) else None


def _summary(results: dict[str, CnoemCellResult], settings: RunSettings, trials_per_cell: int, trials: int) -> dict:
    from agvviz.replay.studies import cnoem_cells
    from agvviz.replay.studies.cnoem_cells import METHODS, PAPER_BASELINE

    cells = list(results.values())
    s = cnoem_cells.summarise(cells)
    per_method = {}
    for name in METHODS:
        errors_m = np.concatenate([r.errors_m[name] for r in cells])
        ok = errors_m[np.isfinite(errors_m)]
        ratios = np.array([r.rms_m(name) / r.crlb_position_m for r in cells], dtype=float) if len(ok) else np.array([])
        ratios = ratios[np.isfinite(ratios)]
        error_m = {"mean": float(np.mean(ok)) if len(ok) else None, **error_statistics(ok)}
        per_method[name] = {
            "failed": int(sum(r.failures(name) for r in cells)),
            "error_m": {k: _number(v) for k, v in error_m.items()},
            "rms_over_crlb": {
                "median": _number(np.median(ratios)) if len(ratios) else None,
                "max": _number(np.max(ratios)) if len(ratios) else None,
            },
        }
    paper, scope = cnoem_cells.paper_ratio(r.cell for r in cells)
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
        "well_conditioned_cells": sum(cnoem_cells.well_conditioned(r.cell) for r in cells),
    }


def read_grid_recording(messages: Iterable[RecordedMessage]) -> dict[str, RecordedCell]:
    """The cycles of an ``auv_under_ice`` ``mode=grid`` recording's messages (role-tagged, file
    order), grouped by cell id in recording order.

    Each trial starts with its ``/markers/map`` message; its first ``/agv/odometry`` and
    ``/agv/ground_truth`` poses are F's (navigation, truth); every ``/markers/corners`` message
    becomes a sighting placed in F through the navigation and the camera's ``/tf_static``
    extrinsic — the same chain as :class:`agvviz.replay.correct.CorrectionCycle`. Corners are taken as
    ideal pixels (the scenario's cameras have no distortion). Raises
    :class:`~agvviz.errors.RecordingError` when the messages hold no trial or a trial that
    cannot be placed (no calibration or extrinsic for its camera, no pose before its corners, a
    marker not on the map, malformed corners).
    """
    K: dict[str, np.ndarray] = {}
    T_agv_cam: dict[str, np.ndarray] = {}
    # per cell id, in recording order: the cell, its trials (truth and navigation at F, the
    # sightings), its longest trial's frames — the values are built once every message is read
    grid_cells: dict[str, GridCell] = {}
    trials: dict[str, list[tuple[np.ndarray, np.ndarray, list[Sighting]]]] = {}
    n_frames: dict[str, int] = {}
    corners: dict[str, np.ndarray] = {}
    nav_F = truth_F = nav_now = None
    frame_index = -1
    current: list[Sighting] | None = None  # the current trial's sightings
    current_cell: str | None = None
    for m in messages:
        v = m.value
        if isinstance(v, CalibrationMsg):
            K[v.cam_name] = v.camera.K
        elif isinstance(v, list) and m.role == ROLE_TF_STATIC:
            for tf in v:
                if tf.parent_frame == AGV_FRAME and tf.child_frame.startswith("cam_"):
                    T_agv_cam[tf.child_frame[4:]] = tf.T_parent_child
        elif m.role == ROLE_MARKER_MAP and isinstance(v, dict):
            try:
                corners = {str(e["id"]): np.asarray(e["corners_world_m"], dtype=float) for e in v.get("markers", [])}
                for marker_id, corners_world_m in corners.items():
                    if corners_world_m.shape != (4, 3) or not np.all(np.isfinite(corners_world_m)):
                        raise ValueError(f"marker {marker_id}: corners_world_m must be 4 finite points, got shape {corners_world_m.shape}")
            except (KeyError, TypeError, ValueError) as exc:
                raise RecordingError(f"{m.topic} message at {m.time_ns} ns is not a marker map: {_detail(exc)}") from None
            nav_F = truth_F = current = current_cell = None
            frame_index = -1
        elif m.role == ROLE_ODOMETRY and isinstance(v, PoseMsg):
            nav_now = v.T
            frame_index += 1
            if nav_F is None:
                nav_F = v.T
            if current_cell is not None:
                n_frames[current_cell] = max(n_frames[current_cell], frame_index + 1)
        elif m.role == ROLE_TRUTH and isinstance(v, PoseMsg) and truth_F is None:
            truth_F = v.T
        elif m.role == ROLE_CORNERS and isinstance(v, dict):
            try:
                cell = GridCell.from_id(str(v["cell"]))
                cam = str(v["cam_name"])
                if nav_F is None or truth_F is None:
                    raise ValueError("no navigation and ground-truth pose of its trial before it")
                if cam not in K or cam not in T_agv_cam:
                    raise ValueError(f"camera {cam!r} has no calibration or no /tf_static extrinsic {AGV_FRAME} → cam_{cam}")
                seen = []
                for marker in v["markers"]:
                    marker_id = str(marker["id"])
                    if marker_id not in corners:
                        raise ValueError(f"marker {marker_id} is not on the trial's marker map")
                    pixels_px = np.asarray(marker["corners_px"], dtype=float)
                    if pixels_px.shape != (4, 2) or not np.all(np.isfinite(pixels_px)):
                        raise ValueError(f"corners_px must be 4 finite (u, v) pixels, got shape {pixels_px.shape}")
                    seen.append((marker_id, pixels_px))
            except (KeyError, TypeError, ValueError) as exc:
                raise RecordingError(
                    f"{m.topic} message at {m.time_ns} ns is not an auv_under_ice grid trial: {_detail(exc)}"
                ) from None
            if current is None:
                current, current_cell = [], cell.cell_id
                grid_cells.setdefault(current_cell, cell)
                trials.setdefault(current_cell, []).append((truth_F, nav_F, current))
                n_frames[current_cell] = max(n_frames.get(current_cell, 0), frame_index + 1)
            T_F_cam = se3.inverse(nav_F) @ nav_now @ T_agv_cam[cam]
            for marker_id, pixels_px in seen:
                current.append(Sighting(marker_id, cam, frame_index, corners[marker_id], pixels_px, K[cam], T_F_cam))
    if not grid_cells:
        raise RecordingError(
            "the recording has no corner messages (/markers/corners) of a grid trial: not an auv_under_ice "
            "mode=grid recording"
        )
    return {
        cell_id: RecordedCell(cell, [CycleTrial(*trial) for trial in trials[cell_id]], n_frames[cell_id])
        for cell_id, cell in grid_cells.items()
    }


def _detail(exc: Exception) -> str:
    return f"missing {exc}" if isinstance(exc, KeyError) else str(exc)


def trials_from_recording(messages: Iterable[RecordedMessage]) -> dict[str, list[CycleTrial]]:
    """The trials alone of :func:`read_grid_recording`, by cell id."""
    return {cell_id: recorded.trials for cell_id, recorded in read_grid_recording(messages).items()}
