"""River channels at bankfull: discharge from the climate, width and depth by
hydraulic geometry, the water level, the bed carved into the ground and the
river surfaces as ribbons (the stage's step 5).

Discharge: the mean annual discharge is the runoff (rain x runoff
coefficient, m/year) accumulated over the drainage area, Q = R A; the
channel is shaped by the bankfull discharge, about the 1.5-year flood
(Leopold, Wolman and Miller 1964, Fluvial Processes in Geomorphology), taken
as a stated multiple of the mean: Q_bf = k Q.

Hydraulic geometry (Leopold and Maddock 1953): bankfull width w = a Q_bf^b,
mean depth d = c Q_bf^f. The defaults are Hey and Thorne's (1986, J. Hydraul.
Eng. 112(8)) fits for gravel-bed rivers: w = 4.33 Q^0.50 (grassy banks),
d = 0.22 Q^0.37 (their grain-size factor left out).

The water level is the terrain's height along the D8 network made
non-increasing downstream (a running minimum, so no reach climbs); a full
lake hands its level to the river leaving it, a lake that does not spill
hands nothing (the river restarts at the first dry cell). The bed is a
parabolic section (its mean depth d, so 1.5 d at the centre) across the
bankfull width at level - depth, flanked by a floor that rises gently from
the water level, then a bank that blends into the terrain: the ground the
world's mesh and the vegetation use.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


PARABOLA_DEPTH = 1.5  # centre depth / mean depth of a parabolic section
FLOOR_GRADE = 0.05  # the floor beside the channel rises 5 cm per metre: it drains into the channel
# the bed's trough is at least 1.5 cells wide (its depth kept): a narrower channel falls between cell centres
# and the ground grid (and a mesh at its resolution) would not hold it below the water
BED_MIN_HALF_CELLS = 0.75
LAKE_FULL_TOLERANCE_M = 0.01  # a lake within this of its spill level spills: its level feeds the river below


def bankfull_discharge(mean_m3_s: np.ndarray, ratio: float) -> np.ndarray:
    """Q_bf = ratio x Q_mean (m^3/s)."""
    return ratio * np.asarray(mean_m3_s, np.float64)


def hydraulic_geometry(q_bf: np.ndarray, a: float, b: float, c: float, f: float) -> tuple[np.ndarray, np.ndarray]:
    """Bankfull width a Q^b and mean depth c Q^f (m) of discharge Q (m^3/s)."""
    q = np.maximum(np.asarray(q_bf, np.float64), 0.0)
    return a * q ** b, c * q ** f


def drawn_lakes(lake_id: np.ndarray, cell_area: float, min_area_m2: float,
                lake_cells: np.ndarray | None = None) -> np.ndarray:
    """bool per cell of lake_id: in a lake of at least min_area_m2 (the lakes
    the USD draws); the lakes' areas from lake_cells (the lake id of each of
    their cells, when lake_id holds only some cells), else from lake_id."""
    return drawn_lake_ids(lake_id if lake_cells is None else lake_cells, cell_area, min_area_m2)[lake_id]


def drawn_lake_ids(lake_cells: np.ndarray, cell_area: float, min_area_m2: float) -> np.ndarray:
    """bool per lake id (0: dry, never drawn): at least min_area_m2, from the lake id of each of its cells."""
    big = np.bincount(np.asarray(lake_cells).ravel(), minlength=1) * cell_area >= min_area_m2
    big[0] = False
    return big


def water_level(rcv: np.ndarray, net: np.ndarray, levels: list, h: np.ndarray, lake_level: np.ndarray,
                lake_full: np.ndarray) -> np.ndarray:
    """Per network cell (flat arrays): min(its height, the level of every
    donor), sources first (`levels`: topological levels of the network); a
    lake cell's level is its lake's (capped by its donors); a lake cell
    hands its level downstream only when its lake spills. NaN off the network."""
    n = rcv.size
    level = np.full(n, np.nan)
    low = np.full(n, np.inf)
    in_lake = np.isfinite(lake_level)
    own = np.where(in_lake, lake_level, h)
    r_in = np.where(net & (rcv >= 0), rcv, -1)
    r_in = np.where((r_in >= 0) & net[np.maximum(r_in, 0)], r_in, -1)
    for lev in levels:
        level[lev] = np.minimum(own[lev], low[lev])
        t = r_in[lev]
        ok = t >= 0
        hand = np.where(in_lake[lev] & ~lake_full[lev], np.inf, level[lev])
        np.minimum.at(low, t[ok], hand[ok])
    return level


@dataclass
class Reach:
    """One polyline of the river surface, upstream first."""
    cells: np.ndarray  # grid cells (flat indices)
    xz: np.ndarray  # (n, 2) smoothed centreline (m)
    level: np.ndarray  # water level (m), non-increasing
    width: np.ndarray  # bankfull width (m), non-decreasing
    depth: np.ndarray  # bankfull mean depth (m), non-decreasing
    discharge: np.ndarray  # bankfull discharge (m^3/s)
    order: int  # Strahler order at its head


def reaches(rcv: np.ndarray, shown: np.ndarray, in_lake: np.ndarray, shape: tuple[int, int], dx: float,
            origin: tuple[float, float], level, width, depth, q_bf, order, smooth_passes: int = 2,
            cells_of: np.ndarray | None = None) -> list[Reach]:
    """Polylines over the shown cells (closed downstream but for lakes):
    from heads, confluences and lake outlets down to the next confluence, a
    lake cell (kept as the last vertex) or the edge. Centrelines are the
    cell centres smoothed by `smooth_passes` passes of (1, 2, 1) / 4 with the
    ends fixed, so reaches meet at their shared cells. The arrays are per
    cell of the world, or per cell of a subset closed downstream (the river
    network: rcv then indexes the subset, cells_of maps it to flat world indices)."""
    rows, cols = shape
    r_sh = np.where(shown & (rcv >= 0), rcv, -1)
    r_sh = np.where((r_sh >= 0) & shown[np.maximum(r_sh, 0)], r_sh, -1)
    ndon = np.bincount(r_sh[r_sh >= 0], minlength=rcv.size)
    out = []
    for s in np.flatnonzero(shown & (ndon != 1)).tolist():
        seg = [s]
        c = s
        while True:
            t = int(rcv[c])
            if t < 0 or not (shown[t] or in_lake[t]):
                break
            seg.append(t)
            if in_lake[t] or ndon[t] != 1:
                break
            c = t
        if len(seg) < 2:
            continue
        at = np.array(seg, np.int64)
        cells = at if cells_of is None else cells_of[at]
        xz = np.stack([origin[0] + (cells % cols + 0.5) * dx, origin[1] + (cells // cols + 0.5) * dx], 1)
        for _ in range(smooth_passes):
            if len(xz) > 2:
                xz[1:-1] = 0.25 * xz[:-2] + 0.5 * xz[1:-1] + 0.25 * xz[2:]
        lv = np.minimum.accumulate(level[at])
        w = np.maximum.accumulate(width[at])
        d = np.maximum.accumulate(depth[at])
        q = np.maximum.accumulate(q_bf[at])
        if in_lake[at[-1]]:  # the last vertex stands in the lake: the reach upstream's width
            w[-1], d[-1], q[-1] = w[-2], d[-2], q[-2]
        out.append(Reach(cells, xz, lv, w, d, q, int(order[at[0]])))
    return out


@dataclass
class Ribbons:
    points: np.ndarray  # (n, 3) float32 x, y, z
    counts: np.ndarray  # (faces,) int32, 4 each
    indices: np.ndarray  # (4 faces,) int32
    st: np.ndarray  # (n, 2) float32: s across (0 left, 1 right), t along (m / 10)
    discharge: np.ndarray  # (n,) float32 bankfull discharge
    edge_cells: np.ndarray  # (n,) int64 the grid cell of each vertex's reach vertex


def ribbons(rs: list[Reach]) -> Ribbons:
    """Quads between the left and right banks of each reach at its water
    level: left = centre - n w/2, right = centre + n w/2 with n = (-t_z, t_x)
    for the tangent t, so every quad faces +Y (USD rightHanded, y up)."""
    pts, idx, st, q, cells = [], [], [], [], []
    base = 0
    for r in rs:
        p = r.xz
        t = np.empty_like(p)
        t[1:-1] = p[2:] - p[:-2]
        t[0], t[-1] = p[1] - p[0], p[-1] - p[-2]
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        nrm = np.stack([-t[:, 1], t[:, 0]], 1) * (0.5 * r.width)[:, None]
        left, right = p - nrm, p + nrm
        m = len(p)
        pts.append(np.stack([np.stack([left[:, 0], r.level, left[:, 1]], 1),
                             np.stack([right[:, 0], r.level, right[:, 1]], 1)], 1).reshape(-1, 3))
        i = base + 2 * np.arange(m - 1)
        idx.append(np.stack([i, i + 1, i + 3, i + 2], 1).ravel())
        along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))] / 10.0
        st.append(np.stack([np.tile([0.0, 1.0], m), np.repeat(along, 2)], 1))
        q.append(np.repeat(r.discharge, 2))
        cells.append(np.repeat(r.cells, 2))
        base += 2 * m
    if not pts:
        z = np.zeros((0, 3), np.float32)
        return Ribbons(z, np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 2), np.float32),
                       np.zeros(0, np.float32), np.zeros(0, np.int64))
    ind = np.concatenate(idx).astype(np.int32)
    return Ribbons(np.concatenate(pts).astype(np.float32), np.full(len(ind) // 4, 4, np.int32), ind,
                   np.concatenate(st).astype(np.float32), np.concatenate(q).astype(np.float32), np.concatenate(cells))


def segments(rs: list[Reach]) -> dict:
    """Every reach segment's ends: a (k, 2), b (k, 2) and per end level, half width, centre depth."""
    keys = ("a", "b", "la", "lb", "ha", "hb", "da", "db")
    parts = {k_: [] for k_ in keys}
    for r in rs:
        parts["a"].append(r.xz[:-1])
        parts["b"].append(r.xz[1:])
        for k_, v in (("l", r.level), ("h", 0.5 * r.width), ("d", PARABOLA_DEPTH * r.depth)):
            parts[k_ + "a"].append(v[:-1])
            parts[k_ + "b"].append(v[1:])
    return {k_: (np.concatenate(v) if v else np.zeros((0, 2) if k_ in "ab" else 0)) for k_, v in parts.items()}


