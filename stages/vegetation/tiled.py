"""The vegetation's fields tile by tile (issue 28): the passes a tiled
vegetation bake runs before its simulation, each a module-level function
for pipeline.tiles.TileRunner.map, each tile's values the whole world's bit
for bit (tests/stages/vegetation/test_vegetation_tiled.py).

1. scan_tile: the lowest finite height (no-data cells stand there) and the
   widest river's half width (the riparian index's reach).
2. land_tile: read with the attributes' halo (the horizon scan's reach,
   attributes.halo_cells) or the riparian index's if wider: the attributes
   (kernels by window), moisture, water, effective altitude, riparian index,
   clearings and avalanche releases; the tile's avalanche lines spread
   (sites.RunOut on the tile and a one-cell halo), those crossing into a
   neighbour returned for it.
3. avalanche_tile, in rounds until no line crosses a tile's edge: each tile
   takes the lines handed to it and spreads them on (RunOut's states are
   the highest over all paths, whatever the order).
4. path_tile: where the lines stand at or above the ground.
5. sites_tile: the avalanche tracks (the distance to a path, read with the
   track's halo), the sites, the splat weights (the moisture filter by
   window) and each species' suitability.

6. sim_tile: each plant species' suitability on the simulation grid
   (ecosystem.to_sim_grid: block means when a simulation cell is f x f
   whole cells and f divides the tile; the cells themselves when it is
   one). The simulation then runs whole on that grid (1/f^2 of the cells),
   and its relative yield (ecosystem.sim_yield) is read back per tile:
7. targets_tile: relative yield, target density (placement.species_target),
   canopy cover and the grass maps; the largest target and the exact sums
   (capped plants, grass density) for the placement.

8. poisson_tile, per plant species in placement order, one round per
   Poisson pass: each tile's share of the species' Poisson grid (the cells
   over its terrain cells), read with placement.POISSON_ROUND_HALO cells of
   the last round's points around it and its radius field's window, runs
   the pass's phases; then each tile's whole blocks keep their counts
   (placement.select_counts by window). The rounds stay in the tiles'
   files, and each task gets the earlier species' plants its darts reach:
   the stage's process holds the placed plants and a tile's points at a
   time, never a species' whole Poisson grid.

9. tufts_tile: the grass tufts of the tile's share of the tufts' grid
   (the density read by window), gathered in the grid's order.

10. instances: the terrain mesh's lattice read tile by tile, each plant's
   and tuft's instance on it; those on cells where the species may not
   grow or in a river's ribbon dropped (the water read around each tile's
   instances with the widest ribbon's reach), and their tints.

Not yet here: the USD layer, the maps and the statistics; until they are,
the stage runs whole on a tiled world.
A tiled run needs the moisture input: the topographic fallback is a box
filter whose running sums differ by window.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from pipeline.tiles import Tile, TileContext, TileOutput
from worldlib.ground import SPLAT_CHANNELS
from worldlib.terrain.mesh import terrain_mesh_by_window
from worldlib.terrain.stats import exact_mean, exact_sum

from . import attributes as attrs
from . import ecosystem, grass, placement, tint
from . import reference as ref
from . import sites as sites_mod
from .params import VegetationParams
from .reference import seed004_sum, stream_key
from .results import HA, preference_table, splat_sums, splat_table
from .sites import CHANNELS as SITE_CHANNELS

F = np.float32
# the land pass's fields, one grid of these channels per tile
FIELDS = ("slope", "aspect", "grad", "curvature", "sky_view", "sunlight", "moisture", "altitude.effective",
          "site.riparian", "site.clearing", "water", "nodata")


def backend(tctx: TileContext):
    """The kernels on the tile's device, else the numpy references."""
    if tctx.cl is not None:
        from . import device

        return device.on(tctx.cl)
    return ref


def _window(source, tile: Tile, halo: int, channel: str) -> np.ndarray:
    return np.asarray(source.read(*tile.window(halo), channel=channel))


def heights(terrain, tile: Tile, halo: int, lowest: float) -> tuple[np.ndarray, np.ndarray]:
    """The terrain's heights on the tile and `halo` cells around it
    (float32), no-data cells at the world's lowest height as the whole run
    has them (stage._terrain); and the raw heights (NaN: no data)."""
    raw = _window(terrain, tile, halo, _channel(terrain, "height")).astype(F)
    return np.where(np.isfinite(raw), raw, F(lowest)).astype(F), raw


def _channel(source, wanted: str) -> str:
    return wanted if wanted in source.channels else source.channels[0]


def scan_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared) -> TileOutput:
    """The tile's lowest finite height and its widest water's half width."""
    terrain = inputs["terrain"]
    h = _window(terrain, tctx.tile, 0, _channel(terrain, "height")).astype(F)
    finite = np.isfinite(h)
    water = _water(inputs, tctx.tile, 0)
    half = _half_widths(inputs, tctx.tile, 0, water)
    return TileOutput(summary={"lowest": float(h[finite].min()) if finite.any() else math.inf,
                               "max_half_m": float(half.max()) if half.size else 0.0})


def _clean(source, tile: Tile, halo: int, channel: str) -> np.ndarray:
    """A window of an input channel as float64, NaN as 0 (stage._optional_channel's)."""
    return np.nan_to_num(_window(source, tile, halo, channel).astype(np.float64), nan=0.0)


