"""Lakes: seed 003's Algorithm 2 as Fill-Spill-Merge on the depression tree.

Every basin receives the runoff volume of its catchment (V = S * K_r, seed
003), fills to the level that holds it, spills its excess over its saddle
into the neighbouring basin, and merges with that basin when both are full;
the excess of a whole depression leaves over its spill point and runs
downstream into the next depression or off the map. All volumes are
float64; the budget (rain in = stored + spilled off the map) closes to
round-off.

Structure:
1. Depression cells D: fill level F > h. F is constant on each 8-connected
   region of D (a "depression"), which spills at level F.
2. Lake routing: inside D the steepest descent on the raw terrain (ends in a
   pit of the same depression); elsewhere the main routing (the
   epsilon-filled surface). Accumulating rain on it gives each pit its
   inflow, and the place where a depression's spill water lands.
3. A union-find sweep over D in increasing height builds the merge tree:
   leaves are pits, an inner node is born where two basins meet at a saddle.
4. Depressions are solved upstream first (by the routing surface at their
   exit, which strictly decreases downstream); each tree top-down: a node
   holding at least its children's capacities is one lake whose flat level
   holds the water; otherwise the fuller child spills into the other.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from worldlib.flow import reference as ref
from worldlib.flow.reference import MergeTree, merge_tree_reference  # noqa: F401 (the lakes' names)


@dataclass
class LakeResult:
    level: np.ndarray  # float64 water level per cell, NaN where dry
    depth: np.ndarray  # float64 water depth per cell (0 where dry)
    lake_id: np.ndarray  # int32 connected lake label, 0 where dry
    stats: dict = field(default_factory=dict)
    spills: list = field(default_factory=list)  # (depression exit cell, target cell or -1, volume m^3)


def terminals(rcv: np.ndarray) -> np.ndarray:
    """The end of every cell's path in a receiver forest (-1 = none), by
    pointer jumping."""
    n = rcv.size
    t = np.where(rcv >= 0, rcv, np.arange(n))
    while True:
        nt = t[t]
        if np.array_equal(nt, t):
            return t
        t = nt


def solve_lakes(h: np.ndarray, kind: np.ndarray, F: np.ndarray, code_main: np.ndarray, code_raw: np.ndarray,
                runoff_m3: np.ndarray, cell_area: float, accumulate, merge_sweep=None) -> LakeResult:
    """h canonical float32 heights; F pure fill; code_main D8 on the routing
    surface; code_raw D8 on h; runoff_m3 water each cell sends to the basins
    (m^3); accumulate(code, int64 weights) -> int64 sums and merge_sweep(cells,
    h, term, cols) -> MergeTree: the device's or the references (default:
    merge_tree_reference)."""
    from scipy import ndimage

    rows, cols = h.shape
    n = rows * cols
    h64 = h.astype(np.float64)
    D = (kind == ref.INTERIOR) & (F > h)
    level = np.full((rows, cols), np.nan)
    runoff = np.where(kind == ref.NODATA, 0.0, np.nan_to_num(runoff_m3, nan=0.0)).astype(np.float64)
    total_in = float(runoff.sum())
    if not D.any():
        return LakeResult(level, np.zeros((rows, cols)), np.zeros((rows, cols), np.int32),
                          {"lakes": 0, "depressions": 0, "volume_in_m3": total_in, "volume_stored_m3": 0.0,
                           "volume_out_m3": total_in, "budget_relative_error": 0.0})

    # 2. lake routing and inflows
    code_lake = np.where(D, code_raw, code_main).astype(np.int8)
    from worldlib.flow.device import quantize

    q, scale = quantize(runoff)
    acc = accumulate(code_lake, q).astype(np.float64).ravel() / scale
    rcv_lake = ref.receivers(code_lake)
    term = terminals(rcv_lake)
    Df = D.ravel()
    pit = Df & (code_lake.ravel() == ref.PIT)

    # exit of each depression: first non-D cell on the main routing path
    rcv_main = ref.receivers(code_main)
    nxt = np.where(Df & (rcv_main >= 0), rcv_main, np.arange(n))
    while True:
        nn = nxt[nxt]
        if np.array_equal(nn, nxt):
            break
        nxt = nn

    # 3. union-find sweep in increasing height (stable by cell index)
    cells = np.flatnonzero(Df)
    cells = cells[np.lexsort((cells, h64.ravel()[cells]))]
    tree = (merge_sweep or merge_tree_reference)(cells, h, term, cols)
    parent_n, child_a, child_b = tree.parent, tree.child_a, tree.child_b
    birth, entry_a, entry_b, cell_node = tree.birth, tree.entry_a, tree.entry_b, tree.cell_node
    nn_ = parent_n.size
    # each node's own cells, grouped in sweep order (so ascending in height)
    own_node = cell_node[cells]
    perm = np.argsort(own_node, kind="stable")
    own_sorted = cells[perm]
    own_start = np.searchsorted(own_node[perm], np.arange(nn_ + 1))

    def own_cells(nd: int) -> np.ndarray:
        return own_sorted[own_start[nd]:own_start[nd + 1]]

    # per node: count and sum of heights of its subtree cells, top level L
    own_cnt = np.diff(own_start).astype(np.float64)
    own_sum = np.bincount(own_node, weights=h64.ravel()[cells], minlength=nn_)
    cnt = own_cnt.copy()
    ssum = own_sum.copy()
    for nd in range(nn_):  # children have smaller ids than parents
        p = parent_n[nd]
        if p >= 0:
            cnt[p] += cnt[nd]
            ssum[p] += ssum[nd]
    top = np.empty(nn_)
    has_parent = parent_n >= 0
    top[has_parent] = birth[parent_n[has_parent]]
    roots_idx = np.flatnonzero(~has_parent)
    # a root's level is its depression's fill level
    rep_cell = np.empty(nn_, np.int64)  # any cell of the subtree (its first own cell, or a child's)
    has_own = own_cnt > 0
    rep_cell[has_own] = own_sorted[own_start[:-1][has_own]]
    for nd in np.flatnonzero(~has_own).tolist():  # inner merge nodes of a saddle joining 3+ basins
        rep_cell[nd] = rep_cell[child_a[nd]]
    top[roots_idx] = F.ravel()[rep_cell[roots_idx]].astype(np.float64)
    cap = cell_area * (cnt * top - ssum)
    # Euler intervals for "is e in the subtree of N"
    tin = np.zeros(nn_, np.int64)
    tout = np.zeros(nn_, np.int64)
    clock = 0
    for r0 in roots_idx.tolist():
        stack = [(r0, 0)]
        while stack:
            nd, state = stack.pop()
            if state == 0:
                tin[nd] = clock
                clock += 1
                stack.append((nd, 1))
                if child_a[nd] >= 0:
                    stack.append((int(child_b[nd]), 0))
                    stack.append((int(child_a[nd]), 0))
            else:
                tout[nd] = clock

    def inside(e, nd):
        return tin[nd] <= tin[e] < tout[nd]

    # direct water per node: inflow at pits (terminals of the lake routing)
    direct = np.zeros(nn_)
    pit_cells = np.flatnonzero(pit)
    np.add.at(direct, cell_node[pit_cells], acc[pit_cells])

    # 4. depressions upstream first: Kahn's order on the graph "spills into"
    tree_of = np.empty(nn_, np.int64)
    for i, r0 in enumerate(roots_idx.tolist()):
        tree_of[r0] = i
    for nd in range(nn_ - 1, -1, -1):
        if parent_n[nd] >= 0:
            tree_of[nd] = tree_of[parent_n[nd]]
    nodes_of_tree = [[] for _ in roots_idx]
    for nd in range(nn_):
        nodes_of_tree[tree_of[nd]].append(nd)
    exit_cell = nxt[rep_cell[roots_idx]]
    tgt_cell = term[exit_cell]
    tgt_tree = np.where(Df[tgt_cell] & (cell_node[tgt_cell] >= 0), tree_of[np.maximum(cell_node[tgt_cell], 0)], -1)
    tgt_tree[tgt_tree == np.arange(len(roots_idx))] = -1
    indeg = np.bincount(tgt_tree[tgt_tree >= 0], minlength=len(roots_idx))
    order_roots = []
    ready = list(np.flatnonzero(indeg == 0)[::-1])
    while ready:
        i = int(ready.pop())
        order_roots.append(i)
        j = int(tgt_tree[i])
        if j >= 0:
            indeg[j] -= 1
            if indeg[j] == 0:
                ready.append(j)
    if len(order_roots) < len(roots_idx):  # a cycle through equal spill levels: cannot happen, kept safe
        done = set(order_roots)
        order_roots += [i for i in range(len(roots_idx)) if i not in done]

    lake_level = np.full(nn_, np.nan)  # level of nodes that are one lake
    stored = 0.0
    out_ocean = 0.0
    spills = []
    own_h = [None] * nn_

    def level_for(nd, water):
        """Flat level holding `water` over the subtree of nd, nd's children full."""
        oh = own_h[nd]
        if oh is None:
            oh = own_h[nd] = h64.ravel()[own_cells(nd)]  # ascending: sweep order
        if child_a[nd] >= 0:
            c0, s0, base = cnt[child_a[nd]] + cnt[child_b[nd]], ssum[child_a[nd]] + ssum[child_b[nd]], birth[nd]
        else:
            c0, s0, base = 0.0, 0.0, -np.inf
        ncum = c0 + np.arange(1, len(oh) + 1)
        scum = s0 + np.cumsum(oh)
        if c0 > 0:
            ncum = np.concatenate([[c0], ncum])
            scum = np.concatenate([[s0], scum])
            lows = np.concatenate([[base], oh])
        else:
            lows = oh
        highs = np.concatenate([lows[1:], [np.inf]])
        lev = (water / cell_area + scum) / ncum
        ok = np.flatnonzero(lev <= highs)
        return float(min(lev[ok[0]], top[nd])) if ok.size else float(top[nd])

    for ti in order_roots:
        r0 = int(roots_idx[ti])
        nodes = nodes_of_tree[ti]
        W0 = {}
        for nd in nodes:  # ascending ids: children first
            w = direct[nd]
            if child_a[nd] >= 0:
                w += W0[child_a[nd]] + W0[child_b[nd]]
            W0[nd] = w
        total = W0[r0]
        excess = max(0.0, total - cap[r0])
        stack = [(r0, min(total, cap[r0]), [])]
        while stack:
            nd, water, ext = stack.pop()
            a_, b_ = int(child_a[nd]), int(child_b[nd])
            if a_ < 0 or water >= cap[a_] + cap[b_]:
                lake_level[nd] = level_for(nd, water)
                continue
            ext_a = [(x, e) for x, e in ext if inside(e, a_)]
            ext_b = [(x, e) for x, e in ext if not inside(e, a_)]
            wa = W0[a_] + direct[nd] + sum(x for x, _ in ext_a)
            wb = W0[b_] + sum(x for x, _ in ext_b)
            if wa > cap[a_]:
                s = wa - cap[a_]
                wa = cap[a_]
                wb += s
                ext_b.append((s, int(entry_b[nd])))
            elif wb > cap[b_]:
                s = wb - cap[b_]
                wb = cap[b_]
                wa += s
                ext_a.append((s, int(entry_a[nd])))
            stack.append((a_, wa, ext_a))
            stack.append((b_, wb, ext_b))
        stored += min(total, cap[r0])
        if excess > 0:
            x = int(exit_cell[ti])
            t = int(tgt_cell[ti])
            if tgt_tree[ti] >= 0:
                direct[cell_node[t]] += excess
                spills.append((x, t, excess))
            else:
                out_ocean += excess
                spills.append((x, -1, excess))

    # levels per cell: the topmost single-lake ancestor
    lake_top = np.full(nn_, -1, np.int64)
    for nd in range(nn_ - 1, -1, -1):
        p = parent_n[nd]
        if p >= 0 and lake_top[p] >= 0:
            lake_top[nd] = lake_top[p]
        elif not np.isnan(lake_level[nd]):
            lake_top[nd] = nd
    lev_cells = np.full(n, np.nan)
    cn_ok = cell_node >= 0
    lt = np.where(cn_ok, lake_top[np.maximum(cell_node, 0)], -1)
    has = lt >= 0
    lev_cells[has] = lake_level[lt[has]]
    depth = np.where(has, np.maximum(lev_cells - h64.ravel(), 0.0), 0.0)
    lev_cells[depth <= 0] = np.nan
    depth = depth.reshape(rows, cols)
    lake_id, nlakes = ndimage.label(depth > 0, structure=np.ones((3, 3), bool))
    vol_cells = float(depth.sum() * cell_area)
    out_direct = float(acc[(kind.ravel() == ref.EDGE)].sum())
    out_total = out_direct + out_ocean
    resid = total_in - stored - out_total
    stats = {
        "lakes": int(nlakes), "depressions": int(len(roots_idx)), "basins": int((child_a < 0).sum()),
        "volume_in_m3": total_in, "volume_stored_m3": stored, "volume_stored_cells_m3": vol_cells,
        "volume_out_m3": out_total, "spills": len(spills),
        "budget_relative_error": abs(resid) / max(total_in, 1e-300),
        "stored_vs_cells_relative_error": abs(stored - vol_cells) / max(stored, 1e-300),
        "lake_area_m2": float((depth > 0).sum() * cell_area),
    }
    return LakeResult(lev_cells.reshape(rows, cols), depth, lake_id.astype(np.int32), stats, spills)
