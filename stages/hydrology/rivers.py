"""Rivers: extraction by drainage area, Strahler order, bankfull width and
depth by hydraulic geometry (channels.py), a water level that never rises
downstream, and Hack's law."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worldlib.flow import longest_path
from worldlib.flow import reference as ref
from worldlib.terrain.stats import strahler_order

from .channels import LAKE_FULL_TOLERANCE_M, bankfull_discharge, drawn_lakes, hydraulic_geometry, water_level


def hack_exponent(code: np.ndarray, area_m2: np.ndarray, dx: float, min_area_m2: float) -> dict:
    """Hack's law L = c A^h (Hack 1957), least squares of log L on log A
    (L in m, A in m^2), L = the mainstream length: the longest upstream D8
    flow path from the cell to the centre of its farthest head cell.

    - hack_exponent: over every cell draining at least min_area_m2 (the
      all-cells protocol, e.g. Rigon et al. 1996);
    - hack_exponent_mainstem: over the main stems only, each traced up from
      a basin outlet (a map-edge or no-data-edge cell, code -1, draining at
      least min_area_m2) by always taking the donor with the longest
      upstream path, cells draining at least min_area_m2 (Hack's own
      protocol: along the main streams)."""
    rcv = ref.receivers(code)
    k = np.clip(code.ravel(), 0, 7)
    step = np.where(k % 2 == 1, dx * np.sqrt(2.0), dx)
    L = longest_path.length_m(*longest_path.longest_whole(code), dx)  # step counts: the same in tiles
    A = area_m2.ravel()
    # main stems: per receiver, the donor with the longest path through it (ties: the last in flat order)
    idx = np.flatnonzero(rcv >= 0)
    best = np.full(rcv.size, -1, np.int64)
    if idx.size:
        o = np.lexsort((L[idx] + step[idx], rcv[idx]))
        r_s = rcv[idx][o]
        last = np.r_[r_s[1:] != r_s[:-1], True]
        best[r_s[last]] = idx[o][last]
    cells = np.flatnonzero(A >= min_area_m2)
    outlet = code.ravel()[cells] == ref.OUTLET
    return hack_fit(cells, A[cells], L[cells], best[cells], outlet, float(L.max()) if L.size else 0.0, min_area_m2)


def hack_fit(cells: np.ndarray, area_m2: np.ndarray, L: np.ndarray, best: np.ndarray, outlet: np.ndarray,
             longest_m: float, min_area_m2: float) -> dict:
    """hack_exponent's fits from the cells draining at least min_area_m2
    (ascending flat indices, however gathered): their area, longest path,
    best donor (flat index, -1 none) and whether each is an outlet; and the
    world's longest path."""
    sel = L > 0
    out = {"hack_exponent": float("nan"), "hack_coefficient": float("nan"), "hack_cells": int(sel.sum()),
           "hack_exponent_mainstem": float("nan"), "hack_mainstem_cells": 0, "hack_mainstem_basins": 0,
           "longest_flow_path_m": longest_m}
    if sel.sum() >= 10:
        h_, logc = np.polyfit(np.log(area_m2[sel]), np.log(L[sel]), 1)
        out.update(hack_exponent=float(h_), hack_coefficient=float(np.exp(logc)))
    outlets = np.flatnonzero(outlet)
    stem = []
    c = outlets  # positions in cells
    while c.size:
        c = c[sel[c]]
        stem.append(c)
        nxt = best[c]
        pos = np.minimum(np.searchsorted(cells, nxt), max(cells.size - 1, 0))
        c = pos[(nxt >= 0) & (cells[pos] == nxt)]  # a donor draining less than min_area_m2 ends the stem
    stem = np.concatenate(stem) if stem else np.zeros(0, np.int64)
    out.update(hack_mainstem_cells=int(stem.size), hack_mainstem_basins=int(outlets.size))
    if stem.size >= 10:
        h_, _ = np.polyfit(np.log(area_m2[stem]), np.log(L[stem]), 1)
        out["hack_exponent_mainstem"] = float(h_)
    return out


