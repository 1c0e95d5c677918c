"""Which source files a stage can run, and their hash for its cache key.

A stage's key must change when any code it runs changes, and only then. The
files are found by reading, not by running: every .py and .cl file in the
stage's folder, then every project module those .py files import (at the top
or inside a function, absolutely or relatively), the packages around them,
the .cl files beside each module (a module loads its kernels by
`Path(__file__).with_name(...)`), and the headers each .cl file includes
(from its own folder or from CL_INCLUDE_DIR, which load_program passes with
-I), all transitively. A stage that imports another stage's module is refused
by a test (tests/stages/test_sources.py), not here.

What is hashed is the normalised text, so comments, blank lines, indentation
of continuation lines and docstrings do not count: Python files as their
syntax tree (ast.dump, docstrings dropped), OpenCL files without comments
and with white space folded. A module that cannot be parsed is hashed as
its bytes (it will fail when it runs; the key still follows it).
"""
from __future__ import annotations

import ast
import functools
import hashlib
import re
from pathlib import Path

PIPELINE_DIR = Path(__file__).resolve().parent
CL_INCLUDE_DIR = PIPELINE_DIR / "cl"
PROJECT_PACKAGES = ("pipeline", "stages")  # top-level packages whose modules are part of a key

_CL_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)
_CL_INCLUDE = re.compile(r'^\s*#\s*include\s*"([^"]+)"', re.M)


# --------------------------------------------------------------------------- normalising


def _drop_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return tree


def normalized_python(text: str) -> bytes:
    """The syntax tree without docstrings: comments and layout are not in it."""
    try:
        tree = ast.parse(text)
    except SyntaxError:
        return text.encode()
    return ast.dump(_drop_docstrings(tree), annotate_fields=False, include_attributes=False).encode()


def normalized_cl(text: str) -> bytes:
    """OpenCL C without comments, each line's white space folded, blank
    lines dropped (lines stay lines: preprocessor directives end there)."""
    text = _CL_COMMENT.sub(" ", text.replace("\\\n", " "))
    lines = (" ".join(line.split()) for line in text.splitlines())
    return "\n".join(line for line in lines if line).encode()


def normalized(path: Path) -> bytes:
    text = path.read_text(encoding="utf-8", errors="surrogateescape")
    return normalized_python(text) if path.suffix == ".py" else normalized_cl(text)


# --------------------------------------------------------------------------- finding


def _module_file(root: Path, dotted: str) -> Path | None:
    parts = dotted.split(".")
    if not parts or parts[0] not in PROJECT_PACKAGES:
        return None
    base = root.joinpath(*parts)
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py")
    return None


def _package_of(root: Path, path: Path) -> list[str]:
    return list(path.relative_to(root).parts[:-1])  # a module's package; __init__.py's own


def imported_modules(root: Path, path: Path) -> set[Path]:
    """Project module files a .py file imports, with the packages on the way."""
    try:
        tree = ast.parse(path.read_text(encoding="utf-8", errors="surrogateescape"))
    except SyntaxError:
        return set()
    package = _package_of(root, path)
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.extend(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1] if node.level > 1 else package
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            names.append(prefix)
            names.extend(f"{prefix}.{a.name}" for a in node.names)  # `from pkg import module`
    found = set()
    for name in names:
        parts = name.split(".")
        for i in range(1, len(parts) + 1):  # importing a.b.c runs a/__init__ and a/b/__init__
            f = _module_file(root, ".".join(parts[:i]))
            if f is not None:
                found.add(f)
    return found


def included_headers(path: Path, include_dir: Path = CL_INCLUDE_DIR) -> set[Path]:
    """The headers a .cl file includes, from its own folder or include_dir."""
    found = set()
    for name in _CL_INCLUDE.findall(path.read_text(encoding="utf-8", errors="surrogateescape")):
        for folder in (path.parent, include_dir):
            if (folder / name).is_file():
                found.add(folder / name)
                break
    return found


def _is_source(p: Path) -> bool:
    return p.suffix in (".py", ".cl", ".h") and "__pycache__" not in p.parts


def stage_source_files(source_dir: Path) -> list[Path]:
    """Every source file a stage can load, sorted. The project root is the
    folder holding `stages/` (source_dir's grandparent), so a copy of the
    project answers for itself."""
    source_dir = Path(source_dir).resolve()
    root = source_dir.parent.parent
    todo = [p for p in source_dir.rglob("*") if _is_source(p)]
    seen: set[Path] = set()
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        if path.suffix == ".py":
            new = imported_modules(root, path)
            new |= {p for p in path.parent.iterdir() if p.suffix == ".cl"}
        else:
            new = included_headers(path, root / CL_INCLUDE_DIR.relative_to(PIPELINE_DIR.parent))
        todo.extend(new - seen)
    return sorted(seen)


@functools.lru_cache(maxsize=None)
def stage_source_hash(source_dir: Path) -> str:
    """sha256 over the project-relative paths and normalised text of
    stage_source_files(source_dir)."""
    source_dir = Path(source_dir).resolve()
    root = source_dir.parent.parent
    h = hashlib.sha256()
    for path in stage_source_files(source_dir):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(normalized(path) + b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=None)
def cl_include_hash() -> str:
    """sha256 of the shared OpenCL headers' bytes (for build caches)."""
    h = hashlib.sha256()
    for path in sorted(CL_INCLUDE_DIR.glob("*.h")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()
