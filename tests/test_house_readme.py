"""The README's architecture section matches the tree: every module of the
engine and every entry of the domain libraries is named there, and every
stage folder is a stage the registry finds."""
from __future__ import annotations

import re
from pathlib import Path

from pipeline.registry import all_stages

ROOT = Path(__file__).resolve().parents[1]


def _architecture() -> str:
    text = (ROOT / "README.md").read_text()
    start = text.index("\n## Architecture")
    end = text.find("\n## ", start + 5)
    return text[start:end if end >= 0 else len(text)]


def test_every_engine_module_is_named_in_the_architecture():
    section = _architecture()
    missing = [p.name for p in sorted((ROOT / "pipeline").glob("*.py"))
               if p.name != "__init__.py" and not re.search(rf"\b{re.escape(p.name)}\b", section)]
    assert not missing, f"README architecture does not name pipeline/{missing}"


def test_every_library_entry_is_named_in_the_architecture():
    section = _architecture()
    entries = [p for p in sorted((ROOT / "worldlib").iterdir()) if p.name not in ("__init__.py", "__pycache__")]
    named = [p.name + ("/" if p.is_dir() else "") for p in entries]
    missing = [n for n in named if n not in section]
    assert not missing, f"README architecture does not name worldlib/{missing}"


def test_every_stage_folder_is_a_registered_stage():
    folders = {p.name for p in (ROOT / "stages").iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == set(all_stages())
