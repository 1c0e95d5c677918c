"""The vegetation stage on a tiled world: tiled.py's passes, then the maps,
the statistics and the preview per tile, the instances layer as the whole
run writes it. Every file is the whole run's (tests/stages/vegetation/
test_vegetation_tiled.py bakes both and compares them)."""
from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.contract import RunContext
from pipeline.errors import StageError
from pipeline.grid import Grid
from pipeline.tiles import TileContext, TileOutput
from worldlib.terrain.hillshade import hillshade

from . import placement, results, tiled, usd_layer
from . import sites as sites_mod
from .params import VegetationParams

F = np.float32


def whole_reason(inputs: dict, params: VegetationParams, shape, dx: float, tile_cells: int) -> str | None:
    """Why this world's vegetation cannot run tiled (None: it can)."""
    t = tile_cells or max(shape)
    block = max(1, int(round(params.density_block_m / dx)))
    window = placement.density_window(placement.Domain(shape[0], shape[1], dx, (0.0, 0.0)))
    if inputs.get("moisture") is None:
        return "no moisture input (the topographic fallback is a box filter over the whole terrain)"
    if params.plant_species() and tiled.sim_factor(shape, dx, params, tile_cells) is None:
        return (f"the simulation cell (sim_cell_m = {params.sim_cell_m:g}) is not a whole number of cells dividing "
                f"the tile of {t}")
    if t % block and t < max(shape):
        return f"the tile of {t} cells cuts the density blocks of {block} cells (density_block_m)"
    if t % window and t < max(shape):
        return f"the tile of {t} cells cuts the density check's windows of {window} cells"
    return None


def run(ctx: RunContext, inputs: dict[str, Any], params: VegetationParams) -> dict[str, Any]:
    clock = results.PhaseClock()
    terrain = inputs["terrain"]
    shape, dx, origin = tuple(terrain.shape), float(terrain.cell_size_m), tuple(terrain.origin_m)
    if shape[0] < 2 or shape[1] < 2:
        raise StageError(f"vegetation: the terrain grid is {shape[0]}x{shape[1]}; at least 2x2 cells are needed")
    runner, seed, be = ctx.tiles, int(ctx.seed), results.backend_modules(ctx.cl)
    plants, gname = params.plant_species(), params.grass_species()
    grow = plants + ([gname] if gname else [])
    with clock.lap("attributes_s"):
        out = tiled.fields(runner, inputs, params, shape, dx, origin, seed, grow,
                           lambda f, m: ctx.progress(f, m))
    ctx.progress(0.1, "ecosystem simulation")
    with clock.lap("ecosystem_s"):
        grown = tiled.growth(runner, out, inputs, params, shape, dx, origin, seed, be)
    ctx.progress(0.45, "placement")
    with clock.lap("placement_s"):
        placed = tiled.place(runner, grown, params, shape, dx, origin, seed,
                             lambda f, m: ctx.progress(0.45 + 0.25 * f, m))
    ctx.progress(0.7, "grass")
    with clock.lap("grass_s"):
        tufts, tuft_stats = tiled.tufts(runner, grown, params, shape, dx, origin, seed)
    ctx.progress(0.75, "instances")
    dom = placement.Domain(shape[0], shape[1], dx, origin)
    with clock.lap("instances_s"):
        sets, dropped, tints = tiled.instances(runner, inputs, out, grown, placed, tufts, params, shape, dx, origin,
                                               seed, out["lowest"], out["max_half_m"])
    maps, parts = _maps(runner, inputs, out, grown, placed, sets, params, shape, dx, origin, grow)
    forest = _forest(out, sets, parts, params, dom)
    ctx.progress(0.8, "USD layer")
    usd_path, ustats = results.write_usd(ctx, shape, dx, origin, sets, tints, params, clock,
                                     {usd_layer.FOREST_BY_SLOPE_KEY: forest["by_slope"],
                                      **({usd_layer.BANKS_KEY: forest["banks"]} if forest["banks"]["species"] else {})})
    species_maps = maps.get("species_maps")
    report = results.species_json(params, sets, placed, tuft_stats, species_maps)
    errors = _density_errors(plants, parts, placement.density_window(dom))
    sums = results.combine_splat_sums(out["splat_sums"])
    stats, timings = results.stats_of(shape, dx, ctx.input_artifacts.get("moisture", ""), sums, grown["sim"], plants,
                                 placed, {n: {"capped_plants": grown["capped_plants"][n]} for n in plants}, errors,
                                 tuft_stats, ustats, sets, dropped, tints, clock)
    results.with_forest(stats, forest, _sites_stats(out, parts, shape))
    ctx.metrics.update(results.run_metrics(stats, report, plants), timings=timings,
                       tiled_steps=f"every step; avalanche lines in {out['avalanche_rounds']} rounds")
    ctx.progress(1.0, "done")
    return {"vegetation.attributes": maps["attributes"], "vegetation.splat": out["splat"],
            "vegetation.grass": grown["grass"], "vegetation.canopy": maps["canopy"], "vegetation.sites": out["sites"],
            "vegetation.instances": usd_path, "vegetation.species": report, "vegetation.species_maps": species_maps,
            "vegetation.placed": {"placed": report["placed"], "prototypes": report["prototypes"]},
            "vegetation.stats": stats, "vegetation.preview": maps["preview"]}


