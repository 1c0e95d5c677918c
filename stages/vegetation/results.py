"""What the vegetation stage makes of its steps, shared by the whole run
(stage.py) and the tiled one (tiled.py, tiled_run.py): the kernels' tables,
the backend, the preview's colours, the instances layer, species.json and
stats.json from the run's results and reductions, the run's clock."""
from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from pipeline.contract import RunContext
from pipeline.errors import StageError
from worldlib.plant_asset import prototype_prim
from worldlib.terrain.stats import exact_mean, exact_sum

from . import usd_layer
from .params import NPREF_ORDER, VegetationParams

F = np.float32


SPECIES_MAPS = "species.exr"
ATTR_CHANNELS = ("attr.slope", "attr.aspect", "attr.curvature", "attr.sky_view", "attr.sunlight", "attr.moisture")
HA = 1e4  # m^2 per hectare


def backend_modules(env):
    """The kernels with reference.py's signatures: on the OpenCL device
    `env` (pipeline.opencl.CL; the stage's ctx.cl), or the numpy references
    (env None)."""
    if env is not None:
        from . import device

        return device.on(env)
    from . import reference

    return reference


def preference_table(params: VegetationParams, names: list[str]) -> np.ndarray:
    """(nsp, NPREF, 4) float32: min, max, 1 / edge (0: hard edge), 0."""
    out = np.zeros((len(names), len(NPREF_ORDER), 4), F)
    for s, name in enumerate(names):
        e = params.species[name]
        for k, key in enumerate(NPREF_ORDER):
            p = getattr(e, key)
            out[s, k] = (p.min, p.max, 1.0 / p.edge if p.edge > 0 else 0.0, 0.0)
    return out


def splat_table(p: VegetationParams) -> np.ndarray:
    def ss(lo, hi):
        return (lo, 1.0 / (hi - lo))
    return np.array([
        *ss(p.snow_min_m, p.snow_max_m), *ss(p.snow_slope_deg - 5.0, p.snow_slope_deg + 5.0), p.snow_melt,
        *ss(p.rock_slope_min_deg, p.rock_slope_max_deg), *ss(p.rock_min_m, p.rock_max_m),
        *ss(p.scree_slope_min_deg, p.scree_slope_max_deg),
        *ss(p.mud_moisture - 0.05, p.mud_moisture + 0.05), *ss(0.5 * p.mud_slope_deg, p.mud_slope_deg),
        *ss(p.dry_moisture - 0.1, p.dry_moisture + 0.1), *ss(p.alpine_min_m, p.alpine_max_m),
    ], F)


def preview_colours(img: np.ndarray, splat: np.ndarray, water: np.ndarray, drawn: dict, names,
                    first=(0, 0)) -> np.ndarray:
    """The preview from the hillshade (float32 RGB), the ground's colours,
    the water and the instances drawn at world cells (drawn: name -> (col,
    row)); a window from cell `first` gets the whole preview's pixels."""
    ground = (splat[..., 0:1] * np.array([120, 115, 110]) + splat[..., 1:2] * np.array([150, 140, 125])
              + splat[..., 2:3] * np.array([90, 140, 60]) + splat[..., 3:4] * np.array([170, 160, 100])
              + splat[..., 4:5] * np.array([100, 80, 60]) + splat[..., 5:6] * np.array([245, 245, 250]))
    img = img * (0.35 + 0.65 * ground / 255.0)
    img = np.where(water[..., None], 0.3 * img + 0.7 * np.array([40, 90, 170]), img)
    for k, name in enumerate(names):
        col, row = drawn.get(name, (np.zeros(0, np.int64), np.zeros(0, np.int64)))
        if not len(col):
            continue
        c = np.array(usd_layer.colour(name, k)) * 255.0
        a = 0.35 if name == "grass" else 0.8
        row, col = row - first[0], col - first[1]
        img[row, col] = (1 - a) * img[row, col] + a * c
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def species_maps_layers(plants: list[str], gname: str | None, suit, share, n_t, counts, dx: float, gsuit,
                        gdens) -> tuple[list, tuple[str, ...]]:
    """vegetation.species_maps' layers and channels: per plant species
    suitability, relative yield, target and placed density (plants per ha;
    counts: instances per cell), for the grass species suitability and tuft
    density. ([], ()) when no species grows."""
    layers = []
    for s in range(len(plants)):
        layers += [suit[s], share[s], n_t[s] * HA, counts[s] * HA / (dx * dx)]
    if gname:
        layers += [gsuit, gdens]
    return layers, species_maps_channels(plants, gname)


