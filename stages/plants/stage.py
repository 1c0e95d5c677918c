"""The plants stage: for every species the scene needs, a USD plant asset
(trunk and branches as one watertight solid, leaves or needles, or grass
blades and tufts) with normals, UVs, a material, wind primvars and a chain
of LODs whose geometric error is measured and stored in the asset.

Species are data: configs/species/<name>.toml presets (conifer, broadleaf,
shrub, grass), available by name, plus any `[plants.species.NAME]` table of
the config (optionally `preset = "conifer"` with overrides). Only the species
listed in `build` are meshed (the vegetation stage will say which were placed).

Outputs, in the artifact folder: plants.usda (defaultPrim /Plants, kind
group, one child per species referencing ./<species>.usdc) and the species
files. Metrics: per species the module, segment, leaf and triangle counts,
the woody solid's checks, each LOD's triangles, Hausdorff error and times.
"""
from __future__ import annotations

import functools
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import pydantic

from pipeline import usdio
from pipeline.contract import (Artifact, Check, CheckContext, Input, Param, ParamError, Params, ReportTable, RunContext,
                               Stage)
from pipeline.errors import InputError, StageError
from worldlib import images, materials

from . import measure, textures
from .asset import write_species, write_top
from .lsystem import compile_lsystem
from .plant import PlantResult, Settings, build_plant, species_seeds
from .report_tables import instance_and_lod_tables
from .species import SpeciesShape, preset_tables, resolve_species


def _default_species() -> dict[str, SpeciesShape]:
    return {k: SpeciesShape.model_validate(v) for k, v in resolve_species({}, preset_tables()).items()}


PRESETS = _default_species()


class PlantsParams(Params):
    species: dict[str, SpeciesShape] = Param(
        PRESETS, description="species by name: the presets of configs/species/*.toml plus the config's own tables "
        "(a table with preset = NAME is merged over that preset)")
    build: list[str] = Param(sorted(PRESETS), description="the species to mesh (those the vegetation map placed); the others cost nothing")
    lod_count: int = Param(4, units="levels", description="levels LOD0 .. LOD(n-1) in the lod variant set", ge=1, le=8)
    lod_ratio: float = Param(0.5, units="", description="each level has at most this share of the triangles of the one before", gt=0.0, le=0.5)
    lod_error_budget: list[float] = Param(
        [0.01, 0.03], units="fraction of the bounding-box diagonal",
        description="largest Hausdorff error allowed at LOD1, LOD2, ...; a level over budget is reported in the metrics")
    max_modules: int = Param(1_000_000, units="modules", description="largest L-system string; a longer one is an error with its size",
                             ge=1, le=50_000_000)
    min_radius: float = Param(0.0005, units="m", description="branches thinner than this are not meshed", ge=0.0, le=1.0)
    hausdorff_samples: int = Param(20000, units="samples", description="samples per direction of the Hausdorff measurement",
                                   ge=100, le=10_000_000)
    leaf_area_compensation: float = Param(
        1.0, units="", description="thinned foliage LODs scale kept leaves by keep^(-c/2): 1 keeps the leaf area, 0 keeps leaf size",
        ge=0.0, le=1.0)
    use_opencl: bool = Param(True, description="generate vertices with the OpenCL kernels (false: the numpy reference)")

    @pydantic.model_validator(mode="before")
    @classmethod
    def _presets(cls, data: Any) -> Any:
        if isinstance(data, dict) and "species" in data:
            data = dict(data)
            try:
                data["species"] = resolve_species(data["species"], preset_tables())
            except ValueError as e:
                raise ValueError(str(e)) from None
        return data

    @pydantic.model_validator(mode="after")
    def _build_names(self):
        missing = [b for b in self.build if b not in self.species]
        if missing:
            raise ValueError(f"build names unknown species {missing}; known: {', '.join(sorted(self.species))}")
        if len(set(self.build)) != len(self.build):
            raise ValueError("build lists a species twice")
        return self


TEXTURE_SIZE = 256  # texels per side of every plant texture (cards, bark, blades)


