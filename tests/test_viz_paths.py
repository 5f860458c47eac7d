"""Entity paths of every .rrd are written in one module, agvviz/viz/paths.py (fast: reads source only).

The sibling of tests/test_real_logs.py::test_topic_names_live_in_one_module: there MCAP topic names
live in agvviz/model/topics.py, here Rerun entity paths in agvviz/viz/paths.py.
"""

from __future__ import annotations

import re
from pathlib import Path

from agvviz.viz import paths

ROOT = Path(__file__).resolve().parents[1]
#: Where entity paths live, and where MCAP topic names live ("/uwb/range" is a topic there, not an
#: entity; test_topic_names_live_in_one_module keeps topics out of every other module).
EXEMPT = {ROOT / "agvviz" / "viz" / "paths.py", ROOT / "agvviz" / "model" / "topics.py"}
#: Media types share a first segment with an entity root ("image/png"); they are not entity paths.
MEDIA_TYPES = ("png", "jpeg")


def entity_roots() -> set[str]:
    """The first segment of every entity path paths.py spells (``world``, ``errors``, ``uwb``, ...)."""
    roots = {
        value.split("/")[0]
        for name, value in vars(paths).items()
        if name.isupper() and isinstance(value, str) and "/" in value
    }
    return roots | {paths.WORLD, paths.ZOOM, paths.BUDGET, paths.OVERLAY_IMAGE, paths.OVERLAY_ERRORS, paths.OVERLAY_DELTA}


def entity_literal() -> re.Pattern:
    """A string literal (f-strings too) that starts like an entity path or a blueprint query of
    one: ``"world/agv"``, ``f"cnoem/trials/{cell}"``, ``"/uwb/range/..."``, ``"+ /world/**"``,
    ``"$origin/errors/..."``."""
    roots = "|".join(sorted(map(re.escape, entity_roots()), key=len, reverse=True))
    media = "|".join(MEDIA_TYPES)
    return re.compile(
        rf"""(?<![\w])[rRfF]{{0,2}}(["'])(?:[+-] ?)?(?:/|\$origin/)?(?:{roots})/(?!(?:{media})\1)"""
    )


def test_entity_roots_are_found():
    roots = entity_roots()
    assert {"world", "errors", "solver", "uwb", "audit", "budget", "cnoem", "mc", "correction", "image"} <= roots
    literal = entity_literal()
    for line in ('x = "world/agv/truth"', 'f"cnoem/trials/{cell_id}/error_m"', 'contents=[f"/uwb/range/{a}/**"]',
                 '["+ /world/markers/**"]', "origin='audit/odometry'"):
        assert literal.search(line), line
    for line in ('media_type="image/png"', 'MEDIA = {"jpeg": "image/jpeg"}', 'frame = "world"', 'path = "runs/x.rrd"',
                 'f"{root}/image"'):
        assert not literal.search(line), line


def test_entity_paths_live_in_one_module():
    """No module of agvviz/ but agvviz/viz/paths.py writes an entity-path literal."""
    literal = entity_literal()
    offenders = []
    for path in sorted((ROOT / "agvviz").rglob("*.py")):
        if path in EXEMPT:
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if literal.search(line) and not line.lstrip().startswith("#"):
                offenders.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not offenders, "entity paths outside agvviz/viz/paths.py:\n" + "\n".join(offenders)