def species_maps_channels(plants: list[str], gname: str | None) -> tuple[str, ...]:
    channels = []
    for name in plants:
        channels += [f"suitability.{name}", f"yield.{name}", f"density.{name}", f"placed.{name}"]
    if gname:
        channels += [f"suitability.{gname}", f"density.{gname}"]
    return tuple(channels)


def preview_cells(positions: np.ndarray, origin, dx: float, shape) -> tuple[np.ndarray, np.ndarray]:
    """(col, row) where the preview draws instances at these world positions."""
    return (np.clip(((positions[:, 0] - origin[0]) / dx).astype(np.int64), 0, shape[1] - 1),
            np.clip(((positions[:, 2] - origin[1]) / dx).astype(np.int64), 0, shape[0] - 1))


def check_steepest(params: VegetationParams, name: str, steepest_deg: float) -> None:
    """A plant never stands where it may not grow: the steepest cell under
    one of its instances is under its species' slope limit."""
    limit = params.species[name].slope_deg.max
    if steepest_deg >= limit:
        raise StageError(f"vegetation: a {name} stands on a {steepest_deg:g} deg slope, its limit is {limit:g} deg")


def species_report(params: VegetationParams, sets, placed, tuft_stats) -> dict[str, dict]:
    """Per species to grow: its kind, instances, whether placed, and the
    target and shortfall (plants) or the tuft spacing (grass)."""
    species_report = {}
    for name in params.grow:
        e = params.species[name]
        n = len(sets[name]) if name in sets else 0
        rep = {"kind": e.kind, "instances": int(n), "placed": bool(n > 0)}
        if e.kind == "plant":
            rep.update(target_instances=round(placed[name].stats.get("target_plants", 0.0), 1),
                       shortfall=int(placed[name].stats.get("shortfall_plants", 0)))
        else:
            rep.update(tuft_spacing_m=tuft_stats.get("tuft_spacing_m"))
        species_report[name] = rep
    return species_report


class PhaseClock:
    """Wall seconds per phase (rounded), and the process CPU seconds (the
    OpenCL runtime's threads included) since the previous phase ended."""

    def __init__(self):
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self.t_all = time.perf_counter()
        self._cpu_mark = time.process_time()

    @contextmanager
    def lap(self, name: str):
        t0 = time.perf_counter()
        yield
        self.wall[name] = round(time.perf_counter() - t0, 4)
        now = time.process_time()
        self.cpu[name.replace("_s", "_cpu_s")] = round(now - self._cpu_mark, 4)
        self._cpu_mark = now


def write_usd(ctx: RunContext, shape, dx: float, origin, sets: dict, tints: dict, params: VegetationParams,
               clock: PhaseClock, custom: dict) -> tuple[Path, dict]:
    """Step 7: the instances layer, written and validated."""
    from pipeline import usdio

    rows, cols = shape
    with clock.lap("usd_s"):
        usd_path = ctx.path("vegetation.instances")
        size = max(cols, rows) * dx
        written = {n: s for n, s in sets.items() if len(s)}
        ustats = usd_layer.write(usd_path, ctx.provenance, written, {n: params.species[n].height_m for n in written},
                                 {n: params.species[n].kind for n in written}, origin[0], origin[1], size,
                                 params.tile_max_instances, params.tile_min_size_m, {n: tints[n] for n in written},
                                 custom)
    with clock.lap("usd_validate_s"):
        errors = usdio.validate(usd_path)
        if errors:
            raise StageError("vegetation: the instances layer fails USD validation: " + "; ".join(errors[:10]))
    return usd_path, ustats


def with_forest(stats: dict, forest: dict, sites_stats: dict) -> None:
    """stats.json's forest by slope, plants on the banks, steepest instances and sites."""
    by = forest["by_slope"]
    stats.update(forest_by_slope=by, plants_on_banks=forest["banks"],
                 forest_by_slope_class={c: {"land_pct": round(100 * a, 2), "trees_pct": round(100 * t, 2),
                                            "trees_per_ha": d} for c, a, t, d in
                                        zip(by["classes_deg"], by["land_share"], by["tree_share"], by["trees_per_ha"])},
                 steepest_instance_slope_deg=forest["steepest"], sites=sites_stats)