def _write_textures(out_dir: Path, layer: Path, name: str, spec, res: PlantResult, provenance: dict, world_seed: int) -> dict:
    """The species' textures in textures/: linear EXR of every texture and an
    8-bit sRGB PNG copy of colour ones (the PNG is what the material reads for
    colour and alpha, the EXR normal map for normals). Returns the looks for
    asset.write_species, paths relative to the species layer."""
    from .plant import species_seeds

    tex_dir = out_dir / "textures"
    tex_dir.mkdir(exist_ok=True)
    seed = species_seeds(world_seed, name)[5]
    looks: dict = {}

    def rel(p: Path) -> str:
        return usdio.relative_asset_path(p, layer)

    def colour(stem: str, rgb, alpha=None) -> Path:
        rgba = rgb if alpha is None else np.concatenate([rgb, alpha[..., None]], -1)
        textures.write_exr(tex_dir / f"{stem}.exr", rgba, ("R", "G", "B", "A")[: rgba.shape[-1]], provenance)
        images.write_png(tex_dir / f"{stem}.png", rgb, alpha)
        return tex_dir / f"{stem}.png"

    def normal(stem: str, n) -> Path:
        textures.write_exr(tex_dir / f"{stem}.exr", materials.encode_normal(n), ("R", "G", "B"), provenance)
        return tex_dir / f"{stem}.exr"

    if any(p.get("Wood") is not None and p["Wood"].n_tris for p in res.lods):
        albedo, nrm = textures.bark_texture(TEXTURE_SIZE, spec.bark_color, seed)
        res.bark = albedo
        looks["bark"] = {"albedo": rel(colour(f"{name}_bark_albedo", albedo)), "normal": rel(normal(f"{name}_bark_normal", nrm)),
                         "wrap": "repeat"}
    if res.cards is not None:
        c = res.cards
        looks["foliage"] = {"albedo": rel(colour(f"{name}_foliage_albedo", c.albedo, c.alpha)),
                            "normal": rel(normal(f"{name}_foliage_normal", c.normal)), "wrap": "clamp", "alpha_test": True}
        if c.translucency is not None:  # data maps for renderers with a translucency / thickness input (asset.py)
            textures.write_exr(tex_dir / f"{name}_foliage_thickness.exr", c.thickness[..., None], ("Y",), provenance)
            looks["foliage"]["thickness"] = rel(tex_dir / f"{name}_foliage_thickness.exr")
            textures.write_exr(tex_dir / f"{name}_foliage_translucency.exr", c.translucency[..., None], ("Y",),
                               provenance)
            looks["foliage"]["translucency"] = rel(tex_dir / f"{name}_foliage_translucency.exr")
        if c.leaf_texture is not None:  # the blade texture the cluster was rendered with (not read by the asset)
            colour(f"{name}_leaf_albedo", c.leaf_texture)
    if res.slices is not None:
        sl = res.slices
        looks["slices"] = {"albedo": rel(colour(f"{name}_slices_albedo", sl.albedo, sl.alpha)),
                           "normal": rel(normal(f"{name}_slices_normal", sl.normal)), "wrap": "clamp", "alpha_test": True}
    if any(p.get("Blades") is not None and p["Blades"].n_tris for p in res.lods):
        blade = textures.blade_texture(TEXTURE_SIZE, spec.leaf_color, spec.leaf_tip_color, seed)
        looks["blades"] = {"albedo": rel(colour(f"{name}_blade_albedo", blade)), "wrap": "clamp"}
    return looks


