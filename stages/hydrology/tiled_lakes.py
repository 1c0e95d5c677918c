"""The lakes of a tiled world (lakes.py's step 4): the depression cells
gathered tile by tile into lakes.DepressionCells, then solved on them alone
(lakes.solve_depressions), bitwise the whole run's lakes.

The world-wide parts of the gather, each exact whatever the tiling:
- the mean rain and the runoff's total: per-tile exact sums (tiled_accum.exact_sum);
- the runoff accumulated on the lake routing (steepest descent on the raw
  terrain inside depressions, the main routing elsewhere): fixed-point
  weights at the world's scale in Barnes' (2017) three passes;
- each depression's exit (the first cell off it on the main routing):
  pointer jumping over the gathered depression cells;
- where an exit's water ends on the lake routing: its path to the end of
  its tile, then from tile to tile through the tiles' perimeter cells.
"""
from __future__ import annotations

import functools
from typing import Any

import numpy as np

from pipeline.errors import StageError
from pipeline.tiles import TileOutput
from worldlib.flow import reference as ref
from worldlib.flow import tiled_accum as ta

from . import lakes as lakes_mod
from .tiled import (_global, _heights, _receivers, _tile_rain, fixed_point_scale, inflow_by_tile, perimeter_summary,
                    weight_sums)


def _tile_state(tctx, inputs: dict[str, Any], params, rain: tuple) -> dict[str, Any]:
    """The tile's depression cells D, lake routing codes and rain
    (rain = (lowest height, rain map path or None, mean rain or None))."""
    terrain, t = inputs["terrain"], tctx.tile
    rows, cols = terrain.shape
    dx = float(terrain.cell_size_m)
    h, kind, halo = _heights(tctx, terrain)
    hmin, rain_map, mean_rain = rain
    r, data = _tile_rain(tctx, terrain, params, (hmin, rain_map, (rows, cols)))
    F = np.asarray(inputs["filled"].tile_array(t))
    D = (kind == ref.INTERIOR) & (F > h)
    state = {"h": h, "kind": kind, "data": data, "rain": r, "F": F, "D": D, "dx": dx}
    if mean_rain is None:
        return state
    # the raw terrain's D8 as lake_maps runs it: no-data at height 0, the world's border beyond the halo
    z = np.where(np.isfinite(halo), halo, np.float32(0))
    rr = np.arange(t.row0 - 1, t.row0 + t.rows + 1)[:, None]
    cc = np.arange(t.col0 - 1, t.col0 + t.cols + 1)[None, :]
    z = np.where((rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols), z, np.float32(np.nan))
    code_raw = ta.tile_d8(z, kind, dx, tctx.cl)
    code_main = np.asarray(inputs["code"].tile_array(t))
    lake_in = params.lake_runoff_depth_m * (dx * dx) * r / mean_rain
    runoff = np.where(kind == ref.NODATA, 0.0, np.nan_to_num(lake_in, nan=0.0)).astype(np.float64)
    return {**state, "code_raw": code_raw, "code_main": code_main, "runoff": runoff,
            "code_lake": np.where(D, code_raw, code_main).astype(np.int8)}


def rain_sums(tctx, inputs: dict[str, Any], params, rain: tuple) -> TileOutput:
    """The tile's rain on its data cells summed exactly, its data cells and depression cells."""
    s = _tile_state(tctx, inputs, params, rain)
    return TileOutput({}, {"rain": str(ta.exact_sum(s["rain"][s["data"]])), "data": int(s["data"].sum()),
                           "depression_cells": int(s["D"].sum())})


