"""Plain numpy / pure-Python implementations of kernels.cl and of the
serial algorithms, small and obviously right, for tests on small grids.

- priority_flood: Barnes 2014 Priority-Flood with one binary heap (heapq);
  with eps=True it is Priority-Flood+epsilon (a single queue, no pit FIFO),
  whose result is the least fixed point that the kernel's relaxation reaches.
- fill_local, fill_levels, fill_combine: the plain fill's three kernels.
- d8: the steepest-descent kernel, same float32 operations.
- accumulate: D8 accumulation by Kahn's topological order (integers).
- accumulate_sweeps: seed 003's Algorithm 1 (fixed-point sweeps), the oracle.
- wetness: the wetness/moisture kernel in float32.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

DR = np.array([-1, -1, 0, 1, 1, 1, 0, -1])
DC = np.array([0, 1, 1, 1, 0, -1, -1, -1])
F32 = np.float32
STEP_SMALL = F32(2.0 ** -23)

INTERIOR, EDGE, NODATA = 0, 1, 2
OUTLET, NODATA_CODE, PIT = -1, -2, -3


def canonical(h: np.ndarray) -> np.ndarray:
    """float32 heights with -0 made +0 and denormals flushed to 0, so that
    every device compares them alike; NaN and +-inf stay (no-data)."""
    h = np.asarray(h, dtype=np.float32).copy()
    with np.errstate(invalid="ignore"):
        h[np.abs(h) < np.finfo(np.float32).tiny] = 0.0
    return h


def cell_kinds(h: np.ndarray) -> np.ndarray:
    """0 interior, 1 edge (map border or 8-adjacent to no-data), 2 no-data."""
    nodata = ~np.isfinite(h)
    rows, cols = h.shape
    near = np.zeros((rows + 2, cols + 2), bool)
    near[0, :] = near[-1, :] = near[:, 0] = near[:, -1] = True
    near[1:-1, 1:-1] = nodata
    adj = np.zeros((rows, cols), bool)
    for dr, dc in zip(DR, DC):
        adj |= near[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols]
    kind = np.where(adj, EDGE, INTERIOR).astype(np.uint8)
    kind[nodata] = NODATA
    return kind


def step_up(x):
    """The kernel's epsilon step: next float up where |x| >= 1, else x + 2^-23."""
    x = np.asarray(x, dtype=np.float32)
    big = np.nextafter(x, F32(np.inf), dtype=np.float32)
    small = (x + STEP_SMALL).astype(np.float32)
    return np.where(np.isinf(x), x, np.where(np.abs(x) >= 1.0, big, small)).astype(np.float32)


def priority_flood(h: np.ndarray, eps: bool = False, kind: np.ndarray | None = None) -> np.ndarray:
    """Fill depressions: the lowest height at which each cell can drain to an
    edge cell (eps: strictly increasing by step_up along the way). No-data
    cells come back as NaN."""
    h = canonical(h)
    kind = cell_kinds(h) if kind is None else kind
    rows, cols = h.shape
    W = np.where(kind == EDGE, h, np.float32(np.inf)).astype(np.float32)
    done = kind != INTERIOR
    heap = [(float(h[r, c]), r, c) for r, c in zip(*np.nonzero(kind == EDGE))]
    heapq.heapify(heap)
    while heap:
        v, r, c = heapq.heappop(heap)
        nv = float(step_up(np.float32(v))) if eps else v
        for dr, dc in zip(DR, DC):
            rr, cc = r + dr, c + dc
            if 0 <= rr < rows and 0 <= cc < cols and not done[rr, cc]:
                done[rr, cc] = True
                W[rr, cc] = max(h[rr, cc], np.float32(nv))
                heapq.heappush(heap, (float(W[rr, cc]), rr, cc))
    W[kind == NODATA] = np.nan
    return W


def fill_local(h: np.ndarray, kind: np.ndarray, tile: int) -> np.ndarray:
    """kernels.cl fill_local's heights: each tile filled alone, its perimeter
    cells and the map's edge cells as seeds at their own heights."""
    W = np.empty(h.shape, np.float32)
    for r0 in range(0, h.shape[0], tile):
        for c0 in range(0, h.shape[1], tile):
            sub = (slice(r0, r0 + tile), slice(c0, c0 + tile))
            k = kind[sub].copy()
            k[[0, -1], :] = np.where(k[[0, -1], :] == NODATA, NODATA, EDGE)
            k[:, [0, -1]] = np.where(k[:, [0, -1]] == NODATA, NODATA, EDGE)
            W[sub] = priority_flood(h[sub], kind=k)
    return W