def _measure_looks(env, spec, res: PlantResult) -> dict:
    """Foliage / wood area, LAI and crown opacity at every LOD (measure.py;
    the renders on the OpenCL device `env`)."""
    cov = res.cards.coverage if res.cards is not None else None
    cpc = measure.cards_per_cluster(spec, res.cards is not None)
    rgba = np.concatenate([res.cards.albedo, res.cards.alpha[..., None]], -1) if res.cards is not None else None
    slices = (np.concatenate([res.slices.albedo, res.slices.alpha[..., None]], -1) if res.slices is not None else None)
    levels = []
    hulls: dict = {}  # levels with the foliage and views of one before reuse its hull masks
    for k, parts in enumerate(res.lods):
        co = measure.crown_opacity(env, parts, spec, rgba, slices_rgba=slices, hulls=hulls)
        levels.append({"level": k, "crown_opacity": co["mean"], "crown_opacity_per_azimuth": co["per_azimuth"],
                       "foliage_area_m2": measure.foliage_area(parts, cov, cpc),
                       "wood_area_m2": measure.surface_area(parts.get("Wood"))})
    l0 = levels[0]
    out = {"foliage_area_m2": l0["foliage_area_m2"], "wood_area_m2": l0["wood_area_m2"],
           "foliage_to_wood": l0["foliage_area_m2"] / l0["wood_area_m2"] if l0["wood_area_m2"] > 0 else None,
           "leaf_area_index": measure.leaf_area_index(res.lods[0], cov, cpc), "crown_opacity": l0["crown_opacity"],
           "crown_opacity_lod_max_drop": max(l0["crown_opacity"] - e["crown_opacity"] for e in levels),
           "card_coverage": cov, "levels": levels}
    gains = measure.translucency_gains(env, res.lods[0], spec, rgba, slices_rgba=slices)
    # what the foliage's colour carries for DCCs (a compromise between views, see translucency_gains), and the two
    # views it is made of
    out["translucency_gain"] = round(gains["dcc"], 4)
    out["translucency_gain_side"] = round(gains["side"], 4)
    out["translucency_gain_front_lit"] = round(gains["front_lit"], 4)
    for name in ("foliage_area_m2", "wood_area_m2", "foliage_to_wood", "leaf_area_index", "crown_opacity",
                 "crown_opacity_lod_max_drop"):
        if out[name] is not None and not np.isfinite(out[name]):
            raise StageError(f"plants: {name} is not finite")
    return out


def _species_job(name: str, spec, seed: int, cfg: Settings, out_dir: Path, top: Path, provenance: dict,
                 params: PlantsParams) -> tuple[str, dict, str, dict]:
    """Everything one species makes: its meshes, textures, look measures and
    USD layer. Returns (name, metrics, layer path relative to the top layer,
    LOD summary). A top-level function so a worker process can run it."""
    res = build_plant(name, spec, seed, cfg)
    t = time.perf_counter()
    path = out_dir / f"{name}.usdc"
    prov = dict(provenance)
    prov["species"] = name
    looks = _write_textures(out_dir, path, name, spec, res, prov, seed)
    res.metrics["seconds_foliage_textures"] = res.metrics.get("seconds_foliage_textures", 0.0) + time.perf_counter() - t
    t = time.perf_counter()
    measures = _measure_looks(cfg.cl, spec, res)
    # the foliage's light through the leaves, which UsdPreviewSurface cannot pass, baked into its colour
    for key in ("foliage", "blades", "slices"):
        if key in looks:
            looks[key]["gain"] = measures["translucency_gain"]
    res.metrics["seconds_look_measures"] = time.perf_counter() - t
    res.metrics["looks"] = measures
    t = time.perf_counter()
    write_species(path, name, spec, res.lods, res.lod_info, prov, looks, measures)
    res.metrics["seconds_usd"] = time.perf_counter() - t
    budget_ok = all(e["hausdorff_fraction"] <= b for e, b in zip(res.lod_info[1:], params.lod_error_budget))
    halving_ok = all(b["triangles"] <= params.lod_ratio * a["triangles"] for a, b in zip(res.lod_info, res.lod_info[1:]))
    res.metrics["lod_budget_ok"] = bool(budget_ok)
    res.metrics["lod_halving_ok"] = bool(halving_ok)
    summary = {"lods": [{"triangles": e["triangles"], "hausdorff_fraction": round(e["hausdorff_fraction"], 6)}
                        for e in res.lod_info]}
    return name, res.metrics, usdio.relative_asset_path(path, top), summary


def _split_times(metrics: dict) -> tuple[dict, dict]:
    """A species' metrics without the run's times (a unit's result: the
    same every build) and those times (its run record, pipeline.units)."""
    kept = {k: v for k, v in metrics.items() if not k.startswith("seconds_")}
    seconds = {k: v for k, v in metrics.items() if k.startswith("seconds_")}
    if isinstance(metrics.get("lods"), list):
        kept["lods"] = [{k: v for k, v in e.items() if k != "simplify_seconds"} for e in metrics["lods"]]
        seconds["lods_simplify_seconds"] = [e.get("simplify_seconds") for e in metrics["lods"]]
    return kept, seconds


def _with_times(kept: dict, seconds: dict) -> dict:
    """_split_times undone: the metrics of a reused species with the times of the run that made it."""
    out = {**kept, **{k: v for k, v in seconds.items() if k != "lods_simplify_seconds"}}
    if isinstance(kept.get("lods"), list) and "lods_simplify_seconds" in seconds:
        out["lods"] = [dict(e, simplify_seconds=t) for e, t in zip(kept["lods"], seconds["lods_simplify_seconds"])]
    return out


