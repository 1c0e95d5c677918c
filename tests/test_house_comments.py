"""Sources say why the code is as it is now, not how fast a run of it was.

Timings, speed-ups, sizes of runs' files and notes on variants that were
tried and dropped belong in bench/ and in commit messages (STYLE.md, "Kernels"
and "Names and comments"): they age the day the code, the machine or the
world changes. This scans, in every .py, .cl and .h under pipeline/, worldlib/
and stages/:

- comments (`#`, `//`, `/* */`);
- docstrings and other bare string statements;
- the `description=` of every `Param(...)`: the README's config reference is
  generated from them.

Physical quantities pass ("40 deg", "1 m", "0.5", "10 % of the relief", a
paper's year); a speed-up ("1.2x faster", "12 % slower", "-5 %"), a timing
("9.3 ms"), a size of a run's files ("1.80 MB"), a date, a report of what was
measured and dropped, and a reference to a document the repository does not
hold fail, each named file:line.
"""
from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "worldlib", "stages")

_NUM = r"\d+(?:\.\d+)?"
_SIZE = rf"{_NUM}\s*(?:kB|KB|KiB|MB|MiB|GB|GiB)\b"
_RUN = r"(?:default[- ]world|default bake|measured|compress\w*|zip|pxr24|piz|dwa\w*|on disk)"
PATTERNS = {
    # 50x faster, 5x slower, 40x the Python loop (2x2x2, 16 x 16 or "3x the memory" are no speeds)
    "speed-up ratio": rf"(?<![\w.]){_NUM}x\s+(?:faster|slower|quicker|as fast|the speed|the (?:pure-)?python|the numpy)",
    # 12 % faster, 20 % slower, 20 % less CPU, 1 % of its kernel
    "percent faster or slower": rf"{_NUM}\s*%\s*(?:faster|slower|quicker|speed-?up|less time|more time|less CPU|of (?:the |its )?(?:kernel|step|time|run|storm|loop|bake|update|flux)\b)",
    # "-8 %", "+2 %": a signed change of a figure (+-25 % is a physical spread)
    "signed percentage": rf"(?<![\w+\-./])[+\-]{_NUM}\s*%",
    # 2 to 10 times faster
    "times faster or slower": rf"{_NUM}\s*times\s+(?:faster|slower|quicker)",
    # faster (its erosion storm 3.6x, ...), slower by 12 %
    "speed figure": rf"\b(?:faster|slower)\b[^.;:]{{0,30}}?{_NUM}\s*(?:x\b|%|ms\b|s\b)",
    # 9.3 ms, 4 us of host time
    "timing": rf"(?<![\w.]){_NUM}\s*(?:ms|µs|us|ns)\b",
    # "took 3 s", "costs 12 seconds", "in about 2.5 min"
    "duration of a run": rf"\b(?:took|takes|costs?|spent|ran in|runs in|bakes? in|in about)\s+(?:about\s+|only\s+)?{_NUM}\s*(?:s|sec|seconds|min|minutes|h|hours)\b",
    # zip EXRs take 1.80 MB, 63 MB on the default world (a memory bound such as "2 GiB as float64" passes)
    "size of a run's files": rf"{_RUN}[^.;]{{0,60}}?{_SIZE}|{_SIZE}[^.;]{{0,40}}?{_RUN}",
    # 2024-05-01, May 2024 (a paper's year passes)
    "date": r"\b(?:19|20)\d\d-[01]\d(?:-[0-3]\d)?\b|\b(?:Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Sept|Oct|Nov|Dec|January|February|March|April|June|July|August|September|October|November|December)\.? (?:19|20)\d\d\b",
    # history of the code
    "tried and dropped": r"\b(?:measured|tried|benchmarked|profiled|tested)\b[^.;]{0,60}?\b(?:and|but) (?:dropped|rejected|abandoned|reverted)\b|\b(?:was|were) (?:tried|dropped|reverted)\b|\bdid not help\b|\bno gain\b|(?-i:\bA/B\b)|\bthis session\b",
    "change note": r"\b(?:used to be|previously|formerly|was only|as before)\b",
}
# physical rates the patterns cannot tell from a speed of code
ALLOWED = ("incises 10 % faster",)
_PATTERNS = [(name, re.compile(p, re.IGNORECASE)) for name, p in PATTERNS.items()]
_DOC_REF = re.compile(r"\b([A-Z][A-Z_]+\.md)\b")


def source_files() -> list[Path]:
    files = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*")):
            if path.suffix in (".py", ".cl", ".h") and "__pycache__" not in path.parts:
                files.append(path)
    return files


_QUOTES = re.compile(r"^[rRbBuU]{0,2}(?:\"{3}|'{3}|[\"'])|(?:\"{3}|'{3}|[\"'])$")  # a literal's quotes and prefix


