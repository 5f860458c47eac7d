"""The scenarios: find and run the scenario modules of this package.

A scenario module defines ``NAME``, ``DESCRIPTION``, a frozen ``Options`` dataclass (every field
with a default and ``metadata={"help": ...}``), ``validate(options)`` and
``record(writer, options, seed, progress=None)``.
"""

from __future__ import annotations

from agvviz.errors import InputError

import importlib
import pkgutil
from pathlib import Path
from types import ModuleType
from typing import Callable

from agvviz import __version__
from agvviz.settings import SettingsError, apply_overrides, as_dict


class ScenarioError(InputError):
    """Unknown scenario or invalid options."""


def available() -> dict[str, ModuleType]:
    """Scenario name → module, for every scenario module in the ``scenarios`` package."""
    found = {}
    for info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(module, "NAME") and hasattr(module, "record"):
            found[module.NAME] = module
    return dict(sorted(found.items()))


def get(name: str) -> ModuleType:
    """The scenario module ``name``: its own module when it is named so (every scenario is),
    without importing the others; else a search of them all."""
    if isinstance(name, str) and name.isidentifier():
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
        else:
            if getattr(module, "NAME", None) == name and hasattr(module, "record"):
                return module
    scenarios = available()
    if name not in scenarios:
        raise ScenarioError(f"unknown scenario {name!r}; available: {', '.join(scenarios)}")
    return scenarios[name]


def build_options(name: str, overrides: list[str]):
    """The scenario's ``Options`` with ``key=value`` overrides applied and validated."""
    module = get(name)
    try:
        options = apply_overrides(module.Options(), overrides)
        module.validate(options)
    except (SettingsError, ValueError) as exc:
        raise ScenarioError(f"scenario {name}: {exc}") from None
    return options


def record(
    name: str,
    out_path: Path,
    *,
    seed: int = 0,
    overrides: list[str] = (),
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Record scenario ``name`` into ``out_path`` (written atomically). Returns its metadata."""
    from agvviz.recording.writer import RecordingWriter

    module = get(name)
    options = build_options(name, list(overrides))
    scenario = {"name": name, "seed": int(seed), "options": as_dict(options)}
    from agvviz.recording import outputs

    out_path = outputs.prepare_output(Path(out_path))  # OutputError: folder cannot be made/written
    try:
        with RecordingWriter(out_path, scenario=scenario) as writer:
            module.record(writer, options, int(seed), progress)
    except outputs.OutputError:
        raise
    except OSError as exc:  # a write failed (disk full, …); the temporary file is already gone
        raise outputs.output_error(exc, out_path) from exc
    return {**scenario, "agvviz_version": __version__}