def carve_reach_cells(seg: dict, dx: float, floor_m: float, bank_m: float) -> int:
    """How many cells from a segment's first end a cell may be and still be
    carved by it: its reach (half width, floor, bank) plus the longest segment."""
    if not len(seg["a"]):
        return 0
    reach = max(float(np.maximum(seg["ha"], seg["hb"]).max()), BED_MIN_HALF_CELLS * dx) + floor_m + bank_m
    seg_len = float(np.linalg.norm(seg["b"] - seg["a"], axis=1).max())
    return int(np.ceil((reach + seg_len) / dx)) + 1


def segments_near(seg: dict, dx: float, origin: tuple[float, float], window: tuple[int, int, int, int],
                  k: int) -> dict:
    """The segments (segments()) whose first end's cell lies within k cells of
    window = (row0, col0, rows, cols): every segment that can carve it."""
    if not len(seg["a"]):
        return seg
    row0, col0, rows, cols = window
    r = np.floor((seg["a"][:, 1] - origin[1]) / dx).astype(np.int64)
    c = np.floor((seg["a"][:, 0] - origin[0]) / dx).astype(np.int64)
    near = (r >= row0 - k) & (r < row0 + rows + k) & (c >= col0 - k) & (c < col0 + cols + k)
    return {key: v[near] for key, v in seg.items()}