@dataclass
class Rivers:
    mask: np.ndarray  # bool, river cells outside the lakes the USD draws
    width: np.ndarray  # bankfull width (m), 0 off rivers
    depth: np.ndarray  # bankfull mean depth (m), 0 off rivers
    discharge_bf: np.ndarray  # bankfull discharge (m^3/s), 0 off rivers
    order: np.ndarray  # Strahler order, 0 off rivers
    surface: np.ndarray  # water level of network cells (non-increasing downstream), NaN elsewhere
    net: np.ndarray  # bool, every network cell (lakes included)
    drawn_lake: np.ndarray  # bool, cells of the lakes the USD draws (the rest are pools of the rivers)
    stats: dict
    network: Network | None = None  # the network's cells ...
    solved: NetworkRivers | None = None  # ... and the rivers on them


@dataclass(frozen=True)
class Network:
    """The river network's cells (drainage area >= river_threshold_m2), in
    ascending flat order, with what the rivers need of each: no array is
    world-sized, so a tiled run gathers it tile by tile."""
    cells: np.ndarray  # int64 flat index in the world
    rcv: np.ndarray  # int64 receiver as an index into cells; -1: none (an outlet, or off the network)
    code: np.ndarray  # int8 D8 code (its step's length)
    area_m2: np.ndarray  # float64 drainage area
    discharge: np.ndarray  # float64 mean discharge (m^3/s)
    h: np.ndarray  # float64 terrain height
    lake_level: np.ndarray  # float64 level of the lake the cell is in, NaN where dry
    lake_full: np.ndarray  # bool: in a lake at its spill level (within LAKE_FULL_TOLERANCE_M)
    lake_id: np.ndarray  # int32 the lake the cell is in, 0 where dry
    drawn_lake: np.ndarray  # bool: in a lake the USD draws


def network_cells(code: np.ndarray, area_m2: np.ndarray, threshold_m2: float) -> np.ndarray:
    """Flat indices (ascending) of the network's cells in a world or a tile."""
    return np.flatnonzero((area_m2.ravel() >= threshold_m2) & (code.ravel() != ref.NODATA_CODE))


def network_of(cells: np.ndarray, rcv_flat: np.ndarray, code: np.ndarray, area_m2: np.ndarray,
               discharge: np.ndarray, h: np.ndarray, lake_depth: np.ndarray, lake_level: np.ndarray,
               lake_id: np.ndarray, filled: np.ndarray, drawn: np.ndarray) -> Network:
    """A Network from its cells' values, however gathered: `cells` ascending,
    rcv_flat their receivers as flat world indices, the lakes' depth, level
    and id there, the pure fill (float32: the level a full lake reaches) and
    whether each is in a lake the USD draws."""
    in_lake = lake_depth > 0
    level = np.where(in_lake, lake_level, np.nan)
    full = in_lake & (level >= filled - LAKE_FULL_TOLERANCE_M)
    return Network(cells, ref.subset_receivers(cells, rcv_flat), code.astype(np.int8), area_m2.astype(np.float64),
                   discharge.astype(np.float64), h.astype(np.float64), level, full, lake_id.astype(np.int32),
                   drawn.astype(bool))


def gather_network(code: np.ndarray, area_m2: np.ndarray, discharge: np.ndarray, h: np.ndarray, lakes,
                   filled: np.ndarray, drawn: np.ndarray, threshold_m2: float) -> Network:
    """The network of a whole world. `lakes`: the stage's LakeMaps (depth,
    level); `filled`: the pure fill; `drawn`: bool per cell, in a lake the USD draws."""
    cells = network_cells(code, area_m2, threshold_m2)
    at = lambda a: a.ravel()[cells]
    return network_of(cells, ref.receivers(code)[cells], at(code), at(area_m2), at(discharge), at(h),
                      at(lakes.depth), at(lakes.level), at(lakes.lake_id), at(filled), at(drawn))


