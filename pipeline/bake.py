"""Keys, planning and running: what `worldbake plan` and `worldbake bake` do.

The cache key of a stage run hashes its name and version, the normalised
text of every source file it can load (pipeline.sources), its canonical
params, the bytes of the files its params name, the content hashes of the
input artifacts it reads (from their producers' manifests: early cutoff),
the seed when it uses one, and the versions of the libraries (and the
OpenCL device) that change its numbers. Never mtimes.
"""
from __future__ import annotations

import fnmatch
import functools
import hashlib
import json
import math
import os
import re
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import exr, tiles, usdio
from .config import WorldConfig, canonical_params
from .contract import Artifact, Check, CheckContext, GridInfo, ParamError, RunContext, Stage
from .errors import InputError, StageError
from .graph import Graph, Step, plan
from .grid import Grid
from .limits import work_refusal
from .sources import stage_source_hash
from .store import MANIFEST, Store, sha256_file, write_json
from .units import Units

# Bump when the engine changes how artifacts are written (file formats,
# provenance layout), so that old keys stop matching.
ENGINE_FORMAT = 2  # 2: grids are tiled EXR (pipeline.exr.GridWriter)
KEY_LENGTH = 20  # hex digits of sha256 kept in folder names (80 bits)


@functools.lru_cache(maxsize=None)
def _fixed_library_versions() -> tuple[tuple[str, str], ...]:
    import OpenImageIO
    import pyopencl
    from pxr import Usd

    return (("numpy", np.__version__), ("OpenImageIO", OpenImageIO.VERSION_STRING),
            ("usd", ".".join(map(str, Usd.GetVersion()))), ("engine_format", str(ENGINE_FORMAT)),
            ("pyopencl", pyopencl.VERSION_TEXT))


def library_versions(uses_opencl: bool) -> dict[str, str]:
    """The versions that change numbers; with OpenCL, the device in use (asked
    each time: tests switch devices with opencl.use_device)."""
    versions = dict(_fixed_library_versions())
    if uses_opencl:
        from .opencl import get_cl

        versions["opencl_device"] = get_cl().fingerprint
    else:
        del versions["pyopencl"]
    return versions