def _maps(runner, inputs, out, grown, placed, sets, params, shape, dx, origin, grow) -> tuple[dict, list]:
    """The maps pass: attributes, canopy, species maps and preview grids,
    and per tile the counts the statistics need."""
    plants, gname = params.plant_species(), params.grass_species()
    dom = placement.Domain(shape[0], shape[1], dx, tuple(origin))
    cells = {n: dom.world_cell(s.positions) for n, s in sets.items()}  # the placed instances' cells
    domain_cells = {n: dom.cell_of(placed[n].x, placed[n].z) for n in plants}  # the density check's
    drawn = {n: results.preview_cells(s.positions, origin, dx, shape) for n, s in sets.items()}

    def part(t, rc):
        idx = tiled.cells_in(t, *rc)
        return rc[0][idx], rc[1][idx]

    per_tile = {}
    for t in runner.tiles(shape):
        per_tile[t.name] = {"dx": dx, "origin": tuple(origin), "world": tuple(shape), "plants": plants,
                            "grass": gname, "grow": grow, "lowest": out["lowest"],
                            "cells": {n: part(t, cells[n]) for n in sets},
                            "drawn": {n: part(t, (row, col))[::-1] for n, (col, row) in drawn.items()},
                            "domain_cells": {n: part(t, domain_cells[n]) for n in plants}}
    species = results.species_maps_channels(plants, gname)
    grids = {"attributes": results.ATTR_CHANNELS, "canopy": ("canopy.cover", "canopy.density"),
             "preview": ("r", "g", "b")}
    if species:
        grids["species_maps"] = species
    ins = {"terrain": inputs["terrain"], **{k: out[k] for k in ("fields", "splat", "sites", "suitability")},
           **{k: grown[k] for k in ("share", "target", "grass", "canopy")}}
    maps, parts = runner.map(maps_tile, "maps", shape, ins, params, per_tile=per_tile, grids=grids, cell_size_m=dx,
                             origin_m=tuple(origin))
    return maps, parts


def maps_tile(tctx: TileContext, inputs: dict, params: VegetationParams, shared: dict) -> TileOutput:
    """The tile's output maps and preview, and its counts for stats.json."""
    t, dx = tctx.tile, shared["dx"]
    cells = (t.rows, t.cols)
    plants, gname = shared["plants"], shared["grass"]
    read = lambda name: np.asarray(inputs[name].read(*t.window(0)))  # noqa: E731
    f = read("fields")
    k = tiled.FIELDS.index
    attributes = f[..., [k("slope"), k("aspect"), k("curvature"), k("sky_view"), k("sunlight"), k("moisture")]]
    land = ~((f[..., k("water")] > 0) | (f[..., k("nodata")] > 0))
    suit = np.moveaxis(read("suitability"), -1, 0)
    share, n_t = np.moveaxis(read("share"), -1, 0), np.moveaxis(read("target"), -1, 0)
    grass_maps, canopy = read("grass"), read("canopy")
    grids = {"attributes": np.ascontiguousarray(attributes, F), "canopy": canopy.astype(F)}
    counts = []
    for name in plants:
        tr, tc = shared["cells"][name]
        counts.append(np.bincount((tr - t.row0) * t.cols + (tc - t.col0), minlength=t.rows * t.cols).reshape(
            cells).astype(np.float64) if len(tr) else np.zeros(cells))
    layers, _ = results.species_maps_layers(plants, gname, suit, share, n_t, counts, dx,
                                            suit[len(plants)] if gname else None, grass_maps[..., 0])
    if layers:
        grids["species_maps"] = np.stack(layers, -1, dtype=F)
    h_halo, _ = tiled.heights(inputs["terrain"], t, 1, shared["lowest"])
    h = h_halo[t.inner(1)]
    grids["preview"] = _preview(h_halo, t, shared, f, read("splat"))
    # the statistics' counts
    slope_cls = sites_mod.slope_class(f[..., k("slope")])
    nclass = len(sites_mod.SLOPE_CLASSES_DEG) - 1
    sites = read("sites")
    rip, clr, alt = sites[..., 1], sites[..., 3], sites[..., 4]
    banks = land & (rip >= sites_mod.BANK_INDEX)
    shift = (h - alt)[land]
    window = placement.density_window(placement.Domain(*shared["world"], dx, (0.0, 0.0)))
    dom = placement.Domain(*shared["world"], dx, shared["origin"])
    density = {}
    for s, name in enumerate(plants):
        tr, tc = shared["domain_cells"][name]
        expect, got = placement.density_windows_of_cells(tr, tc, n_t[s], dom, window, (t.row0, t.col0))
        density[name] = (expect, got)
    summary = {"land_by_class": np.bincount(slope_cls[land], minlength=nclass).astype(np.int64),
               "trees_by_class": np.bincount(np.concatenate(
                   [slope_cls[shared["cells"][n][0] - t.row0, shared["cells"][n][1] - t.col0]
                    for n in plants if params.species[n].tree] or [np.zeros(0, np.int64)]),
                   minlength=nclass).astype(np.int64),
               "bank_cells": int(banks.sum()), "rest_cells": int((land & ~banks).sum()),
               "on_banks": {n: int(banks[c[0] - t.row0, c[1] - t.col0].sum()) for n, c in shared["cells"].items()},
               "off_banks": {n: int((land & ~banks)[c[0] - t.row0, c[1] - t.col0].sum())
                             for n, c in shared["cells"].items()},
               "steepest": {n: float(f[..., k("slope")][c[0] - t.row0, c[1] - t.col0].max())
                            for n, c in shared["cells"].items() if len(c[0])},
               "land_cells": int(land.sum()), "riparian_cells": int(((rip >= 0.5) & land).sum()),
               "clearing_cells": int(((clr >= 0.5) & land).sum()),
               "shift_min": float(shift.min()) if shift.size else None,
               "shift_max": float(shift.max()) if shift.size else None,
               **{f"expect_{n}": e for n, (e, _) in density.items()}, **{f"got_{n}": g for n, (_, g) in density.items()}}
    return TileOutput(grids=grids, summary=summary)