def _water(inputs: dict, tile: Tile, halo: int) -> np.ndarray:
    """stage._water on a window: lakes or rivers."""
    lakes, rivers = inputs.get("lakes"), inputs.get("rivers")
    return sites_mod.water_mask(None if lakes is None else _clean(lakes, tile, halo, _channel(lakes, "lake.depth")),
                                None if rivers is None else _clean(rivers, tile, halo, _channel(rivers, "river.mask")),
                                tile.window(halo)[2:])


def _half_widths(inputs: dict, tile: Tile, halo: int, water: np.ndarray) -> np.ndarray:
    rivers = inputs.get("rivers")
    has = rivers is not None and "river.width" in rivers.channels
    return sites_mod.half_widths(water, _clean(rivers, tile, halo, "river.width") if has else None)


def _levels(inputs: dict, tile: Tile, halo: int, h: np.ndarray) -> np.ndarray:
    """stage._water_levels' levels on a window: a lake's level, else the ground."""
    lakes = inputs.get("lakes")
    if lakes is None or "lake.level" not in lakes.channels or "lake.depth" not in lakes.channels:
        return sites_mod.water_levels(h, None, None)
    return sites_mod.water_levels(h, _clean(lakes, tile, halo, "lake.depth"),
                                  _window(lakes, tile, halo, "lake.level").astype(np.float64))