def fill_levels(kind: np.ndarray, wloc: np.ndarray, label: np.ndarray) -> dict:
    """kernels.cl fill_levels: every pair of 8-adjacent data cells of
    different labels (label -1: the ocean, the map's edge cells) is an edge
    of weight max(wloc, wloc); each label's level is its lowest spill to the
    ocean (a priority flood over the labels). Returns {label: level}."""
    rows, cols = kind.shape
    data = kind != NODATA
    adj: dict = {}
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        r, c = np.nonzero(data)
        rr, cc = r + dr, c + dc
        ok = (rr < rows) & (cc >= 0) & (cc < cols)
        r, c, rr, cc = r[ok], c[ok], rr[ok], cc[ok]
        ok = data[rr, cc] & (label[r, c] != label[rr, cc])
        for a, b, w in zip(label[r, c][ok], label[rr, cc][ok], np.maximum(wloc[r, c], wloc[rr, cc])[ok]):
            for x, y in ((int(a), int(b)), (int(b), int(a))):
                adj.setdefault(x, {})
                adj[x][y] = min(adj[x].get(y, np.inf), float(w))
    level = {-1: -np.inf}
    heap = [(-np.inf, -1)]
    while heap:
        v, x = heapq.heappop(heap)
        if v > level[x]:
            continue
        for y, w in adj.get(x, {}).items():
            cand = max(v, w)
            if cand < level.get(y, np.inf):
                level[y] = cand
                heapq.heappush(heap, (cand, y))
    return level


def fill_combine(h: np.ndarray, kind: np.ndarray, wloc: np.ndarray, label: np.ndarray, level: dict) -> np.ndarray:
    """kernels.cl fill_combine: max(wloc, the level of the cell's label) on
    interior cells, h on edge cells, NaN on no-data."""
    lv = np.vectorize(lambda x: level.get(int(x), np.inf), otypes=[np.float64])(label).astype(np.float32)
    F = np.where(kind == EDGE, h, np.maximum(wloc, lv)).astype(np.float32)
    F[kind == NODATA] = np.nan
    return F


def d8(z: np.ndarray, kind: np.ndarray, dx: float) -> np.ndarray:
    """D8 codes (pysheds order N, NE, E, SE, S, SW, W, NW = 0..7; -1 outlet,
    -2 no-data, -3 no strictly lower neighbour)."""
    rows, cols = z.shape
    dcard, ddiag = F32(dx), F32(dx * np.sqrt(2.0))
    zp = np.pad(z.astype(np.float32), 1, constant_values=np.inf)
    best = np.zeros((rows, cols), np.float32)
    code = np.full((rows, cols), PIT, np.int8)
    for k in range(8):
        zn = zp[1 + DR[k]:1 + DR[k] + rows, 1 + DC[k]:1 + DC[k] + cols]
        with np.errstate(invalid="ignore"):
            s = ((z - zn) / (ddiag if k & 1 else dcard)).astype(np.float32)
            better = s > best
        best = np.where(better, s, best)
        code = np.where(better, np.int8(k), code)
    code[kind == EDGE] = OUTLET
    code[kind == NODATA] = NODATA_CODE
    return code


def receivers(code: np.ndarray) -> np.ndarray:
    """Flat index of each cell's receiver, -1 where it has none."""
    rows, cols = code.shape
    idx = np.arange(rows * cols).reshape(rows, cols)
    k = np.clip(code, 0, 7).astype(np.int64)
    r = idx + DR[k] * cols + DC[k]
    return np.where(code >= 0, r, -1).ravel()


def subset_receivers(cells: np.ndarray, rcv_flat: np.ndarray) -> np.ndarray:
    """Receivers given as flat world indices (-1 none) as indices into the
    ascending `cells`; -1 where the receiver is not one of them."""
    pos = np.searchsorted(cells, rcv_flat)
    pos_ok = np.minimum(pos, max(cells.size - 1, 0))
    hit = (rcv_flat >= 0) & (pos < cells.size) & (cells[pos_ok] == rcv_flat) if cells.size else rcv_flat < -1
    return np.where(hit, pos_ok, -1).astype(np.int64)


def topological_levels(rcv: np.ndarray, member: np.ndarray | None = None) -> list[np.ndarray]:
    """Successive frontiers from the sources down: every cell after all its
    donors (Kahn's algorithm, vectorised). `member` restricts to a subset;
    receivers outside it count as none."""
    n = rcv.size
    member = np.ones(n, bool) if member is None else np.asarray(member, bool).ravel()
    r = np.where(member & (rcv >= 0), rcv, -1)
    r = np.where((r >= 0) & member[np.maximum(r, 0)], r, -1)
    deg = np.bincount(r[r >= 0], minlength=n)
    front = np.flatnonzero(member & (deg == 0))
    levels = []
    while front.size:
        levels.append(front)
        t = r[front]
        t = t[t >= 0]
        if not t.size:
            break
        np.subtract.at(deg, t, 1)
        t = np.unique(t)
        front = t[deg[t] == 0]
    return levels


