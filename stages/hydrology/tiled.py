"""The stage's steps 1 to 3 on a tiled world (pipeline.tiles), each tile a
task: the plain fill in Barnes' (2016) three passes, the epsilon-filled
routing surface in rounds of neighbour perimeters, D8 directions from a
one-cell halo, breaching along them and D8 accumulation in Barnes' (2017)
three passes (worldlib.flow.tiled_fill, drainage_breach, tiled_accum).
Every result is bitwise the untiled one (routing.condition,
flow_directions).
The stage's process holds only the perimeters and the tiles' summaries.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.errors import InputError, StageError
from pipeline.tiles import TileOutput
from worldlib.flow import drainage_breach, longest_path
from worldlib.flow import reference as ref
from worldlib.flow import tiled_accum as ta
from worldlib.flow import tiled_fill as tf

from . import channels, rivers, water_layer
from .grids import GRID_CHANNELS, grid_arrays, preview, river_shown
from .moisture import clean_moisture, water_proximity, water_reach_cells, wetness_kernel
from .routing import SECONDS_PER_YEAR, Land, rain_from_map, rain_m_per_year

MAX_EPS_ROUNDS = 10_000


def _heights(tctx, terrain) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tile's canonical heights (NaN on no-data), kinds, and its heights
    with a one-cell halo (NaN beyond the world)."""
    halo = ref.canonical(terrain.read_padded(tctx.tile, 1, channel=terrain.channels[0]))
    kind = tf.tile_kind(halo)
    h = np.ascontiguousarray(halo[1:-1, 1:-1])
    h[kind == ref.NODATA] = np.nan
    return h, kind, halo


def fill_local(tctx, inputs: dict[str, Any], params, shared) -> TileOutput:
    """Barnes 2016 pass 1: the tile filled with its perimeter open, its watersheds and perimeter."""
    h, kind, _ = _heights(tctx, inputs["terrain"])
    t = tf.fill_tile(h, kind, tctx.cl)
    p = t.perimeter
    summary = {f"{side}_{what}": arr for side, pair in zip(("top", "bottom", "left", "right"),
                                                          (p.top, p.bottom, p.left, p.right))
               for what, arr in zip(("z", "label"), pair)}
    summary.update(n_labels=int(p.n_labels), spill_a=p.spill[0], spill_b=p.spill[1], spill_z=p.spill[2],
                   hmin=float(np.nanmin(h)) if (kind != ref.NODATA).any() else float("inf"))
    return TileOutput({"local": t.filled, "labels": t.labels.astype(np.int32)}, summary)


def _perimeter(s: dict) -> tf.Perimeter:
    sides = [(s[f"{side}_z"], s[f"{side}_label"]) for side in ("top", "bottom", "left", "right")]
    return tf.Perimeter(*sides, int(s["n_labels"]), (s["spill_a"], s["spill_b"], s["spill_z"]))


def fill_finish(tctx, inputs: dict[str, Any], params, level: np.ndarray) -> TileOutput:
    """Barnes 2016 pass 3: max(the tile-local fill, its watershed's level)."""
    local = np.asarray(inputs["local"].tile_array(tctx.tile))
    labels = np.asarray(inputs["labels"].tile_array(tctx.tile))
    return TileOutput({"filled": tf.finish_tile(local, labels, level)})


def eps_round(tctx, inputs: dict[str, Any], params, active: bool) -> TileOutput:
    """One round of the epsilon fill: the tile with its neighbours' values
    of the round before as outlets (inf: not yet known). A tile whose ring
    cannot have changed keeps its value."""
    before = inputs.get("routing")
    if before is not None and not active:
        return TileOutput({"routing": np.array(before.tile_array(tctx.tile))}, {"changed": False})
    h, kind, halo = _heights(tctx, inputs["terrain"])
    if before is None:  # round 1: every neighbour value unknown
        ring = np.where(np.isfinite(halo), np.float32(np.inf), np.float32(np.nan))  # no-data: NaN or +-inf
        old = np.where(np.isnan(h), np.float32(np.nan), np.float32(np.inf))
    else:
        ring = before.read_padded(tctx.tile, 1)
        old = ring[1:-1, 1:-1]
    new = tf.eps_round_tile(h, kind, ring, tctx.cl)
    changed = not np.array_equal(new, old, equal_nan=True)
    return TileOutput({"routing": new}, {"changed": changed})


def directions(tctx, inputs: dict[str, Any], params, shared: tuple[float, bool]) -> TileOutput:
    """D8 on the routing surface from a one-cell halo (kinds from the
    terrain's); shared = (dx, whether to count the cells its epsilon fill
    would raise: tf.eps_unsettled)."""
    dx, settled = shared
    z = inputs["routing"].read_padded(tctx.tile, 1)
    kind = tf.tile_kind(z)  # the routing surface is NaN where the terrain is
    code = ta.tile_d8(z, kind, dx, tctx.cl)
    return TileOutput({"code": code}, {"pits": int((code == ref.PIT).sum()),
                                       "unsettled": tf.eps_unsettled(z, kind) if settled else 0})


def accumulate_local(tctx, inputs: dict[str, Any], params, shared) -> TileOutput:
    """Barnes 2017 pass 1: where each perimeter cell's path leaves the tile, and its local sum."""
    code = np.asarray(inputs["code"].tile_array(tctx.tile))
    return TileOutput({}, perimeter_summary(ta.accumulate_tile(code, (tctx.tile.row0, tctx.tile.col0), None, tctx.cl)))


