"""Rivers: extraction by drainage area, Strahler order, widths from
discharge (seed 003: cross-section = Q / v, v from slope), polylines whose
water surface never rises downstream, and Hack's law."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worldlib.flow import reference as ref
from worldlib.terrain.stats import topological_levels


def topo_levels(rcv: np.ndarray, cells: np.ndarray | None = None) -> list[np.ndarray]:
    """Topological levels of a receiver forest, sources first (every cell
    after all of its donors); `cells` restricts to a subset closed downstream
    within itself. worldlib.terrain.stats.topological_levels on a mask."""
    if cells is None:
        return topological_levels(rcv)
    member = np.zeros(rcv.size, bool)
    member[cells] = True
    return topological_levels(rcv, member)


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
    L = np.zeros(rcv.size)
    for lev in topo_levels(rcv):
        t = rcv[lev]
        ok = t >= 0
        np.maximum.at(L, t[ok], L[lev[ok]] + step[lev[ok]])
    A = area_m2.ravel()
    sel = (A >= min_area_m2) & (L > 0)
    out = {"hack_exponent": float("nan"), "hack_coefficient": float("nan"), "hack_cells": int(sel.sum()),
           "hack_exponent_mainstem": float("nan"), "hack_mainstem_cells": 0, "hack_mainstem_basins": 0,
           "longest_flow_path_m": float(L.max()) if L.size else 0.0}
    if sel.sum() >= 10:
        h_, logc = np.polyfit(np.log(A[sel]), np.log(L[sel]), 1)
        out.update(hack_exponent=float(h_), hack_coefficient=float(np.exp(logc)))
    # main stems: per receiver, the donor with the longest path through it
    idx = np.flatnonzero(rcv >= 0)
    best = np.full(rcv.size, -1, np.int64)
    if idx.size:
        o = np.lexsort((L[idx] + step[idx], rcv[idx]))
        r_s = rcv[idx][o]
        last = np.r_[r_s[1:] != r_s[:-1], True]
        best[r_s[last]] = idx[o][last]
    outlets = np.flatnonzero((code.ravel() == ref.OUTLET) & (A >= min_area_m2))
    stem = []
    c = outlets
    while c.size:
        c = c[(A[c] >= min_area_m2) & (L[c] > 0)]
        stem.append(c)
        c = best[c]
        c = c[c >= 0]
    stem = np.concatenate(stem) if stem else np.zeros(0, np.int64)
    out.update(hack_mainstem_cells=int(stem.size), hack_mainstem_basins=int(outlets.size))
    if stem.size >= 10:
        h_, _ = np.polyfit(np.log(A[stem]), np.log(L[stem]), 1)
        out["hack_exponent_mainstem"] = float(h_)
    return out


@dataclass
class Rivers:
    mask: np.ndarray  # bool, river cells outside lakes
    width: np.ndarray  # m, 0 off rivers
    order: np.ndarray  # Strahler order, 0 off rivers
    surface: np.ndarray  # water surface height of river cells (non-increasing downstream), NaN elsewhere
    curves: list  # list of (cell index array) per polyline, upstream first
    stats: dict


def extract(code: np.ndarray, area_m2: np.ndarray, discharge: np.ndarray, h: np.ndarray, lake_depth: np.ndarray,
            ground: np.ndarray, dx: float, threshold_m2: float, k_v: float, v_min: float, v_max: float,
            min_slope: float, width_depth_ratio: float, lift_m: float) -> Rivers:
    """`ground` is the height the curves sit on (the world's mesh at cell
    centres); the surface is the running minimum of ground + lift_m."""
    rows, cols = code.shape
    n = rows * cols
    rcv = ref.receivers(code)
    net = (area_m2.ravel() >= threshold_m2) & (code.ravel() != ref.NODATA_CODE)
    cells = np.flatnonzero(net)
    order = np.zeros(n, np.int32)
    surface = np.full(n, np.nan)
    g = ground.ravel() + lift_m
    r_in = np.where(net & (rcv >= 0), rcv, -1)
    r_in = np.where((r_in >= 0) & net[np.maximum(r_in, 0)], r_in, -1)
    levels = topo_levels(rcv, cells)
    maxo = np.zeros(n, np.int32)
    nmax = np.zeros(n, np.int32)
    low = np.full(n, np.inf)
    for lev in levels:
        o = np.where(maxo[lev] == 0, 1, np.where(nmax[lev] >= 2, maxo[lev] + 1, maxo[lev]))
        order[lev] = o
        surface[lev] = np.minimum(g[lev], low[lev])
        t = r_in[lev]
        ok = t >= 0
        src, tt = lev[ok], t[ok]
        if tt.size:
            # per receiver: the largest donor order and how many donors have it
            ob = order[src]
            srt = np.lexsort((-ob, tt))
            tt_s, ob_s = tt[srt], ob[srt]
            first = np.r_[True, tt_s[1:] != tt_s[:-1]]
            tmax = ob_s[first]
            grp = np.cumsum(first) - 1
            ut = tt_s[first]
            cnt = np.bincount(grp[ob_s == tmax[grp]], minlength=ut.size)
            newmax = tmax > maxo[ut]
            eq = tmax == maxo[ut]
            nmax[ut] = np.where(newmax, cnt, np.where(eq, nmax[ut] + cnt, nmax[ut]))
            maxo[ut] = np.maximum(maxo[ut], tmax)
            np.minimum.at(low, tt, surface[src])
    # widths: Q / v, v = k_v sqrt(S) clamped, rectangular section of width = ratio * depth
    k = np.clip(code.ravel(), 0, 7)
    dist = np.where(k % 2 == 1, dx * np.sqrt(2.0), dx)
    hf = h.ravel().astype(np.float64)
    slope = np.where(rcv >= 0, (hf - hf[np.maximum(rcv, 0)]) / dist, 0.0)
    slope = np.maximum(np.nan_to_num(slope, nan=0.0), min_slope)
    v = np.clip(k_v * np.sqrt(slope), v_min, v_max)
    section = discharge.ravel() / v
    width = np.where(net, np.sqrt(width_depth_ratio * np.maximum(section, 0.0)), 0.0)
    in_lake = lake_depth.ravel() > 0
    mask = net & ~in_lake
    # polylines: from heads and confluences down to the next confluence, lake or outlet
    ndon = np.bincount(r_in[r_in >= 0], minlength=n)
    starts = np.flatnonzero(mask & (ndon != 1))
    curves = []
    for s in starts.tolist():
        seg = [s]
        c = s
        while True:
            t = int(rcv[c])
            if t < 0 or not net[t]:
                break
            seg.append(t)
            if in_lake[t] or ndon[t] != 1:
                break
            c = t
        if len(seg) >= 2:
            curves.append(np.array(seg, np.int64))
    stats = {"river_cells": int(mask.sum()), "river_length_m": float(dist[mask].sum()),
             "strahler_max": int(order.max()) if cells.size else 0, "river_curves": len(curves),
             "river_width_max_m": float(width.max()) if cells.size else 0.0,
             "drainage_density_per_km": float(dist[mask].sum() / (np.isfinite(hf).sum() * dx * dx) * 1e3)}
    return Rivers(mask.reshape(rows, cols), width.reshape(rows, cols), np.where(net, order, 0).reshape(rows, cols),
                  surface.reshape(rows, cols), curves, stats)


def extract_on(ground: np.ndarray, code: np.ndarray, area_m2: np.ndarray, discharge: np.ndarray, h: np.ndarray,
               lake_depth: np.ndarray, dx: float, params) -> Rivers:
    """extract() with the stage's river parameters."""
    return extract(code, area_m2, discharge, h, lake_depth, ground, dx, params.river_threshold_m2,
                   params.river_velocity_coefficient_m_s, params.river_velocity_min_m_s,
                   params.river_velocity_max_m_s, params.river_min_slope, params.river_width_depth_ratio,
                   params.river_lift_m)