def runoff_sums(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """The tile's lake runoff for fixed_point_scale (weight_sums)."""
    rain, scale = shared
    return TileOutput({}, weight_sums(_tile_state(tctx, inputs, params, rain)["runoff"], scale))


def routing_local(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """Barnes 2017 pass 1 on the lake routing, the fixed-point runoff as weights."""
    rain, scale = shared
    s = _tile_state(tctx, inputs, params, rain)
    t = tctx.tile
    return TileOutput({}, perimeter_summary(
        ta.accumulate_tile(s["code_lake"], (t.row0, t.col0), ta.quantize_tile(s["runoff"], scale), tctx.cl)))


def _ends(t, cols: int, code_lake: np.ndarray, local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the lake routing from each tile-local cell goes on: the next
    tile's cell (-1: none) and, where it ends in this tile, that end (-1: none)."""
    end, leaves = ta.path_ends(code_lake, local)
    nxt = np.where(leaves, _receivers(t, cols, code_lake, end), -1)
    return nxt, np.where(leaves, -1, _global(t, cols, end))


def cells_tile(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """Barnes 2017 pass 3 (the runoff arriving at each cell), then the
    tile's depression cells with what lakes.DepressionCells holds of them,
    its share of the runoff reaching the map's edge, and where the lake
    routing goes on from each perimeter cell."""
    rain, scale, inflow = shared
    s = _tile_state(tctx, inputs, params, rain)
    t, cols = tctx.tile, inputs["terrain"].shape[1]
    acc = ta.finish_tile(s["code_lake"], inflow, ta.quantize_tile(s["runoff"], scale), tctx.cl)
    acc = acc.astype(np.float64).ravel() / scale
    local = np.flatnonzero(s["D"])
    perim = ta.perimeter_cells(t.rows, t.cols)
    nxt, end = _ends(t, cols, s["code_lake"], perim)
    return TileOutput({}, {
        "cells": _global(t, cols, local), "h": s["h"].ravel()[local], "F": s["F"].ravel()[local],
        "rcv": _receivers(t, cols, s["code_raw"], local), "pit": s["code_lake"].ravel()[local] == ref.PIT,
        "acc": acc[local], "rcv_main": _receivers(t, cols, s["code_main"], local),
        "edge_out": str(ta.exact_sum(acc[s["kind"].ravel() == ref.EDGE])),
        "perimeter": _global(t, cols, perim), "perimeter_next": nxt, "perimeter_end": end})


def exits_tile(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """Where the lake routing goes on from the depressions' exits in this tile."""
    rain, exits = shared
    t, cols = tctx.tile, inputs["terrain"].shape[1]
    if not exits.size:
        return TileOutput({}, {"next": exits, "end": exits})
    r, c = np.divmod(exits, cols)
    local = (r - t.row0) * t.cols + (c - t.col0)
    nxt, end = _ends(t, cols, _tile_state(tctx, inputs, params, rain)["code_lake"], local)
    return TileOutput({}, {"next": nxt, "end": end})


def _exits(cells: np.ndarray, rcv_main: np.ndarray) -> np.ndarray:
    """Each depression cell's first cell off the depressions on the main
    routing (or the depression cell where that routing ends), by pointer
    jumping over the depression cells (lakes._lake_routing's `exit`)."""
    own = np.arange(cells.size)
    nxt = np.where(rcv_main >= 0, rcv_main, cells)
    pos = np.minimum(np.searchsorted(cells, nxt), max(cells.size - 1, 0))
    inside = (cells[pos] == nxt) & (pos != own)  # the path goes on through depression cell pos
    while inside.any():
        nxt = np.where(inside, nxt[pos], nxt)
        nxt_inside = np.where(inside, inside[pos], False)
        pos = np.where(inside, pos[pos], pos)
        inside = nxt_inside & (pos != own)
    return nxt


def _chain(start_next: np.ndarray, start_end: np.ndarray, perimeter: dict) -> np.ndarray:
    """Where each path ends: from its first tile's (next cell, end), through
    the perimeter cells' (next, end) of the tiles it crosses."""
    term = start_end.copy()
    for i in np.flatnonzero(start_next >= 0).tolist():
        nxt = int(start_next[i])
        while True:
            nxt, end = perimeter[nxt]
            if nxt < 0:
                term[i] = end
                break
    return term


def gather(runner, terrain, core: dict, params, rain_map, progress=lambda f, m: None):
    """lakes.DepressionCells of a tiled world (core: flow_core's results),
    and the tiles' data cells; None when lakes are off."""
    shape, dx = terrain.shape, terrain.cell_size_m
    rows, cols = shape
    tiles = runner.tiles(shape)
    geo = {"cell_size_m": dx, "origin_m": terrain.origin_m, "keep": False}
    ins = {"terrain": terrain, "filled": core["filled"], "code": core["code"]}
    progress(0.0, "lakes: rain")
    _, parts = runner.map(rain_sums, "lake_rain", shape, ins, params, (core["hmin"], rain_map, None), **geo)
    n_data = sum(p["data"] for p in parts)
    mean_rain = ta.exact_total([int(p["rain"]) for p in parts]) / n_data
    rain = (core["hmin"], rain_map, mean_rain if mean_rain > 0 else 1.0)
    if not sum(p["depression_cells"] for p in parts):
        _, parts = runner.map(runoff_sums, "lake_runoff", shape, ins, params, (rain, None), **geo)
        return lakes_mod.no_depressions(cols, rows * cols, ta.exact_total([int(p["exact"]) for p in parts]))
    total_in, scale = fixed_point_scale(runner, runoff_sums, "lake_runoff", shape, ins, params, rain, "lakes", **geo)
    progress(0.3, "lakes: routing")
    _, parts = runner.map(routing_local, "lake_routing", shape, ins, params, (rain, scale), **geo)
    by_name = {name: (rain, scale, f) for name, f in inflow_by_tile(tiles, parts).items()}
    progress(0.6, "lakes: depression cells")
    _, parts = runner.map(cells_tile, "lake_cells", shape, ins, params, per_tile=by_name, **geo)
    got = {k: np.concatenate([p[k] for p in parts]) for k in ("cells", "h", "F", "rcv", "pit", "acc", "rcv_main")}
    order = np.argsort(got["cells"], kind="stable")
    got = {k: v[order] for k, v in got.items()}
    cells = got["cells"]
    perimeter = {}
    for p in parts:
        perimeter.update(zip(p["perimeter"].tolist(), zip(p["perimeter_next"].tolist(), p["perimeter_end"].tolist())))
    exit_ = _exits(cells, got["rcv_main"])
    exits = np.unique(exit_)
    per_tile = {t.name: (rain, exits[(exits // cols >= t.row0) & (exits // cols < t.row0 + t.rows) &
                                     (exits % cols >= t.col0) & (exits % cols < t.col0 + t.cols)]) for t in tiles}
    _, parts_x = runner.map(exits_tile, "lake_exits", shape, ins, params, per_tile=per_tile, **geo)
    ends = {}
    for t, p in zip(tiles, parts_x):
        ends.update(zip(per_tile[t.name][1].tolist(), zip(p["next"].tolist(), p["end"].tolist())))
    term = _chain(np.array([ends[x][0] for x in exits.tolist()], np.int64),
                  np.array([ends[x][1] for x in exits.tolist()], np.int64), perimeter)
    pos = np.minimum(np.searchsorted(cells, term), cells.size - 1)
    return lakes_mod.DepressionCells(
        cols, rows * cols, total_in, ta.exact_total([int(p["edge_out"]) for p in parts]), cells, got["h"], got["F"],
        got["rcv"], got["pit"], got["acc"], ref.sparse_neighbours(cells, cols, rows * cols), exit_, exits, term,
        cells[pos] == term)


def lakes(runner, terrain, core: dict, params, rain_map, env, progress=lambda f, m: None):
    """The lakes of a tiled world: (the depression cells, their lakes), or None when lakes are off."""
    if not params.lakes:
        return None
    from worldlib.flow import device as dev

    dc = gather(runner, terrain, core, params, rain_map, progress)
    sol = lakes_mod.solve_depressions(dc, terrain.cell_size_m ** 2, functools.partial(dev.merge_sweep, env))
    if sol.stats["budget_relative_error"] > 1e-6:
        raise StageError(f"hydrology: lake volume budget off by {sol.stats['budget_relative_error']:.2e} (relative)")
    return dc, sol