def _python_blocks(text: str) -> list[list[tuple[int, str]]]:
    """Comments (runs of consecutive comment lines), docstrings and the
    string literals of Param descriptions, as blocks of (line, text)."""
    tree = ast.parse(text)
    spans = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            spans.append((node.lineno, node.end_lineno))
        elif isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) == "Param":
            spans.extend((k.value.lineno, k.value.end_lineno) for k in node.keywords if k.arg == "description")
    blocks, comments, strings = [], [], {s: [] for s in spans}
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT:
            if comments and comments[-1][0] != tok.start[0] - 1:
                blocks.append(comments)
                comments = []
            comments.append((tok.start[0], tok.string.lstrip("#")))
        elif tok.type == tokenize.STRING:
            for span in spans:
                if span[0] <= tok.start[0] and tok.end[0] <= span[1]:
                    strings[span].extend((tok.start[0] + k, _QUOTES.sub("", line.strip()))
                                         for k, line in enumerate(tok.string.split("\n")))
    if comments:
        blocks.append(comments)
    return blocks + [b for b in strings.values() if b]


_CL_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)


def _cl_blocks(text: str) -> list[list[tuple[int, str]]]:
    blocks, previous_end = [], -2
    for m in _CL_COMMENT.finditer(text):
        first = text.count("\n", 0, m.start()) + 1
        lines = [(first + k, line.strip().lstrip("/*").rstrip("*/")) for k, line in enumerate(m.group().split("\n"))]
        if m.group().startswith("//") and blocks and previous_end == first - 1 and text[:m.start()].rstrip(" \t").endswith("\n"):
            blocks[-1].extend(lines)  # a run of // lines is one comment
        else:
            blocks.append(lines)
        previous_end = lines[-1][0]
    return blocks


def findings(path: Path) -> list[str]:
    text = path.read_text()
    blocks = _python_blocks(text) if path.suffix == ".py" else _cl_blocks(text)
    found = []
    for block in blocks:
        # a block is matched as one text, so a phrase broken over lines is found
        joined, starts = "", []
        for line, fragment in block:
            starts.append((len(joined), line))
            joined += fragment.strip() + " "
        for name, pattern in _PATTERNS:
            for m in pattern.finditer(joined):
                if any(a in joined[max(0, m.start() - 40):m.end() + 40] and m.group() in a for a in ALLOWED):
                    continue
                line = max(ln for offset, ln in starts if offset <= m.start())
                found.append(f"{path.relative_to(ROOT)}:{line}: {name}: {m.group()!r}")
        for m in _DOC_REF.finditer(joined):
            if not (ROOT / m.group(1)).is_file() and not (path.parent / m.group(1)).is_file():
                line = max(ln for offset, ln in starts if offset <= m.start())
                found.append(f"{path.relative_to(ROOT)}:{line}: cites {m.group(1)}, which the repository does not hold")
    return found


@pytest.mark.parametrize("text", [
    "about 50x faster than the pure-Python heap",
    "PoCL ran the default bake 1.2x faster (its erosion storm 3.6x,",
    "tiles of a few hundred cells were 20 % slower at 2048^2",
    "software prefetch 0 to -8 %; update in place +2 % at best",
    "Measured at 512^2 on 2 Zen 4 cores and dropped",
    "interleaved A/B rounds",
    "zip EXRs take 1.80 MB dense, 0.98 MB as runs",
    "9.3 ms -> 1.4 ms at 1024^2",
    "the bake took 41 s",
    "numpy's float32 power is 10x faster than float64's",
    "16-wide floats (AVX-512: 10-17 % faster than 8 in the bench)",
    "about 40x the Python loop",
    "zip level 1: 20 % less CPU than the default level",
    "63 MB on the default world",
    "PoCL spends about 4 us of host time per clSetKernelArg",
    "baked on 2024-05-03",
])
def test_figures_of_runs_are_found(text):
    assert any(p.search(text) for _, p in _PATTERNS), text


@pytest.mark.parametrize("text", [
    "slopes steeper than 40 deg shed their scree",
    "cells of 1 m, a talus of 0.5",
    "16 x 16 frames of 64 px; mips average 2x2x2 voxels",
    "horizontally by +-25 % of the root-to-tip offset",
    "a full solid voxel lets 0.1 % of the light through its edge",
    "Mei et al. 2007 virtual pipes; Olsen (2004)",
    "a time step of 0.5 s; tau in s",
    "names each device tried and why it failed",
    "coarser is faster",
    "one sort of 64-bit keys, which is faster than numpy's stable argsort",
    "Downsampling by more than 2x aliases; about 3x for the padding",
    "16384^2 (2 GiB as float64); 16 MiB by default; about 1 KiB per module",
    "Quinn et al. 1991; Martz 1997",
    "the buffers are at least 128-byte aligned",
])
def test_physical_numbers_pass(text):
    assert not [m.group() for _, p in _PATTERNS for m in p.finditer(text)], text


def test_sources_hold_no_figures_of_runs_or_history():
    found = [f for path in source_files() for f in findings(path)]
    assert not found, "figures of runs or history in sources:\n" + "\n".join(found)
