"""World configs: TOML with `extends`, `[variants.NAME]` and `--set` overrides,
every key validated before any work.

    name = "default"          # world name: build/worlds/<name>/
    seed = 1                  # the world seed, given to stages that declare uses_seed
    outputs = ["world"]       # stage or artifact names wanted (default: the stages publishing a root layer)
    extends = "base.toml"     # optional, relative to this file, inside the project
    [heightmap]               # one table per stage: its params (see README)
    octaves = 8
    [variants.rough]          # a variant: overrides baked as world "<name>-rough"
    heightmap.octaves = 12

Errors are InputError with one message naming the file, the key and what is
allowed; the CLI turns them into exit status 2.
"""
from __future__ import annotations

import copy
import hashlib
import json
import math
import re
import tomllib
import typing
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pydantic

from .contract import PROJECT_PATH, Params, Stage
from .errors import InputError

TOP_LEVEL_KEYS = {
    "name": "world name (letters, digits, - and _)",
    "seed": "integer world seed, 0 .. 2**32-1",
    "outputs": "list of stage or artifact names to bake",
    "extends": "path of a config this one overrides",
    "variants": "tables of overrides baked side by side",
    "description": "free text",
    "shared": "values of params several stages share (e.g. mesh_max_vertices), set once for all of them",
    "tiling": "how the world's cells are split into tiles for the work: tile_cells (0: one tile), keep_tiles (keep "
              "the tile units once the run is written)",
}

TILE_CELLS_MULTIPLE = 256  # a world tile is whole grid file tiles (pipeline.exr.TILE)


# Names that become file or prim names (worlds, variants, species, every
# key of a table): a safe character set and length. 64 leaves room for
# "<world>-<variant>" and for USD prim names, which may not start with a digit
# only in the prim path (the stages prefix where needed).
SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]{0,63}")
SAFE_NAME_RULE = "1 to 64 letters, digits, - and _ (not starting with -)"
MAX_DEPTH = 16  # tables nested deeper than this are refused (no config needs more than 4)
MAX_CONFIG_BYTES = 1 << 20  # a config file larger than this is refused before it is parsed
MAX_EXTENDS = 16  # a chain of extends longer than this is refused


def check_name(name: Any, where: str, key: str, what: str = "name") -> str:
    """A name that becomes part of a path: refused unless SAFE_NAME."""
    if not isinstance(name, str) or not SAFE_NAME.fullmatch(name):
        shown = repr(name) if len(repr(name)) <= 80 else repr(name)[:77] + "..."
        raise InputError(f"{where}: {key}: must be {SAFE_NAME_RULE} ({what}), got {shown}")
    return name


def _check_values(tree: Any, origin: dict[str, str], shown: str, prefix: str = "", depth: int = 0) -> None:
    """Before any schema: tables not too deep, every table key a safe name,
    every float finite (TOML has nan and inf; no parameter wants them)."""
    if depth > MAX_DEPTH:
        raise InputError(f"{origin.get(prefix.rstrip('.'), shown)}: {prefix.rstrip('.')}: tables nested more than "
                         f"{MAX_DEPTH} deep")
    items = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, list) else ()
    for k, v in items:
        key = f"{prefix}{k}" if isinstance(tree, dict) else f"{prefix.rstrip('.')}[{k}]"
        where = origin.get(key, origin.get(prefix.rstrip("."), shown))
        if isinstance(tree, dict):
            check_name(k, where, key, "a key")
        if isinstance(v, float) and not math.isfinite(v):
            raise InputError(f"{where}: {key}: must be a finite number, got {v!r}")
        if isinstance(v, (dict, list)):
            _check_values(v, origin, shown, key + ".", depth + 1)


