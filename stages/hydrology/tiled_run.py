"""The stage on a tiled world (pipeline.tiles): the same files as the whole
run (stage.run), its steps per tile or on the few cells they concern.

1-3. fill, routing surface, directions, accumulation, discharge: per tile
     (tiled.py: Barnes 2016 and 2017 with exact integer sums);
4.   lakes: the depression cells gathered tile by tile and solved on their
     own (tiled_lakes.py);
5.   rivers: the network's cells gathered tile by tile and solved on their
     own (rivers.Network), reaches and ribbons from them; the beds carved
     per tile with the segments near it;
6.   wetness and moisture per tile, the open water within its reach;
     the maps and the preview per tile, written tile by tile by the engine.

Hack's law: the longest flow paths in Barnes' passes (worldlib.flow.
longest_path), the fit on the cells draining enough, gathered per tile.

The ribbons' fit on the carved ground: each tile samples the ground
under the bank vertices and mesh lattice lines it holds.

The terrain statistics: the height's from windows of the files
(stats.field_statistics), the network's from its cells.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from pipeline.timing import StepTimes as Timings
from worldlib.flow import reference as ref

from . import channels, rivers, summary, tiled, tiled_lakes, water_layer


def _lakes(ctx, terrain, core: dict, params, rain_map) -> tuple[tiled.SparseCells, dict]:
    """The lakes on the depression cells (depth, level, lake_id), and their stats."""
    got = tiled_lakes.lakes(ctx.tiles, terrain, core, params, rain_map, ctx.cl, lambda f, m: ctx.progress(0.45, m))
    if got is None:
        empty = np.zeros(0)
        return tiled.SparseCells(terrain.shape[1], np.zeros(0, np.int64),
                                 {"depth": empty, "level": empty, "lake_id": np.zeros(0, np.int32)}), {"lakes": 0}
    dc, sol = got
    return tiled.SparseCells(terrain.shape[1], dc.cells, {"depth": sol.depth, "level": sol.level,
                                                          "lake_id": sol.lake_id}), sol.stats


def _network(net: dict, lakes: tiled.SparseCells, cell_area: float, params) -> rivers.Network:
    """rivers.Network from the gathered cells and the lakes there; the lakes
    the USD draws: those of at least lake_min_area_m2 (channels.drawn_lakes)."""
    cells = net["cells"]
    pos = np.minimum(np.searchsorted(lakes.cells, cells), max(lakes.cells.size - 1, 0))
    hit = lakes.cells[pos] == cells if lakes.cells.size else np.zeros(cells.size, bool)
    at = lambda name, fill: np.where(hit, lakes.values[name][pos] if lakes.cells.size else fill, fill)
    lake_id = at("lake_id", 0).astype(np.int32)
    drawn = channels.drawn_lakes(lake_id, cell_area, params.lake_min_area_m2, lakes.values["lake_id"])
    return rivers.network_of(cells, net["rcv"], net["code"], net["area_m2"], net["discharge"], net["h"],
                             at("depth", 0.0), at("level", np.nan), lake_id, net["filled"], drawn)


def run(ctx, inputs: dict[str, Any], params, write_water_layer) -> dict[str, Any]:
    """The stage's outputs on a tiled world (depression = fill, flow = d8);
    write_water_layer: the stage's USD writer."""
    t_all = time.perf_counter()
    T = Timings()
    terrain = inputs["terrain"]
    shape, dx, origin = terrain.shape, float(terrain.cell_size_m), tuple(terrain.origin_m)
    rain_map = None if params.rain_map_path is None else ctx.resolve(params.rain_map_path)
    with T.lap("tiled_flow_s"):
        core = tiled.flow_core(ctx.tiles, terrain, params, lambda f, m: ctx.progress(0.3 * f, m))
    with T.lap("discharge_s"):
        core["discharge"] = tiled.discharge(ctx.tiles, terrain, core, params, rain_map,
                                            lambda f, m: ctx.progress(0.3, m))
    with T.lap("lakes_s"):
        lakes, lstats = _lakes(ctx, terrain, core, params, rain_map)
    ctx.progress(0.6, "rivers")
    with T.lap("rivers_s"):
        net, sums = tiled.network(ctx.tiles, terrain, core, params, rain_map)
        nw = _network(net, lakes, dx * dx, params)
        sol = rivers.solve_network(nw, dx, sums["n_data"], params)
        rivers_cells = tiled.SparseCells(shape[1], nw.cells, {"mask": sol.mask, "width": sol.width,
                                                              "order": sol.order})
    with T.lap("river_beds_s"):
        rs, pool_ids = water_layer.river_reaches(nw, sol, shape, dx, origin, params)
        grounds, gstats = tiled.carved_ground(ctx.tiles, terrain, channels.segments(rs), pool_ids, lakes, params)
        rib = channels.ribbons(rs)
        wstats = {**water_layer.reach_stats(rs, rib, params), **gstats,
                  **tiled.bed_fit(ctx.tiles, terrain, grounds["ground"], lakes, rib,
                                  nw.drawn_lake[np.searchsorted(nw.cells, rib.edge_cells)], core["hmin"], params)}
    ctx.progress(0.7, "wetness and moisture")
    with T.lap("wetness_s"):
        wet_maps = tiled.wetness(ctx.tiles, terrain, core["counts"], inputs.get("erosion_moisture"), grounds["wet"],
                                 rivers_cells, lakes, params)
    with T.lap("hack_s"):
        hack, paths = tiled.hack(ctx.tiles, terrain, core, params)
    with T.lap("terrain_statistics_s"):
        terrain_stats = _terrain_statistics(terrain, core, nw, paths["L"][np.searchsorted(paths["cells"], nw.cells)],
                                            sums["n_data"], params)
    ctx.progress(0.8, "water layer")
    width_table = channels.width_table(nw.area_m2, sol.width, np.ones(nw.cells.size, bool))
    with T.lap("usd_s"):
        lake_list = tiled.lake_outlines(lakes, terrain, params.lake_min_area_m2) if lstats.get("lakes", 0) else []
        usd_path, uinfo = write_water_layer(ctx, rib, width_table, lake_list, dx, origin)
    ctx.progress(0.9, "maps")
    with T.lap("maps_s"):
        out = tiled.maps(ctx.tiles, terrain, core, {**grounds, **wet_maps}, lakes, rivers_cells)
    out["hydrology.water"] = usd_path
    T["total_s"] = time.perf_counter() - t_all
    stats = summary.stats_json(shape, sums["n_data"], dx, sums["depression_cells"], core["outlet_cells"],
                               sums["discharge_out_m3_s"], lstats, {**sol.stats, **wstats}, hack, uinfo,
                               terrain_stats)
    stats.update(summary.climate(sums["mean_rain_m"], params), river_width_by_area=width_table)
    if rain_map is not None:
        ctx.metrics["rain_map_mean_mm_per_year"] = sums["mean_rain_m"] * 1000.0
    ctx.metrics.update(stats, timings=dict(T), fill_run={"tiled_routing_rounds": core["rounds"]},
                       tiled_steps=f"every step; "
                       f"routing surface in {core['rounds']} rounds")
    out["hydrology.stats"] = stats
    ctx.progress(1.0, "done")
    return out


def _terrain_statistics(terrain, core: dict, nw: rivers.Network, L: np.ndarray, n_data: int, params) -> dict:
    """worldlib.terrain.stats.terrain_statistics of a tiled world: the
    height's statistics from windows of the files, the network's from its
    cells (nw; L: their longest paths)."""
    from worldlib.terrain import stats

    shape, dx = terrain.shape, float(terrain.cell_size_m)

    def read(r0: int, c0: int, nr: int, nc: int) -> np.ndarray:
        h = ref.canonical(terrain.read(r0, c0, nr, nc, channel=terrain.channels[0])).astype(np.float64)
        return np.where(np.isfinite(h), h, np.nan)

    field = stats.field_statistics(read, shape, dx, lambda r0, c0, nr, nc: core["filled"].read(r0, c0, nr, nc))
    net = stats.channel_statistics(nw.rcv, nw.code, nw.area_m2, nw.h, L, n_data, dx)
    return stats.combined_statistics(field, net, params.river_threshold_m2, shape[0] * shape[1], dx)