def _preview(h_halo, t, shared, f, splat) -> np.ndarray:
    """stage.preview on the tile: its hillshade from the heights with a one-cell halo."""
    img = hillshade(Grid(h_halo, shared["dx"], ("height",)))[t.inner(1)].astype(np.float32)
    water = f[..., tiled.FIELDS.index("water")] > 0
    return results.preview_colours(img, splat, water, shared["drawn"], shared["grow"], (t.row0, t.col0))


def _forest(out, sets, parts, params, dom) -> dict:
    """stage._forest from the tiles' counts."""
    plants = params.plant_species()
    nclass = len(sites_mod.SLOPE_CLASSES_DEG) - 1
    land = np.zeros(nclass, np.int64)
    trees = np.zeros(nclass, np.int64)
    for p in parts:
        land += p["land_by_class"]
        trees += p["trees_by_class"]
    steepest = {}
    for name in plants:
        if not len(sets[name]):
            continue
        steepest[name] = round(max(p["steepest"][name] for p in parts if name in p["steepest"]), 3)
        results.check_steepest(params, name, steepest[name])
    with_instances = sorted(n for n in plants if len(sets[n]))
    banks = sites_mod.banks_table(sum(p["bank_cells"] for p in parts), sum(p["rest_cells"] for p in parts),
                                  with_instances, [sum(p["on_banks"][n] for p in parts) for n in with_instances],
                                  [sum(p["off_banks"][n] for p in parts) for n in with_instances], dom.dx)
    return {"by_slope": sites_mod.forest_table(land, trees, dom.dx), "banks": banks, "steepest": steepest}


def _density_errors(plants, parts, w: int) -> dict:
    """placement.density_error from the tiles' windows (its sums are exact:
    any order)."""
    out = {}
    for name in plants:
        expect = np.concatenate([np.ravel(p[f"expect_{name}"]) for p in parts])
        got = np.concatenate([np.ravel(p[f"got_{name}"]) for p in parts])
        out[name] = placement.density_error_of(expect, got, w)
    return out


def _sites_stats(out, parts, shape) -> dict:
    """sites.compute's statistics from the tiles' counts."""
    lo = [p["shift_min"] for p in parts if p["shift_min"] is not None]
    hi = [p["shift_max"] for p in parts if p["shift_max"] is not None]
    avalanche = sites_mod.avalanche_stats(out["release_cells"], out["path_cells"], out["track_cells"],
                                          shape[0] * shape[1])
    return sites_mod.site_stats(avalanche, sum(p["land_cells"] for p in parts), sum(p["riparian_cells"] for p in parts),
                                sum(p["clearing_cells"] for p in parts), min(lo) if lo else None,
                                max(hi) if hi else None)