def _check_depth(tree: dict, shown: str) -> None:
    """Refuse tables or lists nested more than MAX_DEPTH deep, read without
    recursion: a parsed file can hold nesting deeper than Python's stack
    (a dotted key of 20000 parts), which merging would recurse into."""
    todo: list[tuple[Any, str, int]] = [(tree, "", 0)]
    while todo:
        node, key, depth = todo.pop()
        if depth > MAX_DEPTH:
            shown_key = key if len(key) <= 60 else key[:57] + "..."
            raise InputError(f"{shown}: {shown_key}: tables nested more than {MAX_DEPTH} deep")
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        for k, v in items:
            if isinstance(v, (dict, list)):
                todo.append((v, f"{key}.{k}" if key and isinstance(node, dict) else f"{key}[{k}]" if key else str(k),
                             depth + 1))


# The type of each top-level key other than tables of stage params (checked
# before the stages' schemas, so a wrong type is named as such).
TOP_LEVEL_TYPES = {"name": str, "description": str, "extends": str}


@dataclass(frozen=True)
class WorldConfig:
    path: Path  # the config file given by the user
    project_root: Path
    name: str  # world name, with "-<variant>" for a variant
    variant: str | None
    seed: int
    outputs: tuple[str, ...]
    params: dict[str, Params]  # per stage, validated
    file_hashes: dict[str, str]  # "stage.param" -> sha256 of the file a ProjectPath names
    # [tiling] tile_cells: cells per side of a world tile (0: one tile); how the work is split, so in no key
    tile_cells: int = 0
    # [tiling] keep_tiles: keep a tiled run's tile units in the store once its artifacts are written (they only
    # resume a run stopped part way, and a 16384^2 hydrology's take tens of GB); how the work is done, in no key
    keep_tiles: bool = False
    origin: dict[str, str] = dataclasses.field(default_factory=dict, compare=False)  # key -> the file (or --set) it came from
    overrides: dict[str, Any] = dataclasses.field(default_factory=dict)  # --set KEY=VALUE, in order (the world's history)


def _flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v and k != "variants":
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def deep_merge(base: dict, override: dict) -> dict:
    """A new dict: `override` merged into `base`, tables recursively; neither
    input is modified. Stages use it for presets overridden by config tables."""
    return _merge(base, override, {}, "")


def _merge(base: dict, override: dict, origin: dict[str, str], source: str, prefix: str = "") -> dict:
    """Deep merge; `origin` records which file each leaf key came from."""
    out = copy.deepcopy(base)
    for k, v in override.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and isinstance(out.get(k), dict) and k != "variants":
            out[k] = _merge(out[k], v, origin, source, key + ".")
        else:
            out[k] = copy.deepcopy(v)
            for leaf in _flatten({k: v}, prefix) if isinstance(v, dict) else [key]:
                origin[leaf] = source
    return out


def _inside(path: Path, root: Path) -> bool:
    try:
        path.resolve().relative_to(root.resolve())
        return True
    except ValueError:
        return False


def _display(path: Path, root: Path) -> str:
    try:
        return str(path.resolve().relative_to(root.resolve()))
    except ValueError:
        return str(path)


def _read_toml(path: Path, root: Path, seen: tuple[Path, ...], origin: dict[str, str]) -> dict:
    shown = _display(path, root)
    if path.resolve() in seen:
        raise InputError(f"{shown}: extends forms a cycle: {' -> '.join(_display(p, root) for p in seen + (path,))}")
    if not _inside(path, root):  # resolved: a symlink to a file outside counts as outside
        raise InputError(f"{shown}: the config file is outside the project ({root}); copy it in")
    if len(seen) >= MAX_EXTENDS:
        raise InputError(f"{shown}: extends: a chain of more than {MAX_EXTENDS} config files")
    try:
        if path.stat().st_size > MAX_CONFIG_BYTES:
            raise InputError(f"{shown}: {path.stat().st_size:,} bytes; a config file may hold at most "
                             f"{MAX_CONFIG_BYTES:,} (it is read whole before any check)")
        # utf-8-sig: a byte-order mark some editors write is not part of the TOML
        raw = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise InputError(f"{shown}: config file not found") from None
    except IsADirectoryError:
        raise InputError(f"{shown}: is a folder, not a config file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{shown}: cannot read: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{shown}: not valid TOML: {e}") from None
    except RecursionError:
        raise InputError(f"{shown}: not valid TOML: nested too deep") from None
    _check_depth(raw, shown)
    parent = raw.pop("extends", None)
    if parent is None:
        base: dict = {}
    else:
        if not isinstance(parent, str):
            raise InputError(f"{shown}: extends: must be a path string, got {parent!r}")
        parent_path = (path.parent / parent)
        if not _inside(parent_path, root):
            raise InputError(f"{shown}: extends: {parent!r} leaves the project ({root})")
        base = _read_toml(parent_path, root, seen + (path.resolve(),), origin)
    return _merge(base, raw, origin, shown)


