"""The vegetation map stage: where each species grows on this terrain, placed
without overlap, instanced in USD.

1. Local attributes (attributes.py, kernel `attributes`): slope, aspect,
   curvature, sky view and sunlight with terrain shadows; altitude; moisture
   from hydrology (else erosion, else the topographic position); water
   (lakes, rivers) blocks everything. Sites (sites.py): the effective
   altitude (tree line by aspect), the riparian index (banks and
   flood-prone valley floors), avalanche tracks and clearings.
2. Splat weights (kernels `moisture_filter`, `splat`): rock, scree, grass,
   dry grass, mud, snow from slope, altitude, filtered moisture and water,
   seed 004 with both defects fixed; they sum to 1.
3. Suitability per species (kernel `suitability`): soft ranges of altitude
   (the effective altitude), slope, moisture, sunlight, curvature; then the
   site factors: the riparian preference, and for trees 1 - avalanche and
   1 - clearing. No species' slope limit is over 50 deg (params.py).
4. Competition (ecosystem.py): the self-thinning simulation for `years`, on
   a grid of sim_cell_m; each species' share of space.
5. Targets and placement (placement.py): density maps = density x
   suitability x relative yield x clumping; variable-radius Poisson disk by grid
   phases, exact counts per block, trunk clearance between species.
6. Grass (grass.py): density and height fields, jittered-grid tufts.
7. The USD layer (usd_layer.py), a preview, maps and statistics: among
   them the forest by slope class against the land's and the plants per
   hectare on the banks and elsewhere (stats.json, customData of
   /World/Vegetation, the report's tables: report_tables.py), and each
   species' steepest instance (checked under its slope limit).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.contract import (Artifact, Check, CheckContext, Input, ParamError, Relief, ReportMap, ReportTable,
                               ReportWarning, RunContext, Stage, ValueRange)
from pipeline.errors import InputError, StageError
from pipeline.grid import Grid
from pipeline.limits import leading_key
from worldlib.ground import GROUND_MAP_COLOURS, SPLAT_CHANNELS
from worldlib.terrain import GROUND_SOURCES, TERRAIN_SOURCES
from worldlib.terrain.hillshade import hillshade

from . import attributes as attrs
from . import ecosystem, grass, placement, tint, usd_layer
from . import sites as sites_mod
from .params import FILL, KAPPA, VegetationParams
from .report_tables import forest_tables
from .results import (ATTR_CHANNELS, HA, SPECIES_MAPS, PhaseClock, backend_modules, check_steepest, preference_table,
                      preview_cells, preview_colours, run_metrics, species_json, species_maps_layers, splat_sums,
                      splat_table, stats_of, with_forest, write_usd)

SITE_CHANNELS = sites_mod.CHANNELS
SITE_COLOURS = (("other", (120, 150, 90)), ("riparian", (60, 120, 200)), ("avalanche", (235, 235, 245)),
                ("clearing", (230, 190, 80)))
F = np.float32








def _optional_channel(inputs: dict, role: str, channel: str, shape) -> np.ndarray | None:
    g = inputs.get(role)
    if g is None:
        return None
    a = g.channel(channel) if channel in g.channels else g.channel(g.channels[0])
    if a.shape != shape:
        raise InputError(f"vegetation: input {role} is {a.shape}, the terrain {shape}")
    return np.nan_to_num(a.astype(np.float64), nan=0.0)


def preview(height: Grid, splat: np.ndarray, gdens: np.ndarray, water: np.ndarray, sets: dict, dom, names) -> np.ndarray:
    drawn = {name: preview_cells(inst.positions, dom.origin_m, dom.dx, gdens.shape) for name, inst in sets.items()}
    return preview_colours(hillshade(height).astype(np.float32), splat, water, drawn, names)






def _terrain(terrain: Grid) -> tuple[np.ndarray, np.ndarray, float, tuple[float, float]]:
    """Heights with no-data cells at the lowest height, the no-data mask,
    the cell size and the origin."""
    h_raw = terrain.channel(terrain.channels[0]).astype(F)
    rows, cols = h_raw.shape
    if rows < 2 or cols < 2:
        raise InputError(f"vegetation: the terrain grid is {rows}x{cols}; at least 2x2 cells are needed")
    nodata = ~np.isfinite(h_raw)
    if nodata.all():
        raise InputError("vegetation: the terrain has no finite height")
    h = np.where(nodata, np.float32(np.nanmin(h_raw)), h_raw).astype(F)
    return h, nodata, float(terrain.cell_size_m), tuple(terrain.origin_m)


def _moisture(ctx: RunContext, inputs: dict[str, Any], h: np.ndarray, dx: float,
              params: VegetationParams) -> tuple[np.ndarray, str]:
    """Moisture 0..1 and where it came from: the input (hydrology's, else
    the erosion storm's), else the topographic position."""
    moist = _optional_channel(inputs, "moisture", "moisture", h.shape)
    source = ctx.input_artifacts.get("moisture", "")
    if moist is None:
        moist = attrs.fallback_moisture(h, dx, params.moisture_fallback_radius_m, params.moisture_fallback_scale_m)
        source = "topographic position"
    return np.clip(moist, 0.0, 1.0).astype(F), source


def _water(inputs: dict[str, Any], shape: tuple[int, int]) -> np.ndarray:
    """Where lakes or rivers are (nothing grows there)."""
    return sites_mod.water_mask(_optional_channel(inputs, "lakes", "lake.depth", shape),
                                _optional_channel(inputs, "rivers", "river.mask", shape), shape)


def _water_levels(inputs: dict[str, Any], h: np.ndarray, water: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per water cell its level (a lake's level, else the ground) and half
    its width (rivers; 0 for lakes), for the riparian index."""
    lakes, rivers = inputs.get("lakes"), inputs.get("rivers")
    depth = level = width = None
    if lakes is not None and "lake.level" in lakes.channels and "lake.depth" in lakes.channels:
        depth = np.nan_to_num(lakes.channel("lake.depth").astype(np.float64), nan=0.0)
        level = lakes.channel("lake.level").astype(np.float64)
    if rivers is not None and "river.width" in rivers.channels:
        width = np.nan_to_num(rivers.channel("river.width").astype(np.float64), nan=0.0)
    return sites_mod.water_levels(h, depth, level), sites_mod.half_widths(water, width)


def _species_maps(plants, gname, sets, dom, suit, share, n_t, gsuit, gdens, g) -> Grid | None:
    """vegetation.species_maps (results.species_maps_layers); None when no species grows."""
    rows, cols = dom.rows, dom.cols
    counts = []
    for name in plants:
        c = np.zeros((rows, cols))
        if len(sets[name]):
            tr, tc = dom.world_cell(sets[name].positions)
            c = np.bincount(tr * cols + tc, minlength=rows * cols).reshape(rows, cols).astype(np.float64)
        counts.append(c)
    layers, channels = species_maps_layers(plants, gname, suit, share, n_t, counts, dom.dx, gsuit, gdens)
    return g(np.stack(layers, -1), channels) if layers else None


@dataclass(frozen=True)
class _Land:
    """The terrain and what grows on it does not depend on."""
    h: np.ndarray  # float32 height, no-data cells at the lowest height
    nodata: np.ndarray  # bool
    dx: float
    origin: tuple[float, float]
    attributes: dict  # attributes.compute's fields
    moisture: np.ndarray  # float32 0..1
    moisture_source: str
    water: np.ndarray  # bool: lakes or rivers
    water_half_m: np.ndarray  # per river cell half its bankfull width (0 elsewhere and on lakes)
    sites: sites_mod.Sites  # effective altitude, riparian index, avalanche tracks, clearings

    @property
    def shape(self) -> tuple[int, int]:
        return self.h.shape


@dataclass(frozen=True)
class _Splat:
    weights: np.ndarray  # float32 (rows, cols, 6)
    moisture_filtered: np.ndarray
    sums: np.ndarray  # float64 sum of the weights per cell
    seed004_sum: np.ndarray  # the sum seed 004's unfixed weights would have


@dataclass(frozen=True)
class _Growth:
    """Steps 3 to 5: suitability, competition, targets and placement."""
    plants: list
    grass_name: str | None
    suit_all: np.ndarray  # (species to grow, rows, cols)
    sim: Any  # the ecosystem simulation, None without plants
    share: np.ndarray  # relative yield per plant species
    dom: placement.Domain
    n_t: np.ndarray  # target density per plant species (plants per m^2)
    cap_info: dict
    placed: dict

    @property
    def suit(self) -> np.ndarray:
        return self.suit_all[: len(self.plants)]

    @property
    def grow(self) -> list:
        return self.plants + ([self.grass_name] if self.grass_name else [])


@dataclass(frozen=True)
class _Grass:
    cover: np.ndarray  # canopy cover 0..1
    suit: np.ndarray | None
    density: np.ndarray
    height: np.ndarray
    tufts: Any
    stats: dict


def run(ctx: RunContext, inputs: dict[str, Any], params: VegetationParams) -> dict[str, Any]:
    clock = PhaseClock()
    terrain = _terrain(inputs["terrain"])
    be = backend_modules(ctx.cl)
    seed = int(ctx.seed)
    ctx.progress(0.0, "attributes")
    land = _land(ctx, inputs, terrain, params, be, clock)
    ctx.progress(0.05, "splat weights")
    with clock.lap("splat_s"):
        splat = _splat(land, params, seed, be)
    growth = _grow(ctx, land, params, seed, be, clock)
    ctx.progress(0.7, "grass")
    with clock.lap("grass_s"):
        grass_layer = _grass(land, growth, splat, params, seed, be)
    ctx.progress(0.75, "instances")
    with clock.lap("instances_s"):
        sets, dropped, tints = _instances(land, growth, grass_layer, params, seed)
        forest = _forest(land, growth, sets, params)
    ctx.progress(0.8, "USD layer")
    usd_path, ustats = write_usd(ctx, land.shape, land.dx, land.origin, sets, tints, params, clock,
                                  {usd_layer.FOREST_BY_SLOPE_KEY: forest["by_slope"],
                                   **({usd_layer.BANKS_KEY: forest["banks"]} if forest["banks"]["species"] else {})})
    ctx.progress(0.9, "maps")
    with clock.lap("maps_s"):
        species_maps = _species_maps(growth.plants, growth.grass_name, sets, growth.dom, growth.suit, growth.share,
                                     growth.n_t, grass_layer.suit, grass_layer.density, _grid_maker(land))
    report = species_json(params, sets, growth.placed, grass_layer.stats, species_maps)
    stats, timings = _stats(land, splat, growth, grass_layer, sets, dropped, tints, ustats, clock)
    with_forest(stats, forest, land.sites.stats)
    ctx.metrics.update(run_metrics(stats, report, growth.plants), timings=timings)
    ctx.progress(1.0, "done")
    return _outputs(land, splat, growth, grass_layer, sets, usd_path, report, species_maps, stats)


def _land(ctx: RunContext, inputs: dict[str, Any], terrain: tuple, params: VegetationParams, be,
          clock: PhaseClock) -> _Land:
    """Step 1: the terrain's (_terrain's) attributes, moisture and water."""
    h, nodata, dx, origin = terrain
    with clock.lap("attributes_s"):
        a = attrs.compute(h, dx, params, be)
    moist, source = _moisture(ctx, inputs, h, dx, params)
    water = _water(inputs, h.shape)
    with clock.lap("sites_s"):
        level, half = _water_levels(inputs, h, water)
        sites = sites_mod.compute(h, a, water, water | nodata, level, half, params, dx, origin, int(ctx.seed))
    return _Land(h, nodata, dx, origin, a, moist, source, water, half, sites)


def _splat(land: _Land, params: VegetationParams, seed: int, be) -> _Splat:
    """Step 2: the splat weights, checked to lie in [0, 1] and sum to 1."""
    from .reference import seed004_sum, stream_key

    a = land.attributes
    mf = be.moisture_filter(land.moisture, params.moisture_jitter_m / land.dx, stream_key(seed, "moisture-jitter"))
    stab = splat_table(params)
    splat = be.splat(land.h, a["slope"], a["grad"], mf, land.water.astype(np.uint8), stab)
    sums = splat.astype(np.float64).sum(axis=-1)
    if not (np.isfinite(splat).all() and splat.min() >= 0.0 and splat.max() <= 1.0 and np.abs(sums - 1).max() <= 1e-6):
        raise StageError(f"vegetation: splat weights out of [0, 1] or not summing to 1 (max |sum - 1| = "
                         f"{float(np.abs(sums - 1).max()):.3g})")
    return _Splat(splat, mf, sums, seed004_sum(land.h, a["slope"], a["grad"], mf, stab))


def _grow(ctx: RunContext, land: _Land, params: VegetationParams, seed: int, be, clock: PhaseClock) -> _Growth:
    """Steps 3 to 5: suitability, the competition simulation, target densities and placement."""
    rows, cols = land.shape
    ctx.progress(0.1, "suitability")
    with clock.lap("suitability_s"):
        plants, gname = params.plant_species(), params.grass_species()
        suit_all = _suitability(land, params, plants + ([gname] if gname else []), be)
    ctx.progress(0.15, "ecosystem simulation")
    with clock.lap("ecosystem_s"):
        sim, share = _compete(ctx, land, suit_all[: len(plants)], params, plants, seed, be)
    ctx.progress(0.45, "placement")
    with clock.lap("placement_s"):
        dom = placement.Domain(rows, cols, land.dx, land.origin)
        n_t, cap_info = placement.target_density(params, plants, suit_all[: len(plants)], share, land.dx,
                                                 land.origin, seed)
        placed = placement.place_species(params, plants, n_t, dom, seed, be,
                                         progress=lambda f, m: ctx.progress(0.45 + 0.25 * f, m))
    return _Growth(plants, gname, suit_all, sim, share, dom, n_t, cap_info, placed)


def _suitability(land: _Land, params: VegetationParams, grow: list, be) -> np.ndarray:
    """(species to grow, rows, cols) suitability; water and no-data cells
    blocked; altitude judged by the effective altitude (tree line by aspect),
    then the site factors (riparian preference; trees out of avalanche
    tracks and clearings: sites.py)."""
    if not grow:
        return np.zeros((0, *land.shape), F)
    a = land.attributes
    blocked = (land.water | land.nodata).astype(np.uint8)
    suit = be.suitability(land.sites.altitude, a["slope"], land.moisture, a["sunlight"], a["curvature"], blocked,
                          preference_table(params, grow))
    return sites_mod.apply(suit, grow, params, land.sites)


def _compete(ctx: RunContext, land: _Land, suit: np.ndarray, params: VegetationParams, plants: list, seed: int, be):
    """Step 4: the self-thinning simulation and each plant species' relative yield."""
    rows, cols = land.shape
    dx = land.dx
    if not plants:
        return None, np.zeros((0, rows, cols))
    grid = ecosystem.sim_grid(cols, rows, dx, params.sim_cell_m)
    suit_sim = ecosystem.to_sim_grid(suit, dx, grid)
    sim = ecosystem.simulate(suit_sim, grid, params, plants, seed, be,
                             progress=lambda f, m: ctx.progress(0.15 + 0.25 * f, m))
    ctx.progress(0.4, "ecosystem calibration (each species alone)")
    alone = ecosystem.alone_density(params, plants, grid.g, seed, be)
    share = ecosystem.relative_yield(sim, params, suit_sim, alone, dx, (rows, cols))
    sim.stats["alone_plants_per_ha_at_full_suitability"] = ecosystem.alone_at_full(alone, plants, grid.g)
    return sim, share


def _grass(land: _Land, growth: _Growth, splat: _Splat, params: VegetationParams, seed: int, be) -> _Grass:
    """Step 6: grass density and height under the canopy, and its tufts."""
    gname = growth.grass_name
    cover = grass.canopy_cover(params, growth.plants, growth.n_t)
    gsuit = growth.suit_all[len(growth.plants)] if gname else None
    gdens, gheight = grass.grass_maps(params, gname, gsuit, splat.weights, cover, splat.moisture_filtered, land.dx,
                                      land.origin, seed)
    tufts, tuft_stats = grass.place_tufts(params, gname, gdens, growth.dom, seed, be)
    return _Grass(cover, gsuit, gdens, gheight, tufts, tuft_stats)


def _instances(land: _Land, growth: _Growth, grass_layer: _Grass, params: VegetationParams, seed: int):
    """Instances on the terrain mesh, those outside the allowed cells or in a
    river's ribbon dropped ({"cell_edges", "in_rivers"}: counts per species),
    and per-instance colour variation (tint.py)."""
    from worldlib.terrain.mesh import build_terrain_mesh

    dom, gname = growth.dom, growth.grass_name
    mesh = build_terrain_mesh(Grid(land.h, land.dx, ("height",), land.origin), params.mesh_max_vertices)
    sets: dict[str, placement.Instances] = {}
    dropped = {}
    for s, name in enumerate(growth.plants):
        inst = placement.instances(growth.placed[name], s, params, dom, mesh, growth.sim, seed)
        sets[name], dropped[name] = placement.keep_allowed(inst, growth.n_t[s] > 0, dom)
    if grass_layer.tufts is not None:
        inst = grass.tuft_instances(grass_layer.tufts, params, grass_layer.height, dom, mesh, seed)
        sets[gname], dropped[gname] = placement.keep_allowed(inst, grass_layer.density > 0, dom)
    in_rivers = {}
    for name in sets:  # a river's ribbon is wider than its cells: nothing stands in it
        sets[name], in_rivers[name] = placement.keep_out_of_water(sets[name], land.water, land.water_half_m, dom,
                                                                  placement.BANK_MARGIN_M)
    dropped = {"cell_edges": dropped, "in_rivers": in_rivers}
    tints = {}
    for name, inst in sets.items():
        e = params.species[name]
        tints[name] = tint.instance_tints(seed, name, inst.ids, land.moisture[dom.world_cell(inst.positions)],
                                          inst.age, e.maturity_years if e.kind == "plant" else 1.0,
                                          params.tint_variation)
    return sets, dropped, tints


def _forest(land: _Land, growth: _Growth, sets: dict, params: VegetationParams) -> dict:
    """The forest by slope class (sites.forest_by_slope) and per plant
    species the steepest cell slope under one of its instances, checked
    against its slope limit: a plant never stands where it may not grow."""
    slope = land.attributes["slope"]
    trees, steepest, cells = [], {}, {}
    for name in growth.plants:
        inst = sets[name]
        if not len(inst):
            continue
        tr, tc = cells[name] = growth.dom.world_cell(inst.positions)
        steepest[name] = round(float(slope[tr, tc].max()), 3)
        check_steepest(params, name, steepest[name])
        if params.species[name].tree:
            trees.append((tr, tc))
    land_mask = ~(land.water | land.nodata)
    return {"by_slope": sites_mod.forest_by_slope(slope, land_mask, trees, land.dx),
            "banks": sites_mod.plants_on_banks(land.sites.riparian, land_mask, cells, land.dx),
            "steepest": steepest}




def _grid_maker(land: _Land):
    def g(data, channels):
        return Grid(np.ascontiguousarray(data, dtype=F), land.dx, channels, land.origin)

    return g






def _stats(land: _Land, splat: _Splat, growth: _Growth, grass_layer: _Grass, sets: dict, dropped: dict,
           tints: dict, ustats: dict, clock: PhaseClock) -> tuple[dict, dict]:
    """stats.json, what the run made (the same every bake), and the run's
    timings (the manifest's metrics, a run record)."""
    placed = growth.placed
    errors = {name: placement.density_error(placed[name].x, placed[name].z, growth.n_t[s], growth.dom)
              for s, name in enumerate(growth.plants)}
    sums = splat_sums(splat.sums, splat.seed004_sum, splat.moisture_filtered, land.moisture)
    return stats_of(land.shape, land.dx, land.moisture_source, sums, growth.sim, growth.plants, placed,
                    growth.cap_info, errors, grass_layer.stats, ustats, sets, dropped, tints, clock)














def _outputs(land: _Land, splat: _Splat, growth: _Growth, grass_layer: _Grass, sets: dict, usd_path: Path,
             report: dict, species_maps, stats: dict) -> dict[str, Any]:
    rows, cols = land.shape
    a, g = land.attributes, _grid_maker(land)
    total_density = growth.n_t.sum(axis=0) * HA if len(growth.plants) else np.zeros((rows, cols))
    return {
        "vegetation.attributes": g(np.stack([a["slope"], a["aspect"], a["curvature"], a["sky_view"], a["sunlight"],
                                             land.moisture], -1), ATTR_CHANNELS),
        "vegetation.splat": g(splat.weights, SPLAT_CHANNELS),
        "vegetation.grass": g(np.stack([grass_layer.density, grass_layer.height], -1), ("grass.density", "grass.height")),
        "vegetation.canopy": g(np.stack([grass_layer.cover, total_density], -1), ("canopy.cover", "canopy.density")),
        "vegetation.sites": g(*land.sites.channels()),
        "vegetation.instances": usd_path,
        "vegetation.species": report,
        "vegetation.species_maps": species_maps,
        "vegetation.placed": {"placed": report["placed"], "prototypes": report["prototypes"]},
        "vegetation.stats": stats,
        "vegetation.preview": preview(Grid(land.h, land.dx, ("height",), land.origin), splat.weights,
                                      grass_layer.density, land.water, sets, growth.dom, growth.grow),
    }


def _grid(name, file, channels, units, description):
    return Artifact(name, kind="grid", file=file, channels=channels, units=units, description=description)


# Memory: about 70 float32/float64 fields a terrain cell (attributes,
# moisture, sites and their distance transforms, splat, grass, canopy, the
# horizon scan's buffers) and 6 per
# species (suitability, yield, densities, placed counts); the simulation
# grid holds about 12 float64 values a simulation cell and 2 per species.
BYTES_PER_CELL, BYTES_PER_CELL_SPECIES = 400, 48
BYTES_PER_SIM_CELL, BYTES_PER_SIM_CELL_SPECIES = 96, 16
MAX_CELL_STEPS = 1e10  # simulation cell-steps and Poisson cell-passes of a run (the default world: about 1e8)
MAX_HORIZON_SAMPLES = 256  # samples per direction of the horizon scan (growth 1.3 over 1500 m of 1 m cells: 28)


def run_tiled(ctx: RunContext, inputs: dict[str, Any], params: VegetationParams) -> dict[str, Any]:
    """run on a tiled world: every step per tile (tiled.py, tiled_run.py),
    the same files; the world's simulation grid in this process (the Poisson
    grids stay in the tiles' files). Runs whole (and says why) where a step cannot be tiled exactly."""
    from pipeline import exr
    from pipeline.tiles import GridFile

    from . import tiled_run

    terrain = inputs["terrain"]
    why = tiled_run.whole_reason(inputs, params, tuple(terrain.shape), float(terrain.cell_size_m),
                                 ctx.tiles.tile_cells)
    if why is None:
        return tiled_run.run(ctx, inputs, params)
    ctx.metrics["tiled_steps"] = f"none: {why}; the stage ran whole"
    return run(ctx, {role: exr.read_grid(v.path) if isinstance(v, GridFile) else v for role, v in inputs.items()},
               params)


# a tiled run holds a tile pass at a time: the tile's maps (as the whole run's cells) and the heights around it
# the horizon scan reads, or a tile's window of a species' Poisson grid (16 B a Poisson cell, three copies: the
# last round's, the device's and the result); and in this process the world's simulation grid and the placed plants
BYTES_PER_HALO_CELL = 16
BYTES_PER_POISSON_WINDOW_CELL = 48


def check(params: VegetationParams, ctx: CheckContext) -> Check:
    """The horizon scan's samples and the memory of the maps and of the
    simulation grid, from the terrain's size, before any stage runs. Work, in
    cell-steps: the simulation's cells times its steps (each a seeding, an
    update and the thinning) and the Poisson-disk cells times poisson_passes,
    at most MAX_CELL_STEPS."""
    terrain = ctx.inputs.get("terrain")
    if terrain is None:
        return Check()
    rows, cols = terrain.shape
    dx = terrain.cell_size_m
    limit = max(params.horizon_distance_m / dx, 1.0)
    samples = int(math.log(limit) / math.log(params.horizon_step_growth)) + 1
    if samples > MAX_HORIZON_SAMPLES:
        raise ParamError("horizon_step_growth", f"{params.horizon_step_growth:g} takes {samples:,} samples per "
                         f"direction to reach horizon_distance_m = {params.horizon_distance_m:g} on {dx:g} m cells "
                         f"(at most {MAX_HORIZON_SAMPLES}); raise it or lower horizon_distance_m")
    sim = ecosystem.sim_grid(cols, rows, dx, params.sim_cell_m)
    n = len(params.grow)
    held = rows * cols
    how = f"the terrain's {rows * cols:,} cells"
    extra, extra_how = 0, ""
    if ctx.tile_cells and ctx.tile_cells < max(rows, cols):
        from .attributes import halo_cells

        t = ctx.tile_cells
        held = t * t
        how = f"a tile's {held:,} cells"
        halo = min(t + 2 * halo_cells(dx, params), max(rows, cols))
        finest = max(species_poisson_cells(params, t * dx, t * dx).values(), default=0.0)  # a tile's, a side
        window = int(math.isqrt(int(finest)) + 2 * placement.POISSON_ROUND_HALO) ** 2 if finest else 0
        extra = max(BYTES_PER_HALO_CELL * halo * halo, BYTES_PER_POISSON_WINDOW_CELL * window)
        extra_how = (f" + the larger of the horizon's heights ({halo}^2 cells x {BYTES_PER_HALO_CELL} B) and a "
                     f"tile's Poisson window ({window:,} cells x {BYTES_PER_POISSON_WINDOW_CELL} B)")
    memory = (held * (BYTES_PER_CELL + BYTES_PER_CELL_SPECIES * n)
              + sim.nx * sim.nz * (BYTES_PER_SIM_CELL + BYTES_PER_SIM_CELL_SPECIES * n) + extra)
    steps = params.years // params.step_years + 1  # the first thinning, then one a step
    poisson = poisson_cells(params, (cols - 1) * dx, (rows - 1) * dx)
    return Check(memory_bytes=memory,
                 memory_how=f"{how} x ({BYTES_PER_CELL} + {BYTES_PER_CELL_SPECIES} x {n} "
                 f"species) B + vegetation.sim_cell_m = {params.sim_cell_m:g}: {sim.nx * sim.nz:,} simulation cells x "
                 f"({BYTES_PER_SIM_CELL} + {BYTES_PER_SIM_CELL_SPECIES} x {n}) B{extra_how}",
                 work=sim.nx * sim.nz * steps + poisson * params.poisson_passes, work_unit="cell-steps",
                 work_limit=MAX_CELL_STEPS, work_how=f"{sim.nx * sim.nz:,} simulation cells x {steps:,} steps "
                 f"(years // step_years + 1) + at most {poisson:,.0f} Poisson-disk cells x {params.poisson_passes} "
                 "poisson_passes",
                 work_key=leading_key(params, grows=("years", "poisson_passes"), shrinks=("step_years", "sim_cell_m")))


def poisson_cells(params: VegetationParams, width_m: float, depth_m: float) -> float:
    """The Poisson-disk grid cells of every plant species grown, at most:
    placement.poisson_sample's cell is r_lo / sqrt(2), r_lo at least
    min_spacing_m and the spacing its density_per_ha fills at most."""
    return sum(species_poisson_cells(params, width_m, depth_m).values())


def species_poisson_cells(params: VegetationParams, width_m: float, depth_m: float) -> dict[str, float]:
    """poisson_cells per plant species grown."""
    out = {}
    for name in params.grow:
        e = params.species.get(name)
        if e is None or e.kind != "plant":
            continue
        r_lo = max(e.min_spacing_m, math.sqrt(KAPPA * FILL * 1e4 / e.density_per_ha))
        c = r_lo / math.sqrt(2.0)
        out[name] = (width_m // c + 1) * (depth_m // c + 1)
    return out


STAGE = Stage(
    name="vegetation",
    version=1,
    description="Vegetation map: local attributes and sunlight, sites (tree line by aspect, river banks, avalanche "
    "tracks, clearings), per-species suitability with slope limits of real plants, competition by an ecosystem "
    "simulation (Deussen 1998 self-thinning), variable-radius Poisson-disk placement on the terrain mesh, grass "
    "density and tufts, terrain splat weights (seed 004, fixed), and the instances as UsdGeom.PointInstancers in "
    "quadtree tiles",
    inputs=(
        Input("terrain", one_of=GROUND_SOURCES, description="the ground: the final terrain with the river beds carved", channels=("height",), units="m"),
        Input("moisture", one_of=("hydrology.moisture", "erosion.moisture"), optional=True, channels=("moisture",),
              units="1", description="moisture 0..1: hydrology's, else the erosion storm's, else none (the stage "
              "derives it from the topographic position)"),
        Input("lakes", one_of=("hydrology.lakes",), optional=True, description="lake depth: nothing grows in lakes",
              channels=("lake.depth",), units="m"),
        Input("rivers", one_of=("hydrology.rivers",), optional=True, description="river mask: nothing grows in rivers",
              channels=("river.mask",), units="1"),
    ),
    outputs=(
        _grid("vegetation.attributes", "attributes.exr", ATTR_CHANNELS, "deg, deg, 1/m, 1, 1, 1",
              "local attributes: slope, aspect (clockwise from north, the way the slope faces), curvature "
              "(Laplacian, > 0 concave), sky view (0..1), sunlight (insolation relative to open flat ground), moisture"),
        _grid("vegetation.splat", "splat.exr", SPLAT_CHANNELS, "1",
              "terrain splat weights for the ground material, each in [0, 1], summing to 1"),
        _grid("vegetation.grass", "grass.exr", ("grass.density", "grass.height"), "1, m",
              "grass density (probability of a tuft, 0..1) and grass height (m)"),
        _grid("vegetation.canopy", "canopy.exr", ("canopy.cover", "canopy.density"), "1, 1/ha",
              "tree and shrub crown cover (0..1) and their total target density (plants per ha)"),
        _grid("vegetation.sites", "sites.exr", SITE_CHANNELS, "1, 1, 1, 1, m",
              "sites (sites.py), weights 0..1: the rest (1 - the largest of the others), riparian index (banks and "
              "flood-prone valley floor), avalanche track, clearing; and the effective altitude the species' "
              "altitude ranges judge (lower on sun-facing slopes: the tree line by aspect)"),
        Artifact("vegetation.instances", kind="usd", file="instances.usdc", shape="any", beside=("tiles/*.usdc",),
                 description="/World/Vegetation: quadtree tiles of UsdGeom.PointInstancers, one per species per tile, "
                 "each leaf tile a payload (tiles/q<digits>.usdc), whose instanceable prototypes inherit "
                 "/World/Vegetation/Prototypes/<species> (placeholder cones until the plant assets are referenced "
                 "there): one set of meshes per species"),
        Artifact("vegetation.species", kind="json", file="species.json", shape="any",
                 description="the placed species with instance counts (the plants stage builds only these), the "
                 "unplaced ones, the prototype prim paths and the per-species maps in species.exr"),
        Artifact("vegetation.species_maps", kind="grid", file=SPECIES_MAPS, optional=True,
                 channels=("suitability.{plant}", "yield.{plant}", "density.{plant}", "placed.{plant}",
                           "suitability.{grass}", "density.{grass}"), units="1, 1, 1/ha, 1/ha, 1, 1",
                 description="per placed species: suitability (0..1), relative yield of the simulation (plants only), "
                 "target density and placed density (plants per ha); for the grass species suitability and tuft "
                 "density (0..1); absent when no species grows"),
        Artifact("vegetation.placed", kind="json", file="placed.json", shape="any",
                 description="only the names of the placed species and their prototype prims: what the plants stage "
                 "reads, so a bake that places the same species again builds no plant (early cutoff)"),
        Artifact("vegetation.stats", kind="json", file="stats.json", shape="any",
                 description="ecosystem history and stability, placement and density errors, splat checks (the timings are metrics)"),
        Artifact("vegetation.preview", kind="image", file="preview.png", dtype="uint8",
                 description="the placement over the hillshade and ground colours, 8-bit RGB"),
    ),
    params=VegetationParams,
    run=run,
    run_tiled=run_tiled,
    check=check,
    report=(ReportTable("Forest by slope class, plants on the banks", forest_tables),
            ReportMap("vegetation.splat", "splat.{ground}", name="ground",
                      title="Ground types ({artifact}, largest weight)", categories=tuple(GROUND_MAP_COLOURS.items()),
                      relief=Relief(hillshade, TERRAIN_SOURCES, "height", strength=0.4)),
            ReportMap("vegetation.sites", "site.{site}", name="sites", title="Sites ({artifact}, largest weight)",
                      categories=SITE_COLOURS, relief=Relief(hillshade, TERRAIN_SOURCES, "height", strength=0.5)),
            ReportMap("vegetation.species_maps", "density.{species}", name="density_{species}", title="Density: {species}",
                      palette="greens", values=ValueRange(lo=0.0), relief=Relief(hillshade, TERRAIN_SOURCES, "height")),
            ReportWarning("vegetation.species_maps", "suitability.{species}",
                          "species {species} found no suitable land (suitability is 0 everywhere)")),
    source_dir=Path(__file__).resolve().parent,
    uses_seed=True,
    uses_opencl=True,
    shared_params=("mesh_max_vertices",),
)