def species_json(params: VegetationParams, sets: dict, placed: dict, tuft_stats: dict, species_maps) -> dict:
    """vegetation.species: which species were placed, their prototypes and the maps' channels."""
    per_species = species_report(params, sets, placed, tuft_stats)
    placed_names = [n for n in params.grow if per_species[n]["placed"]]
    return {
        "placed": placed_names,
        "unplaced": [n for n in params.grow if not per_species[n]["placed"]],
        "species": per_species,
        "prototypes": {n: prototype_prim(n) for n in placed_names},
        "maps": {"file": SPECIES_MAPS, "channels": list(species_maps.channels) if species_maps is not None else [],
                 "units": "suitability, yield (relative yield from the simulation): 1; density (target), placed: plants per ha; grass density: 1"},
    }


def splat_sums(sums: np.ndarray, seed004: np.ndarray, mf: np.ndarray, moisture: np.ndarray) -> dict:
    """The splat's and moisture filter's reductions of stats.json over some
    cells (the world's, or a tile's: maxima, counts and exact sums combine
    with combine_splat_sums)."""
    return {"max_sum_error": float(np.abs(sums - 1).max()), "seed004_max": float(seed004.max()),
            "seed004_over": int((seed004 > 1 + 1e-6).sum()), "filtered": exact_sum(mf), "moisture": exact_sum(moisture)}


def combine_splat_sums(parts: list[dict]) -> dict:
    return {"max_sum_error": max(p["max_sum_error"] for p in parts), "seed004_max": max(p["seed004_max"] for p in parts),
            "seed004_over": sum(p["seed004_over"] for p in parts), "filtered": sum(p["filtered"] for p in parts),
            "moisture": sum(p["moisture"] for p in parts)}


def stats_of(shape, dx: float, moisture_source: str, sums: dict, sim, plants: list, placed: dict, cap_info: dict,
             errors: dict, grass_stats: dict, ustats: dict, sets: dict, dropped: dict, tints: dict,
             clock: PhaseClock) -> tuple[dict, dict]:
    """stats.json and the timings from what the run made and its reductions."""
    rows, cols = shape
    n = rows * cols
    stats = {
        "moisture_source": moisture_source,
        "cells": int(n), "cell_size_m": dx,
        "splat_max_sum_error": sums["max_sum_error"],
        "seed004_unfixed_sum_max": sums["seed004_max"],
        "seed004_unfixed_cells_over_1": sums["seed004_over"] / n,
        "moisture_filter_mean_gain": exact_mean(sums["filtered"], n) / max(exact_mean(sums["moisture"], n), 1e-12),
        "ecosystem": without_times(sim.stats) if sim else {},
        "ecosystem_history": sim.history if sim else [],
        "placement": {p: {**without_times(placed[p].stats), **cap_info[p], "density_error": errors[p]}
                      for p in plants},
        "grass": grass_stats,
        "usd": ustats,
        "instances": {p: int(len(s)) for p, s in sets.items()},
        "dropped_at_cell_edges": dropped["cell_edges"], "dropped_in_rivers": dropped["in_rivers"],
        "tint": {p: {"mean": [round(float(v), 4) for v in t.mean(axis=0)],
                     "std": [round(float(v), 4) for v in t.std(axis=0)]} for p, t in tints.items() if len(t)},
    }
    timings = {**clock.wall, "total_s": round(time.perf_counter() - clock.t_all, 4), **clock.cpu,
               "ecosystem_simulation_s": sim.stats.get("seconds") if sim else None,
               "placement_species_s": {p: placed[p].stats.get("seconds") for p in plants},
               "poisson_species_s": {p: placed[p].stats.get("poisson_seconds") for p in plants}}
    return stats, timings


RUN_TIMES = ("seconds", "poisson_seconds")  # what the ecosystem and placement measure of their run, not of the land


def without_times(stats: dict) -> dict:
    return {k: v for k, v in stats.items() if k not in RUN_TIMES}


def run_metrics(stats: dict, report: dict, plants: list) -> dict:
    return {
        "instances": stats["instances"], "unplaced": report["unplaced"], "moisture_source": stats["moisture_source"],
        "splat_max_sum_error": stats["splat_max_sum_error"],
        "density_max_relative_error": {n: stats["placement"][n]["density_error"]["max_relative_error"]
                                       for n in plants},
        "ecosystem_plateau_relative_change": stats["ecosystem"].get("plateau_relative_change"),
        "ecosystem_species_shares": stats["ecosystem"].get("species_shares"),
    }
