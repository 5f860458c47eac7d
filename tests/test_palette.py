"""Colours are defined once, in agvviz/viz/style.py (the palette), and every view picks from there
(issue 26). Fast: reads source only.

An AST scan of agvviz/, the sibling of tests/test_viz_paths.py (entity paths only in viz/paths.py):
outside the palette module no module may write

- an RGB(A) tuple or list of integer literals 0..255 as a ``color``/``colors``/``*_color(s)``
  keyword argument, or as the value of a name that says it is a colour (``COLOR_X = (..)``,
  ``SOLVER_COLORS = {..: (..)}``);
- a hex colour: a string ``"#rrggbb"`` / ``"#rrggbbaa"`` or an integer written ``0xRRGGBBAA``.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

from agvviz.viz import style

ROOT = Path(__file__).resolve().parents[1]
PALETTE_MODULE = ROOT / "agvviz" / "viz" / "style.py"
HEX_STRING = re.compile(r"#[0-9a-fA-F]{6}(?:[0-9a-fA-F]{2})?")


def _is_rgb_literal(node: ast.AST) -> bool:
    """A tuple/list of 3 or 4 integer literals in 0..255 (an RGB or RGBA colour)."""
    if not isinstance(node, (ast.Tuple, ast.List)) or len(node.elts) not in (3, 4):
        return False
    values = [e.value for e in node.elts if isinstance(e, ast.Constant) and type(e.value) is int]
    return len(values) == len(node.elts) and all(0 <= v <= 255 for v in values)


def _has_rgb_literal(node: ast.AST) -> bool:
    return any(_is_rgb_literal(n) for n in ast.walk(node))


def _colourish(name: str) -> bool:
    return "color" in name.lower() or "colour" in name.lower()


def colour_offences(source: str) -> list[tuple[int, str]]:
    """(line, what) of every colour literal in ``source``."""
    offences = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.keyword) and node.arg and _colourish(node.arg) and _has_rgb_literal(node.value):
            offences.append((node.value.lineno, f"RGB literal as {node.arg}="))
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names = [t.id if isinstance(t, ast.Name) else getattr(t, "attr", "") for t in targets]
            if any(_colourish(n) for n in names) and node.value is not None and _has_rgb_literal(node.value):
                offences.append((node.lineno, f"RGB literal assigned to {', '.join(names)}"))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and HEX_STRING.fullmatch(node.value.strip()):
            offences.append((node.lineno, f"hex colour {node.value!r}"))
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.NUMBER and re.fullmatch(r"0[xX](?:[0-9a-fA-F]{6}|[0-9a-fA-F]{8})", token.string):
            offences.append((token.start[0], f"hex colour {token.string}"))
    return offences


def test_the_scan_finds_colours():
    """The scan is able to fail: each form of a colour literal is found, indices and shapes are not."""
    for line in ('rec.log(e, rr.Points3D(p, colors=(110, 110, 110)))', "COLOR_DELTA = (235, 235, 235)",
                 'SOLVER_COLORS = {"p4p": (60, 120, 255)}', 'x = f(color=[255, 0, 0, 128])', 'c = "#1e90ff"',
                 "c = 0xFF8800FF", "x = g(colors=[(1, 2, 3), (4, 5, 6)])"):
        assert colour_offences(line), line
    for line in ("_TRIPLES = ((0, 1, 2), (0, 1, 3))", "a.reshape(1, 4, 2)", "x = f(colors=COLOR_TRUTH)",
                 "x = f(colors=(*COLOR_CAMERA, 160))", "shape = (3, 3, 3)", 'name = "#15"', "mask = 0xFF"):
        assert not colour_offences(line), line


def test_colours_live_in_the_palette_module():
    offenders = []
    for path in sorted((ROOT / "agvviz").rglob("*.py")):
        if path == PALETTE_MODULE:
            continue
        for line, what in colour_offences(path.read_text()):
            offenders.append(f"{path.relative_to(ROOT)}:{line}: {what}")
    assert not offenders, "colours outside agvviz/viz/style.py:\n" + "\n".join(offenders)


def _distance(a, b) -> float:
    return sum((x - y) ** 2 for x, y in zip(a[:3], b[:3])) ** 0.5


#: RGB distance below which two colours read as one on the dark background (the old sweep #3,
#: (30, 144, 255), was 57 from the markers' blue).
MIN_DISTANCE = 80.0


def test_overlay_runs_stand_apart_from_what_the_overlay_also_draws():
    """A sweep's or diff's runs are not the truth green, the map markers' blue, the UWB blue, the
    detected cyan or the images' white, and not each other."""
    others = {"truth": style.COLOR_TRUTH, "markers": style.COLOR_MARKER, "UWB": style.COLOR_UWB,
              "anchors": style.COLOR_ANCHOR, "detected corners": style.COLOR_DETECTED, "white": (255, 255, 255)}
    for i, run in enumerate(style.PALETTE):
        for name, other in others.items():
            assert _distance(run, other) >= MIN_DISTANCE, f"overlay run #{i + 1} {run} looks like {name} {other}"
        for j, second in enumerate(style.PALETTE[:i]):
            assert _distance(run, second) >= MIN_DISTANCE, f"overlay runs #{j + 1} and #{i + 1} look alike"
    assert len(style.PALETTE_NAMES) == len(style.PALETTE)
    assert (style.COLOR_RUN_A, style.COLOR_RUN_B) == (style.color_of(0), style.color_of(1))


def test_study_solvers_are_told_apart():
    """Each solver of the Monte-Carlo study has its own colour, far from every other."""
    from agvviz.replay.studies.monte_carlo_cells import SOLVERS

    names = [*SOLVERS, "crlb"]
    assert set(names) <= set(style.SOLVER_COLORS)
    for i, a in enumerate(names):
        for b in names[:i]:
            assert _distance(style.SOLVER_COLORS[a], style.SOLVER_COLORS[b]) >= MIN_DISTANCE, (a, b)


def test_the_docs_list_the_palette():
    """docs/architecture.md's palette table names every COLOR_ constant with its hex value."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    for name, value in vars(style).items():
        if name.startswith("COLOR_") and isinstance(value, tuple) and name not in ("COLOR_FLAGGED", "COLOR_OK", "COLOR_SEEN_TOO_LITTLE", "COLOR_RUN_A", "COLOR_RUN_B", "COLOR_OTHER", "COLOR_THRESHOLD", "COLOR_MARKER_FILL"):
            assert f"| `{name}` | `#{value[0]:02x}{value[1]:02x}{value[2]:02x}` |" in text, name
