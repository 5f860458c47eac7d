"""docs/make_pictures.py and the docs agree: every picture it renders is shown on a page, every
picture a page shows is one it renders (so regenerating it refreshes them all), and each picture
is on the page its shot names."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _make_pictures():
    spec = importlib.util.spec_from_file_location("make_pictures", ROOT / "docs" / "make_pictures.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def _shown() -> dict[str, set[str]]:
    """Picture name → the pages (README.md, docs/x.md) that show it."""
    shown: dict[str, set[str]] = {}
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for name in re.findall(r"\]\((?:docs/)?images/([^)]+)\.png\)", page.read_text()):
            shown.setdefault(name, set()).add(str(page.relative_to(ROOT)))
    return shown


def test_every_rendered_picture_is_shown_on_its_page_and_every_shown_one_is_rendered():
    module = _make_pictures()
    shown = _shown()
    rendered = {}
    for group in module.GROUPS:
        for shots in group.shots:
            for shot in shots:
                rendered[shot.name] = shot.doc
                assert shot.caption, f"{shot.name}: no caption"
    assert set(shown) == set(rendered)
    for name, page in rendered.items():
        assert page in shown[name], f"{name}.png is on {sorted(shown[name])}, not on its page {page}"
    assert set(shown) == {p.stem for p in (ROOT / "docs" / "images").glob("*.png")}