def accumulate_finish(tctx, inputs: dict[str, Any], params, inflow: np.ndarray) -> TileOutput:
    """Barnes 2017 pass 3: the tile's accumulation with the inflow from other tiles."""
    code = np.asarray(inputs["code"].tile_array(tctx.tile))
    counts = ta.finish_tile(code, inflow, None, tctx.cl)
    kind = tf.tile_kind(inputs["routing"].read_padded(tctx.tile, 1))
    return TileOutput({"counts": counts}, {"outlet_cells": int(counts[kind == ref.EDGE].astype(np.int64).sum()),
                                           "data_cells": int((kind != ref.NODATA).sum())})


def depression_cells(tctx, inputs: dict[str, Any], params, shared) -> TileOutput:
    """Breaching's gather: the tile's depression and rim cells (world flat
    indices) with their flood keys (drainage_breach.flood_codes)."""
    _, _, halo = _heights(tctx, inputs["terrain"])
    inside, rim = drainage_breach.depression_sets(halo, inputs["filled"].read_padded(tctx.tile, 1))
    inside, rim = inside[1:-1, 1:-1], rim[1:-1, 1:-1]
    local = np.flatnonzero(inside | rim)
    key = np.where(inside, halo[1:-1, 1:-1], inputs["routing"].tile_array(tctx.tile)).ravel()[local]
    return TileOutput({}, {"cells": _global(tctx.tile, inputs["terrain"].shape[1], local), "key": key,
                           "inside": inside.ravel()[local]})


def flood_paths(tiles, parts: list[dict], shape) -> dict:
    """The depressions' flood codes from the tiles' depression_cells, by
    tile name: (tile-local flat cells, their codes)."""
    rows, cols = shape
    got = {k: np.concatenate([p[k] for p in parts]) for k in ("cells", "key", "inside")}
    order = np.argsort(got["cells"], kind="stable")
    cells = got["cells"][order]
    codes = drainage_breach.flood_codes(cells, got["key"][order], got["inside"][order], cols, rows * cols) \
        if cells.size else np.zeros(0, np.int8)
    cells, codes = cells[codes >= 0], codes[codes >= 0]
    r, c = np.divmod(cells, cols)
    out = {}
    for t in tiles:
        mine = (r >= t.row0) & (r < t.row0 + t.rows) & (c >= t.col0) & (c < t.col0 + t.cols)
        out[t.name] = ((r[mine] - t.row0) * t.cols + (c[mine] - t.col0), codes[mine])
    return out