def accumulate(code: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """D8 accumulation by Kahn's algorithm in pure Python (int64; unit
    weights = cell counts, no-data cells weigh 0)."""
    rcv = receivers(code)
    n = rcv.size
    w = (code.ravel() != NODATA_CODE).astype(np.int64) if weights is None else np.asarray(weights, np.int64).ravel()
    acc = w.copy()
    deg = np.bincount(rcv[rcv >= 0], minlength=n)
    stack = list(np.nonzero(deg == 0)[0])
    while stack:
        c = stack.pop()
        r = rcv[c]
        if r >= 0:
            acc[r] += acc[c]
            deg[r] -= 1
            if deg[r] == 0:
                stack.append(r)
    if (deg > 0).any():
        raise ValueError("the receiver graph has a cycle")
    return acc.reshape(code.shape)


def accumulate_sweeps(code: np.ndarray) -> np.ndarray:
    """Seed 003's Algorithm 1: S(a) = 1 + sum of S over donors, repeated
    until nothing changes (as many sweeps as the longest flow path)."""
    rcv = receivers(code)
    w = (code.ravel() != NODATA_CODE).astype(np.int64)
    S = w.copy()
    has = rcv >= 0
    while True:
        new = w + np.bincount(rcv[has], weights=S[has], minlength=S.size).astype(np.int64)
        if np.array_equal(new, S):
            return S.reshape(code.shape)
        S = new


def wetness(h, kind, acc_m2, water, ext, dx, tan_min, twi_dry, twi_wet):
    """The wetness kernel in float32: (twi, moisture)."""
    rows, cols = h.shape
    dcard, ddiag = F32(dx), F32(dx * np.sqrt(2.0))
    hp = np.pad(h.astype(np.float32), 1, constant_values=np.nan)
    best = np.zeros((rows, cols), np.float32)
    for k in range(8):
        hn = hp[1 + DR[k]:1 + DR[k] + rows, 1 + DC[k]:1 + DC[k] + cols]
        with np.errstate(invalid="ignore"):
            s = ((h - hn) / (ddiag if k & 1 else dcard)).astype(np.float32)
            best = np.where(s > best, s, best)
    tb = np.maximum(best, F32(tan_min))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.log(((acc_m2.astype(np.float32) / F32(dx)) / tb).astype(np.float32)).astype(np.float32)
        m = np.clip((t - F32(twi_dry)) / (F32(twi_wet) - F32(twi_dry)), 0, 1).astype(np.float32)
    mo = (F32(1) - (F32(1) - m) * (F32(1) - water.astype(np.float32)) * (F32(1) - ext.astype(np.float32))).astype(np.float32)
    t[kind == NODATA] = np.nan
    mo[kind == NODATA] = np.nan
    return t, mo


def pits(h: np.ndarray, kind: np.ndarray) -> np.ndarray:
    """Interior cells with no strictly lower neighbour (no-data is never lower)."""
    rows, cols = h.shape
    hp = np.pad(np.where(np.isfinite(h), h, np.inf), 1, constant_values=np.inf)
    lower = np.zeros((rows, cols), bool)
    for dr, dc in zip(DR, DC):
        lower |= hp[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols] < h
    return (kind == INTERIOR) & ~lower


def breach(h: np.ndarray, kind: np.ndarray | None = None) -> np.ndarray:
    """Complete breaching (Lindsay 2016, as in RichDEM's Priority-Flood
    breaching): flood from the edges in height order; when a pit (a cell
    with no strictly lower neighbour) is reached, lower the cells on the
    path that flooded it, back toward the edge, to just below the pit's
    height (one step per cell) until a cell is already low enough. Serial
    (one heap); no-data cells come back as NaN."""
    h = canonical(h)
    kind = cell_kinds(h) if kind is None else kind
    rows, cols = h.shape
    n = rows * cols
    z = h.ravel().astype(np.float32).copy()
    pit = pits(h, kind).ravel()
    back = np.full(n, -1, np.int64)
    done = (kind != INTERIOR).ravel().copy()
    heap = [(float(z[i]), int(i)) for i in np.flatnonzero(kind.ravel() == EDGE)]
    heapq.heapify(heap)
    zl = z.tolist()
    while heap:
        v, c = heapq.heappop(heap)
        if pit[c]:
            cc = int(back[c])
            target = np.float32(zl[c])
            while cc >= 0 and zl[cc] > target:
                zl[cc] = float(target)
                cc = int(back[cc])
                target = np.nextafter(target, np.float32(-np.inf), dtype=np.float32)
        r, col = divmod(c, cols)
        for dr, dc in zip(DR.tolist(), DC.tolist()):
            rr, c2 = r + dr, col + dc
            if 0 <= rr < rows and 0 <= c2 < cols:
                j = rr * cols + c2
                if not done[j]:
                    done[j] = True
                    back[j] = c
                    heapq.heappush(heap, (zl[j], j))
    out = np.array(zl, np.float32).reshape(rows, cols)
    out[kind == NODATA] = np.nan
    return out


# --------------------------------------------------------------------------- depression merge tree


@dataclass
class MergeTree:
    """The depression merge tree: nodes in creation order (children before
    parents); leaves are pits, an inner node is born at a saddle."""
    parent: np.ndarray  # int64, -1 at roots
    child_a: np.ndarray  # int64, -1 at leaves (the child with the smaller id)
    child_b: np.ndarray
    birth: np.ndarray  # float64 height at which the node is born
    entry_a: np.ndarray  # int64 node where spill water from b enters a's side (-1 at leaves)
    entry_b: np.ndarray  # int64 node where spill water from a enters b's side
    cell_node: np.ndarray  # int64 per depression cell (sparse index): the node it joined


def sparse_neighbours(cells: np.ndarray, cols: int, n_cells: int) -> np.ndarray:
    """int32 (len(cells), 8): each cell's 8 neighbours (DR/DC order) as
    positions in `cells` (flat indices, ascending), -1 where the neighbour is
    off the map or not in `cells`."""
    cells = np.asarray(cells, np.int64)
    r, c = cells // cols, cells % cols
    out = np.full((cells.size, 8), -1, np.int32)
    for k in range(8):
        rr, cc = r + DR[k], c + DC[k]
        nb = rr * cols + cc
        ok = (rr >= 0) & (cc >= 0) & (cc < cols) & (nb < n_cells)
        pos = np.minimum(np.searchsorted(cells, nb), max(cells.size - 1, 0))
        ok &= cells[pos] == nb if cells.size else ok
        out[ok, k] = pos[ok]
    return out


def merge_tree_reference(order: np.ndarray, h: np.ndarray, term: np.ndarray, nbr: np.ndarray) -> MergeTree:
    """The union-find sweep in pure Python on the depression cells alone
    (sparse indices: positions in the ascending list of their flat indices):
    order visits them in increasing (height, index); a cell joins the
    components of its already swept 8-neighbours (nbr, -1 outside), merging
    them pairwise in node order at its height; spill water between two
    merged basins enters each at the node of the pit that the lowest
    neighbour of the saddle cell drains to (term, -1 when its path leaves
    the depressions: no entry)."""
    hl = np.asarray(h, np.float64).ravel().tolist()
    nbl = np.asarray(nbr).tolist()
    terml = np.asarray(term).tolist()
    m = len(hl)
    uf = [-1] * m
    comp_node = [0] * m
    cell_node = [-1] * m
    parent_n, child_a, child_b, birth, entry_a, entry_b = [], [], [], [], [], []

    def find(x):
        root = x
        while uf[root] != root:
            root = uf[root]
        while uf[x] != root:
            uf[x], x = root, uf[x]
        return root

    def new_node(a, b, lev, ea, eb):
        parent_n.append(-1)
        child_a.append(a)
        child_b.append(b)
        birth.append(lev)
        entry_a.append(ea)
        entry_b.append(eb)
        return len(parent_n) - 1

    def entry(c):
        t = terml[c]
        return cell_node[t] if t >= 0 else -1

    for c in np.asarray(order).tolist():
        hc = hl[c]
        roots = []
        low = {}  # per neighbouring component: its lowest neighbour of c (entry for spill water)
        for nb in nbl[c]:
            if nb >= 0 and uf[nb] >= 0:
                k = find(nb)
                if k not in low:
                    roots.append(k)
                    low[k] = nb
                elif (hl[nb], nb) < (hl[low[k]], low[k]):
                    low[k] = nb
        uf[c] = c
        if not roots:
            node = new_node(-1, -1, hc, -1, -1)
        else:
            roots.sort(key=lambda k: comp_node[k])
            k0 = roots[0]
            node = comp_node[k0]
            for k in roots[1:]:
                other = comp_node[k]
                p = new_node(node, other, hc, entry(low[k0]), entry(low[k]))
                parent_n[node] = p
                parent_n[other] = p
                node = p
            for k in roots:
                uf[k] = c
            uf[c] = c
        comp_node[find(c)] = node
        cell_node[c] = node

    def i64(x):
        return np.array(x, np.int64)

    return MergeTree(i64(parent_n), i64(child_a), i64(child_b), np.array(birth, np.float64), i64(entry_a),
                     i64(entry_b), i64(cell_node))
