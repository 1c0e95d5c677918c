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

PROJECT_ROOT = Path(__file__).resolve().parent.parent
# The project's own top-level packages (engine, domain libraries, stages): a
# module of theirs that a stage imports is part of its key.
PROJECT_PACKAGES = ("pipeline", "worldlib", "stages")
# Shared OpenCL headers, passed to every kernel build with -I.
CL_INCLUDE_DIR = PROJECT_ROOT / "worldlib" / "cl"

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


class _FactsCache:
    """Per file, by its path and bytes: the sha256 of its normalised text and
    the dotted names it imports. Parsing is most of the cost of keying a bake
    (about 100 modules, several seconds), so the facts persist between runs
    in WORLDBAKE_CACHE_DIR (default ~/.cache/worldbake), keyed by content: a
    changed file is a new key, a stale entry is never read. Which files the
    names resolve to is decided on every run."""

    def __init__(self):
        self.entries: dict[str, list] | None = None
        self.dirty = False

    @property
    def path(self) -> Path:
        import os

        folder = os.environ.get("WORLDBAKE_CACHE_DIR") or Path.home() / ".cache" / "worldbake"
        return Path(folder) / f"source-facts-{FACTS_FORMAT}.json"

    def _load(self) -> dict[str, list]:
        if self.entries is None:
            import json

            try:
                self.entries = dict(json.loads(self.path.read_text()))
            except (OSError, ValueError, TypeError):
                self.entries = {}
        return self.entries

    def facts(self, root: Path, path: Path) -> tuple[str, list[str]]:
        raw = path.read_bytes()
        key = f"{path.relative_to(root).as_posix()}:{hashlib.sha256(raw).hexdigest()}"
        entries = self._load()
        if key not in entries:
            text = raw.decode("utf-8", errors="surrogateescape")
            if path.suffix == ".py":
                entries[key] = [hashlib.sha256(normalized_python(text)).hexdigest(), _import_names(root, path, text)]
            else:
                entries[key] = [hashlib.sha256(normalized_cl(text)).hexdigest(), []]
            self.dirty = True
        digest, names = entries[key]
        return digest, names

    def save(self) -> None:
        """Write the facts (atomically: parallel bakes and test workers share the file)."""
        import json
        import os
        import tempfile

        if not self.dirty:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.path.parent, suffix=".tmp")
            with os.fdopen(fd, "w") as f:
                json.dump(self.entries, f)
            os.replace(tmp, self.path)
            self.dirty = False
        except OSError:
            pass  # a read-only home only costs the parsing again


FACTS_FORMAT = 1  # bump when normalized_python, normalized_cl or _import_names change what they return
_FACTS = _FactsCache()


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
    found = set()
    for name in _FACTS.facts(root, path)[1]:
        parts = name.split(".")
        for i in range(1, len(parts) + 1):  # importing a.b.c runs a/__init__ and a/b/__init__
            f = _module_file(root, ".".join(parts[:i]))
            if f is not None:
                found.add(f)
    return found


def _import_names(root: Path, path: Path, text: str) -> list[str]:
    """The dotted names a .py file imports (relative imports made absolute)."""
    try:
        tree = ast.parse(text)
    except SyntaxError:
        return []
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
    return sorted(set(names))


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
            new = included_headers(path, root / CL_INCLUDE_DIR.relative_to(PROJECT_ROOT))
        todo.extend(new - seen)
    return sorted(seen)


@functools.lru_cache(maxsize=None)
def stage_source_hash(source_dir: Path) -> str:
    """sha256 over the project-relative paths and the hashes of the
    normalised text of stage_source_files(source_dir)."""
    source_dir = Path(source_dir).resolve()
    root = source_dir.parent.parent
    h = hashlib.sha256()
    for path in stage_source_files(source_dir):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(_FACTS.facts(root, path)[0].encode() + b"\0")
    _FACTS.save()
    return h.hexdigest()


@functools.lru_cache(maxsize=None)
def cl_include_hash() -> str:
    """sha256 of the shared OpenCL headers' bytes (for build caches)."""
    h = hashlib.sha256()
    for path in sorted(CL_INCLUDE_DIR.glob("*.h")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()