def _carve_inputs(tctx, inputs: dict[str, Any], flood: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tile's heights with a halo, kinds, and the carves' paths: the
    drainage's codes, the floods' on the depression cells."""
    _, kind, halo = _heights(tctx, inputs["terrain"])
    code = np.array(inputs["code"].tile_array(tctx.tile), np.int8)
    local, codes = flood
    code.ravel()[local] = codes
    return halo, kind, code


def breach_local(tctx, inputs: dict[str, Any], params, flood: tuple) -> TileOutput:
    """Breaching's pass 1: the tile's own carves, and how a carve arriving at each perimeter cell crosses it."""
    c = drainage_breach.carve_tile(*_carve_inputs(tctx, inputs, flood), (tctx.tile.row0, tctx.tile.col0))
    return TileOutput({}, {**perimeter_summary(c.perimeter), "threshold": c.threshold, "steps": c.steps})


def carves_by_tile(tiles, parts: list[dict]) -> dict:
    """Breaching's pass 2 from the tiles' breach_local summaries: the carves arriving at each tile's perimeter."""
    got = [drainage_breach.CarvePerimeter(
        ta.Perimeter((t.row0, t.col0), (t.rows, t.cols), s["code"], s["exit"], s["local_sum"]), s["threshold"],
        s["steps"]) for t, s in zip(tiles, parts)]
    arriving = drainage_breach.solve_carves(_grid_of(tiles, got))
    return {t.name: a for t, a in zip(tiles, [a for row in arriving for a in row])}


def breach_finish(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """Breaching's pass 3: the tile's breached surface, the carves from other tiles carving on in it."""
    flood, arriving = shared
    return TileOutput({"breached": drainage_breach.finish_tile(*_carve_inputs(tctx, inputs, flood), arriving)})


def _grid_of(tiles, values: list) -> list[list]:
    rows = max(t.row for t in tiles) + 1
    return [[v for t, v in zip(tiles, values) if t.row == i] for i in range(rows)]


def perimeter_summary(p: ta.Perimeter) -> dict:
    """Barnes 2017 pass 1's answer for one tile, as a tile's summary."""
    return {"code": p.code, "exit": p.exit, "local_sum": p.local_sum}


def inflow_by_tile(tiles, parts: list[dict]) -> dict:
    """Barnes 2017 pass 2 from the tiles' perimeter_summary: each tile's inflow at its perimeter cells, by tile name."""
    perims = [ta.Perimeter((t.row0, t.col0), (t.rows, t.cols), s["code"], s["exit"], s["local_sum"])
              for t, s in zip(tiles, parts)]
    inflow = ta.solve_inflow(_grid_of(tiles, perims))
    return {t.name: f for t, f in zip(tiles, [f for row in inflow for f in row])}


def weight_sums(weights: np.ndarray, scale: float | None) -> dict:
    """A tile's summary for fixed_point_scale: its weights summed exactly
    (scale None), or in fixed point at the candidate scale and half of it."""
    if scale is None:
        return {"exact": str(ta.exact_sum(weights))}
    return {"q": [str(x) for x in ta.tile_quantized_sums(weights, scale)]}


def fixed_point_scale(runner, fn, pass_name: str, shape, inputs: dict, params, shared, what: str,
                      **geo) -> tuple[float, float]:
    """The world's total weight and device.quantize's scale for it, from
    two passes of fn(tctx, inputs, params, (shared, scale or None)) ->
    weight_sums' summary: exact per-tile totals, then integer sums at the
    candidate scale (ta.quantize_scale)."""
    geo = {**geo, "keep": False}  # cheap passes: remade on a resume
    _, parts = runner.map(fn, pass_name, shape, inputs, params, (shared, None), **geo)
    total = ta.exact_total([int(p["exact"]) for p in parts])
    _, parts = runner.map(fn, pass_name + "_q", shape, inputs, params, (shared, ta.first_scale(total)), **geo)
    try:
        return total, ta.quantize_scale(total, [tuple(int(x) for x in p["q"]) for p in parts])
    except ValueError as e:
        raise StageError(f"hydrology: {what}: {e}") from None


def flow_core(runner, terrain, params, progress=lambda f, m: None) -> dict[str, Any]:
    """filled, routing, code and counts of the whole world as TileArrays."""
    shape, dx = terrain.shape, terrain.cell_size_m
    tiles = runner.tiles(shape)
    geo = {"cell_size_m": dx, "origin_m": terrain.origin_m}
    progress(0.0, "fill: tiles")
    local, parts = runner.map(fill_local, "fill", shape, {"terrain": terrain}, params,
                              grids={"local": ("filled",), "labels": ("label",)}, **geo)
    hmin = min(s["hmin"] for s in parts)
    levels = tf.solve_levels(_grid_of(tiles, [_perimeter(s) for s in parts]))
    by_name = {t.name: lv for t, lv in zip(tiles, [lv for row in levels for lv in row])}
    filled, _ = runner.map(fill_finish, "filled", shape, dict(local), params, per_tile=by_name,
                           grids={"filled": ("filled",)}, **geo)
    routing, rounds = _epsilon_fill(runner, "routing", terrain, params, progress, geo)
    code, _ = _directions(runner, "directions" if params.depression == "fill" else "drainage", shape, routing,
                          params, dx, {**geo, "keep": params.depression == "fill"})
    if params.depression == "breach":
        progress(0.15, "breaching: the depressions' floods")
        ins = {"terrain": terrain, "filled": filled["filled"], "routing": routing, **code}
        _, parts = runner.map(depression_cells, "breach_depressions", shape, ins, params, keep=False, **geo)
        paths = flood_paths(tiles, parts, shape)
        progress(0.2, "breaching: tiles")
        _, parts = runner.map(breach_local, "breach", shape, ins, params, per_tile=paths, keep=False, **geo)
        arriving = carves_by_tile(tiles, parts)
        breached, _ = runner.map(breach_finish, "breached", shape, ins, params,
                                 per_tile={name: (paths[name], arriving[name]) for name in paths},
                                 grids={"breached": ("routing",)}, keep=False, **geo)
        runner.discard(routing)
        runner.discard(code["code"])
        routing = breached["breached"]
        # above 1 m every carve's float step is a step of the epsilon fill: the breached surface is its own fill
        code, unsettled = _directions(runner, "directions", shape, routing, params, dx, geo, settled=True)
        if unsettled:
            runner.discard(code["code"])
            routing, more = _epsilon_fill(runner, "breached_routing", routing, params, progress, geo)
            runner.discard(breached["breached"])
            rounds += more
            code, _ = _directions(runner, "directions", shape, routing, params, dx, geo)
    _, parts = runner.map(accumulate_local, "accumulation", shape, dict(code), params, **geo)
    by_name = inflow_by_tile(tiles, parts)
    counts, parts = runner.map(accumulate_finish, "counts", shape, {**code, "routing": routing}, params,
                               per_tile=by_name,
                               grids={"counts": ("counts",)}, **geo)
    outlet, data = sum(s["outlet_cells"] for s in parts), sum(s["data_cells"] for s in parts)
    if outlet != data:
        raise StageError(f"hydrology: accumulation at the outlets is {outlet} cells, not {data}")
    return {"filled": filled["filled"], "routing": routing, "code": code["code"], "counts": counts["counts"],
            "rounds": rounds, "hmin": hmin, "outlet_cells": outlet}


def _epsilon_fill(runner, pass_name: str, base, params, progress, geo: dict):
    """The epsilon fill of base (the terrain, or a breached surface) in
    rounds of neighbour perimeters: the routing surface as TileArrays, and
    the rounds it took."""
    tiles = runner.tiles(base.shape)
    routing, active = None, {t.name for t in tiles}
    for rnd in range(1, MAX_EPS_ROUNDS + 1):
        progress(0.02, f"routing surface: round {rnd}, {len(active)} tiles")
        ins = {"terrain": base, **({"routing": routing} if routing is not None else {})}
        # the rounds are not kept as units: dozens of world-sized arrays, each cheaper to remake than to store;
        # a round reads only the one before, which goes once this one is made (21 rounds at 16384^2: 23 GB)
        routing_now, parts = runner.map(eps_round, f"{pass_name}{rnd}", base.shape, ins, params,
                                        per_tile={t.name: t.name in active for t in tiles},
                                        grids={"routing": ("routing",)}, keep=False, **geo)
        before, routing = routing, routing_now["routing"]
        runner.discard(before)
        changed = {(t.row, t.col) for t, s in zip(tiles, parts) if s["changed"]}
        if not changed:
            return routing, rnd
        # a tile reads its 8 neighbours' values: it runs again when one of them (or itself) changed
        active = {t.name for t in tiles if any((t.row + i, t.col + j) in changed for i in (-1, 0, 1) for j in (-1, 0, 1))}
    raise StageError(f"hydrology: the tiled routing surface found no fixed point after {MAX_EPS_ROUNDS} rounds")


def _directions(runner, pass_name: str, shape, routing, params, dx: float, geo: dict,
                settled: bool = False) -> tuple[dict, int]:
    """The D8 codes of a routing surface and (settled) the cells its
    epsilon fill would raise; checked to leave no pit when it is its own
    epsilon fill."""
    code, parts = runner.map(directions, pass_name, shape, {"routing": routing}, params, (dx, settled),
                             grids={"code": ("code",)}, **geo)
    unsettled = sum(s["unsettled"] for s in parts)
    if sum(s["pits"] for s in parts) and not unsettled:
        raise StageError("hydrology: a cell has no downslope path after depression handling (broken invariant)")
    return code, unsettled


# --------------------------------------------------------------------------- discharge


def _global(t, cols: int, local: np.ndarray) -> np.ndarray:
    r, c = np.divmod(np.asarray(local, np.int64), t.cols)
    return (r + t.row0) * cols + (c + t.col0)


def _receivers(t, cols: int, code: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Flat world index of the receiver of each tile-local cell, -1 where it has none."""
    k = code.ravel()[local].astype(np.int64)
    kk = np.clip(k, 0, 7)
    return np.where(k >= 0, _global(t, cols, local) + ref.DR[kk] * cols + ref.DC[kk], -1)


def _tile_rain(tctx, terrain, params, rain: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The tile's yearly rain (routing.rain_m_per_year on the tile, from the
    world's lowest height and rain map: rain = (hmin, the map's path or
    None, world shape)) and its cells with data."""
    hmin, rain_map, (rows, cols) = rain
    h, kind, _ = _heights(tctx, terrain)
    data = kind != ref.NODATA
    t = tctx.tile
    land = Land(h, kind, data, float(terrain.cell_size_m), terrain.origin_m, hmin)
    rain_mm = None if rain_map is None else rain_from_map(rain_map, rows, cols, (t.col0, t.row0, t.cols, t.rows))
    return rain_m_per_year(land, params, rain_mm), data


def _runoff_weights(tctx, terrain, params, rain: tuple) -> np.ndarray:
    """The runoff each cell of the tile sends down (m^3/year, float64, 0 on no-data)."""
    r, _ = _tile_rain(tctx, terrain, params, rain)
    return r * params.runoff_coefficient * (float(terrain.cell_size_m) ** 2)


def runoff_sums(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """The tile's runoff for fixed_point_scale (weight_sums)."""
    rain, scale = shared
    return TileOutput({}, weight_sums(_runoff_weights(tctx, inputs["terrain"], params, rain), scale))


def discharge_local(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """Barnes 2017 pass 1 with the fixed-point runoff as weights."""
    rain, scale = shared
    q = ta.quantize_tile(_runoff_weights(tctx, inputs["terrain"], params, rain), scale)
    code = np.asarray(inputs["code"].tile_array(tctx.tile))
    return TileOutput({}, perimeter_summary(ta.accumulate_tile(code, (tctx.tile.row0, tctx.tile.col0), q, tctx.cl)))


def discharge_finish(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """Barnes 2017 pass 3: the accumulated runoff, as mean discharge (m^3/s, float64)."""
    rain, scale, inflow = shared
    q = ta.quantize_tile(_runoff_weights(tctx, inputs["terrain"], params, rain), scale)
    code = np.asarray(inputs["code"].tile_array(tctx.tile))
    acc = ta.finish_tile(code, inflow, q, tctx.cl)
    return TileOutput({"discharge": acc.astype(np.float64) / scale / SECONDS_PER_YEAR})


def uniform_discharge(tctx, inputs: dict[str, Any], params, cell_area: float) -> TileOutput:
    """Uniform rain: the drainage area times the runoff (routing.discharge_m3_s, cell by cell)."""
    area_m2 = np.asarray(inputs["counts"].tile_array(tctx.tile)).astype(np.float64) * cell_area
    return TileOutput({"discharge": area_m2 * (params.rain_mm_per_year / 1000.0 * params.runoff_coefficient)
                       / SECONDS_PER_YEAR})


def discharge(runner, terrain, core: dict, params, rain_map, progress=lambda f, m: None):
    """Mean discharge (m^3/s) per cell as TileArrays: routing.discharge_m3_s
    tile by tile, bitwise. Rain that varies is accumulated as fixed-point
    weights at the world's scale (ta.quantize_scale: an exact total, then
    integer sums), in Barnes' three passes."""
    shape, dx = terrain.shape, terrain.cell_size_m
    tiles = runner.tiles(shape)
    geo = {"cell_size_m": dx, "origin_m": terrain.origin_m}
    grids = {"discharge": ("discharge",)}
    if params.uniform_rain:
        out, _ = runner.map(uniform_discharge, "discharge", shape, {"counts": core["counts"]}, params, dx * dx,
                            grids=grids, **geo)
        return out["discharge"]
    rain = (core["hmin"], rain_map, shape)
    progress(0.0, "discharge: runoff totals")
    _, scale = fixed_point_scale(runner, runoff_sums, "runoff", shape, {"terrain": terrain}, params, rain,
                                 "discharge", **geo)
    ins = {"terrain": terrain, "code": core["code"]}
    _, parts = runner.map(discharge_local, "discharge_local", shape, ins, params, (rain, scale), **geo)
    by_name = {name: (rain, scale, f) for name, f in inflow_by_tile(tiles, parts).items()}
    out, _ = runner.map(discharge_finish, "discharge", shape, ins, params, per_tile=by_name, grids=grids, **geo)
    return out["discharge"]


# --------------------------------------------------------------------------- the river network


def network_tile(tctx, inputs: dict[str, Any], params, rain: tuple) -> TileOutput:
    """The tile's network cells (rivers.network_cells) with their receivers
    as flat world indices and what rivers.Network holds of each but the
    lakes'; and the tile's exact sums for the stats (rain on its data cells,
    discharge at its map-edge cells) and depression cells."""
    t, cols = tctx.tile, inputs["code"].shape[1]
    dx = float(inputs["terrain"].cell_size_m)
    code = np.asarray(inputs["code"].tile_array(t))
    area = np.asarray(inputs["counts"].tile_array(t)).astype(np.float64) * (dx * dx)
    local = rivers.network_cells(code, area, params.river_threshold_m2)
    h, kind, _ = _heights(tctx, inputs["terrain"])
    filled = np.asarray(inputs["filled"].tile_array(t))
    discharge = np.asarray(inputs["discharge"].tile_array(t))
    rain_m, data = _tile_rain(tctx, inputs["terrain"], params, rain)
    at = lambda a: np.asarray(a).ravel()[local]
    return TileOutput({}, {"cells": _global(t, cols, local), "rcv": _receivers(t, cols, code, local),
                           "code": at(code), "area_m2": at(area),
                           "discharge": at(discharge), "h": at(h), "filled": at(filled),
                           "rain_sum": str(ta.exact_sum(rain_m[data])), "data_cells": int(data.sum()),
                           "edge_discharge": str(ta.exact_sum(discharge[kind == ref.EDGE])),
                           "depression_cells": int((filled > h).sum())})


NETWORK_FIELDS = ("cells", "rcv", "code", "area_m2", "discharge", "h", "filled")


def network(runner, terrain, core: dict, params, rain_map=None) -> tuple[dict[str, np.ndarray], dict]:
    """The river network's cells of the whole world (rivers.Network's
    fields but the lakes', and the fill), ascending: gathered tile by tile,
    nothing world-sized; and the world's sums (mean rain, discharge out of
    the map, depression cells). `core`: flow_core's results and the discharge."""
    shape, dx = terrain.shape, terrain.cell_size_m
    ins = {"terrain": terrain, **{k: core[k] for k in ("code", "counts", "discharge", "filled")}}
    _, parts = runner.map(network_tile, "network", shape, ins, params, (core["hmin"], rain_map, shape), keep=False,
                          cell_size_m=dx, origin_m=terrain.origin_m)
    out = {k: np.concatenate([p[k] for p in parts]) for k in NETWORK_FIELDS}
    order = np.argsort(out["cells"], kind="stable")
    n_data = sum(p["data_cells"] for p in parts)
    sums = {"mean_rain_m": ta.exact_total([int(p["rain_sum"]) for p in parts]) / max(n_data, 1), "n_data": n_data,
            "discharge_out_m3_s": ta.exact_total([int(p["edge_discharge"]) for p in parts]),
            "depression_cells": sum(p["depression_cells"] for p in parts)}
    return {k: v[order] for k, v in out.items()}, sums


# --------------------------------------------------------------------------- values on a few cells


@dataclass(frozen=True)
class SparseCells:
    """Values on a few cells of a world (flat indices, ascending): the lakes
    on the depression cells, the rivers on the network's. A tile is sent the
    part in its window and makes its maps from it."""
    cols: int  # the world's columns
    cells: np.ndarray  # int64 flat indices, ascending
    values: dict  # name -> array per cell

    def part(self, window: tuple[int, int, int, int]) -> "SparseCells":
        """The cells in window = (row0, col0, rows, cols) (it may reach beyond the world)."""
        r0, c0, rows, cols = window
        r = np.arange(max(r0, 0), r0 + rows, dtype=np.int64)
        lo = np.searchsorted(self.cells, r * self.cols + max(c0, 0))
        hi = np.searchsorted(self.cells, r * self.cols + min(c0 + cols, self.cols))
        sel = np.concatenate([np.arange(a, b) for a, b in zip(lo.tolist(), hi.tolist())] or [np.zeros(0, np.int64)])
        return SparseCells(self.cols, self.cells[sel], {k: v[sel] for k, v in self.values.items()})

    def grid(self, name: str, window: tuple[int, int, int, int], fill, dtype) -> np.ndarray:
        """Values `name` on the window's cells, `fill` elsewhere."""
        r0, c0, rows, cols = window
        out = np.full((rows, cols), fill, dtype)
        r, c = np.divmod(self.cells, self.cols)
        ok = (r >= r0) & (r < r0 + rows) & (c >= c0) & (c < c0 + cols)
        out[r[ok] - r0, c[ok] - c0] = self.values[name][ok]
        return out


def _lake_grids(lakes: SparseCells, window) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lakes' depth, level and id on a window (dry elsewhere: lakes.lake_maps_of's fills)."""
    return (lakes.grid("depth", window, 0.0, np.float64), lakes.grid("level", window, np.nan, np.float64),
            lakes.grid("lake_id", window, 0, np.int32))


def _padded_window(t, halo: int) -> tuple[int, int, int, int]:
    return t.row0 - halo, t.col0 - halo, t.rows + 2 * halo, t.cols + 2 * halo


# --------------------------------------------------------------------------- the carved ground


def ground_tile(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """The tile's ground with the beds of the segments near it carved
    (water_layer.carved_ground on the tile: its cells as the whole world's)."""
    seg, pool_ids, lakes = shared
    terrain, t = inputs["terrain"], tctx.tile
    h, kind, _ = _heights(tctx, terrain)
    _, level, lake_id = _lake_grids(lakes, t.window(0))
    ground, wet, pools = water_layer.carved_ground(h, lake_id, level, seg, pool_ids, terrain.cell_size_m,
                                                   tuple(terrain.origin_m), params,
                                                   window=(t.row0, t.col0, *terrain.shape))
    return TileOutput({"ground": ground, "wet": wet},
                      {"has_data": bool((kind != ref.NODATA).any()), **water_layer.ground_stats(h, ground, wet, pools)})


def carved_ground(runner, terrain, seg: dict, pool_ids: np.ndarray, lakes: SparseCells, params) -> tuple[dict, dict]:
    """The carved ground and the cells under the rivers as TileArrays, and
    water_layer.ground_stats of the world. Each tile gets the segments that
    can reach it (channels.segments_near) and the lakes' cells in it."""
    shape, dx, origin = terrain.shape, terrain.cell_size_m, tuple(terrain.origin_m)
    k = channels.carve_reach_cells(seg, dx, params.river_floor_m, params.river_bank_m)
    shared = {t.name: (channels.segments_near(seg, dx, origin, t.window(0), k), pool_ids, lakes.part(t.window(0)))
              for t in runner.tiles(shape)}
    out, parts = runner.map(ground_tile, "ground", shape, {"terrain": terrain}, params, per_tile=shared,
                            grids={"ground": ("height",), "wet": ("wet",)}, cell_size_m=dx, origin_m=origin)
    return out, water_layer.tiles_ground_stats([(s.pop("has_data"), s) for s in parts])


# --------------------------------------------------------------------------- wetness and moisture


def wetness_tile(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """moisture.wetness_and_moisture on the tile: the kernel on the tile with
    a one-cell halo (its slopes), the moisture from the open water (rivers,
    the cells under their surfaces, lakes) within water_reach_cells of it."""
    rivers_part, lakes_part = shared
    terrain, t = inputs["terrain"], tctx.tile
    dx = float(terrain.cell_size_m)
    reach = water_reach_cells(dx, params.moisture_water_distance_m)
    win = _padded_window(t, reach)
    open_water = rivers_part.grid("mask", win, False, bool) | (lakes_part.grid("depth", win, 0.0, np.float64) > 0) | \
        inputs["wet"].read_padded(t, reach, fill=False)
    inner = slice(reach - 1, reach + 1 + t.rows), slice(reach - 1, reach + 1 + t.cols)
    m_water = water_proximity(open_water, dx, params.moisture_water_distance_m)[inner]
    halo = ref.canonical(terrain.read_padded(t, 1, channel=terrain.channels[0]))
    area = inputs["counts"].read_padded(t, 1, fill=0).astype(np.float64) * (dx * dx)
    ext = inputs.get("erosion_moisture")
    m_ext = np.zeros(halo.shape) if ext is None else \
        clean_moisture(ext.read_padded(t, 1, fill=0.0, channel=ext.channels[0]))
    twi, moist = wetness_kernel(tctx.cl, np.where(np.isfinite(halo), halo, np.float32(np.nan)), ref.cell_kinds(halo),
                                area, m_water, m_ext, dx, params)
    return TileOutput({"wetness": twi[1:-1, 1:-1], "moisture": moist[1:-1, 1:-1]})


def wetness(runner, terrain, counts, erosion_moisture, wet, rivers_: SparseCells, lakes: SparseCells,
            params) -> dict:
    """The wetness index and moisture as TileArrays (D8 drainage area); the
    open water: the rivers' mask, the lakes and `wet` (the cells under the
    rivers' surfaces, TileArrays), each tile sent the part within its reach."""
    shape, dx = terrain.shape, terrain.cell_size_m
    if erosion_moisture is not None and tuple(erosion_moisture.shape) != tuple(shape):
        raise InputError(f"hydrology: erosion moisture is {tuple(erosion_moisture.shape)}, the terrain {tuple(shape)}")
    reach = water_reach_cells(dx, params.moisture_water_distance_m)
    ins = {"terrain": terrain, "counts": counts, "wet": wet,
           **({"erosion_moisture": erosion_moisture} if erosion_moisture else {})}
    per_tile = {t.name: (rivers_.part(_padded_window(t, reach)), lakes.part(_padded_window(t, reach)))
                for t in runner.tiles(shape)}
    out, _ = runner.map(wetness_tile, "wetness", shape, ins, params, per_tile=per_tile,
                        grids={"wetness": ("wetness",), "moisture": ("moisture",)}, cell_size_m=dx,
                        origin_m=terrain.origin_m)
    return out


# --------------------------------------------------------------------------- the stage's maps


def maps_tile(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """The stage's grids and preview on the tile (grids.grid_arrays, preview
    from a one-cell halo). shared: the world's lowest height and the lakes'
    and rivers' cells in the tile's window(1)."""
    from pipeline.grid import Grid

    hmin, lakes, rivers_ = shared
    terrain, t = inputs["terrain"], tctx.tile
    dx = float(terrain.cell_size_m)
    win = t.window(1)
    h = ref.canonical(terrain.read(*win, channel=terrain.channels[0]))
    h[~np.isfinite(h)] = np.nan
    inner = t.inner(1)
    own = lambda name: np.asarray(inputs[name].tile_array(t))
    wet = inputs["wet"].read(*win)
    lake_depth, lake_level, lake_id = _lake_grids(lakes, win)
    mask, width, order = (rivers_.grid(n, win, f, d) for n, f, d in (("mask", False, bool), ("width", 0.0, np.float64),
                                                                     ("order", 0, np.int32)))
    arrays = grid_arrays(np.isfinite(h[inner]), own("filled"), own("routing"), own("code"),
                         own("counts").astype(np.float64) * (dx * dx), own("discharge"), lake_depth[inner],
                         lake_level[inner], lake_id[inner], mask[inner], width[inner], order[inner],
                         wet[inner], own("wetness"), own("moisture"), own("ground"))
    shade = preview(Grid(h, dx, ("height",)), lake_depth, river_shown(mask, wet, lake_depth), hmin)
    return TileOutput({**{name.removeprefix("hydrology."): a for name, a in arrays.items()},
                       "preview": np.ascontiguousarray(shade[inner])})


def maps(runner, terrain, core: dict, grids: dict, lakes: SparseCells, rivers_: SparseCells) -> dict:
    """The stage's grids and preview as TileArrays, by artifact name. grids:
    the tiled passes' wet, ground, wetness and moisture; lakes (depth,
    level, lake_id) and rivers (mask, width, order) on their cells."""
    shape, dx = terrain.shape, terrain.cell_size_m
    ins = {"terrain": terrain, **{k: core[k] for k in ("filled", "routing", "code", "counts", "discharge")}, **grids}
    per_tile = {t.name: (core["hmin"], lakes.part(t.window(1)), rivers_.part(t.window(1))) for t in runner.tiles(shape)}
    out, _ = runner.map(maps_tile, "maps", shape, ins, None, per_tile=per_tile,
                        grids={**{name.removeprefix("hydrology."): chans for name, chans in GRID_CHANNELS.items()},
                               "preview": ("r", "g", "b")},
                        cell_size_m=dx, origin_m=terrain.origin_m)
    return {f"hydrology.{name}": arrays for name, arrays in out.items()}


def lake_outlines(lakes: SparseCells, terrain, min_area_m2: float) -> list:
    """water_layer.lake_outlines from the lakes' cells: each lake of at least
    min_area_m2, its level and its cells grown by one onto data cells (the
    terrain read on the lake's box)."""
    from scipy import ndimage

    rows, cols = terrain.shape
    cell_area = float(terrain.cell_size_m) ** 2
    wet = lakes.values["lake_id"] > 0
    ids, cells = lakes.values["lake_id"][wet], lakes.cells[wet]
    levels = lakes.values["level"][wet]
    order = np.argsort(ids, kind="stable")
    ids, cells, levels = ids[order], cells[order], levels[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]]) if ids.size else np.zeros(0, np.int64)
    out = []
    for a, b in zip(starts.tolist(), np.r_[starts[1:], ids.size].tolist()):
        if (b - a) * cell_area < min_area_m2:
            continue
        r, c = np.divmod(cells[a:b], cols)
        r0, r1 = max(int(r.min()) - 1, 0), min(int(r.max()) + 2, rows)
        c0, c1 = max(int(c.min()) - 1, 0), min(int(c.max()) + 2, cols)
        m = np.zeros((r1 - r0, c1 - c0), bool)
        m[r - r0, c - c0] = True
        data = np.isfinite(terrain.read(r0, c0, r1 - r0, c1 - c0, channel=terrain.channels[0]))
        grown = ndimage.binary_dilation(m, structure=np.ones((3, 3), bool)) & data
        rr, cc = np.nonzero(grown)
        out.append((int(ids[a]), float(np.nanmax(levels[a:b])), (rr + r0, cc + c0)))
    return out


# --------------------------------------------------------------------------- Hack's law


def paths_local(tctx, inputs: dict[str, Any], params, shared) -> TileOutput:
    """longest_path's pass 1: the tile's longest paths with nothing flowing in, and its perimeter's."""
    t = tctx.tile
    p = longest_path.tile_paths(np.asarray(inputs["code"].tile_array(t)), (t.row0, t.col0))
    return TileOutput({}, {"code": p.code, "exit": p.exit, "a": p.a, "b": p.b, "to_a": p.to_exit_a,
                           "to_b": p.to_exit_b})


def paths_finish(tctx, inputs: dict[str, Any], params, entry: tuple) -> TileOutput:
    """longest_path's pass 3: the step counts of each cell's longest path."""
    t = tctx.tile
    a, b = longest_path.finish_tile(np.asarray(inputs["code"].tile_array(t)), *entry)
    return TileOutput({"path_a": a.reshape(t.rows, t.cols), "path_b": b.reshape(t.rows, t.cols)})


def hack_tile(tctx, inputs: dict[str, Any], params, dx: float) -> TileOutput:
    """The tile's cells draining at least hack_min_area_m2 with what
    rivers.hack_fit needs of each (its best donor from a one-cell halo:
    rivers.hack_exponent's, ties to the last in flat order), and its longest path."""
    t, cols = tctx.tile, inputs["code"].shape[1]
    win = t.window(1)
    code = inputs["code"].read(*win)
    L = longest_path.length_m(inputs["path_a"].read(*win), inputs["path_b"].read(*win), dx)
    step = np.where(np.clip(code, 0, 7) % 2 == 1, dx * np.sqrt(2.0), dx)
    inner = t.inner(1)
    area = np.asarray(inputs["counts"].tile_array(t)).astype(np.float64) * (dx * dx)
    local = np.flatnonzero(area >= min(params.hack_min_area_m2, params.river_threshold_m2))
    r, c = np.divmod(local, t.cols)
    wr, wc = r + inner[0].start, c + inner[1].start  # in the window
    best_v, best = np.full(local.size, -np.inf), np.full(local.size, -1, np.int64)
    for k in range(8):
        dr, dc = wr + ref.DR[k], wc + ref.DC[k]
        ok = (dr >= 0) & (dr < code.shape[0]) & (dc >= 0) & (dc < code.shape[1])
        drs, dcs = np.where(ok, dr, 0), np.where(ok, dc, 0)
        ok &= code[drs, dcs] == (k + 4) % 8  # the neighbour drains into the cell
        v = np.where(ok, L[drs, dcs] + step[drs, dcs], -np.inf)
        idx = (drs + win[0]) * cols + (dcs + win[1])
        take = ok & ((v > best_v) | ((v == best_v) & (idx > best)))
        best_v, best = np.where(take, v, best_v), np.where(take, idx, best)
    own = lambda a: a[inner].ravel()[local]
    return TileOutput({}, {"cells": (r + t.row0) * cols + (c + t.col0), "area": area.ravel()[local], "L": own(L),
                           "best": best, "outlet": own(code) == ref.OUTLET, "longest": float(L[inner].max())})


def hack(runner, terrain, core: dict, params) -> tuple[dict, dict]:
    """rivers.hack_exponent of a tiled world: the longest paths in
    longest_path's three passes, the fit on the cells draining at least
    hack_min_area_m2 gathered tile by tile; and the longest paths (m) of the
    cells draining at least either that or river_threshold_m2 ("cells", "L")."""
    shape, dx = terrain.shape, float(terrain.cell_size_m)
    tiles = runner.tiles(shape)
    geo = {"cell_size_m": dx, "origin_m": terrain.origin_m}
    _, parts = runner.map(paths_local, "paths", shape, {"code": core["code"]}, params, keep=False, **geo)
    got = [longest_path.TilePaths((t.row0, t.col0), (t.rows, t.cols), s["code"], s["exit"], s["a"], s["b"],
                                  s["to_a"], s["to_b"]) for t, s in zip(tiles, parts)]
    entries = longest_path.solve_entries(_grid_of(tiles, got))
    by_name = {t.name: e for t, e in zip(tiles, [e for row in entries for e in row])}
    paths, _ = runner.map(paths_finish, "paths_finish", shape, {"code": core["code"]}, params, per_tile=by_name,
                          grids={"path_a": ("a",), "path_b": ("b",)}, keep=False, **geo)
    _, parts = runner.map(hack_tile, "hack", shape, {"code": core["code"], "counts": core["counts"], **paths}, params,
                          dx, keep=False, **geo)
    for arrays in paths.values():  # two world-sized arrays no later pass reads
        runner.discard(arrays)
    out = {k: np.concatenate([p[k] for p in parts]) for k in ("cells", "area", "L", "best", "outlet")}
    order = np.argsort(out["cells"], kind="stable")
    out = {k: v[order] for k, v in out.items()}
    fit = out["area"] >= params.hack_min_area_m2
    return rivers.hack_fit(*(out[k][fit] for k in ("cells", "area", "L", "best", "outlet")),
                           max(p["longest"] for p in parts), params.hack_min_area_m2), out


# --------------------------------------------------------------------------- the ribbons' fit on the ground


def bed_fit_tile(tctx, inputs: dict[str, Any], params, shared: tuple) -> TileOutput:
    """The fit ground (water_layer.bed_fit's: the carved ground, the level of
    the lakes the USD draws, no-data at the lowest height) under the bank
    vertices and lattice lines whose first tap lies in the tile."""
    from worldlib.terrain.mesh import bilinear_taps

    hmin, lakes, drawn_ids, bank_taps, lattice = shared
    t, (rows, cols) = tctx.tile, inputs["ground"].shape
    win = (t.row0, t.col0, min(t.rows + 1, rows - t.row0), min(t.cols + 1, cols - t.col0))
    lake_id = lakes.grid("lake_id", win, 0, np.int32)
    fit = np.where(np.isin(lake_id, drawn_ids), lakes.grid("level", win, np.nan, np.float64),
                   inputs["ground"].read(*win))
    g0 = np.nan_to_num(fit, nan=hmin)
    bank = channels.bilinear_points(g0, bank_taps, (t.row0, t.col0))
    hv = None if lattice is None else bilinear_taps(g0.astype(np.float32), *lattice, origin=(t.row0, t.col0))
    return TileOutput({}, {"bank": bank, **({} if hv is None else {"lattice": hv})})


def bed_fit(runner, terrain, ground, lakes: SparseCells, rib, in_drawn_lake: np.ndarray, hmin: float, params) -> dict:
    """water_layer.bed_fit of a tiled world: each tile samples the fit
    ground under the bank vertices and mesh lattice lines whose first tap
    it holds (with a one-cell margin for the second), the stats from them.
    in_drawn_lake: per ribbon vertex, whether its cell is in a lake the USD draws."""
    if not len(rib.points):
        return dict(water_layer.NO_FIT)
    shape, dx = terrain.shape, float(terrain.cell_size_m)
    q = water_layer.BedFitQuery.of(rib, ~in_drawn_lake, shape, dx, tuple(terrain.origin_m), params.mesh_max_vertices)
    drawn_ids = np.flatnonzero(channels.drawn_lake_ids(lakes.values["lake_id"], dx * dx, params.lake_min_area_m2))
    T = runner.tile_cells or max(shape)
    bank_row, bank_col = q.bank_taps[0] // T, q.bank_taps[2] // T
    per_tile, picks = {}, {}
    for t in runner.tiles(shape):
        sel = np.flatnonzero((bank_row == t.row) & (bank_col == t.col))
        lattice, ij = None, None
        if q.lattice is not None:
            (r0, r1, fr), (c0, c1, fc) = q.lattice[2], q.lattice[3]
            i, j = np.flatnonzero(r0 // T == t.row), np.flatnonzero(c0 // T == t.col)
            if i.size and j.size:
                lattice, ij = ((r0[i], r1[i], fr[i]), (c0[j], c1[j], fc[j])), (i, j)
        per_tile[t.name] = (hmin, lakes.part((t.row0, t.col0, t.rows + 1, t.cols + 1)), drawn_ids,
                            tuple(a[sel] for a in q.bank_taps), lattice)
        picks[t.name] = (sel, ij)
    _, parts = runner.map(bed_fit_tile, "bed_fit", shape, {"ground": ground}, params, per_tile=per_tile, keep=False,
                          cell_size_m=dx, origin_m=terrain.origin_m)
    bank = np.empty(q.bank_taps[0].size)
    hv = None if q.lattice is None else np.empty((q.lattice[0].size, q.lattice[1].size))
    for t, p in zip(runner.tiles(shape), parts):
        sel, ij = picks[t.name]
        bank[sel] = p["bank"]
        if ij is not None:
            hv[np.ix_(*ij)] = p["lattice"]
    return water_layer.bed_fit_stats(q, bank, hv)
