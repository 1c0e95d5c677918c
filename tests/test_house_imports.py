"""No import circle between the modules of pipeline/, worldlib/ and stages/.

The graph has one node per module (a package is its `__init__.py`) and an
edge for every import statement in a module's source, wherever it stands:
at the top, inside a function or under `if TYPE_CHECKING:`. An import in a
function dodges a circle at start-up but not in the design, so it counts.

What an import statement points at:

- `import a.b.c` points at `a.b.c`;
- `from a.b import c` points at `a.b.c` when that is a module, else at `a.b`
  (the name comes from the package's `__init__`);
- relative imports are resolved against the importing module's package.

A package's `__init__` importing its own submodules is how a package is
built, and Python running `a/__init__.py` before `a/b.py` when something
imports `a.b` is the import machinery, not an edge of `a.b`. So `a` ->
`a.b` alone is no circle; but a submodule that takes a name from its
package's `__init__` (`from . import Thing` in `a/b.py`) while that
`__init__` imports the submodule is one: the two modules need each other.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "worldlib", "stages")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def project_modules() -> dict[str, Path]:
    """Dotted name -> file, for every .py under the project's packages."""
    modules = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if "__pycache__" not in path.parts:
                modules[_module_name(path)] = path
    return modules


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules one module's import statements point at."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module
            for alias in node.names:
                submodule = f"{prefix}.{alias.name}"
                targets.add(submodule if submodule in modules else prefix)
    return {t for t in targets if t in modules and t != name}


def import_graph() -> dict[str, set[str]]:
    modules = project_modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's components with more than one module (no module imports itself)."""
    index, low, on_stack, stack, components = {}, {}, set(), [], []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return components


def simple_cycles(graph: dict[str, set[str]], limit: int = 200) -> list[list[str]]:
    """Every elementary circle, each starting at its smallest module name."""
    cycles = []
    for component in _strongly_connected(graph):
        members = set(component)
        for start in component:
            allowed = {m for m in members if m >= start}
            path = [start]

            def walk(v: str) -> None:
                for w in sorted(graph[v] & allowed):
                    if len(cycles) >= limit:
                        return
                    if w == start:
                        cycles.append(path + [start])
                    elif w not in path:
                        path.append(w)
                        walk(w)
                        path.pop()

            walk(start)
    return cycles


def test_the_graph_sees_the_project():
    graph = import_graph()
    assert "pipeline.bake" in graph and "worldlib.render" in graph
    assert "pipeline.contract" in graph["pipeline.bake"]


def test_no_import_circle():
    cycles = simple_cycles(import_graph())
    assert not cycles, "import circles:\n" + "\n".join(" -> ".join(c) for c in cycles)


LAYERS = {"pipeline": 0, "worldlib": 1, "stages": 2}


def test_each_package_imports_only_the_ones_below_it():
    """The engine imports neither the libraries nor a stage (its registry
    imports only the `stages` package, empty, to find the stage folders in
    it); the libraries import no stage; a stage imports no other stage's
    modules."""
    wrong = []
    for name, targets in import_graph().items():
        top = name.split(".")[0]
        for target in sorted(targets):
            other = target.split(".")[0]
            if (name, target) == ("pipeline.registry", "stages"):
                continue
            if LAYERS[other] > LAYERS[top]:
                wrong.append(f"{name} imports {target}")
            elif top == other == "stages" and name.split(".")[1] != target.split(".")[1] and target != "stages":
                wrong.append(f"{name} imports another stage's {target}")
    assert not wrong, "\n".join(wrong)
