"""The error budget's counterfactual runs behind ``agvviz budget`` and ``agvviz run --budget``.

For an agvviz recording made under a non-ideal realism profile (:mod:`agvviz.sim.realism`),
each error source that is on is switched off in turn: the scenario is recorded again with the
same seed and options plus ``realism_off=<existing>,<source>``
(:func:`agvviz.scenarios.record`), replayed with the same run settings
(:func:`agvviz.app.run.run_recording`), its run loaded back (:func:`agvviz.app.run_series.load_run`)
and compared with the replay of the recording itself. The mathematics — shares, the remainder,
per-frame differences, the table — is :mod:`agvviz.evaluation.error_budget`'s. Returns values,
prints nothing.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from agvviz.errors import InputError, RunError
from agvviz.evaluation.error_budget import ErrorBudget, SourceBudget, matched_difference, share
from agvviz.settings import RunSettings, as_dict


# -- what is on -----------------------------------------------------------------------------
def _scenario_of(recording_path: Path) -> dict:
    from agvviz.recording.source import open_recording

    if not Path(recording_path).exists():
        raise InputError(f"{recording_path}: no such file; give an agvviz .mcap recording")
    scenario = open_recording(recording_path).scenario
    if not scenario or "name" not in scenario or "options" not in scenario:
        raise InputError(
            f"{Path(recording_path).name} is not an agvviz recording (no scenario metadata): an error budget "
            "re-records the scenario, so it needs one made by `agvviz record`"
        )
    return scenario


def sources_on(options: dict, scenario: str | None = None) -> list[str]:
    """The error sources of :data:`agvviz.sim.realism.SOURCES` whose parameters differ from the
    ``ideal`` profile's under the scenario options ``options`` (``realism``, ``realism_off``,
    ``realism_set``) — of those the scenario ``scenario`` applies (its module's
    ``realism_sources(options)``; e.g. no slip without odometry), when given."""
    from agvviz import scenarios as scenario_registry
    from agvviz.sim import realism as rl

    realism = rl.make_realism(options["realism"], options.get("realism_off", ""), options.get("realism_set", ""))
    ideal = rl.PROFILES["ideal"].parameters()
    params = realism.parameters()
    if scenario is not None:
        applies = getattr(scenario_registry.get(scenario), "realism_sources", None)
        if applies is not None:
            used = set(applies(options))
            return [s for s in rl.SOURCES if params[s] != ideal[s] and s in used]
    return [s for s in rl.SOURCES if params[s] != ideal[s]]


def _overrides(module, options: dict, off: list[str]) -> list[str]:
    """``key=value`` overrides that rebuild ``options`` (only those differing from the scenario's
    defaults), with ``realism_off`` set to ``off``."""
    defaults = as_dict(module.Options())
    pairs = []
    for key, value in options.items():
        if key == "realism_off" or key not in defaults or defaults[key] == value:
            continue
        pairs.append(f"{key}={value!r}" if isinstance(value, float) else f"{key}={value}")
    if off:
        pairs.append(f"realism_off={','.join(off)}")
    return pairs


# -- the budget -----------------------------------------------------------------------------
def _per_frame(run_path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, time_ns, position error mm with NaN where unsolved) of a run ``.rrd``."""
    from agvviz.app.run_series import load_run

    run = load_run(run_path)
    errors = np.where(run.solved, run.errors["position"], np.nan)
    return run.frames, run.time_ns, errors


