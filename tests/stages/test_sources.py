"""A stage's key covers every source file it can load, and nothing that
cannot change its results (pipeline.sources)."""
from __future__ import annotations

import ast
import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from pipeline.bake import plan_bake
from pipeline.config import load_config
from pipeline.graph import build_graph
from pipeline.registry import all_stages
from pipeline.sources import imported_modules, stage_source_files, stage_source_hash

ROOT = Path(__file__).resolve().parents[2]
STAGES = all_stages()


def _stage_files(root: Path, name: str) -> list[Path]:
    return sorted(p for p in (root / "stages" / name).rglob("*.py") if "__pycache__" not in p.parts)


@pytest.mark.parametrize("name", sorted(STAGES))
def test_no_stage_imports_another_stages_module(name):
    """Shared code lives in worldlib/, the domain libraries."""
    for path in _stage_files(ROOT, name):
        for module in imported_modules(ROOT, path):
            rel = module.relative_to(ROOT).parts
            if rel[0] == "stages" and len(rel) > 2:
                assert rel[1] == name, f"{path.relative_to(ROOT)} imports {module.relative_to(ROOT)}"


@pytest.mark.parametrize("name", sorted(STAGES))
def test_the_key_covers_every_project_module_the_stage_loads(name):
    """Import the stage in a fresh interpreter and call nothing: every
    project module loaded is among the files its key hashes. (Imports inside
    functions are covered by the same reading of the source.)"""
    code = ("import sys, json, importlib; importlib.import_module('stages.%s');"
            "print(json.dumps(sorted(getattr(m, '__file__', None) or '' for m in list(sys.modules.values()))))" % name)
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    loaded = {Path(f).resolve() for f in json.loads(out) if f}
    project = {f for f in loaded if f.is_relative_to(ROOT) and f.parts[len(ROOT.parts)] in ("pipeline", "worldlib", "stages")}
    stage_dirs = {ROOT / "stages" / other for other in STAGES if other != name}
    covered = set(stage_source_files(STAGES[name].source_dir))
    for f in project:
        if any(f.is_relative_to(d) for d in stage_dirs):
            continue  # the registry imports every stage when asked; not this stage's code
        assert f in covered, f"stage {name} loads {f.relative_to(ROOT)}, which its key does not cover"


@pytest.fixture(scope="module")
def project_copy(tmp_path_factory):
    """pipeline/, worldlib/, stages/ and configs/ in a temporary folder, to edit."""
    root = tmp_path_factory.mktemp("copy")
    for folder in ("pipeline", "worldlib", "stages", "configs"):
        shutil.copytree(ROOT / folder, root / folder, ignore=shutil.ignore_patterns("__pycache__"))
    return root


def _hashes(root: Path) -> dict[str, str]:
    stage_source_hash.cache_clear()
    return {name: stage_source_hash(root / "stages" / name) for name in STAGES}


def _erosion_key(root: Path) -> str:
    """The erosion step's recipe (its key but for the inputs' content, which
    is the same here) for the default config with stream power on, hashing
    the sources in `root`."""
    stage_source_hash.cache_clear()
    stages = {n: replace(s, source_dir=root / "stages" / n) for n, s in STAGES.items()}
    config = load_config(ROOT / "configs" / "default.toml", stages, project_root=ROOT,
                         sets=["erosion.geological_years=100000", "outputs=['erosion']"])
    steps = plan_bake(build_graph(stages), config)
    return next(ps.recipe for ps in steps if ps.stage.name == "erosion")


def test_editing_the_flow_kernels_changes_erosions_key(project_copy):
    kernels = project_copy / "worldlib" / "flow" / "kernels.cl"
    text = kernels.read_text()
    marker = "#define ACC_T uint"
    before = _erosion_key(project_copy)
    hydrology_before = _hashes(project_copy)["hydrology"]
    try:
        edited = text.replace(marker, "#define ACC_T ulong")
        assert edited != text
        kernels.write_text(edited)
        assert _erosion_key(project_copy) != before
        assert _hashes(project_copy)["hydrology"] != hydrology_before
    finally:
        kernels.write_text(text)
        stage_source_hash.cache_clear()


def _changed_by(root: Path, rel: str, old: str, new: str) -> set[str]:
    """The stages whose source hash changes when `old` becomes `new` in the
    file `rel` of the copy (restored after)."""
    path = root / rel
    text = path.read_text()
    assert old in text
    before = _hashes(root)
    try:
        path.write_text(text.replace(old, new))
        after = _hashes(root)
    finally:
        path.write_text(text)
        stage_source_hash.cache_clear()
    return {n for n in STAGES if after[n] != before[n]}


def test_editing_a_shared_header_changes_the_keys_of_the_stages_including_it(project_copy):
    changed = _changed_by(project_copy, "worldlib/cl/worldbake_hash.h", "h ^= h >> 15;", "h ^= h >> 14;")
    including = {n for n in STAGES if any('#include "worldbake_hash.h"' in p.read_text()
                                          for p in (project_copy / "stages" / n).glob("*.cl"))}
    assert including == {"heightmap", "vegetation"} and changed == including


def test_editing_the_d8_header_changes_the_keys_of_the_stages_routing_flow(project_copy):
    changed = _changed_by(project_copy, "worldlib/cl/worldbake_d8.h", "{-1, -1, 0, 1, 1, 1, 0, -1}",
                          "{-1, -1, 0, 1, 1, 1, 0, 1}")
    assert changed >= {"erosion", "hydrology"}


