"""The package's shape (issue 24): imports point down, no import loops, few top-level modules,
no long file without a reason.

- :func:`test_import_contracts` runs ``lint-imports`` on the contracts in pyproject.toml
  (``[tool.importlinter]``: the layers, only viz/ imports rerun, only recording/ imports mcap,
  rosbags and the ROS decoders, evaluation/ reads no files, no loops between siblings);
- the other tests read the sources with :mod:`ast` (no import, fast): no import cycle between
  agvviz modules (an import inside a function counts as much as one at the top of the file), at
  most the six allowed modules at the top of ``agvviz/``, and no file over
  :data:`MAX_LINES` lines unless its module docstring has a line starting with
  :data:`LONG_FILE_REASON` that says why.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "agvviz"
#: The only modules allowed at the top of agvviz/ (``cli`` may be a package instead).
TOP_LEVEL_MODULES = {"__init__", "__main__", "cli", "settings", "conventions", "errors"}
MAX_LINES = 600
#: A file longer than MAX_LINES says why in a line of its module docstring starting with this.
LONG_FILE_REASON = f"Longer than {MAX_LINES} lines because"


def test_import_contracts():
    """``lint-imports`` keeps every contract of pyproject.toml's ``[tool.importlinter]``."""
    lint_imports = Path(sys.executable).with_name("lint-imports")
    try:
        import importlinter  # noqa: F401
    except ImportError:
        pytest.skip("import-linter is not installed (pip install -e '.[test]' installs it)")
    if not lint_imports.exists():
        pytest.skip(f"import-linter is installed but its console script is not next to the interpreter ({lint_imports})")
    env = dict(os.environ)
    # The agvviz linted is this checkout's, whatever is installed.
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    result = subprocess.run(
        [str(lint_imports), "--no-cache"], cwd=REPO, env=env, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, f"lint-imports found broken contracts:\n{result.stdout}\n{result.stderr}"


# -- the import graph, from the sources ---------------------------------------------------------
def _modules() -> dict[str, tuple[Path, bool]]:
    """Every module of agvviz: dotted name → (file, is a package's __init__)."""
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(REPO).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        modules[".".join(parts)] = (path, is_package)
    return modules


def _import_graph() -> dict[str, dict[str, int]]:
    """importer → {imported agvviz module: first line}. Every ``import``/``from … import``
    anywhere in the file (module level, functions, ``if TYPE_CHECKING``) counts. ``from p
    import name`` is an import of module ``p.name`` when that is a module, else of ``p``; a
    module's own parent packages, which Python also runs, are not counted (as import-linter)."""
    modules = _modules()

    def known(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, dict[str, int]] = {name: {} for name in modules}
    for name, (path, is_package) in modules.items():
        package = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    source = ".".join(base + ([node.module] if node.module else []))
                else:
                    source = node.module or ""
                targets = [f"{source}.{a.name}" if f"{source}.{a.name}" in modules else source for a in node.names]
            else:
                continue
            for target in targets:
                imported = known(target) if target.split(".")[0] == "agvviz" else None
                if imported and imported != name:
                    graph[name].setdefault(imported, node.lineno)
    return graph


def _cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            for succ in successors:
                if succ not in index:
                    index[succ] = low[succ] = len(index)
                    stack.append(succ)
                    on_stack.add(succ)
                    work.append((succ, iter(sorted(graph[succ]))))
                    break
                if succ in on_stack:
                    low[node] = min(low[node], index[succ])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return sorted(found)


def test_cycle_finder_finds_a_loop():
    graph = {"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1, "d": 1}, "d": {}, "e": {"e": 1}}
    assert _cycles(graph) == [["a", "b", "c"]]


def test_no_import_cycles():
    """No two agvviz modules import each other, directly or through others."""
    graph = _import_graph()
    cycles = _cycles(graph)
    lines = []
    for component in cycles:
        members = set(component)
        lines.append(f"{len(component)} modules: " + ", ".join(component))
        for importer in component:
            for imported, lineno in sorted(graph[importer].items()):
                if imported in members:
                    lines.append(f"    {importer} -> {imported} (l.{lineno})")
    assert not cycles, "import cycles in agvviz:\n" + "\n".join(lines)


def test_few_modules_at_the_top():
    """At most cli, settings, conventions, errors, __init__ and __main__ at the top of agvviz/."""
    top = {path.stem for path in PACKAGE.glob("*.py")}
    extra = sorted(top - TOP_LEVEL_MODULES)
    assert not extra, f"modules at the top of agvviz/ beyond {sorted(TOP_LEVEL_MODULES)}: {extra}"


def test_no_long_file_without_a_reason():
    """No agvviz file over MAX_LINES lines unless its module docstring says why."""
    long_files = []
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        n_lines = len(text.splitlines())
        if n_lines <= MAX_LINES:
            continue
        docstring = ast.get_docstring(ast.parse(text)) or ""
        if not any(line.strip().startswith(LONG_FILE_REASON) for line in docstring.splitlines()):
            long_files.append(f"{path.relative_to(REPO)}: {n_lines} lines")
    assert not long_files, (
        f"files over {MAX_LINES} lines whose module docstring has no line starting "
        f"{LONG_FILE_REASON!r}:\n" + "\n".join(long_files)
    )