def error_budget(
    recording_path: str | Path,
    settings: RunSettings = RunSettings(),
    *,
    work_dir: str | Path | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    sources: Sequence[str] | None = None,
    jobs: int | None = 1,
    cache_dir: Path | None | bool = False,
) -> ErrorBudget:
    """The error budget of ``recording_path`` replayed under ``settings``.

    Re-records the scenario (same seed and options) once per error source that is on, with
    that source switched off, and once with every source off (the floor), into ``work_dir``
    (None: a temporary folder removed afterwards; else kept, with the recordings and runs in
    it); replays each with ``settings`` and compares with the replay of the recording itself.
    ``sources`` limits the budget to these (names of :data:`agvviz.sim.realism.SOURCES` or
    ``imaging.<effect>``; default: every source that is on). ``progress(done, total, what)``
    is called before and after each step (one step: a recording or a replay). ``jobs`` and
    ``cache_dir`` are passed to :func:`agvviz.app.run.run_recording`.

    Raises
    ------
    InputError
        Not an agvviz recording (no scenario metadata), an unknown scenario, a scenario with
        no realism options, an ideal recording (nothing to budget) or an unknown source.
    RunError
        The recording's run solved no frame (no RMSE to share out).
    """
    from agvviz import scenarios as scenario_registry
    from agvviz.recording.source import open_recording
    from agvviz.app.run import run_recording

    recording_path = Path(recording_path)
    scenario = _scenario_of(recording_path)
    name, seed, options = scenario["name"], int(scenario.get("seed", 0)), dict(scenario["options"])
    module = scenario_registry.get(name)  # ScenarioError (an InputError): unknown scenario
    if "realism" not in options:
        raise InputError(
            f"{recording_path.name}: scenario {name} was recorded without realism options (by an agvviz "
            "before them, or a scenario without error sources); nothing to budget — record it again with "
            "--set realism=typical"
        )
    on = sources_on(options, name)
    if not on:
        raise InputError(
            f"{recording_path.name} was recorded under the ideal world (realism={options['realism']}"
            + (f", realism_off={options.get('realism_off')}" if options.get("realism_off") else "")
            + "): no error source is on, nothing to budget; record it with --set realism=typical"
        )
    if sources is not None:
        from agvviz.sim import realism as rl

        for s in sources:
            group, _, effect = s.partition(".")
            if s not in rl.SOURCES and not (group == "imaging" and effect in rl.IMAGING_EFFECTS):
                raise InputError(f"unknown error source {s!r}; sources on in this recording: {', '.join(on)}")
        budget_sources = list(dict.fromkeys(sources))
    else:
        budget_sources = on
    existing = [s.strip() for s in str(options.get("realism_off", "")).split(",") if s.strip()]

    temporary = work_dir is None
    work = Path(tempfile.mkdtemp(prefix="agvviz-budget-")) if temporary else Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    total = 2 * len(budget_sources) + 4  # replay it, reproduce it, per source and the floor
    done = 0

    def step(what: str) -> None:
        if progress is not None:
            progress(done, total, what)

    def finished() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total, "")

    def replay(path: Path, label: str):
        step(f"replaying {label}")
        outcome = run_recording(path, settings, work / f"{label}.rrd", jobs=jobs, cache_dir=cache_dir)
        finished()
        return outcome

    def rerecord(off: list[str], label: str) -> Path:
        step(f"recording {label}")
        out = work / f"{label}.mcap"
        scenario_registry.record(name, out, seed=seed, overrides=_overrides(module, options, off))
        finished()
        return out

    try:
        warnings: list[str] = []
        base = replay(recording_path, "all_on")
        rmse_all = base.summary["position_error_mm"]["rmse"]
        if rmse_all is None:
            raise RunError(f"{recording_path.name}: the run solved no frame; no position error to budget")
        frames, time_all, err_all = _per_frame(base.out_path)
        # The re-recorded worlds are exact counterfactuals only if this agvviz records the
        # recording itself again byte for byte.
        again = rerecord(existing, "reproduced")
        if open_recording(again).sha256() != open_recording(recording_path).sha256():
            warnings.append(
                "re-recording the scenario with the recording's seed and options does not give the same file "
                "(another agvviz version?); the budget compares worlds recorded by this version"
            )
        again.unlink(missing_ok=True)
        results = []
        for source in budget_sources:
            label = "off_" + source.replace(".", "_")
            path = rerecord(existing + [source], label)
            outcome = replay(path, label)
            _, time_off, err_off = _per_frame(outcome.out_path)
            rmse_off = outcome.summary["position_error_mm"]["rmse"]
            results.append(SourceBudget(
                source=source,
                rmse_off_mm=rmse_off,
                share=share(rmse_all, rmse_off),
                solved_off=int(outcome.summary["solved"]),
                time_ns=time_off,
                position_error_off_mm=err_off,
                delta_mm=matched_difference(time_all, err_all, time_off, err_off),
            ))
            if rmse_off is None:
                warnings.append(f"with {source} off no frame was solved; its share is unknown")
        floor = replay(rerecord(existing + on, "all_off"), "all_off")
        return ErrorBudget(
            recording=recording_path,
            scenario=name,
            seed=seed,
            profile=str(options["realism"]),
            realism_off=",".join(existing),
            settings=dict(base.manifest.get("settings", as_dict(settings))),
            rmse_all_mm=float(rmse_all),
            solved_all=int(base.summary["solved"]),
            floor_rmse_mm=floor.summary["position_error_mm"]["rmse"],
            time_ns=time_all,
            frames=frames,
            position_error_all_mm=err_all,
            sources=results,
            warnings=warnings,
        )
    finally:
        if temporary:
            shutil.rmtree(work, ignore_errors=True)