def _comment_edits(path: Path) -> str:
    """The file with comments added and changed and blank lines inserted,
    its code untouched."""
    text = path.read_text()
    if path.suffix == ".py":
        text = "# an added comment line\n\n" + text.replace("  # ", "  #  edited: ", 3)
        return text.replace("\n\n\n", "\n\n\n\n", 2) + "\n# trailing comment\n"
    return "/* an added comment */\n\n" + text.replace("/*", "/* edited:", 3) + "\n// trailing comment\n"


def test_comment_only_edits_change_no_key(project_copy):
    before = _hashes(project_copy)
    edited: dict[Path, str] = {}
    try:
        for folder in ("stages", "worldlib", "pipeline"):
            for path in (project_copy / folder).rglob("*"):
                if path.suffix in (".py", ".cl", ".h") and "__pycache__" not in path.parts:
                    edited[path] = path.read_text()
                    path.write_text(_comment_edits(path))
                    if path.suffix == ".py":
                        ast.parse(path.read_text())  # the edit kept the file valid
        assert _hashes(project_copy) == before
    finally:
        for path, text in edited.items():
            path.write_text(text)
        stage_source_hash.cache_clear()


def test_a_code_edit_in_a_stage_changes_only_that_stages_key(project_copy):
    assert _changed_by(project_copy, "stages/world/stage.py", "\nSTAGE = Stage(", "\nEXTRA = 1\nSTAGE = Stage(") == {"world"}


def _docstring_nodes(tree: ast.AST) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body \
                and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant):
            ids.add(id(node.body[0].value))
    return ids


def test_the_engine_names_no_stage():
    """pipeline/ is stage-agnostic: no string in its code is a stage's name
    or one of its artifacts' names (examples in docstrings, comments and help
    texts are words, not dependencies; the keys of the engine's own JSON
    name the engine's notions)."""
    # "world" is also the engine's own notion (a baked world: build/worlds/<name>)
    names = (set(STAGES) - {"world"}) | {a.name for s in STAGES.values() for a in s.outputs}
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        tree = ast.parse(path.read_text())
        skip = _docstring_nodes(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Dict):
                skip.update(id(k) for k in node.keys if k is not None)
            if isinstance(node, ast.Subscript):
                skip.add(id(node.slice))
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
                assert node.value not in names, f"{path.relative_to(ROOT)}:{node.lineno} names {node.value!r}"


def _domain_words() -> tuple[set[str], tuple[str, ...]]:
    """Names the engine must not hold: the stages' declared channels, the
    species (configs/species and the default world's), the ground types and
    the plant assets' variant sets, variants and customData keys; and the
    fixed heads of channel patterns ("density.") and of channel groups
    ("splat.")."""
    import tomllib

    from worldlib.ground import GROUND_TYPES

    channels = {c for s in STAGES.values() for a in s.outputs for c in a.channels} | \
               {c for s in STAGES.values() for i in s.inputs for c in i.channels}
    default = tomllib.loads((ROOT / "configs" / "default.toml").read_text())
    species = {p.stem for p in (ROOT / "configs" / "species").glob("*.toml")} | \
        set(default.get("vegetation", {}).get("species", {}))
    variants = {"lod", "impostor", "worldbake:lod_switch_m", "worldbake:impostor"} | {f"LOD{i}" for i in range(10)}
    names = {c for c in channels if "{" not in c} | species | set(GROUND_TYPES) | variants
    heads = {c.split("{")[0] for c in channels if "{" in c} | {c.split(".")[0] + "." for c in channels if "." in c}
    return names, tuple(sorted(heads))


# The grid's one exception: a Grid made without channel names holds heights
# (pipeline.grid.Grid's default, which dozens of stage calls rely on).
GRID_DEFAULT = ("pipeline/grid.py", "height")


def test_the_engine_names_no_channel_species_ground_type_or_variant():
    """No string in pipeline/'s code (docstrings aside; dictionary keys
    included) is a declared channel, begins with a channel pattern's fixed
    head, or names a species, a ground type or a plant asset's variant: the
    report, say, shows maps and tables because stages declare them."""
    names, heads = _domain_words()
    assert {"moisture", "broadleaf", "snow", "LOD0"} <= names and "density." in heads  # the lists are read
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        tree = ast.parse(path.read_text())
        skip = _docstring_nodes(tree)
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Constant) and isinstance(node.value, str)) or (rel, node.value) == GRID_DEFAULT:
                continue
            if id(node) not in skip:
                assert node.value not in names and not node.value.startswith(heads), \
                    f"{rel}:{node.lineno} names {node.value!r}"


def test_the_persisted_source_facts_give_the_same_keys_and_survive_corruption(tmp_path, monkeypatch):
    import pipeline.sources as sources

    monkeypatch.setenv("WORLDBAKE_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(sources, "_FACTS", sources._FactsCache())
    fresh = _hashes(ROOT)  # parses every file and writes the cache
    cache = tmp_path / f"source-facts-{sources.FACTS_FORMAT}.json"
    entries = json.loads(cache.read_text())
    assert len(entries) > 20
    monkeypatch.setattr(sources, "_FACTS", sources._FactsCache())
    assert _hashes(ROOT) == fresh  # read back from the file
    cache.write_text("{not json")
    monkeypatch.setattr(sources, "_FACTS", sources._FactsCache())
    assert _hashes(ROOT) == fresh  # a corrupt cache is parsed again, not trusted
    stage_source_hash.cache_clear()