# Species are independent (own seeds, own files), and most of a species'
# time is single-threaded (pymeshlab, numpy): with at least this many
# L-system modules in all, a second process builds species beside this one.
PARALLEL_MIN_MODULES = 20_000


def _species_cost(name: str, spec, seed: int, max_modules: int) -> int:
    """L-system modules of the species (grass: its blades): the order in
    which species are handed out, largest first."""
    if spec.kind != "lsystem":
        return spec.grass.blades if spec.kind == "grass" else 0
    system = compile_lsystem(spec.lsystem, name)
    return len(system.derive(spec.lsystem.iterations, species_seeds(seed, name)[0], max_modules))


def _parallel_ok() -> bool:
    import multiprocessing

    # a daemonic process (a Dask worker) is left alone: one stage, one process
    return not multiprocessing.current_process().daemon and (os.cpu_count() or 1) > 1


def _run_jobs(names: list[str], job, costs: dict[str, int], progress) -> dict[str, tuple]:
    """Run job(name) for every name, largest first: in this process and, when
    the work is large enough, in one worker process beside it (worker.py;
    each takes the next name when it is free). Results do not depend on who
    ran what."""
    order = sorted(names, key=lambda n: (-costs[n], n))
    done: dict[str, tuple] = {}
    if len(order) < 2 or sum(costs.values()) < PARALLEL_MIN_MODULES or not _parallel_ok():
        for i, name in enumerate(order):
            progress(i / len(order), f"plants: building {name}")
            done[name] = job(name)
        return done
    import pickle
    import select
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "stages.plants.worker"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE)

    def send(name: str) -> None:
        pickle.dump((job, (name,)), proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        proc.stdin.flush()

    def receive() -> tuple:
        try:
            status, value = pickle.load(proc.stdout)
        except EOFError:
            raise StageError(f"plants: the worker process ended (exit status {proc.wait()})") from None
        if status == "error":
            raise value
        return value

    ok = False
    try:
        queue = list(order)
        send(queue.pop(0))
        busy = True
        while busy or queue:
            if busy and (not queue or select.select([proc.stdout], [], [], 0)[0]):
                result = receive()
                done[result[0]] = result
                busy = False
                if queue:
                    send(queue.pop(0))
                    busy = True
                continue
            name = queue.pop(0)
            progress(len(done) / len(order), f"plants: building {name}")
            done[name] = job(name)
        ok = True
    finally:
        if ok:
            proc.stdin.close()
            proc.wait()
        else:
            proc.kill()
            proc.wait()
    return done


def run(ctx: RunContext, inputs: dict[str, Any], params: PlantsParams) -> dict[str, Path]:
    cfg = Settings(lod_count=params.lod_count, lod_ratio=params.lod_ratio, max_modules=params.max_modules,
                   min_radius=params.min_radius, hausdorff_samples=params.hausdorff_samples,
                   leaf_area_compensation=params.leaf_area_compensation, use_opencl=params.use_opencl, cl=ctx.cl,
                   lod_error_budget=tuple(params.lod_error_budget))
    out_dir = Path(ctx.out_dir)
    top = ctx.path("plants.assets")
    files: dict[str, str] = {}
    summary: dict[str, Any] = {}
    metrics: dict[str, Any] = {"species": {}}
    t0 = time.perf_counter()
    names = list(params.build)
    placed = inputs.get("placed")
    if placed is not None:
        # Only what the vegetation map placed is built; a placed species
        # without a shape here keeps its placeholder in the world (reported).
        names = [n for n in names if n in placed["placed"]]
        metrics["not_placed"] = [n for n in params.build if n not in placed["placed"]]
        metrics["placed_without_shape"] = [n for n in placed["placed"] if n not in params.build]
    # A species is a unit (pipeline.units): one whose shape and the stage's settings did not change is linked
    # from its earlier build when another species' change re-runs the stage.
    shared = {k: v for k, v in params.model_dump(mode="json").items() if k not in ("species", "build", "enabled")}
    units = {n: ctx.unit(n, {"species": params.species[n].model_dump(mode="json"), "params": shared}) for n in names}
    done: dict[str, tuple] = {}
    for name in names:
        saved = units[name].restore(out_dir)
        if saved is not None:
            metrics_of = _with_times(saved["metrics"], units[name].record.get("seconds", {}))
            done[name] = (name, {**metrics_of, "reused": True}, saved["file"], saved["lods"])
            ctx.progress(len(done) / max(len(names), 1), f"plants: {name} unchanged, reused")
    todo = [n for n in names if n not in done]
    costs = {n: _species_cost(n, params.species[n], ctx.seed, params.max_modules) for n in todo}
    # each species is made in a folder of its own (the same layout as out_dir), so its files are known
    staging = out_dir / ".species"
    job = functools.partial(_job_by_name, species=params.species, seed=ctx.seed, cfg=cfg, staging=staging,
                            provenances={n: units[n].provenance for n in todo}, params=params)
    made = _run_jobs(todo, job, costs, ctx.progress)
    for name in todo:
        folder = staging / name
        made_files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
        for rel in made_files:
            (out_dir / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(folder / rel, out_dir / rel)
        _, species_metrics, file, lods = made[name]
        kept, seconds = _split_times(json.loads(json.dumps(species_metrics, default=_json_scalar)))
        units[name].save(out_dir, made_files, json.loads(json.dumps({"metrics": kept, "file": file, "lods": lods},
                                                                    default=_json_scalar)), record={"seconds": seconds})
        done[name] = (name, {**species_metrics, "reused": False}, file, lods)
    shutil.rmtree(staging, ignore_errors=True)
    for name in names:  # in the build order, whichever process made them
        _, species_metrics, file, lods = done[name]
        files[name] = file
        metrics["species"][name] = species_metrics
        summary[name] = lods
    write_top(top, files, ctx.provenance, summary)
    errors = usdio.validate(top)
    if errors:
        raise StageError("plants: the assets fail USD validation: " + "; ".join(errors[:10]))
    metrics["seconds"] = time.perf_counter() - t0
    metrics["built"] = names
    ctx.metrics.update(metrics)
    ctx.progress(1.0, "plants: done")
    return {"plants.assets": top}


def _job_by_name(name: str, species: dict, staging: Path, provenances: dict, **kw) -> tuple:
    folder = staging / name
    folder.mkdir(parents=True, exist_ok=True)
    return _species_job(name, species[name], out_dir=folder, top=folder / "plants.usda", provenance=provenances[name],
                        **kw)


def _json_scalar(value):
    """numpy scalars in a species' metrics as JSON numbers."""
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON")


def check(params: PlantsParams, ctx: CheckContext) -> Check:
    """Every species to build: its L-system compiled and derived with the
    bake's seed (exactly what run() will derive), so a rule that divides by
    zero, overflows, gives NaN or grows past max_modules is found before any
    stage runs, naming the species and the rule."""
    modules = 0
    for name in params.build:
        spec = params.species[name]
        if spec.kind != "lsystem":
            continue
        try:
            system = compile_lsystem(spec.lsystem, name)
            modules += len(system.derive(spec.lsystem.iterations, species_seeds(ctx.seed, name)[0], params.max_modules))
        except InputError as e:
            raise ParamError(f"species.{name}.lsystem", str(e)) from None
    # the largest string, its skeleton and meshes: about 1 KiB per module is
    # an upper bound seen on the presets (mesh buffers dominate)
    return Check(memory_bytes=1024.0 * modules, memory_how=f"{modules:,} L-system modules x 1 KiB")


STAGE = Stage(
    name="plants",
    version=2,
    description="plant assets in USD: L-system trees and shrubs (watertight woody solid, leaves) and grass tufts, "
    "with a measured lod variant set, wind primvars and materials",
    inputs=(Input("placed", one_of=("vegetation.placed",), optional=True,
                  description="the species the vegetation map placed; only those are built"),),
    outputs=(Artifact("plants.assets", kind="usd", file="plants.usda", shape="any",
                      beside=("*.usdc", "textures/*.exr", "textures/*.png"),
                      description="/Plants (kind group): one prim per built species referencing ./<species>.usdc "
                      "(kind component, lod variant set LOD0..LODn, extentsHint, UsdPreviewSurface, wind primvars)"),),
    params=PlantsParams,
    run=run,
    check=check,
    report=(ReportTable("Instances and triangles", instance_and_lod_tables),),
    source_dir=Path(__file__).parent,
    uses_seed=True,
    uses_opencl=True,
)