def rivers_on_mesh(land, code: np.ndarray, area_m2: np.ndarray, discharge: np.ndarray, lake_depth: np.ndarray,
                   params):
    """The stage's step 5: the terrain mesh the curves sit on (None for a
    grid thinner than 2 cells) and the rivers, whose surfaces follow the mesh
    at the cells the curves pass."""
    from pipeline.grid import Grid
    from worldlib.terrain.mesh import build_terrain_mesh, height_on_mesh

    h, dx, hmin = land.h, land.dx, land.hmin
    rows, cols = land.shape
    mesh = None
    if rows >= 2 and cols >= 2:
        mesh = build_terrain_mesh(Grid(np.nan_to_num(h, nan=hmin), dx, ("height",), land.origin_m), params.mesh_max_vertices)
    ground = np.nan_to_num(h, nan=hmin).astype(np.float64)
    riv = extract_on(ground, code, area_m2, discharge, h, lake_depth, dx, params)
    if mesh is not None and riv.curves:
        used = np.unique(np.concatenate(riv.curves))
        ox, oz = land.origin_m
        gm = ground.ravel().copy()
        gm[used] = height_on_mesh(mesh, ox + (used % cols + 0.5) * dx, oz + (used // cols + 0.5) * dx)
        riv = extract_on(gm.reshape(rows, cols), code, area_m2, discharge, h, lake_depth, dx, params)
    return mesh, riv


def follow_mesh(surface, x: np.ndarray, y: np.ndarray, z: np.ndarray, width: np.ndarray, discharge: np.ndarray,
                max_rise_m: float, samples_per_segment: int = 16, rounds: int = 4):
    """Insert vertices where a straight segment would pass over higher ground.

    surface(x, z) gives the height a curve vertex sits at (the terrain mesh
    plus the river's lift). Along each segment the surface is sampled at
    samples_per_segment points; where it rises more than max_rise_m above
    the higher of the segment's two ends, a vertex is inserted at the highest
    sample (on the surface; width and discharge interpolated), and the new
    segments are checked again, up to `rounds` times. Returns the new
    (x, y, z, width, discharge)."""
    f = np.linspace(0.0, 1.0, samples_per_segment + 2)[1:-1]
    for _ in range(rounds):
        if x.size < 2:
            break
        sx = x[:-1, None] + (x[1:, None] - x[:-1, None]) * f
        sz = z[:-1, None] + (z[1:, None] - z[:-1, None]) * f
        ground = surface(sx.ravel(), sz.ravel()).reshape(sx.shape)
        top = np.argmax(ground, axis=1)
        rise = ground[np.arange(ground.shape[0]), top] - np.maximum(y[:-1], y[1:])
        bad = np.flatnonzero(rise > max_rise_m)
        if not bad.size:
            break
        t = f[top[bad]]
        new = {"x": sx[bad, top[bad]], "z": sz[bad, top[bad]], "y": ground[bad, top[bad]],
               "w": width[bad] + (width[bad + 1] - width[bad]) * t,
               "q": discharge[bad] + (discharge[bad + 1] - discharge[bad]) * t}
        at = bad + 1
        x, y, z = np.insert(x, at, new["x"]), np.insert(y, at, new["y"]), np.insert(z, at, new["z"])
        width, discharge = np.insert(width, at, new["w"]), np.insert(discharge, at, new["q"])
    return x, y, z, width, discharge