def _parse_set(assignment: str) -> tuple[str, Any]:
    """`erosion.iterations=400`: the value is read as TOML (numbers, booleans,
    strings in quotes, lists); a bare word is taken as a string."""
    if "=" not in assignment:
        raise InputError(f"--set {assignment}: expected KEY=VALUE, e.g. heightmap.octaves=8")
    key, text = (s.strip() for s in assignment.split("=", 1))
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text
    return key, value


def _set_dotted(tree: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = tree
    for p in parts[:-1]:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise InputError(f"--set {dotted}: {p} is not a table")
    node[parts[-1]] = value


def list_variants(path: Path, project_root: Path) -> list[str]:
    raw = _read_toml(path, project_root, (), {})
    variants = raw.get("variants", {})
    if not isinstance(variants, dict):
        raise InputError(f"{_display(path, project_root)}: variants: must be a table of tables")
    return list(variants)


def _format_pydantic(err: pydantic.ValidationError, stage: str, origin: dict[str, str], default_file: str,
                     model: type[Params]) -> str:
    e = err.errors()[0]
    loc = ".".join(str(p) for p in e["loc"])
    key = f"{stage}.{loc}" if loc else stage
    where = origin.get(key, default_file)
    got = e.get("input")
    msg = e["msg"]
    if e["type"] == "extra_forbidden":
        allowed = ", ".join(sorted(model.model_fields))
        return f"{where}: {key}: unknown key (allowed in [{stage}]: {allowed})"
    field = model.model_fields.get(str(e["loc"][0])) if e["loc"] else None
    hint = f"; allowed: {describe_allowed(field)}" if field is not None else ""
    return f"{where}: {key}: {msg}, got {got!r}{hint}"


def describe_allowed(field: pydantic.fields.FieldInfo) -> str:
    """'2 .. 64 cells, cells per side' from a field's declared bounds, units and description."""
    bounds = {}
    for m in field.metadata:
        for attr, name in (("ge", "Ge"), ("gt", "Gt"), ("le", "Le"), ("lt", "Lt")):
            if getattr(m, attr, None) is not None:
                bounds[name] = getattr(m, attr)
    lo = f"{bounds['Ge']}" if "Ge" in bounds else (f"> {bounds['Gt']}" if "Gt" in bounds else "")
    hi = f"{bounds['Le']}" if "Le" in bounds else (f"< {bounds['Lt']}" if "Lt" in bounds else "")
    units = (field.json_schema_extra or {}).get("units", "") if isinstance(field.json_schema_extra, dict) else ""
    parts = []
    if lo or hi:
        parts.append(f"{lo or '-inf'} .. {hi or 'inf'}" + (f" {units}" if units else ""))
    elif field.annotation is not None:
        parts.append(getattr(field.annotation, "__name__", None) or str(field.annotation).replace("typing.", ""))
    if field.description:
        parts.append(field.description)
    return ", ".join(parts)


def _is_project_path(field: pydantic.fields.FieldInfo) -> bool:
    """A ProjectPath field, also inside Optional[...] (where pydantic keeps
    the marker on the inner Annotated type rather than in field.metadata)."""
    if any(m is PROJECT_PATH for m in field.metadata):
        return True
    stack = [field.annotation]
    while stack:
        t = stack.pop()
        if PROJECT_PATH in getattr(t, "__metadata__", ()):
            return True
        stack.extend(typing.get_args(t))
    return False


def _check_paths(stage: Stage, model: Params, root: Path, origin: dict[str, str], default_file: str) -> dict[str, str]:
    hashes = {}
    for fname, field in type(model).model_fields.items():
        if not _is_project_path(field):
            continue
        value = getattr(model, fname)
        if value is None or value == "":
            continue
        key = f"{stage.name}.{fname}"
        where = origin.get(key, default_file)
        target = root / value
        if Path(value).is_absolute() or not _inside(target, root):
            raise InputError(f"{where}: {key}: {value!r} leaves the project; give a path inside {root}")
        if not target.is_file():
            raise InputError(f"{where}: {key}: file {value!r} not found (paths are relative to the project root {root})")
        hashes[key] = hashlib.sha256(target.read_bytes()).hexdigest()
    return hashes


def load_config(path: Path | str, stages: dict[str, Stage], *, project_root: Path | str | None = None,
                variant: str | None = None, sets: list[str] = ()) -> WorldConfig:
    """Read, merge and validate a world config; raise InputError on the first problem."""
    path = Path(path)
    root = Path(project_root or Path.cwd()).resolve()
    origin: dict[str, str] = {}
    overrides: dict[str, Any] = {}
    shown = _display(path, root)
    tree = _read_toml(path, root, (), origin)

    variants = tree.pop("variants", {})
    if not isinstance(variants, dict) or not all(isinstance(v, dict) for v in variants.values()):
        raise InputError(f"{shown}: variants: must be a table of tables, e.g. [variants.rough]")
    if variant is not None:
        if variant not in variants:
            raise InputError(f"{shown}: no variant {variant!r} (defined: {', '.join(variants) or 'none'})")
        if "name" in variants[variant] or "variants" in variants[variant]:
            raise InputError(f"{shown}: variants.{variant}: a variant may not set name or variants")
        tree = _merge(tree, variants[variant], origin, f"{shown} [variants.{variant}]")
    for assignment in sets:
        key, value = _parse_set(assignment)
        if key.split(".")[0] in ("extends", "variants"):
            raise InputError(f"--set {assignment}: {key.split('.')[0]} cannot be set from the command line "
                             f"(it is read before --set applies); edit the config file")
        _set_dotted(tree, key, value)
        origin[key] = "--set"
        overrides[key] = value
    _check_values(tree, origin, shown)

    for key in tree:
        if key not in TOP_LEVEL_KEYS and key not in stages:
            allowed = ", ".join(list(TOP_LEVEL_KEYS) + sorted(stages))
            raise InputError(f"{origin.get(key, shown)}: {key}: unknown key (allowed at the top level: {allowed})")

    for key, kind in TOP_LEVEL_TYPES.items():
        if key in tree and not isinstance(tree[key], kind):
            raise InputError(f"{origin.get(key, shown)}: {key}: must be a {kind.__name__} ({TOP_LEVEL_KEYS[key]}), "
                             f"got {tree[key]!r}")
    name = check_name(tree.get("name", path.stem), origin.get("name", shown), "name", "the world name")
    for v in variants:
        check_name(v, shown, f"variants.{v}", "a variant name")
    if variant is not None:
        name = f"{name}-{variant}"
    seed = tree.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**32:
        raise InputError(f"{origin.get('seed', shown)}: seed: must be an integer in 0 .. 2**32-1, got {seed!r}")
    # by default, the stages that publish a world root layer
    outputs = tree.get("outputs", sorted({s.name for s in stages.values() for a in s.outputs if a.publish}))
    if not isinstance(outputs, list) or not outputs or not all(isinstance(o, str) for o in outputs):
        raise InputError(f"{origin.get('outputs', shown)}: outputs: must be a non-empty list of stage or artifact names, got {outputs!r}")

    tile_cells = _tile_cells(tree.get("tiling", {}), origin, shown)
    keep_tiles = _keep_tiles(tree.get("tiling", {}), origin, shown)

    shared = tree.get("shared", {})
    shareable = {p for s in stages.values() for p in s.shared_params}
    if not isinstance(shared, dict):
        raise InputError(f"{origin.get('shared', shown)}: shared: must be a table")
    for key in shared:
        if key not in shareable:
            raise InputError(f"{origin.get('shared.' + key, shown)}: shared.{key}: unknown key (shared params: {', '.join(sorted(shareable)) or 'none'})")

    params: dict[str, Params] = {}
    file_hashes: dict[str, str] = {}
    for stage_name, stage in stages.items():
        table = tree.get(stage_name, {})
        if not isinstance(table, dict):
            raise InputError(f"{origin.get(stage_name, shown)}: {stage_name}: must be a table of parameters, got {table!r}")
        table = dict(table)
        for key in stage.shared_params:
            if key in shared and key not in table:
                table[key] = shared[key]
                origin.setdefault(f"{stage_name}.{key}", origin.get(f"shared.{key}", shown))
        try:
            # strict: a TOML string "8" is not an integer; ints are still floats
            model = stage.params.model_validate(table, strict=True)
        except pydantic.ValidationError as err:
            raise InputError(_format_pydantic(err, stage_name, origin, shown, stage.params)) from None
        params[stage_name] = model
        file_hashes.update(_check_paths(stage, model, root, origin, shown))

    for key in shareable:
        values = {name: getattr(params[name], key) for name, st in stages.items() if key in st.shared_params}
        if len(set(map(repr, values.values()))) > 1:
            listing = ", ".join(f"{name}.{key} = {v!r}" for name, v in values.items())
            raise InputError(f"{shown}: {listing}: these must agree; set it once as shared.{key}")

    if variant is None:
        # every variant's keys are checked whichever world is baked
        for other in variants:
            load_config(path, stages, project_root=root, variant=other, sets=sets)
    return WorldConfig(path=path, project_root=root, name=name, variant=variant, seed=seed,
                       outputs=tuple(outputs), params=params, file_hashes=file_hashes, tile_cells=tile_cells,
                       keep_tiles=keep_tiles, origin=dict(origin), overrides=overrides)


def _keep_tiles(tiling: dict, origin: dict[str, str], shown: str) -> bool:
    """[tiling] keep_tiles: true or false (default)."""
    value = tiling.get("keep_tiles", False)
    if not isinstance(value, bool):
        raise InputError(f"{origin.get('tiling.keep_tiles', shown)}: tiling.keep_tiles: must be true or false, "
                         f"got {value!r}")
    return value


def _tile_cells(tiling: Any, origin: dict[str, str], shown: str) -> int:
    """[tiling] tile_cells: 0 (one tile) or a positive multiple of TILE_CELLS_MULTIPLE."""
    if not isinstance(tiling, dict):
        raise InputError(f"{origin.get('tiling', shown)}: tiling: must be a table, e.g. [tiling] tile_cells = 1024")
    for key in tiling:
        if key not in ("tile_cells", "keep_tiles"):
            raise InputError(f"{origin.get('tiling.' + key, shown)}: tiling.{key}: unknown key (allowed: tile_cells, "
                             f"keep_tiles)")
    value = tiling.get("tile_cells", 0)
    if (not isinstance(value, int) or isinstance(value, bool) or value < 0 or value % TILE_CELLS_MULTIPLE
            or value > 1 << 20):
        raise InputError(f"{origin.get('tiling.tile_cells', shown)}: tiling.tile_cells: must be 0 (one tile) or a "
                         f"positive multiple of {TILE_CELLS_MULTIPLE} up to {1 << 20}, got {value!r}")
    return value


def canonical_params(model: Params) -> str:
    """The canonical JSON of a stage's params: sorted keys, no whitespace;
    what the cache key and the provenance hold."""
    return json.dumps(model.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