def carve(h: np.ndarray, dx: float, origin: tuple[float, float], rs: list[Reach] | dict, floor_m: float,
          bank_m: float, chunk: int = 4096, window: tuple[int, int, int, int] | None = None
          ) -> tuple[np.ndarray, np.ndarray]:
    """The ground with the reaches' beds (float64, NaN kept) and the cells
    under the water (bool: centre within the bankfull half width).

    Per segment and cell at distance r from it, with level L, half width B
    (at least BED_MIN_HALF_CELLS cells) and centre depth D interpolated along
    it: the target is L - D (1 - (r/B)^2) in the channel, L + FLOOR_GRADE
    (r - B) beyond it; the ground is lowered to the target out to B + floor_m
    and by a share of the same cut that falls smoothly to 0 at B + floor_m +
    bank_m (the bank). Each cell takes
    the cut of its nearest segment; the ground is never above the terrain.

    rs: the reaches, or their segments(); window = (row0, col0, world rows,
    world cols) when h is the part of a world from (row0, col0) on: its
    cells come out as the whole world's would (given every segment near it)."""
    row0, col0, rows, cols = window if window is not None else (0, 0, *h.shape)
    t_rows, t_cols = h.shape
    g = h.astype(np.float64).copy()
    wet = np.zeros(h.shape, bool)
    s = rs if isinstance(rs, dict) else segments(rs)
    if not len(s["a"]):
        return g, wet
    k = carve_reach_cells(s, dx, floor_m, bank_m)
    off_r, off_c = np.mgrid[-k:k + 1, -k:k + 1]
    off_r, off_c = off_r.ravel(), off_c.ravel()
    hf = h.astype(np.float64).ravel()
    gf, wf = g.ravel(), wet.ravel()
    found = []
    for i0 in range(0, len(s["a"]), chunk):
        sl = slice(i0, i0 + chunk)
        a, b = s["a"][sl], s["b"][sl]
        r0 = np.floor((a[:, 1] - origin[1]) / dx).astype(np.int64)
        c0 = np.floor((a[:, 0] - origin[0]) / dx).astype(np.int64)
        rr, cc = r0[:, None] + off_r, c0[:, None] + off_c
        inside = (rr >= max(row0, 0)) & (rr < min(row0 + t_rows, rows)) & (cc >= max(col0, 0)) & \
            (cc < min(col0 + t_cols, cols))
        cell = np.where(inside, (rr - row0) * t_cols + (cc - col0), 0)
        px, pz = origin[0] + (cc + 0.5) * dx, origin[1] + (rr + 0.5) * dx
        ab = b - a
        L2 = np.maximum((ab ** 2).sum(1), 1e-12)[:, None]
        t = np.clip(((px - a[:, :1]) * ab[:, :1] + (pz - a[:, 1:]) * ab[:, 1:]) / L2, 0.0, 1.0)
        r = np.hypot(px - (a[:, :1] + t * ab[:, :1]), pz - (a[:, 1:] + t * ab[:, 1:]))

        def along(key):
            return s[key + "a"][sl, None] + t * (s[key + "b"][sl, None] - s[key + "a"][sl, None])
        lv, half, dep = along("l"), np.maximum(along("h"), 1e-6), along("d")
        trough = np.maximum(half, BED_MIN_HALF_CELLS * dx)
        target = np.where(r <= trough, lv - dep * (1.0 - (r / trough) ** 2), lv + FLOOR_GRADE * (r - trough))
        u = np.clip((r - trough - floor_m) / max(bank_m, 1e-9), 0.0, 1.0)
        share = 1.0 - u * u * (3.0 - 2.0 * u)
        hc = hf[cell]
        cand = hc - np.maximum(hc - target, 0.0) * share
        ok = inside & np.isfinite(hc) & (share > 0)
        found.append((cell[ok], r[ok], cand[ok]))
        wf[cell[inside & (r <= half)]] = True
    # each cell takes the cut of its nearest segment (ties: the lower), so a steep reach's lower segments
    # do not undercut the banks beside its higher ones
    cell, r, cand = (np.concatenate(v) for v in zip(*found))
    if not cell.size:
        return g, wf.reshape(t_rows, t_cols)
    order = np.lexsort((cand, r, cell))
    first = np.r_[True, cell[order][1:] != cell[order][:-1]]
    pick = order[first]
    gf[cell[pick]] = np.minimum(hf[cell[pick]], cand[pick])
    return gf.reshape(t_rows, t_cols), wf.reshape(t_rows, t_cols)