@dataclass
class NetworkRivers:
    """The rivers on a Network's cells (arrays in its order)."""
    order: np.ndarray  # int32 Strahler order
    width: np.ndarray  # bankfull width (m)
    depth: np.ndarray  # bankfull mean depth (m)
    discharge_bf: np.ndarray  # bankfull discharge (m^3/s)
    surface: np.ndarray  # water level, non-increasing downstream
    mask: np.ndarray  # bool: a river the USD draws (not in a drawn lake)
    stats: dict


def solve_network(nw: Network, dx: float, n_data: int, params) -> NetworkRivers:
    """Strahler order, bankfull discharge, width and depth (channels.py) and
    water level of the network's cells; the stats (sums over the cells in
    flat order: the same whatever gathered them). n_data: the world's cells
    with a height (the drainage density's area)."""
    levels = ref.topological_levels(nw.rcv)
    order = strahler_order(nw.rcv, np.ones(nw.cells.size, bool), levels)
    q_bf = bankfull_discharge(nw.discharge, params.bankfull_discharge_ratio)
    width, depth = hydraulic_geometry(q_bf, params.width_coefficient, params.width_exponent,
                                      params.depth_coefficient, params.depth_exponent)
    surface = water_level(nw.rcv, np.ones(nw.cells.size, bool), levels, nw.h, nw.lake_level, nw.lake_full)
    mask = ~nw.drawn_lake
    k = np.clip(nw.code, 0, 7)
    dist = np.where(k % 2 == 1, dx * np.sqrt(2.0), dx)
    some = nw.cells.size > 0
    stats = {"river_cells": int(mask.sum()), "river_length_m": float(dist[mask].sum()),
             "strahler_max": int(order.max()) if some else 0,
             "river_width_max_m": float(width.max()) if some else 0.0,
             "river_depth_max_m": float(depth.max()) if some else 0.0,
             "bankfull_discharge_max_m3_s": float(q_bf.max()) if some else 0.0,
             "drainage_density_per_km": float(dist[mask].sum() / (n_data * dx * dx) * 1e3)}
    return NetworkRivers(order, width, depth, q_bf, surface, mask, stats)


def extract(code: np.ndarray, area_m2: np.ndarray, discharge: np.ndarray, h: np.ndarray, lakes, filled: np.ndarray,
            dx: float, params) -> Rivers:
    """The network (drainage area >= river_threshold_m2), its Strahler
    order, bankfull discharge, width and depth (channels.py) and water level
    on a whole world: gather_network, solve_network, the results as maps.
    `lakes`: the stage's LakeMaps (depth, level, lake_id); `filled`: the pure
    fill, whose level a full lake reaches."""
    # lakes too small for the USD are pools the river runs through
    drawn = drawn_lakes(lakes.lake_id, dx * dx, params.lake_min_area_m2)
    nw = gather_network(code, area_m2, discharge, h, lakes, filled, drawn, params.river_threshold_m2)
    return rivers_of(nw, code.shape, dx, int(np.isfinite(h).sum()), drawn, params)


def rivers_of(nw: Network, shape: tuple[int, int], dx: float, n_data: int, drawn: np.ndarray, params) -> Rivers:
    """The network solved (solve_network) and its results as maps of the
    world; `drawn`: bool per cell, in a lake the USD draws."""
    rows, cols = shape
    sol = solve_network(nw, dx, n_data, params)

    def grid(values, fill, dtype):
        out = np.full(rows * cols, fill, dtype)
        out[nw.cells] = values
        return out.reshape(rows, cols)
    return Rivers(grid(sol.mask, False, bool), grid(sol.width, 0.0, np.float64), grid(sol.depth, 0.0, np.float64),
                  grid(sol.discharge_bf, 0.0, np.float64), grid(sol.order, 0, np.int32),
                  grid(sol.surface, np.nan, np.float64), grid(True, False, bool), drawn, sol.stats, nw, sol)