def cells_in(tile: Tile, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The indices of the cells (rows, cols) that lie in the tile."""
    return np.flatnonzero((rows >= tile.row0) & (rows < tile.row0 + tile.rows) & (cols >= tile.col0)
                          & (cols < tile.col0 + tile.cols))


def land_halo(dx: float, params: VegetationParams, max_half_m: float) -> int:
    return max(attrs.halo_cells(dx, params), sites_mod.riparian_halo(dx, params, max_half_m), 1)


def land_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """Pass 2 (the module's doc). shared: lowest, max_half_m, dx, origin."""
    tile, dx, origin = tctx.tile, shared["dx"], tuple(shared["origin"])
    halo = land_halo(dx, params, shared["max_half_m"])
    terrain = inputs["terrain"]
    h, raw = heights(terrain, tile, halo, shared["lowest"])
    inner = tile.inner(halo)
    a = attrs.compute(h, dx, params, backend(tctx), window=ref.Window.of(tile, halo))
    moisture = _moisture(inputs, tile)
    # the riparian index on its own (narrower) window: the distance transform's cost is that window's
    rhalo = sites_mod.riparian_halo(dx, params, shared["max_half_m"])
    r0, c0, rows, cols = tile.window(rhalo)
    wr0, wc0, _, _ = tile.window(halo)
    h_r = h[r0 - wr0:r0 - wr0 + rows, c0 - wc0:c0 - wc0 + cols]
    water_r = _water(inputs, tile, rhalo)
    rinner = tile.inner(rhalo)
    water, nodata = water_r[rinner], ~np.isfinite(raw[inner])
    blocked = water | nodata
    p = params
    ht = h[inner]
    alt = sites_mod.effective_altitude(ht, a["slope"], a["aspect"], p.treeline_aspect_shift_m, p.latitude_deg)
    rip = sites_mod.riparian_index(h_r, water_r, _levels(inputs, tile, rhalo, h_r),
                                   _half_widths(inputs, tile, rhalo, water_r), dx, p.riparian_height_m,
                                   p.riparian_distance_m)[rinner]
    first = (tile.row0, tile.col0)
    clr = sites_mod.clearings(ht.shape, p, dx, origin, int(tctx.seed), first)
    release = sites_mod.release_cells(ht, a["slope"], blocked, p, dx, origin, int(tctx.seed), first)
    run, frame = _run_out(h, tile, halo, dx, p)
    cells = np.flatnonzero(_in_frame(release, tile, frame).ravel())
    crossing = run.spread(run.seed(cells, np.full(cells.size, sites_mod.NO_HEADING), run.hf[cells]))
    fields = np.stack([a["slope"], a["aspect"], a["grad"], a["curvature"], a["sky_view"], a["sunlight"], moisture,
                       alt, rip, clr, water.astype(F), nodata.astype(F)], -1).astype(F)
    return TileOutput(grids={"fields": fields},
                      summary={**_state(run), **_crossings(crossing, frame), "release_cells": int(release.sum())})


def _moisture(inputs: dict, tile: Tile) -> np.ndarray:
    src = inputs.get("moisture")
    if src is None:
        raise ValueError("vegetation: a tiled run needs the moisture input (the topographic fallback runs whole)")
    m = np.nan_to_num(_window(src, tile, 0, _channel(src, "moisture")).astype(np.float64), nan=0.0)
    return np.clip(m, 0.0, 1.0).astype(F)


def _run_out(h_halo: np.ndarray, tile: Tile, halo: int, dx: float, params: VegetationParams):
    """RunOut on the tile and one cell around it (cut from a window of
    `halo`), the tile's cells owned; and that frame's (row0, col0, cols)."""
    r0, c0, rows, cols = tile.window(1)
    wr0, wc0, _, _ = tile.window(halo)
    h = h_halo[r0 - wr0:r0 - wr0 + rows, c0 - wc0:c0 - wc0 + cols]
    own = np.zeros(h.shape, bool)
    own[tile.inner(1)] = True
    return sites_mod.RunOut(h, sites_mod.d8_receivers(h, dx), dx, params.avalanche_alpha_deg, own), (r0, c0, cols)


def _in_frame(a: np.ndarray, tile: Tile, frame) -> np.ndarray:
    """A tile-sized array placed in its one-cell frame (False around)."""
    out = np.zeros(tile.window(1)[2:], bool)
    out[tile.inner(1)] = a
    return out


def _state(run: sites_mod.RunOut) -> dict:
    """RunOut's raised states, sparse: what the next round restores."""
    flat = run.line.ravel()
    idx = np.flatnonzero(np.isfinite(flat))
    return {"state_index": idx.astype(np.int64), "state_line": flat[idx]}


def _crossings(crossing, frame) -> dict:
    """The lines handed on, as world flat cells of the frame's grid."""
    cells, headings, values = crossing
    r0, c0, cols = frame
    return {"cross_row": (r0 + cells // cols).astype(np.int64), "cross_col": (c0 + cells % cols).astype(np.int64),
            "cross_heading": headings.astype(np.int64), "cross_line": values.astype(np.float64)}


def avalanche_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """Pass 3, one round: the tile's states restored, the lines handed to it
    seeded, spread on. shared (this tile's): lowest, dx, state, incoming."""
    tile, dx = tctx.tile, shared["dx"]
    terrain = inputs["terrain"]
    h, _ = heights(terrain, tile, 1, shared["lowest"])
    run, frame = _run_out(h, tile, 1, dx, params)
    run.line.ravel()[shared["state_index"]] = shared["state_line"]
    r0, c0, cols = frame
    rows_in, cols_in, headings, lines = shared["incoming"]
    cells = (rows_in - r0) * cols + (cols_in - c0)
    crossing = run.spread(run.seed(cells, run.slot(cells, headings), lines))
    return TileOutput(summary={**_state(run), **_crossings(crossing, frame)})


def path_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """Pass 4: where the tile's lines stand at or above the ground."""
    tile = tctx.tile
    terrain = inputs["terrain"]
    h, _ = heights(terrain, tile, 1, shared["lowest"])
    run, _ = _run_out(h, tile, 1, shared["dx"], params)
    run.line.ravel()[shared["state_index"]] = shared["state_line"]
    return TileOutput(grids={"path": run.path()[tile.inner(1)].astype(np.uint8)})


def track_halo(dx: float, params: VegetationParams) -> int:
    """Cells within which a path widens into its track (1.5 half widths)."""
    return int(math.ceil(0.75 * params.avalanche_track_width_m / dx)) + 1


def sites_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """Pass 5: tracks, sites, splat weights and suitability. inputs: the
    land pass's fields and the path pass's paths (TileArrays), the
    moisture; shared: dx, grow (the species to grow), splat table,
    preference table, jitter key."""
    tile, dx, p = tctx.tile, shared["dx"], params
    fields = np.asarray(inputs["fields"].read(*tile.window(0)), F)
    f = {name: fields[..., k] for k, name in enumerate(FIELDS)}
    blocked = (f["water"] > 0) | (f["nodata"] > 0)
    half = 0.5 * p.avalanche_track_width_m
    halo = track_halo(dx, p)
    path = np.asarray(inputs["path"].read(*tile.window(halo))) > 0
    if not path.any():
        track = np.zeros(blocked.shape, F)
    elif half > 0.0:
        d = ndimage.distance_transform_edt(~path)[tile.inner(halo)] * dx
        track = (1.0 - sites_mod.smooth01((d - 0.5 * half) / half)).astype(F)
    else:
        track = path[tile.inner(halo)].astype(F)
    site = sites_mod.Sites(f["altitude.effective"], f["site.riparian"], np.where(blocked, F(0), track).astype(F),
                           f["site.clearing"])
    be = backend(tctx)
    mhalo = ref.moisture_filter_halo(p.moisture_jitter_m / dx)
    src = inputs["moisture"]
    m = np.clip(np.nan_to_num(_window(src, tile, mhalo, _channel(src, "moisture")).astype(np.float64), nan=0.0),
                0.0, 1.0).astype(F)
    mf = be.moisture_filter(m, p.moisture_jitter_m / dx, shared["jitter_key"], window=ref.Window.of(tile, mhalo))
    terrain = inputs["terrain"]
    h, _ = heights(terrain, tile, 0, shared["lowest"])
    splat = be.splat(h, f["slope"], f["grad"], mf, (f["water"] > 0).astype(np.uint8), shared["splat_table"])
    grow = list(shared["grow"])
    if grow:
        suit = be.suitability(site.altitude, f["slope"], f["moisture"], f["sunlight"], f["curvature"],
                              blocked.astype(np.uint8), shared["preferences"])
        suit = sites_mod.apply(suit, grow, p, site)
    else:
        suit = np.zeros((0,) + blocked.shape, F)
    sites_grid, _ = site.channels()

    sums = splat_sums(splat.astype(np.float64).sum(axis=-1), seed004_sum(h, f["slope"], f["grad"], mf,
                                                                        shared["splat_table"]), mf, f["moisture"])
    return TileOutput(grids={"sites": sites_grid, "splat": splat, "moisture_filtered": mf,
                             "suitability": np.moveaxis(suit, 0, -1)},
                      summary={"path_cells": int(path[tile.inner(halo)].sum()), "track_cells": int((track >= 0.5).sum()),
                               "splat_sums": sums})


def fields(runner, inputs: dict, params: VegetationParams, shape: tuple[int, int], dx: float, origin, seed: int,
           grow: list[str], progress=lambda f, m: None) -> dict:
    """Passes 1 to 5 on a TileRunner: the TileArrays fields, path, sites,
    splat, moisture_filtered and suitability (channels: grow), and the
    avalanche rounds run."""

    common = {"dx": dx, "origin": tuple(origin)}
    grid = {"cell_size_m": dx, "origin_m": tuple(origin)}
    _, scans = runner.map(scan_tile, "scan", shape, inputs, params, common, keep=False, **grid)
    finite = [s["lowest"] for s in scans if math.isfinite(s["lowest"])]
    if not finite:
        raise ValueError("vegetation: the terrain has no finite height")
    common.update(lowest=min(finite), max_half_m=max(s["max_half_m"] for s in scans))
    progress(0.02, "attributes and sites by tile")
    land, land_summaries = runner.map(land_tile, "land", shape, inputs, params, common, grids={"fields": FIELDS},
                                      **grid)
    summaries = land_summaries  # the last round's: the avalanche lines each tile hands on
    tiles = runner.tiles(shape)
    states = {t.name: (s["state_index"], s["state_line"]) for t, s in zip(tiles, summaries)}
    rounds = 0
    while True:
        incoming = _route(tiles, summaries, runner.tile_cells or max(shape))
        if not any(len(v[0]) for v in incoming.values()):
            break
        rounds += 1
        progress(0.03, f"avalanche lines across tiles, round {rounds}")
        per_tile = {t.name: {**common, "state_index": states[t.name][0], "state_line": states[t.name][1],
                             "incoming": incoming[t.name]} for t in tiles}
        _, summaries = runner.map(avalanche_tile, f"avalanche{rounds}", shape, inputs, params, keep=False,
                                  per_tile=per_tile, **grid)
        states = {t.name: (s["state_index"], s["state_line"]) for t, s in zip(tiles, summaries)}
    per_tile = {t.name: {**common, "state_index": states[t.name][0], "state_line": states[t.name][1]}
                for t in tiles}
    paths, _ = runner.map(path_tile, "path", shape, inputs, params, keep=False, per_tile=per_tile,
                          grids={"path": ("path",)}, **grid)
    common.update(grow=list(grow), splat_table=splat_table(params), preferences=preference_table(params, list(grow)),
                  jitter_key=stream_key(seed, "moisture-jitter"))
    out, site_summaries = runner.map(
        sites_tile, "sites", shape, {**inputs, "fields": land["fields"], "path": paths["path"]}, params, common,
        grids={"sites": SITE_CHANNELS, "splat": SPLAT_CHANNELS, "moisture_filtered": ("moisture",),
               "suitability": tuple(f"suitability.{n}" for n in grow)}, **grid)
    return {**land, **paths, **out, "avalanche_rounds": rounds, "lowest": common["lowest"],
            "max_half_m": common["max_half_m"], "release_cells": sum(s_["release_cells"] for s_ in land_summaries),
            "path_cells": sum(s_["path_cells"] for s_ in site_summaries),
            "track_cells": sum(s_["track_cells"] for s_ in site_summaries),
            "splat_sums": [s_["splat_sums"] for s_ in site_summaries]}


def _route(tiles: list[Tile], summaries: list[dict], tile_cells: int) -> dict:
    """The lines each tile hands on, gathered per receiving tile: (rows,
    cols, headings, lines) in world cells."""
    parts = {t.name: [] for t in tiles}
    by_place = {(t.row, t.col): t.name for t in tiles}
    for s in summaries:
        r, c = s["cross_row"], s["cross_col"]
        if not len(r):
            continue
        owner_r, owner_c = r // tile_cells, c // tile_cells
        for key in set(zip(owner_r.tolist(), owner_c.tolist())):
            mine = (owner_r == key[0]) & (owner_c == key[1])
            parts[by_place[key]].append((r[mine], c[mine], s["cross_heading"][mine], s["cross_line"][mine]))
    cat = np.concatenate
    return {name: tuple(cat([p[k] for p in got]) for k in range(4)) if got else
            (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
            for name, got in parts.items()}


def sim_factor(shape: tuple[int, int], dx: float, params: VegetationParams, tile_cells: int) -> int | None:
    """Terrain cells per simulation cell side when the simulation grid can be
    made tile by tile (1: the cells themselves; f: f x f blocks dividing the
    tile), else None."""
    grid = ecosystem.sim_grid(shape[1], shape[0], dx, params.sim_cell_m)
    if grid.nx == shape[1] and grid.nz == shape[0] and abs(params.sim_cell_m - dx) <= 1e-9 * dx:
        return 1
    f = ecosystem.block_factor(shape[0], shape[1], dx, grid)
    return f if f and (tile_cells or max(shape)) % f == 0 else None


def sim_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """Pass 6: the tile's plant suitability on the simulation grid."""
    tile, dx = tctx.tile, shared["dx"]
    suit = np.moveaxis(np.asarray(inputs["suitability"].read(*tile.window(0)), F), -1, 0)[:shared["plants"]]
    grid = ecosystem.sim_grid(tile.cols, tile.rows, dx, params.sim_cell_m)
    return TileOutput(summary={"sim_suitability": ecosystem.to_sim_grid(suit, dx, grid)})


def targets_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """Pass 7: relative yield, targets, canopy and grass maps of the tile.
    shared: dx, origin, world (rows, cols), plants, grass, ry (sim_yield's),
    g (the simulation cell)."""
    tile, dx, origin, p = tctx.tile, shared["dx"], tuple(shared["origin"]), params
    first, cells = (tile.row0, tile.col0), (tile.rows, tile.cols)
    plants, gname = list(shared["plants"]), shared["grass"]
    suit = np.moveaxis(np.asarray(inputs["suitability"].read(*tile.window(0)), F), -1, 0)
    share = ecosystem.yield_on_terrain(shared["ry"], shared["g"], dx, shared["world"], first, cells)
    n_t = np.zeros((len(plants),) + cells)
    excess, nmax = [], []
    for s, name in enumerate(plants):
        n_t[s], over = placement.species_target(p, name, suit[s], share[s], dx, origin, int(tctx.seed), first,
                                                shared["world"])
        excess.append(over)
        nmax.append(float(n_t[s].max()) if n_t[s].size else 0.0)
    cover = grass.canopy_cover(p, plants, n_t)
    splat = np.asarray(inputs["splat"].read(*tile.window(0)), F)
    mf = np.asarray(inputs["moisture_filtered"].read(*tile.window(0)), F).reshape(cells)
    gdens, gheight = grass.grass_maps(p, gname, suit[len(plants)] if gname else None, splat, cover, mf, dx, origin,
                                      int(tctx.seed), first)
    total = n_t.sum(axis=0) * HA if plants else np.zeros(cells)
    return TileOutput(grids={"share": np.moveaxis(share, 0, -1), "target": np.moveaxis(n_t, 0, -1),
                             "grass": np.stack([gdens, gheight], -1), "canopy": np.stack([cover, total], -1)},
                      summary={"capped_exact": excess, "target_max": nmax, "grass_density_exact": exact_sum(gdens)})


def growth(runner, out: dict, inputs: dict, params: VegetationParams, shape: tuple[int, int], dx: float, origin,
           seed: int, backend_, progress=lambda f, m: None) -> dict:
    """Passes 6 and 7 around the simulation on fields()'s output: the
    TileArrays share, target, grass and canopy, the simulation, the
    calibration, and per plant species its largest target and capped
    plants, the grass density's exact sum."""
    plants, gname = params.plant_species(), params.grass_species()
    grid_kw = {"cell_size_m": dx, "origin_m": tuple(origin)}
    common = {"dx": dx, "origin": tuple(origin), "world": tuple(shape), "plants": plants, "grass": gname}
    sim = ry = None
    grid = ecosystem.sim_grid(shape[1], shape[0], dx, params.sim_cell_m)
    if plants:
        f = sim_factor(shape, dx, params, runner.tile_cells)
        if f is None:
            raise ValueError("vegetation: the simulation grid is not whole blocks of the tiles")
        _, parts = runner.map(sim_tile, "sim", shape, {"suitability": out["suitability"]}, params,
                              {"dx": dx, "plants": len(plants)}, keep=False, **grid_kw)
        suit_sim = np.zeros((len(plants), grid.nz, grid.nx), F)
        for t, part in zip(runner.tiles(shape), parts):
            suit_sim[:, t.row0 // f:(t.row0 + t.rows) // f, t.col0 // f:(t.col0 + t.cols) // f] = part["sim_suitability"]
        progress(0.15, "ecosystem simulation")
        sim = ecosystem.simulate(suit_sim, grid, params, plants, seed, backend_)
        alone = ecosystem.alone_density(params, plants, grid.g, seed, backend_)
        ry = ecosystem.sim_yield(sim, params, suit_sim, alone)
        sim.stats["alone_plants_per_ha_at_full_suitability"] = ecosystem.alone_at_full(alone, plants, grid.g)
    maps, parts = runner.map(targets_tile, "targets", shape,
                             {k: out[k] for k in ("suitability", "splat", "moisture_filtered")}, params,
                             {**common, "ry": ry if ry is not None else np.zeros((0, 1, 1)), "g": grid.g},
                             grids={"share": tuple(f"yield.{n}" for n in plants),
                                    "target": tuple(f"target.{n}" for n in plants),
                                    "grass": ("grass.density", "grass.height"),
                                    "canopy": ("canopy.cover", "canopy.density")}, **grid_kw)
    capped = {n: sum(p["capped_exact"][s] for p in parts) for s, n in enumerate(plants)}
    return {**maps, "sim": sim, "sim_yield": ry, "sim_grid": grid,
            "target_max": {n: max(p["target_max"][s] for p in parts) for s, n in enumerate(plants)},
            "capped_plants": {n: exact_mean(v, 1) * dx * dx for n, v in capped.items()},
            "grass_density_exact": sum(p["grass_density_exact"] for p in parts)}


def poisson_span(tile: Tile, c: float, dx: float, n_points: tuple[int, int]) -> tuple[int, int, int, int]:
    """The Poisson cells a tile owns, (x0, x1, z0, z1): those whose first
    corner lies over its terrain cells (the last tiles take the rest)."""
    def edge(cell: int, cells: int, n: int) -> int:
        return n if cell >= cells else min(n, math.ceil(cell * dx / c))
    rows, cols = tile.world_shape
    nx, nz = n_points
    return (edge(tile.col0, cols, nx), edge(tile.col0 + tile.cols, cols, nx),
            edge(tile.row0, rows, nz), edge(tile.row0 + tile.rows, rows, nz))


def _overlapping(spans: dict, x0: int, x1: int, z0: int, z1: int) -> list[str]:
    """The tiles whose Poisson spans (x0, x1, z0, z1) meet the cells [x0, x1) x [z0, z1)."""
    return [name for name, (a0, a1, b0, b1) in spans.items() if a0 < x1 and x0 < a1 and b0 < z1 and z0 < b1]


def _gather(parts: list[tuple[str, tuple]], x0: int, x1: int, z0: int, z1: int) -> np.ndarray:
    """The Poisson cells [x0, x1) x [z0, z1), (z, x, 4), from the files of the
    tiles' spans that meet them (parts: (path, span)); free where none does."""
    out = np.zeros((z1 - z0, x1 - x0, 4), F)
    for path, (a0, a1, b0, b1) in parts:
        part = np.load(path, mmap_mode="r")
        ax0, ax1, bz0, bz1 = max(a0, x0), min(a1, x1), max(b0, z0), min(b1, z1)
        if ax0 < ax1 and bz0 < bz1:
            out[bz0 - z0:bz1 - z0, ax0 - x0:ax1 - x0] = part[bz0 - b0:bz1 - b0, ax0 - a0:ax1 - a0]
    return out


def poisson_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """Pass 8, one round: one Poisson pass on the tile's share of the grid.
    shared (this tile's): species (target channel), r_lo, c, n_points,
    domain (rows, cols, dx, origin), pass, key, obstacles (the part its
    darts reach), window (wx0, wx1, wz0, wz1), span (poisson_span) and the
    last round's points as files: (path, span) of the tiles whose spans meet
    the window. Its span's points stay in a file (TileOutput.files)."""
    dom = placement.Domain(*shared["domain"])
    nx, nz = shared["n_points"]
    wx0, wx1, wz0, wz1 = shared["window"]
    state = _gather(shared["previous"], wx0, wx1, wz0, wz1)
    win, (rs, cs) = placement.point_window(wx0, wz0, state.shape[1], state.shape[0], shared["c"], dom)
    n = np.asarray(inputs["target"].read(rs.start, cs.start, rs.stop - rs.start, cs.stop - cs.start),
                   np.float64)[..., shared["species"]]
    rad = placement.radius_field(n, shared["r_lo"])
    sampler = backend(tctx).Poisson(nx, nz, shared["c"], dom.width, dom.depth, rad, dom.dx, placement.MARGIN_M,
                                    *shared["obstacles"], window=win, pts=state)
    P = ref.PN + 1
    for pz in range(P):
        for px in range(P):
            sampler.phase(px, pz, shared["pass"], shared["key"])
    pts = sampler.read().reshape(state.shape)
    x0, x1, z0, z1 = shared["span"]
    return TileOutput(files={"points": pts[z0 - wz0:z1 - wz0, x0 - wx0:x1 - wx0]})


def place(runner, grown: dict, params: VegetationParams, shape: tuple[int, int], dx: float, origin, seed: int,
          progress=lambda f, m: None) -> dict:
    """Pass 8 for every plant species in placement order: placement.Placed
    per species, the whole run's (placement.place_species) bit for bit.
    The Poisson grid of a species stays in the tiles' files, round after
    round; each task reads its window of the last round and gets the
    obstacles its darts reach, and each tile's plants are selected from the
    points around it: no process holds the species' whole grid."""
    import time

    plants = params.plant_species()
    dom = placement.Domain(shape[0], shape[1], dx, tuple(origin))
    block = max(1, int(round(params.density_block_m / dx)))
    tiles = runner.tiles(shape)
    if any((t.rows % block and t.row0 + t.rows != shape[0]) or (t.cols % block and t.col0 + t.cols != shape[1])
           for t in tiles):
        raise ValueError(f"vegetation: tiles of {runner.tile_cells} cells cut the density blocks of {block} cells")
    done: dict[str, placement.Placed] = {}
    prev: list[tuple[placement.Placed, float]] = []
    grid_kw = {"cell_size_m": dx, "origin_m": tuple(origin)}
    for k, name in enumerate(placement.placement_order(params, plants)):
        s, e, t0 = plants.index(name), params.species[name], time.perf_counter()
        nmax = grown["target_max"][name]
        if nmax <= 0:
            done[name] = placement.Placed(name, np.zeros(0, F), np.zeros(0, F), np.zeros(0, F), np.zeros(0, np.int64),
                                          {"target_plants": 0.0, "candidates": 0, "placed": 0, "shortfall_plants": 0})
            prev.append((done[name], e.collision_radius_m))
            continue
        r_lo = placement.lowest_radius(e, nmax)
        c = r_lo / math.sqrt(2.0)
        nx, nz = int(dom.width // c) + 1, int(dom.depth // c) + 1
        key, halo = ref.stream_key(seed, "poisson", name), placement.POISSON_ROUND_HALO
        spans = {t.name: poisson_span(t, c, dx, (nx, nz)) for t in tiles}
        windows, obstacles = {}, {}
        for t in tiles:
            x0, x1, z0, z1 = spans[t.name]
            windows[t.name] = (max(x0 - halo, 0), min(x1 + halo, nx), max(z0 - halo, 0), min(z1 + halo, nz))
            wx0, wx1, wz0, wz1 = windows[t.name]
            obstacles[t.name] = placement._obstacles(prev, e.collision_radius_m, dom, c,
                                                     window_m=(wx0 * c, wx1 * c, wz0 * c, wz1 * c))
        files: dict[str, str] = {}
        for pss in range(params.poisson_passes):
            progress(k / len(plants), f"{name}: Poisson pass {pss + 1} of {params.poisson_passes}")
            per_tile = {}
            for t in tiles:
                wx0, wx1, wz0, wz1 = windows[t.name]
                per_tile[t.name] = {"species": s, "r_lo": r_lo, "c": c, "n_points": (nx, nz), "pass": pss,
                                    "domain": (dom.rows, dom.cols, dx, tuple(origin)), "key": key,
                                    "obstacles": obstacles[t.name], "window": windows[t.name],
                                    "span": spans[t.name],
                                    "previous": [(files[o], spans[o]) for o in _overlapping(spans, *windows[t.name])
                                                 if o in files]}
            _, parts = runner.map(poisson_tile, f"poisson-{name}-{pss}", shape, {"target": grown["target"]}, params,
                                  keep=False, per_tile=per_tile, **grid_kw)
            runner.discard_files(files.values())  # the round before: the tasks have read it
            files = {t.name: part["points"] for t, part in zip(tiles, parts)}
        kept_parts, back = [], int(math.ceil(0.5 * dx / c)) + 1
        totals = {"candidates": 0, "placed": 0, "shortfall_plants": 0, "blocks_short": 0}
        target = 0
        for t in tiles:
            # the tile's plants: darts of its own span and of the cells before it whose darts round into its
            # first terrain cells (Domain.cell_of: half a cell back), in the whole grid's cell order
            x0, x1, z0, z1 = spans[t.name]
            x0, z0 = max(x0 - back, 0), max(z0 - back, 0)
            near = _gather([(files[o], spans[o]) for o in _overlapping(spans, x0, x1, z0, z1)], x0, x1, z0, z1)
            zi, xi = np.nonzero(near[..., 2] > 0)
            pts = near[zi, xi]
            cells = (zi + z0).astype(np.int64) * nx + (xi + x0)
            tr, tc = dom.cell_of(pts[:, 0], pts[:, 1])
            mine = cells_in(t, tr, tc)
            n_tile = np.asarray(grown["target"].read(*t.window(0)), np.float64)[..., s]
            kept_tile, stats, exact = placement.select_counts(pts[mine], cells[mine], n_tile, dom, block,
                                                              ref.stream_key(seed, "select", name), (t.row0, t.col0))
            kept_parts.append((pts[mine][kept_tile], cells[mine][kept_tile]))
            target += exact
            for key_ in totals:
                totals[key_] += stats[key_]
        runner.discard_files(files.values())
        pts = np.concatenate([p for p, _ in kept_parts]) if kept_parts else np.zeros((0, 4), F)
        cells = np.concatenate([c_ for _, c_ in kept_parts]) if kept_parts else np.zeros(0, np.int64)
        order = np.argsort(cells, kind="stable")  # the whole grid's order, as the untiled run keeps them
        pts, cells = pts[order], cells[order]
        stats = {"target_plants": exact_mean(target, 1), **totals, "poisson_cells": nx * nz, "poisson_cell_m": c,
                 "r_lo_m": r_lo, "seconds": time.perf_counter() - t0,
                 "obstacles": sum(len(p.x) for p, _ in prev)}
        done[name] = placement.Placed(name, pts[:, 0], pts[:, 1], pts[:, 2], cells, stats)
        prev.append((done[name], e.collision_radius_m))
    return done


def tufts_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """Pass 9: the kept tufts of the tile's share of the tufts' grid: their
    grid cells and positions. shared: sp, n_points, key, domain."""
    dom = placement.Domain(*shared["domain"])
    nx, nz = shared["n_points"]
    x0, x1, z0, z1 = poisson_span(tctx.tile, shared["sp"], dom.dx, (nx, nz))
    if x1 <= x0 or z1 <= z0:
        return TileOutput(summary={"cell": np.zeros(0, np.int64), "x": np.zeros(0, F), "z": np.zeros(0, F)})
    win, (rs, cs) = placement.point_window(x0, z0, x1 - x0, z1 - z0, shared["sp"], dom)
    dens = np.asarray(inputs["grass"].read(rs.start, cs.start, rs.stop - rs.start, cs.stop - cs.start), F)[..., 0]
    out = backend(tctx).grass_tufts(np.ascontiguousarray(dens), dom.dx, nx, nz, shared["sp"], params.grass_jitter,
                                    dom.width, dom.depth, shared["key"], window=win)
    kept = np.nonzero(out[:, 3] > 0)[0]
    zz, xx = np.divmod(kept, x1 - x0)
    return TileOutput(summary={"cell": ((z0 + zz) * nx + x0 + xx).astype(np.int64), "x": out[kept, 0].copy(),
                               "z": out[kept, 1].copy()})


def tufts(runner, grown: dict, params: VegetationParams, shape: tuple[int, int], dx: float, origin,
          seed: int) -> tuple[placement.Placed | None, dict]:
    """grass.place_tufts by tile: the same Placed, tufts in the grid's order."""
    name = params.grass_species()
    if name is None or not grown["grass_density_exact"] or params.grass_max_tufts == 0:
        return None, {"tufts": 0}
    dom = placement.Domain(shape[0], shape[1], dx, tuple(origin))
    sp, expected = grass.tuft_spacing_of(params, name, grown["grass_density_exact"], dx)
    nx, nz = int(dom.width // sp) + 1, int(dom.depth // sp) + 1
    shared = {"sp": sp, "n_points": (nx, nz), "key": ref.stream_key(seed, "tufts", name),
              "domain": (dom.rows, dom.cols, dx, tuple(origin))}
    _, parts = runner.map(tufts_tile, "tufts", shape, {"grass": grown["grass"]}, params, shared, keep=False,
                          cell_size_m=dx, origin_m=tuple(origin))
    cell = np.concatenate([p["cell"] for p in parts])
    order = np.argsort(cell, kind="stable")
    x, z = np.concatenate([p["x"] for p in parts])[order], np.concatenate([p["z"] for p in parts])[order]
    min_dist = (1.0 - params.grass_jitter) * sp
    p = placement.Placed(name, x, z, np.full(len(x), min_dist, F), cell[order],
                         {"tuft_spacing_m": sp, "expected_tufts": expected, "tufts": int(len(x)),
                          "candidates": nx * nz})
    return p, p.stats


class AtCells:
    """A tiled grid's channel read at cells (`grid[rows, cols]`, as the whole
    run indexes its arrays), tile by tile."""

    def __init__(self, arrays, channel: int, fn=None):
        self.arrays, self.channel, self.fn = arrays, channel, fn

    def __getitem__(self, cells):
        rows, cols = (np.asarray(c, np.int64) for c in cells)
        t = self.arrays.tile_cells
        out = None
        tile_of = (rows // t) * (1 << 32) + cols // t
        for key in np.unique(tile_of).tolist():
            mine = np.flatnonzero(tile_of == key)
            i, j = divmod(key, 1 << 32)
            part = np.asarray(self.arrays.read(i * t, j * t, min(t, self.arrays.shape[0] - i * t),
                                               min(t, self.arrays.shape[1] - j * t)))
            part = part[..., self.channel] if part.ndim == 3 else part
            v = part[rows[mine] - i * t, cols[mine] - j * t]
            v = self.fn(v) if self.fn is not None else v
            if out is None:
                out = np.empty(rows.shape, v.dtype)
            out[mine] = v
        if out is None:  # no cells
            empty = np.zeros(rows.shape, F)
            return self.fn(empty) if self.fn is not None else empty
        return out


def terrain_mesh(inputs: dict, shape: tuple[int, int], dx: float, origin, lowest: float,
                 max_vertices: int):
    """worldlib.terrain.mesh.build_terrain_mesh of the filled heights, its
    lattice read band by band."""
    terrain = inputs["terrain"]
    channel = _channel(terrain, "height")

    def filled(r0, c0, rows, cols):  # no-data cells at the world's lowest height, as heights() has them
        raw = terrain.read(r0, c0, rows, cols, channel=channel).astype(F)
        return np.where(np.isfinite(raw), raw, F(lowest)).astype(F)
    return terrain_mesh_by_window(filled, shape, dx, tuple(origin), max_vertices)


def instances(runner, inputs: dict, out: dict, grown: dict, placed: dict, tuft_set, params: VegetationParams,
              shape: tuple[int, int], dx: float, origin, seed: int, lowest: float, max_half_m: float):
    """stage._instances by tile: (sets, dropped, tints)."""
    plants, gname = params.plant_species(), params.grass_species()
    dom = placement.Domain(shape[0], shape[1], dx, tuple(origin))
    mesh = terrain_mesh(inputs, shape, dx, origin, lowest, params.mesh_max_vertices)
    sets, dropped = {}, {}
    positive = lambda v: v > 0  # noqa: E731
    for s, name in enumerate(plants):
        inst = placement.instances(placed[name], s, params, dom, mesh, grown["sim"], seed)
        sets[name], dropped[name] = placement.keep_allowed(inst, AtCells(grown["target"], s, positive), dom)
    if tuft_set is not None:
        inst = grass.tuft_instances(tuft_set, params, AtCells(grown["grass"], 1), dom, mesh, seed)
        sets[gname], dropped[gname] = placement.keep_allowed(inst, AtCells(grown["grass"], 0, positive), dom)
    reach = int(np.ceil((max_half_m + placement.BANK_MARGIN_M) / dx)) + 1
    in_rivers = {}
    for name in sets:
        sets[name], in_rivers[name] = _out_of_water(runner, inputs, sets[name], dom, shape, reach)
    moisture = AtCells(out["fields"], FIELDS.index("moisture"))
    tints = {}
    for name, inst in sets.items():
        e = params.species[name]
        tints[name] = tint.instance_tints(seed, name, inst.ids, moisture[dom.world_cell(inst.positions)], inst.age,
                                          e.maturity_years if e.kind == "plant" else 1.0, params.tint_variation)
    return sets, {"cell_edges": dropped, "in_rivers": in_rivers}, tints


def _out_of_water(runner, inputs: dict, inst, dom, shape, reach: int):
    """placement.keep_out_of_water tile by tile: each tile's instances with
    the water `reach` cells around the tile."""
    if not len(inst):
        return inst, 0
    tr, tc = dom.world_cell(inst.positions)
    wet = np.zeros(len(inst), bool)
    for t in runner.tiles(shape):
        mine = cells_in(t, tr, tc)
        if not len(mine):
            continue
        water = _water(inputs, t, reach)
        half = _half_widths(inputs, t, reach, water)
        r0, c0, _, _ = t.window(reach)
        wet[mine] = placement.in_water(inst.subset(mine), water, half, dom, placement.BANK_MARGIN_M, (r0, c0))
    return (inst, 0) if not wet.any() else (inst.subset(~wet), int(wet.sum()))