def point_taps(shape: tuple[int, int], dx: float, origin: tuple[float, float], x: np.ndarray, z: np.ndarray):
    """bilinear_at's cells and weights for points (x, z) on a grid of `shape`:
    (r0, r1, c0, c1, u, v)."""
    rows, cols = shape
    fc = np.clip((np.asarray(x) - origin[0]) / dx - 0.5, 0.0, cols - 1.0)
    fr = np.clip((np.asarray(z) - origin[1]) / dx - 0.5, 0.0, rows - 1.0)
    c0 = np.minimum(np.floor(fc).astype(np.int64), max(cols - 2, 0))
    r0 = np.minimum(np.floor(fr).astype(np.int64), max(rows - 2, 0))
    c1, r1 = np.minimum(c0 + 1, cols - 1), np.minimum(r0 + 1, rows - 1)
    return r0, r1, c0, c1, fc - c0, fr - r0


def bilinear_points(values: np.ndarray, taps: tuple, origin_rc: tuple[int, int] = (0, 0)) -> np.ndarray:
    """bilinear_at from its taps (point_taps) on values that hold the grid's
    cells from (row, col) = origin_rc on: a window gives the whole grid's numbers."""
    r0, r1, c0, c1, u, v = taps
    r0, r1, c0, c1 = r0 - origin_rc[0], r1 - origin_rc[0], c0 - origin_rc[1], c1 - origin_rc[1]
    top = values[r0, c0] * (1 - u) + values[r0, c1] * u
    bot = values[r1, c0] * (1 - u) + values[r1, c1] * u
    return top * (1 - v) + bot * v


def bilinear_at(grid: np.ndarray, dx: float, origin: tuple[float, float], x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The grid (values at cell centres) bilinearly interpolated at points (x, z)."""
    return bilinear_points(grid, point_taps(grid.shape, dx, origin, x, z))


def width_table(area_m2: np.ndarray, width: np.ndarray, net: np.ndarray,
                bins_km2=(0.0, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)) -> list[dict]:
    """Bankfull width against drainage area over the network's cells: per
    area class the cells and the least, median and largest width (m)."""
    a = area_m2.ravel()[net.ravel()] / 1e6
    w = width.ravel()[net.ravel()]
    rows = []
    edges = list(bins_km2) + [np.inf]
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (a >= lo) & (a < hi)
        if not sel.any():
            continue
        rows.append({"area_km2_from": lo, "area_km2_to": None if hi == np.inf else hi, "cells": int(sel.sum()),
                     "width_min_m": float(w[sel].min()), "width_median_m": float(np.median(w[sel])),
                     "width_max_m": float(w[sel].max())})
    return rows
