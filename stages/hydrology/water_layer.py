"""What the USD water layer draws: river ribbons on their carved beds and lake outlines."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import channels
from . import rivers as rivers_mod
from .routing import Land

BED_TOLERANCE_M = 0.5  # a ribbon's banks lie within this of the carved ground


@dataclass
class RiverWater:
    reaches: list  # channels.Reach
    ribbons: channels.Ribbons
    ground: np.ndarray  # the terrain with the beds carved (float64, NaN kept)
    wet: np.ndarray  # bool: cells whose centre is under a ribbon
    stats: dict


def river_water(land: Land, code: np.ndarray, riv: rivers_mod.Rivers, lake_id: np.ndarray, lake_level: np.ndarray,
                params, grounds=None) -> RiverWater:
    """Reaches of the rivers at least river_mesh_min_width_m wide, their
    ribbons, the carved ground and how well the ribbons sit on it.
    grounds(segments, pool ids) -> (ground, wet, ground_stats): the carving
    done elsewhere (a tiled run's, tile by tile); default: here, on the whole world."""
    rs, pool_ids = river_reaches(riv.network, riv.solved, land.shape, land.dx, tuple(land.origin_m), params)
    seg = channels.segments(rs)
    if grounds is None:
        ground, wet, pools = carved_ground(land.h, lake_id, lake_level, seg, pool_ids, land.dx, tuple(land.origin_m),
                                           params)
        gstats = ground_stats(land.h, ground, wet, pools)
    else:
        ground, wet, gstats = grounds(seg, pool_ids)
    rib = channels.ribbons(rs)
    stats = {**reach_stats(rs, rib, params), **gstats,
             **bed_fit(rib, np.where(riv.drawn_lake, lake_level, ground), land, riv.drawn_lake.ravel(),
                       params.mesh_max_vertices)}
    return RiverWater(rs, rib, ground, wet, stats)


def river_reaches(nw: rivers_mod.Network, sol: rivers_mod.NetworkRivers, shape: tuple[int, int], dx: float,
                  origin: tuple[float, float], params) -> tuple[list, np.ndarray]:
    """The reaches of the rivers the USD draws (on the network's cells), and
    the ids of the pools (lakes it leaves out) they pass."""
    shown = sol.mask & (sol.width >= params.river_mesh_min_width_m)
    rs = channels.reaches(nw.rcv, shown, nw.drawn_lake, shape, dx, origin, sol.surface,
                          sol.width, sol.depth, sol.discharge_bf, sol.order, cells_of=nw.cells)
    ids = np.unique(nw.lake_id[shown])
    return rs, ids[ids > 0]


def carved_ground(h: np.ndarray, lake_id: np.ndarray, lake_level: np.ndarray, seg: dict, pool_ids: np.ndarray,
                  dx: float, origin: tuple[float, float], params, window=None):
    """The ground (float64) with the beds carved into it, the cells under a
    river (bool) and the pools' cells (bool): pools are filled up to their
    level (sediment) so the river runs over them. window: as channels.carve's,
    when the arrays are the part of a world from (row0, col0) on."""
    pools = np.isin(lake_id, pool_ids)
    base = np.where(pools, np.fmax(h, lake_level), h)
    ground, wet = channels.carve(base, dx, origin, seg, params.river_floor_m, params.river_bank_m, window=window)
    return ground, wet, pools


def reach_stats(rs: list, rib: channels.Ribbons, params) -> dict:
    return {"river_reaches": len(rs), "river_mesh_vertices": int(len(rib.points)),
            "river_mesh_quads": int(len(rib.counts)),
            "river_mesh_min_width_m": params.river_mesh_min_width_m,
            "river_segments_climbing": int(sum((np.diff(r.level) > 0).sum() for r in rs))}


def ground_stats(h: np.ndarray, ground: np.ndarray, wet: np.ndarray, pools: np.ndarray) -> dict:
    """How deep and where the beds cut (of a world, or of a tile: tiles_ground_stats adds them up)."""
    cut = h - ground
    return {"river_carve_max_m": float(np.nanmax(cut)) if np.isfinite(h).any() else 0.0,
            "river_carved_cells": int((np.nan_to_num(cut) > 1e-6).sum()),
            "river_wet_cells": int(wet.sum()), "river_pool_cells_filled": int(pools.sum())}


def tiles_ground_stats(parts: list[tuple[bool, dict]]) -> dict:
    """ground_stats of a world from its tiles' (whether the tile has a height, its ground_stats)."""
    data = [s for has, s in parts if has]
    return {"river_carve_max_m": max((s["river_carve_max_m"] for s in data), default=0.0),
            **{k: sum(s[k] for _, s in parts) for k in ("river_carved_cells", "river_wet_cells",
                                                         "river_pool_cells_filled")}}


@dataclass(frozen=True)
class BedFitQuery:
    """Where bed_fit samples the carved ground: the ribbons' bank vertices
    off the lakes (point_taps), and the lattice of the world's terrain mesh."""
    points: np.ndarray  # (n, 3) float64 the ribbons' vertices
    keep: np.ndarray  # bool per vertex: off the lakes the USD draws
    bank_taps: tuple  # channels.point_taps of the kept vertices
    lattice: tuple | None  # (ri, ci, row taps, col taps) of the mesh's lattice (mesh.lattice_of), None: no mesh
    dx: float
    origin: tuple[float, float]
    shape: tuple[int, int]

    @staticmethod
    def of(rib: channels.Ribbons, keep: np.ndarray, shape: tuple[int, int], dx: float, origin: tuple[float, float],
           mesh_max_vertices: int) -> "BedFitQuery":
        from worldlib.terrain.mesh import lattice_of, lattice_taps

        p = rib.points.astype(np.float64)
        taps = channels.point_taps(shape, dx, origin, p[keep, 0], p[keep, 2])
        lattice = None
        if shape[0] >= 2 and shape[1] >= 2:
            ri, ci = lattice_of(*shape, mesh_max_vertices)
            lattice = (ri, ci, lattice_taps(shape[0], ri), lattice_taps(shape[1], ci))
        return BedFitQuery(p, keep, taps, lattice, dx, origin, shape)


NO_FIT = {"river_bank_vertices": 0, "river_banks_on_bed_share": 1.0, "river_bank_above_ground_max_m": 0.0,
          "river_bank_below_ground_max_m": 0.0, "river_visible_over_mesh_share": 1.0}


def bed_fit(rib: channels.Ribbons, ground: np.ndarray, land: Land, in_lake: np.ndarray, mesh_max_vertices: int) -> dict:
    """How the ribbons sit on the carved ground: at every bank vertex off
    the lakes, its height above the ground (bilinear between cell centres):
    the share within BED_TOLERANCE_M and the extremes; and the share of bank
    vertices and centreline points not below the world's terrain mesh of
    the carved ground (mesh_max_vertices per side: what a renderer shows)."""
    if not len(rib.points):
        return dict(NO_FIT)
    from worldlib.terrain.mesh import bilinear_taps

    q = BedFitQuery.of(rib, ~in_lake[rib.edge_cells], land.shape, land.dx, tuple(land.origin_m), mesh_max_vertices)
    g0 = np.nan_to_num(ground, nan=land.hmin)
    hv = None if q.lattice is None else bilinear_taps(g0.astype(np.float32), q.lattice[2], q.lattice[3])
    return bed_fit_stats(q, channels.bilinear_points(g0, q.bank_taps), hv)


def bed_fit_stats(q: BedFitQuery, bank_ground: np.ndarray, lattice_heights: np.ndarray | None) -> dict:
    """bed_fit's numbers from the ground under the kept bank vertices and the mesh's lattice heights."""
    from worldlib.terrain.mesh import height_on_mesh, mesh_from_lattice

    out = dict(NO_FIT)
    p, keep = q.points, q.keep
    dy = p[keep, 1] - bank_ground
    out.update(river_bank_vertices=int(keep.sum()))
    if dy.size:
        out.update(river_banks_on_bed_share=float((np.abs(dy) <= BED_TOLERANCE_M).mean()),
                   river_bank_above_ground_max_m=float(max(dy.max(), 0.0)),
                   river_bank_below_ground_max_m=float(max(-dy.min(), 0.0)))
    if lattice_heights is not None:
        rows, cols = q.shape
        mesh = mesh_from_lattice(lattice_heights, q.lattice[0], q.lattice[1], q.dx, q.origin,
                                 (cols * q.dx, rows * q.dx))
        mid = 0.5 * (p[0::2] + p[1::2])
        pts = np.concatenate([p[keep], mid[keep[0::2]]])
        vis = pts[:, 1] >= height_on_mesh(mesh, pts[:, 0], pts[:, 2]) - 0.05
        out["river_visible_over_mesh_share"] = float(vis.mean()) if vis.size else 1.0
    return out


def lake_outlines(land: Land, lake_id: np.ndarray, lake_level: np.ndarray, min_area_m2: float) -> list:
    """(lake id, level, (rows, cols) of its cells grown by one cell onto
    data cells) of every lake of at least min_area_m2."""
    from scipy import ndimage

    rows, cols = land.shape
    lake_list = []
    for lid, sl in enumerate(ndimage.find_objects(lake_id), start=1):
        if sl is None:
            continue
        r0, r1 = max(sl[0].start - 1, 0), min(sl[0].stop + 1, rows)
        c0, c1 = max(sl[1].start - 1, 0), min(sl[1].stop + 1, cols)
        m = lake_id[r0:r1, c0:c1] == lid
        if m.sum() * land.cell_area < min_area_m2:
            continue
        grown = ndimage.binary_dilation(m, structure=np.ones((3, 3), bool)) & land.data[r0:r1, c0:c1]
        rr, cc = np.nonzero(grown)
        lake_list.append((lid, float(np.nanmax(lake_level[r0:r1, c0:c1][m])), (rr + r0, cc + c0)))
    return lake_list