def _digest(material: dict) -> str:
    return hashlib.sha256(json.dumps(material, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:KEY_LENGTH]


@dataclass(frozen=True)
class PlannedStep:
    """A step as the config alone defines it, before its inputs exist.

    `recipe` hashes everything of the key but the inputs' content, with the
    producers' recipes in its place: it names the step while planning (the
    same recipe needed by two worlds is one task). The key itself is known
    only once the inputs are made (key_step)."""

    stage: Stage
    recipe: str
    inputs: dict[str, tuple[str, str]]  # role -> (artifact name, producer stage)
    params_json: str
    material: dict[str, Any]  # the key material without the inputs


@dataclass(frozen=True)
class KeyedStep:
    """A step whose inputs are made: its cache key and where its inputs are."""

    stage: Stage
    key: str
    inputs: dict[str, tuple[str, str, str]]  # role -> (artifact name, producer stage, producer key)
    params_json: str
    key_material: dict[str, Any]


def plan_bake(graph: Graph, config: WorldConfig) -> list[PlannedStep]:
    enabled = {name: p.enabled for name, p in config.params.items()}
    steps = plan(graph, enabled, config.outputs, str(config.path))
    recipes: dict[str, str] = {}
    planned = []
    for step in steps:
        stage = step.stage
        params_json = canonical_params(config.params[stage.name])
        inputs = {role: (art, graph.producers[art][0].name) for role, art in sorted(step.inputs.items())}
        material = {
            "stage": stage.name,
            "version": stage.version,
            "source": stage_source_hash(stage.source_dir),
            "params": json.loads(params_json),
            "files": {k: v for k, v in sorted(config.file_hashes.items()) if k.startswith(stage.name + ".")},
            "seed": config.seed if stage.uses_seed else None,
            "libraries": library_versions(stage.uses_opencl),
        }
        recipe = _digest({**material, "inputs": {r: [a, recipes[p]] for r, (a, p) in inputs.items()}})
        recipes[stage.name] = recipe
        planned.append(PlannedStep(stage, recipe, inputs, params_json, material))
    return planned


def artifact_content_hash(manifest: dict, artifact: Artifact, producer: Stage) -> str:
    """What a consumer of `artifact` reads, as one hash: the content hash the
    engine recorded when writing it (grids: the values; json: the canonical
    text), else the file hashes of the producer's manifest: the artifact's
    file, and for USD layers and textures also the files beside it that no
    other output names (the layers and images it references)."""
    if manifest.get("outputs", {}).get(artifact.name, {}).get("absent"):
        return "absent"
    recorded = manifest.get("outputs", {}).get(artifact.name, {}).get("content")
    if recorded:
        return recorded
    files = manifest["files"]
    if artifact.kind in ("usd", "texture"):
        others = {a.file for a in producer.outputs if a.name != artifact.name} | {MANIFEST}
        parts = {f: h for f, h in files.items() if f not in others}
    else:
        parts = {artifact.file: files[artifact.file]}
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


def key_step(ps: PlannedStep, store: Store, graph: Graph, keys: dict[str, str]) -> KeyedStep:
    """The key of a planned step whose producers have run (keys: stage ->
    the key it ran or was cached under). Early cutoff: the key hashes the
    content of the inputs, not the producers' keys, so a producer that re-ran
    and wrote the same bytes leaves this key as it was."""
    inputs, content = {}, {}
    for role, (art, producer) in ps.inputs.items():
        inputs[role] = (art, producer, keys[producer])
        producer_stage, artifact = graph.producers[art]
        content[role] = [art, artifact_content_hash(store.manifest(producer, keys[producer]), artifact, producer_stage)]
    material = {**ps.material, "inputs": content}
    return KeyedStep(ps.stage, _digest(material), inputs, ps.params_json, material)


# --------------------------------------------------------------------------- checking


def memory_limit_bytes() -> tuple[float, str]:
    """What a bake may hold at once: WORLDBAKE_MAX_MEMORY_GB when set, else
    80 % of the machine's physical memory (the rest is the system's and the
    other processes')."""
    env = os.environ.get("WORLDBAKE_MAX_MEMORY_GB", "").strip()
    if env:
        try:
            return float(env) * 2**30, f"WORLDBAKE_MAX_MEMORY_GB = {env}"
        except ValueError:
            raise InputError(f"WORLDBAKE_MAX_MEMORY_GB = {env!r}: must be a number of GiB") from None
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return 0.8 * total, f"80 % of this machine's {total / 2**30:.1f} GiB"


def _origin_of(config: WorldConfig, key: str) -> str:
    """The file (or --set) a key or the table holding it came from."""
    parts = key.split(".")
    for n in range(len(parts), 0, -1):
        prefix = ".".join(parts[:n])
        for k, where in config.origin.items():
            if k == prefix or k.startswith(prefix + "."):
                return where
    return str(config.path)


def _size_keys(config: WorldConfig, stage: Stage, result: Check, inputs: dict[str, GridInfo]) -> list[str]:
    """The config keys that set the size of a stage's run, most direct first:
    those its memory estimate names (`world.texture_size`, or a bare param
    of its own: `atlas_px`), the keys that set its own grids', then its
    inputs' (GridInfo.set_by, the largest grid first)."""
    keys = []
    for a, b in re.findall(r"\b([a-z_][a-z0-9_]*)\.([a-z_][a-z0-9_]*)\b", result.memory_how):
        if a in config.params and b in type(config.params[a]).model_fields:
            keys.append(f"{a}.{b}")
    own = type(config.params[stage.name]).model_fields
    keys += [f"{stage.name}.{k}" for k in re.findall(r"(?<![.\w])([a-z_][a-z0-9_]*) =", result.memory_how) if k in own]
    keys += [g.set_by for g in result.grids.values() if g.set_by]
    keys += [g.set_by for g in sorted(inputs.values(), key=lambda g: -g.shape[0] * g.shape[1]) if g.set_by]
    return keys


def _memory_origin(config: WorldConfig, stage: Stage, result: Check, inputs: dict[str, GridInfo]) -> str:
    """The file (or --set) that set the size a memory refusal is about: of
    _size_keys, the first some file sets; else the stage's table's."""
    for key in _size_keys(config, stage, result, inputs):
        if key in config.origin:
            return config.origin[key]
    return _origin_of(config, stage.name)


def check_world(graph: Graph, config: WorldConfig) -> dict[str, Check]:
    """Every planned stage's check, in plan order, before any work: bad
    values, unreadable files and runs too large for the machine are an
    InputError naming the config file and key (a run estimated past its
    memory or its stated work limit too: pipeline.limits)."""
    limit, limit_how = memory_limit_bytes()
    sizes: dict[str, GridInfo] = {}  # artifact name -> size
    results = {}
    for ps in plan_bake(graph, config):
        stage = ps.stage
        inputs = {role: sizes[art] for role, (art, _) in ps.inputs.items() if art in sizes}
        ctx = CheckContext(seed=config.seed, project_root=config.project_root, inputs=inputs,
                           tile_cells=config.tile_cells if stage.run_tiled is not None else 0)
        params = config.params[stage.name]
        result = Check()
        if stage.check is not None:
            try:
                result = stage.check(params, ctx) or Check()
            except ParamError as e:
                key = f"{stage.name}.{e.key}" if e.key else stage.name
                raise InputError(f"{_origin_of(config, key)}: {key}: {e.message}") from None
        terrain = next((inputs[i.role] for i in stage.inputs if i.role in inputs
                        and graph.producers[ps.inputs[i.role][0]][1].shape == "terrain"), None)
        for art in stage.outputs:
            if art.kind == "grid":
                info = result.grids.get(art.name) or (terrain if art.shape == "terrain" else None)
                if info is not None:
                    sizes[art.name] = info
        if result.memory_bytes > limit:
            grids = "".join(f"; its input {role} is {g.shape[0]} x {g.shape[1]} cells"
                            + (f", set by {g.set_by}" if g.set_by else "") for role, g in inputs.items())
            raise InputError(f"{_memory_origin(config, stage, result, inputs)}: {stage.name}: the run would hold "
                             f"about {result.memory_bytes / 2**30:.1f} GiB ({result.memory_how}), more than the "
                             f"{limit / 2**30:.1f} GiB a bake may use ({limit_how}){grids}; lower the sizes named")
        too_much = work_refusal(stage.name, result.work, result.work_limit, result.work_unit, result.work_how)
        if too_much:
            # the param the stage names, else the file that set its inputs' size (as a memory refusal)
            key = f"{stage.name}.{result.work_key}" if result.work_key else stage.name
            origin = _origin_of(config, key) if result.work_key else _memory_origin(config, stage, result, inputs)
            raise InputError(f"{origin}: {key}: {too_much}")
        results[stage.name] = result
    return results


# --------------------------------------------------------------------------- running


def _load_input(store: Store, artifact: Artifact, producer: str, key: str) -> Any:
    path = store.folder(producer, key) / artifact.file
    if artifact.kind == "grid":
        return exr.read_grid(path)
    if artifact.kind == "json":
        return json.loads(path.read_text())
    return path


def _check_grid(stage: Stage, art: Artifact, value: Any, terrain_shape: tuple[int, int] | None) -> Grid:
    if not isinstance(value, Grid):
        raise StageError(f"stage {stage.name}: output {art.name} must be a Grid, got {type(value).__name__}")
    wrong = art.channel_sets(tuple(value.channels))
    if wrong:
        raise StageError(f"stage {stage.name}: output {art.name} {wrong}")
    if value.data.dtype != np.dtype(art.dtype):
        raise StageError(f"stage {stage.name}: output {art.name} is {value.data.dtype}, declared {art.dtype}")
    if art.shape == "terrain" and terrain_shape is not None and value.shape != terrain_shape:
        raise StageError(f"stage {stage.name}: output {art.name} has shape {value.shape}, the terrain is {terrain_shape}")
    bad = np.isinf(value.data) if art.nodata_nan else ~np.isfinite(value.data)
    if bad.any():
        r, c = np.argwhere(bad)[0][:2]
        raise StageError(f"stage {stage.name}: output {art.name} has {int(bad.sum())} non-finite values "
                         f"(first at row {r}, col {c}); not written")
    return value


def _declared_file(stage: Stage, name: str) -> bool:
    """A file in a run's folder that some output declares: its file, or
    one its `beside` patterns match."""
    return any(name == a.file or any(fnmatch.fnmatchcase(name, pat) for pat in a.beside) for a in stage.outputs)


def _finite_metrics(metrics: dict) -> dict:
    """JSON cannot hold NaN; a diagnostic that is not finite is shown as text."""
    def fix(v):
        if isinstance(v, dict):
            return {k: fix(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [fix(x) for x in v]
        if isinstance(v, (np.floating, float)):
            return float(v) if math.isfinite(v) else str(v)
        if isinstance(v, np.integer):
            return int(v)
        return v
    return fix(metrics)


def run_step(store: Store, ps: KeyedStep, config: WorldConfig, graph: Graph,
             progress: Callable[[float, str], None]) -> dict:
    """Run one stage into a temporary folder and rename it into place."""
    stage = ps.stage
    tiled = bool(config.tile_cells) and stage.run_tiled is not None
    inputs = {}
    terrain_shape = None
    for role, (art_name, producer, key) in ps.inputs.items():
        art = graph.producers[art_name][1]
        if art.optional and store.manifest(producer, key)["outputs"].get(art_name, {}).get("absent"):
            continue  # the producer wrote nothing for it (its consumers take it as optional)
        if tiled and art.kind == "grid":  # read by window, never whole
            inputs[role] = tiles.GridFile(store.folder(producer, key) / art.file)
        else:
            inputs[role] = _load_input(store, art, producer, key)
        if art.kind == "grid" and art.shape == "terrain":
            terrain_shape = inputs[role].shape
    provenance = {"stage": stage.name, "version": stage.version, "key": ps.key,
                  "params": ps.params_json, "seed": config.seed if stage.uses_seed else "none"}
    # a unit's key: the stage's code and the unit's own material (its inputs' content, the params it uses)
    code_material = {k: ps.key_material[k] for k in ("stage", "version", "source", "files", "seed", "libraries")}
    # the device this process chose (a Dask worker chooses its own), handed to the stage
    device = None
    if stage.uses_opencl:
        from .opencl import get_cl

        device = get_cl()
    with store.writing(stage.name, ps.key) as work:
        ctx = RunContext(stage=stage, key=ps.key, out_dir=work, seed=config.seed, provenance=provenance,
                         project_root=config.project_root, progress=progress,
                         final_dir=store.folder(stage.name, ps.key),
                         input_artifacts={role: art for role, (art, _, _) in ps.inputs.items() if role in inputs},
                         units=Units(store.units, store.tmp, stage.name, code_material), cl=device)
        tile_work = store.tmp / f"tiles-{stage.name}-{ps.key}-{os.getpid()}"
        if tiled:
            ctx.tiles = tiles.TileRunner(config.tile_cells, stage=stage, run_key=ps.key, seed=config.seed,
                                         project_root=config.project_root, units=ctx.units, work=tile_work,
                                         progress=progress)
        t0 = time.perf_counter()
        try:
            run = stage.run_tiled if tiled else stage.run
            outputs = run(ctx, inputs, config.params[stage.name])
        except FloatingPointError as e:
            shutil.rmtree(tile_work, ignore_errors=True)
            raise StageError(f"stage {stage.name}: numerical failure: {e}") from e
        except BaseException:
            shutil.rmtree(tile_work, ignore_errors=True)
            raise
        dropped_tiles = tiled and not config.keep_tiles  # the tile units go once the run is in place
        if tiled:
            ctx.metrics["tiling"] = {"tile_cells": config.tile_cells, "passes": ctx.tiles.passes,
                                     "tile_units_kept": not dropped_tiles}
        t_run = time.perf_counter() - t0
        missing = [a.name for a in stage.outputs if a.name not in outputs and not a.optional]
        extra = [n for n in outputs if n not in {a.name for a in stage.outputs}]
        if missing or extra:
            raise StageError(f"stage {stage.name}: returned {sorted(outputs)}, declared {[a.name for a in stage.outputs]}")
        t1 = time.perf_counter()
        out_meta = _write_outputs(stage, outputs, work, provenance, terrain_shape)
        written = [p for p in sorted(work.rglob("*")) if p.is_file()]
        files = {p.relative_to(work).as_posix(): sha256_file(p) for p in written}
        # size and mtime as written: a later bake notices a file changed since (Store.damaged) without hashing it
        file_stats = {p.relative_to(work).as_posix(): [p.stat().st_size, p.stat().st_mtime_ns] for p in written}
        undeclared = [f for f in files if not _declared_file(stage, f)]
        if undeclared:
            raise StageError(f"stage {stage.name}: wrote files no output declares: {undeclared[:10]} "
                             f"(declare them as artifacts, or in an artifact's `beside` patterns)")
        manifest = {
            "stage": stage.name, "version": stage.version, "key": ps.key,
            "params": json.loads(ps.params_json), "seed": provenance["seed"],
            "inputs": {role: {"artifact": a, "stage": s, "key": k, "content": ps.key_material["inputs"][role][1]}
                       for role, (a, s, k) in ps.inputs.items()},
            "outputs": out_meta, "files": files, "file_stats": file_stats,
            "units": dict(sorted((name, key) for name, key in ctx.units.used.items()
                                 if not dropped_tiles or name not in ctx.tiles.tile_units)),
            "exr_channels": {f: exr.channel_names(work / f) for f in files if f.lower().endswith(".exr")},
            "timings": {"run_s": round(t_run, 4), "write_s": round(time.perf_counter() - t1, 4)},
            "metrics": _finite_metrics(ctx.metrics),
            "key_material": ps.key_material,
        }
        write_json(work / MANIFEST, manifest)  # last: its presence means the folder is whole
    shutil.rmtree(tile_work, ignore_errors=True)  # the tiles' arrays live on in their units
    if dropped_tiles:
        ctx.tiles.drop_units()
    return manifest


def _write_outputs(stage: Stage, outputs: dict[str, Any], work: Path, provenance: dict,
                   terrain_shape: tuple[int, int] | None) -> dict[str, dict]:
    """Each declared output into its file in `work` (grids held whole or per
    tile, previews, JSON; USD and textures the stage wrote itself, checked);
    the manifest's entry of each."""
    out_meta = {}
    for art in stage.outputs:
        value = outputs.get(art.name)
        target = work / art.file
        meta: dict[str, Any] = {"file": art.file, "kind": art.kind, "units": art.units}
        if value is None:
            if not art.optional:
                raise StageError(f"stage {stage.name}: output {art.name} is None but not declared optional")
            out_meta[art.name] = {**meta, "absent": True}
            continue
        if art.kind == "grid" and isinstance(value, tiles.TileArrays):
            units = art.channel_units(tuple(value.channels))
            content = _write_tiled_grid(stage, art, value, terrain_shape, target, {**provenance, "units": units})
            terrain_shape = terrain_shape or (value.shape if art.shape == "terrain" else None)
            meta.update(channels=exr.channel_names(target), channel_units=units, shape=list(value.shape),
                        cell_size_m=value.cell_size_m, content=content)
        elif art.kind == "grid":
            grid = _check_grid(stage, art, value, terrain_shape)
            terrain_shape = terrain_shape or (grid.shape if art.shape == "terrain" else None)
            units = art.channel_units(tuple(grid.channels))
            exr.write_grid(target, grid, {**provenance, "units": units})
            # the file's order (OpenEXR sorts channels by name), not the order the stage made them in
            meta.update(channels=exr.channel_names(target), channel_units=units, shape=list(grid.shape),
                        cell_size_m=grid.cell_size_m, content=grid.content_hash())
        elif art.kind == "image" and isinstance(value, tiles.TileArrays):
            exr.write_png_rows(target, value.shape, _tile_rows(value))
        elif art.kind == "image":
            exr.write_png(target, value)
        elif art.kind == "json":
            write_json(target, _finite_metrics(value))
            meta["content"] = sha256_file(target)
        elif art.kind in ("usd", "texture"):
            if Path(value).resolve() != target.resolve() or not target.is_file():
                raise StageError(f"stage {stage.name}: output {art.name} must be written to ctx.path({art.name!r})")
        out_meta[art.name] = meta
    return out_meta


def _tile_rows(arrays: tiles.TileArrays):
    """The rows of tiles of a tiled grid, each as one array, north to south."""
    by_row: dict[int, list[tiles.Tile]] = {}
    for t in arrays.tiles():
        by_row.setdefault(t.row, []).append(t)
    for row in sorted(by_row):
        yield np.concatenate([arrays.tile_array(t) for t in by_row[row]], axis=1)


def _write_tiled_grid(stage: Stage, art: Artifact, value: tiles.TileArrays, terrain_shape: tuple[int, int] | None,
                      target: Path, provenance: dict) -> str:
    """A grid output held per tile, written into its EXR tile by tile (the
    bytes of write_grid of the whole map); returns its content hash."""
    wrong = art.channel_sets(tuple(value.channels))
    if wrong:
        raise StageError(f"stage {stage.name}: output {art.name} {wrong}")
    if art.shape == "terrain" and terrain_shape is not None and value.shape != terrain_shape:
        raise StageError(f"stage {stage.name}: output {art.name} has shape {value.shape}, the terrain is {terrain_shape}")
    with exr.GridWriter(target, value.shape, value.channels, value.cell_size_m, value.origin_m, provenance) as out:
        for t in value.tiles():
            block = value.tile_array(t)
            if block.dtype != np.dtype(art.dtype):
                raise StageError(f"stage {stage.name}: output {art.name} is {block.dtype}, declared {art.dtype}")
            bad = np.isinf(block) if art.nodata_nan else ~np.isfinite(block)
            if bad.any():
                r, c = np.argwhere(bad)[0][:2]
                raise StageError(f"stage {stage.name}: output {art.name} has {int(bad.sum())} non-finite values in "
                                 f"tile {t.name} (first at row {t.row0 + r}, col {t.col0 + c}); not written")
            out.write_window(t.row0, t.col0, block)
    return out.content_hash()


# --------------------------------------------------------------------------- publishing


def publish_world(store: Store, config: WorldConfig, planned: list[KeyedStep], steps: list | None = None) -> Path:
    """build/worlds/<name>/: manifest.json naming every artifact key used
    (with early cutoff, a cached step may reference the output of an earlier
    run of its producer: those are named too, so gc keeps them), the
    --set overrides and each stage's params (what `worldbake worlds` and
    `worldbake diff` read), how each step went (`steps`: StepReports), and,
    when a planned stage publishes a root layer, world.usda composing it by a
    relative path, with the overrides in its customLayerData; then
    report.html beside them (pipeline.report)."""
    reporting = os.environ.get("WORLDBAKE_REPORT", "1").strip() != "0"  # 0: no report (the test suite's many bakes)
    with store.publishing(config.name) as work:
        roots = [(ps, art) for ps in planned for art in ps.stage.outputs if art.publish]
        if roots:
            ps, art = roots[-1]
            target = store.folder(ps.stage.name, ps.key) / art.file
            # relative to the final folder, not to work/ (a temporary folder elsewhere)
            final_layer = store.worlds / config.name / "world.usda"
            usdio.write_root_layer(work / "world.usda",
                                   {"world": config.name, "config": str(config.path), "seed": config.seed, "key": ps.key,
                                    "overrides": config.overrides},
                                   [usdio.relative_asset_path(target, final_layer)])
        manifest = {
            "world": config.name, "config": str(config.path), "variant": config.variant, "seed": config.seed,
            "outputs": list(config.outputs), "overrides": config.overrides,
            "params": {ps.stage.name: json.loads(ps.params_json) for ps in planned},
            "artifacts": [{"stage": ps.stage.name, "key": ps.key} for ps in planned],
            "uses": [{"stage": s, "key": k} for s, k in sorted(store.closure({(ps.stage.name, ps.key) for ps in planned}))],
            "steps": [{"stage": r.stage, "key": r.key, "status": r.status, "seconds": round(r.seconds, 3)}
                      for r in steps or ()],
        }
        write_json(work / MANIFEST, manifest)
        if reporting:
            from .report import carry_figures

            carry_figures(store.worlds / config.name, work)
    final = store.worlds / config.name
    if reporting:
        from .report import write_report  # after the rename: the layer's relative paths resolve from there

        world_usda = final / "world.usda"
        write_report(store, final, manifest, world_usda if world_usda.is_file() else None)
    return final


# --------------------------------------------------------------------------- the bake


@dataclass
class StepReport:
    stage: str
    key: str
    status: str  # "ran" or "cached"
    seconds: float
    metrics: dict = field(default_factory=dict)


def _progress_printer(stage: str, stream=sys.stderr) -> Callable[[float, str], None]:
    last = [0.0]

    def show(fraction: float, message: str) -> None:
        now = time.monotonic()
        if now - last[0] >= 1.0 or fraction >= 1.0:
            last[0] = now
            print(f"    {stage}: {100 * fraction:5.1f} %  {message}", file=stream, flush=True)
    return show
