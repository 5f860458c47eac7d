"""Library API behind ``agvviz budget``: the error budget of a run, by re-recording.

For an agvviz recording made under a non-ideal realism profile (:mod:`agvviz.sim.realism`),
each error source that is on is switched off in turn: the scenario is recorded again with the
same seed and options plus ``realism_off=<existing>,<source>``
(:func:`agvviz.scenarios.record`), replayed with the same run settings
(:func:`agvviz.replay.run.run_recording`) and compared with the replay of the recording itself.
Every source draws from its own random stream, so that counterfactual world differs from the
original only by the source switched off: the budget is exact, not a Monte-Carlo estimate.

The share of the position error a source causes is a share of the *mean squared* error::

    share(source) = (rmse_all² − rmse_off²) / rmse_all²

Variances, not RMSEs, because independent error sources add in the mean square (the RMSE of
the sum of independent errors is the root of the sum of their squares): with independent,
additive sources the shares are fractions of one total that sum to 1 less the floor's part.
Sources interact, however — a bump that tilts the camera changes how much a calibration error
costs, a dropped frame removes a frame from the RMSE, a solver is not linear — so the shares
need not sum to 1, and one may even be negative (switching that source off made the error
larger). :attr:`ErrorBudget.interaction` is the remainder ``1 − Σ shares`` ("interaction /
other"): what the sources cause only together, plus the floor. The floor itself,
:attr:`ErrorBudget.floor_rmse_mm`, is the RMSE of the ideal world (every source off: only the
solver, the detector and the ideal profile's own blur and noise remain).

The per-frame differences (:attr:`SourceBudget.delta_mm` = error with every source on − error
with this one off, mm, on the frames both runs solved, matched by their time stamp) show *when*
a source costs what it costs. Returns values, prints nothing.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from agvviz.errors import InputError, RunError
from agvviz.settings import RunSettings, as_dict

#: Name of the remainder ``1 − Σ shares`` in tables and the ``.rrd``.
INTERACTION = "interaction/other"


@dataclass
class SourceBudget:
    """One error source: the run with it switched off and its share of the position error."""

    source: str
    rmse_off_mm: float | None  # position RMSE with this source off (None: no frame solved)
    share: float  # (rmse_all² − rmse_off²) / rmse_all² (NaN when rmse_all is 0 or rmse_off None)
    solved_off: int  # frames solved with the source off
    time_ns: np.ndarray  # per frame of the run with the source off (its time stamps)
    position_error_off_mm: np.ndarray  # per frame, NaN where not solved
    delta_mm: np.ndarray  # per frame of time_ns: error all on − error this off (NaN: either unsolved)


@dataclass
class ErrorBudget:
    """The error budget of one recording under one set of run settings."""

    recording: Path
    scenario: str
    seed: int
    profile: str  # the realism profile the recording was made under
    realism_off: str  # what the recording itself already had switched off
    settings: dict
    rmse_all_mm: float  # position RMSE of the recording as it is
    solved_all: int
    floor_rmse_mm: float | None  # every source off: the ideal world's RMSE
    time_ns: np.ndarray  # per frame of the recording's run
    frames: np.ndarray  # frame index per entry of time_ns
    position_error_all_mm: np.ndarray  # per frame, NaN where not solved
    sources: list[SourceBudget] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def interaction(self) -> float:
        """``1 − Σ shares``: what the sources cause only together (and the floor's part)."""
        return 1.0 - float(sum(s.share for s in self.sources if math.isfinite(s.share)))

    def summary(self) -> dict:
        """Plain data for a run summary (``summary["error_budget"]``): the profile, the RMSE
        with every source on and off, and per source its RMSE when off and its share."""
        return {
            "profile": self.profile,
            "realism_off": self.realism_off,
            "rmse_all_mm": self.rmse_all_mm,
            "floor_rmse_mm": self.floor_rmse_mm,
            "sources": [
                {"source": s.source, "rmse_off_mm": s.rmse_off_mm, "share": _finite_or_none(s.share)}
                for s in self.sources
            ],
            "interaction": _finite_or_none(self.interaction),
            "warnings": list(self.warnings),
        }

    def rows(self) -> list[tuple[str, str, str]]:
        """(source, RMSE with it off, share %) rows, then the remainder, all on and the floor."""
        rows = [(s.source, _mm(s.rmse_off_mm), _pct(s.share)) for s in self.sources]
        rows.append((INTERACTION, "", _pct(self.interaction)))
        rows.append(("all on (the recording)", _mm(self.rmse_all_mm), "100.0"))
        rows.append(("floor (all off, ideal)", _mm(self.floor_rmse_mm), _pct(_share(self.rmse_all_mm, self.floor_rmse_mm, floor=True))))
        return rows

    def markdown(self) -> str:
        """The budget as a markdown table with a few lines of explanation."""
        lines = [
            f"# Error budget of {self.recording.name}",
            "",
            f"Scenario `{self.scenario}`, seed {self.seed}, realism `{self.profile}`"
            + (f" (already off: `{self.realism_off}`)" if self.realism_off else "")
            + f"; run settings `{_settings_text(self.settings)}`.",
            "",
            "| source | position RMSE with it off (mm) | share of the error (%) |",
            "|---|---:|---:|",
        ]
        lines += [f"| {a} | {b} | {c} |" for a, b, c in self.rows()]
        lines += [
            "",
            "share = (RMSE_all² − RMSE_off²) / RMSE_all² — a share of the mean squared error. "
            f"Sources interact, so the shares need not sum to 100 %; `{INTERACTION}` is the remainder "
            "(1 − Σ shares). The floor's share is RMSE_floor² / RMSE_all²: what remains with every source off.",
        ]
        lines += [f"\n*warning:* {w}" for w in self.warnings]
        return "\n".join(lines) + "\n"


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _mm(value: float | None) -> str:
    return "—" if value is None else f"{value:.3f}"


def _pct(share: float) -> str:
    return "—" if not math.isfinite(share) else f"{100.0 * share:.1f}"


def _share(rmse_all: float, rmse_off: float | None, floor: bool = False) -> float:
    if rmse_off is None or not rmse_all > 0.0:
        return float("nan")
    if floor:
        return rmse_off**2 / rmse_all**2
    return (rmse_all**2 - rmse_off**2) / rmse_all**2


def _settings_text(settings: dict) -> str:
    default = as_dict(RunSettings())
    changed = {k: v for k, v in settings.items() if default.get(k) != v}
    return ", ".join(f"{k}={v}" for k, v in changed.items()) or "defaults"


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
    from agvviz.app.compare import load_run

    run = load_run(run_path)
    errors = np.where(run.solved, run.errors["position"], np.nan)
    return run.frames, run.time_ns, errors


def _matched(time_a: np.ndarray, err_a: np.ndarray, time_b: np.ndarray, err_b: np.ndarray) -> np.ndarray:
    """err_a − err_b at each time of ``time_a`` (NaN where b has no such frame or either is NaN)."""
    where = {int(t): k for k, t in enumerate(time_b)}
    out = np.full(len(time_a), np.nan)
    for k, t in enumerate(time_a):
        j = where.get(int(t))
        if j is not None:
            out[k] = err_a[k] - err_b[j]
    return out


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
    ``cache_dir`` are passed to :func:`agvviz.replay.run.run_recording`.

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
                share=_share(rmse_all, rmse_off),
                solved_off=int(outcome.summary["solved"]),
                time_ns=time_off,
                position_error_off_mm=err_off,
                delta_mm=_matched(time_all, err_all, time_off, err_off),
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


__all__ = ["INTERACTION", "ErrorBudget", "SourceBudget", "error_budget", "sources_on"]
