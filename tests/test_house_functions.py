"""No function longer than 100 lines in pipeline/, worldlib/ or stages/.

A function's length counts from its `def` line to its last line, docstring,
comments and blank lines included (a decorator does not count); nested
functions count on their own and inside the function that holds them. A long
function is split the way the house style (STYLE.md) asks: a stage's `run()` reads like the
list of its steps, each a call of a few lines, one module per part of the work.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "worldlib", "stages")
MAX_LINES = 100


def long_functions(root: Path = ROOT, max_lines: int = MAX_LINES) -> list[str]:
    """`path:line name length` of every function longer than max_lines."""
    found = []
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
            for node in ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    length = node.end_lineno - node.lineno + 1
                    if length > max_lines:
                        found.append(f"{path.relative_to(root)}:{node.lineno} {node.name} {length}")
    return found


def test_no_function_over_100_lines():
    offenders = long_functions()
    assert not offenders, (f"{len(offenders)} function(s) over {MAX_LINES} lines (split them into steps):\n"
                           + "\n".join(offenders))


def test_the_walk_finds_a_long_function(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    (tmp_path / "stages").mkdir()
    (tmp_path / "stages" / "long.py").write_text(f"def short():\n    return 1\n\n\ndef long():\n{body}\n")
    assert long_functions(tmp_path) == [f"stages/long.py:5 long {MAX_LINES + 1}"]
