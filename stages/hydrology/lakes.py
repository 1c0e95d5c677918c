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

Steps 3 and 4 read only the depression cells (DepressionCells: per cell, per
depression exit or scalar, nothing world-sized): gather_depressions collects
them from whole maps, a tiled world can collect the same set tile by tile,
and solve_depressions solves them. Its sums are math.fsum (correctly
rounded), so they do not depend on how the cells were split.
"""
from __future__ import annotations

import math
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
    (m^3); accumulate(code, int64 weights) -> int64 sums and merge_sweep(order,
    h, term, nbr) -> MergeTree: the device's or the reference (default:
    merge_tree_reference). The depression cells gathered, solved, and
    written into whole maps."""
    dc = gather_depressions(h, kind, F, code_main, code_raw, runoff_m3, accumulate)
    sol = solve_depressions(dc, cell_area, merge_sweep)
    maps = lake_maps_of(dc, sol, h.shape)
    return LakeResult(maps.level, maps.depth, maps.lake_id, sol.stats, sol.spills)


def lake_maps_of(dc: DepressionCells, sol: DepressionLakes, shape: tuple[int, int]) -> LakeMaps:
    """The lakes on the depression cells as maps of the world (dry elsewhere)."""
    rows, cols = shape
    level = np.full(rows * cols, np.nan)
    depth = np.zeros(rows * cols)
    lake_id = np.zeros(rows * cols, np.int32)
    level[dc.cells], depth[dc.cells], lake_id[dc.cells] = sol.level, sol.depth, sol.lake_id
    return LakeMaps(depth.reshape(rows, cols), level.reshape(rows, cols), lake_id.reshape(rows, cols), sol.stats)


def no_lakes(shape: tuple[int, int]) -> LakeMaps:
    """params.lakes off: every cell dry."""
    return LakeMaps(np.zeros(shape), np.full(shape, np.nan), np.zeros(shape, np.int32), {"lakes": 0})


@dataclass(frozen=True)
class DepressionCells:
    """Everything the lake solve reads: the depression cells D (interior,
    F > h) and, per cell, per depression exit or as a scalar, only what the
    solve needs: nothing world-sized, so a tiled world can gather it tile by
    tile. Per-cell arrays follow `cells`; a cell's sparse index is its
    position there (ascending flat index, so sparse order is raster order)."""
    cols: int  # the world's columns (flat index = row * cols + col)
    n_cells: int  # the world's cells
    total_in: float  # runoff of the whole map (m^3, math.fsum: the same however it is split)
    out_direct: float  # runoff that reaches the map's edge cells on the lake routing (m^3, math.fsum)
    cells: np.ndarray  # int64 flat index of each depression cell, ascending
    h: np.ndarray  # float32 terrain height
    F: np.ndarray  # fill level (F's dtype)
    rcv: np.ndarray  # int64 flat index of the receiver on the lake routing, -1 at a pit
    pit: np.ndarray  # bool: the lake routing ends here
    acc: np.ndarray  # float64 runoff accumulated on the lake routing arriving at the cell (m^3)
    nbr: np.ndarray  # int32 (cells, 8): the 8 neighbours (ref.DR/DC order) as sparse indices, -1 outside D
    exit: np.ndarray  # int64 flat index of the first non-D cell on the main routing (or the D cell where it ends)
    exits: np.ndarray  # int64 per exit: the distinct values of `exit`, ascending
    exit_term: np.ndarray  # int64 per exit: the flat index where its path on the lake routing ends
    exit_term_in: np.ndarray  # bool per exit: that end cell is a depression cell

    PER_CELL = ("cells", "h", "F", "rcv", "pit", "acc", "nbr", "exit")
    PER_EXIT = ("exits", "exit_term", "exit_term_in")

    def __post_init__(self):
        m, k = self.cells.size, self.exits.size
        for name in self.PER_CELL + self.PER_EXIT:
            n = m if name in self.PER_CELL else k
            if getattr(self, name).shape[0] != n:
                raise ValueError(f"DepressionCells.{name} has {getattr(self, name).shape[0]} rows, not {n}")

    @property
    def size(self) -> int:
        return int(self.cells.size)


def no_depressions(cols: int, n_cells: int, total_in: float) -> DepressionCells:
    i8, f4 = np.zeros(0, np.int64), np.zeros(0, np.float32)
    return DepressionCells(cols, n_cells, total_in, total_in, i8, f4, f4, i8, np.zeros(0, bool), np.zeros(0),
                           np.zeros((0, 8), np.int32), i8, i8, i8, np.zeros(0, bool))


def gather_depressions(h: np.ndarray, kind: np.ndarray, F: np.ndarray, code_main: np.ndarray, code_raw: np.ndarray,
                       runoff_m3: np.ndarray, accumulate) -> DepressionCells:
    """The depression cells of whole maps (solve_lakes' inputs), with the lake
    routing's accumulation, terminals and exits computed on the whole maps."""
    rows, cols = h.shape
    D = (kind == ref.INTERIOR) & (F > h)
    runoff = np.where(kind == ref.NODATA, 0.0, np.nan_to_num(runoff_m3, nan=0.0)).astype(np.float64)
    total_in = math.fsum(runoff.ravel().tolist())
    if not D.any():
        return no_depressions(cols, rows * cols, total_in)
    routing = _lake_routing(D, code_main, code_raw, runoff, accumulate)  # 2.
    cells = np.flatnonzero(routing.in_depression)
    code = code_raw.ravel()[cells].astype(np.int64)
    k = np.clip(code, 0, 7)
    rcv = np.where(code >= 0, cells + ref.DR[k] * cols + ref.DC[k], -1)
    exit_ = routing.exit[cells]
    exits = np.unique(exit_)
    term = routing.term[exits]
    out_direct = math.fsum(routing.acc[kind.ravel() == ref.EDGE].tolist())
    return DepressionCells(cols, rows * cols, total_in, out_direct, cells, h.ravel()[cells], F.ravel()[cells], rcv,
                           routing.pit[cells], routing.acc[cells], ref.sparse_neighbours(cells, cols, rows * cols),
                           exit_, exits, term, routing.in_depression[term])


@dataclass(frozen=True)
class DepressionLakes:
    """The lakes on the depression cells (per cell of DepressionCells.cells); every other cell is dry."""
    level: np.ndarray  # float64 water level, NaN where dry
    depth: np.ndarray  # float64 water depth (0 where dry)
    lake_id: np.ndarray  # int32 connected lake label (8-connected, numbered in raster order), 0 where dry
    stats: dict
    spills: list  # (depression exit cell, target cell or -1, volume m^3), flat indices


def solve_depressions(dc: DepressionCells, cell_area: float, merge_sweep=None) -> DepressionLakes:
    """Fill-Spill-Merge on the depression cells alone (steps 3 and 4)."""
    m = dc.size
    if m == 0:
        return DepressionLakes(np.zeros(0), np.zeros(0), np.zeros(0, np.int32), _no_lakes_stats(dc.total_in), [])
    h64 = dc.h.astype(np.float64)
    order = np.lexsort((np.arange(m), h64))  # 3. increasing height, ties by index
    tree = (merge_sweep or merge_tree_reference)(order, dc.h, _sparse_terminals(dc), dc.nbr)
    nodes = _node_table(tree, order, h64, dc.F, cell_area)
    direct = _pit_inflow(nodes, dc)
    dorder = _depressions_upstream_first(nodes, dc)  # 4.
    lake_level, stored, out_ocean, spills = _fill_depressions(nodes, dorder, direct, h64, cell_area)
    level, depth = _cell_levels(nodes, lake_level, h64)
    lake_id, nlakes = _label_lakes(depth > 0, dc.nbr)
    stats = _lake_stats(nodes, depth, cell_area, nlakes, dc.total_in, stored, dc.out_direct + out_ocean, len(spills))
    return DepressionLakes(level, depth, lake_id, stats, spills)


def _sparse_terminals(dc: DepressionCells) -> np.ndarray:
    """Sparse index of the end of each depression cell's path on the lake
    routing (a pit: steepest descent from a depression cell stays in D), -1
    if a path left D."""
    m = dc.size
    pos = np.minimum(np.searchsorted(dc.cells, dc.rcv), m - 1)
    t = np.where(dc.rcv < 0, np.arange(m), np.where(dc.cells[pos] == dc.rcv, pos, -1))
    while True:
        nt = np.where(t >= 0, t[np.maximum(t, 0)], -1)
        if np.array_equal(nt, t):
            return t
        t = nt


def _label_lakes(wet: np.ndarray, nbr: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected components of the wet cells, numbered 1.. in raster order
    of each component's first cell (scipy.ndimage.label's numbering)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    lake_id = np.zeros(wet.size, np.int32)
    idx = np.flatnonzero(wet)
    if idx.size == 0:
        return lake_id, 0
    pos = np.full(wet.size, -1, np.int64)
    pos[idx] = np.arange(idx.size)
    a = np.repeat(np.arange(idx.size), 8)
    b = nbr[idx].ravel().astype(np.int64)
    ok = b >= 0
    ok[ok] = wet[b[ok]]
    g = coo_matrix((np.ones(int(ok.sum()), np.int8), (a[ok], pos[b[ok]])), shape=(idx.size, idx.size))
    n, comp = connected_components(g, directed=False)
    first = np.full(n, idx.size, np.int64)
    np.minimum.at(first, comp, np.arange(idx.size))
    rank = np.empty(n, np.int64)
    rank[np.argsort(first)] = np.arange(n)
    lake_id[idx] = (rank[comp] + 1).astype(np.int32)
    return lake_id, int(n)


def _no_lakes_stats(total_in: float) -> dict:
    return {"lakes": 0, "depressions": 0, "volume_in_m3": total_in, "volume_stored_m3": 0.0,
            "volume_out_m3": total_in, "budget_relative_error": 0.0}


@dataclass(frozen=True)
class _LakeRouting:
    """Step 2: where each cell's water goes on the lake routing."""
    in_depression: np.ndarray  # bool per cell (flat): in a depression D
    acc: np.ndarray  # float64 per cell: runoff accumulated on the lake routing (m^3)
    term: np.ndarray  # int64 per cell: the end of its path on the lake routing
    pit: np.ndarray  # bool per cell: a pit of a depression
    exit: np.ndarray  # int64 per cell: a depression cell's first non-D cell on the main routing


def _lake_routing(D: np.ndarray, code_main: np.ndarray, code_raw: np.ndarray, runoff: np.ndarray,
                  accumulate) -> _LakeRouting:
    """Steepest descent on the raw terrain inside D, the main routing elsewhere;
    the runoff accumulated on it; each depression cell's exit."""
    from worldlib.flow.device import quantize

    code_lake = np.where(D, code_raw, code_main).astype(np.int8)
    q, scale = quantize(runoff)
    acc = accumulate(code_lake, q).astype(np.float64).ravel() / scale
    term = terminals(ref.receivers(code_lake))
    Df = D.ravel()
    pit = Df & (code_lake.ravel() == ref.PIT)
    rcv_main = ref.receivers(code_main)
    nxt = np.where(Df & (rcv_main >= 0), rcv_main, np.arange(Df.size))
    while True:
        nn = nxt[nxt]
        if np.array_equal(nn, nxt):
            break
        nxt = nn
    return _LakeRouting(Df, acc, term, pit, nxt)


@dataclass(frozen=True)
class _NodeTable:
    """The merge tree with what the filling needs per node."""
    tree: MergeTree
    own_sorted: np.ndarray  # each node's own cells, grouped in sweep order (so ascending in height)
    own_start: np.ndarray  # node nd's own cells: own_sorted[own_start[nd]:own_start[nd + 1]]
    cnt: np.ndarray  # float64 cells of each node's subtree
    ssum: np.ndarray  # float64 sum of the heights of each node's subtree
    top: np.ndarray  # float64 level at which each node's basin spills (its parent's birth, a root's fill level)
    cap: np.ndarray  # float64 capacity of each node's basin (m^3)
    roots: np.ndarray  # the roots, one per depression
    rep_cell: np.ndarray  # any cell of each node's subtree (sparse index, as own_sorted)
    tin: np.ndarray  # Euler intervals for "is e in the subtree of nd"
    tout: np.ndarray

    @property
    def size(self) -> int:
        return self.tree.parent.size

    def own_cells(self, nd: int) -> np.ndarray:
        return self.own_sorted[self.own_start[nd]:self.own_start[nd + 1]]

    def inside(self, e, nd) -> bool:
        return self.tin[nd] <= self.tin[e] < self.tout[nd]


def _node_table(tree: MergeTree, cells: np.ndarray, h64: np.ndarray, F: np.ndarray, cell_area: float) -> _NodeTable:
    """cells: the sweep order (sparse indices); h64 and F per depression cell."""
    parent_n, child_a, birth, cell_node = tree.parent, tree.child_a, tree.birth, tree.cell_node
    nn_ = parent_n.size
    own_node = cell_node[cells]
    perm = np.argsort(own_node, kind="stable")
    own_sorted = cells[perm]
    own_start = np.searchsorted(own_node[perm], np.arange(nn_ + 1))
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
    tin, tout = _euler_intervals(tree, roots_idx)
    return _NodeTable(tree, own_sorted, own_start, cnt, ssum, top, cap, roots_idx, rep_cell, tin, tout)


def _euler_intervals(tree: MergeTree, roots_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit clocks of a depth-first walk: e is in the subtree of nd
    when tin[nd] <= tin[e] < tout[nd]."""
    child_a, child_b = tree.child_a, tree.child_b
    nn_ = tree.parent.size
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
    return tin, tout


def _pit_inflow(nodes: _NodeTable, dc: DepressionCells) -> np.ndarray:
    """Direct water per node: inflow at pits (terminals of the lake routing)."""
    direct = np.zeros(nodes.size)
    pit_cells = np.flatnonzero(dc.pit)
    np.add.at(direct, nodes.tree.cell_node[pit_cells], dc.acc[pit_cells])
    return direct


@dataclass(frozen=True)
class _DepressionOrder:
    """Step 4's order: depressions upstream first, and where each spills."""
    nodes_of_tree: list  # node ids of each depression's tree, ascending
    exit_cell: np.ndarray  # each depression's spill cell (flat index)
    tgt_cell: np.ndarray  # where its spill water lands (flat index)
    tgt_sparse: np.ndarray  # that cell's sparse index, -1 outside D
    tgt_tree: np.ndarray  # the depression it spills into, -1 off the map
    order: list  # depression indices, upstream first


def _depressions_upstream_first(nodes: _NodeTable, dc: DepressionCells) -> _DepressionOrder:
    """Kahn's order on the graph "spills into"."""
    parent_n, cell_node, roots_idx = nodes.tree.parent, nodes.tree.cell_node, nodes.roots
    nn_ = nodes.size
    tree_of = np.empty(nn_, np.int64)
    for i, r0 in enumerate(roots_idx.tolist()):
        tree_of[r0] = i
    for nd in range(nn_ - 1, -1, -1):
        if parent_n[nd] >= 0:
            tree_of[nd] = tree_of[parent_n[nd]]
    nodes_of_tree = [[] for _ in roots_idx]
    for nd in range(nn_):
        nodes_of_tree[tree_of[nd]].append(nd)
    exit_cell = dc.exit[nodes.rep_cell[roots_idx]]
    k = np.searchsorted(dc.exits, exit_cell)
    tgt_cell, tgt_in = dc.exit_term[k], dc.exit_term_in[k]
    tgt_sparse = np.where(tgt_in, np.searchsorted(dc.cells, tgt_cell), -1)
    tgt_node = np.where(tgt_in, cell_node[np.maximum(tgt_sparse, 0)], -1)
    tgt_tree = np.where(tgt_node >= 0, tree_of[np.maximum(tgt_node, 0)], -1)
    tgt_tree[tgt_tree == np.arange(len(roots_idx))] = -1
    return _DepressionOrder(nodes_of_tree, exit_cell, tgt_cell, tgt_sparse, tgt_tree, _kahn_order(tgt_tree))


def _kahn_order(tgt_tree: np.ndarray) -> list:
    n_trees = len(tgt_tree)
    indeg = np.bincount(tgt_tree[tgt_tree >= 0], minlength=n_trees)
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
    if len(order_roots) < n_trees:  # a cycle through equal spill levels: cannot happen, kept safe
        done = set(order_roots)
        order_roots += [i for i in range(n_trees) if i not in done]
    return order_roots


class _LakeLevels:
    """Flat lake levels over a node's subtree; each node's own heights read once."""

    def __init__(self, nodes: _NodeTable, h64: np.ndarray, cell_area: float):
        self.nodes, self.h64, self.cell_area = nodes, h64, cell_area
        self.own_h = [None] * nodes.size

    def level_for(self, nd, water):
        """Flat level holding `water` over the subtree of nd, nd's children full."""
        nodes, tree = self.nodes, self.nodes.tree
        oh = self.own_h[nd]
        if oh is None:
            oh = self.own_h[nd] = self.h64.ravel()[nodes.own_cells(nd)]  # ascending: sweep order
        if tree.child_a[nd] >= 0:
            a_, b_ = tree.child_a[nd], tree.child_b[nd]
            c0, s0, base = nodes.cnt[a_] + nodes.cnt[b_], nodes.ssum[a_] + nodes.ssum[b_], tree.birth[nd]
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
        lev = (water / self.cell_area + scum) / ncum
        ok = np.flatnonzero(lev <= highs)
        return float(min(lev[ok[0]], nodes.top[nd])) if ok.size else float(nodes.top[nd])


def _fill_depressions(nodes: _NodeTable, order: _DepressionOrder, direct: np.ndarray, h64: np.ndarray,
                      cell_area: float) -> tuple[np.ndarray, float, float, list]:
    """Each depression upstream first: its tree filled, its excess spilled
    downstream (into `direct`, changed) or off the map. Returns the level of
    nodes that are one lake, the stored and the off-map volume, the spills."""
    lake_level = np.full(nodes.size, np.nan)
    levels = _LakeLevels(nodes, h64, cell_area)
    cell_node = nodes.tree.cell_node
    stored = 0.0
    out_ocean = 0.0
    spills = []
    for ti in order.order:
        r0 = int(nodes.roots[ti])
        total = _fill_tree(nodes, r0, order.nodes_of_tree[ti], direct, levels, lake_level)
        excess = max(0.0, total - nodes.cap[r0])
        stored += min(total, nodes.cap[r0])
        if excess > 0:
            x = int(order.exit_cell[ti])
            t = int(order.tgt_cell[ti])
            if order.tgt_tree[ti] >= 0:
                direct[cell_node[order.tgt_sparse[ti]]] += excess
                spills.append((x, t, excess))
            else:
                out_ocean += excess
                spills.append((x, -1, excess))
    return lake_level, stored, out_ocean, spills


def _fill_tree(nodes: _NodeTable, r0: int, tree_nodes: list, direct: np.ndarray, levels: _LakeLevels,
               lake_level: np.ndarray) -> float:
    """One depression top-down: a node holding at least its children's
    capacities is one lake (its level into lake_level); otherwise the fuller
    child spills into the other. Returns the water the depression received."""
    child_a, child_b, cap = nodes.tree.child_a, nodes.tree.child_b, nodes.cap
    W0 = {}
    for nd in tree_nodes:  # ascending ids: children first
        w = direct[nd]
        if child_a[nd] >= 0:
            w += W0[child_a[nd]] + W0[child_b[nd]]
        W0[nd] = w
    total = W0[r0]
    stack = [(r0, min(total, cap[r0]), [])]
    while stack:
        nd, water, ext = stack.pop()
        a_, b_ = int(child_a[nd]), int(child_b[nd])
        if a_ < 0 or water >= cap[a_] + cap[b_]:
            lake_level[nd] = levels.level_for(nd, water)
            continue
        ext_a = [(x, e) for x, e in ext if nodes.inside(e, a_)]
        ext_b = [(x, e) for x, e in ext if not nodes.inside(e, a_)]
        wa = W0[a_] + direct[nd] + sum(x for x, _ in ext_a)
        wb = W0[b_] + sum(x for x, _ in ext_b)
        if wa > cap[a_]:
            s = wa - cap[a_]
            wa = cap[a_]
            wb += s
            ext_b.append((s, int(nodes.tree.entry_b[nd])))
        elif wb > cap[b_]:
            s = wb - cap[b_]
            wb = cap[b_]
            wa += s
            ext_a.append((s, int(nodes.tree.entry_a[nd])))
        stack.append((a_, wa, ext_a))
        stack.append((b_, wb, ext_b))
    return total


def _cell_levels(nodes: _NodeTable, lake_level: np.ndarray, h64: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Levels per depression cell: the topmost single-lake ancestor's; NaN where dry. And depths."""
    parent_n, cell_node = nodes.tree.parent, nodes.tree.cell_node
    nn_ = nodes.size
    lake_top = np.full(nn_, -1, np.int64)
    for nd in range(nn_ - 1, -1, -1):
        p = parent_n[nd]
        if p >= 0 and lake_top[p] >= 0:
            lake_top[nd] = lake_top[p]
        elif not np.isnan(lake_level[nd]):
            lake_top[nd] = nd
    lev_cells = np.full(h64.size, np.nan)
    cn_ok = cell_node >= 0
    lt = np.where(cn_ok, lake_top[np.maximum(cell_node, 0)], -1)
    has = lt >= 0
    lev_cells[has] = lake_level[lt[has]]
    depth = np.where(has, np.maximum(lev_cells - h64.ravel(), 0.0), 0.0)
    lev_cells[depth <= 0] = np.nan
    return lev_cells, depth


def _lake_stats(nodes: _NodeTable, depth: np.ndarray, cell_area: float, nlakes: int, total_in: float,
                stored: float, out_total: float, n_spills: int) -> dict:
    vol_cells = float(math.fsum(depth.tolist()) * cell_area)  # correctly rounded: the same however D is split
    resid = total_in - stored - out_total
    return {
        "lakes": nlakes, "depressions": int(len(nodes.roots)), "basins": int((nodes.tree.child_a < 0).sum()),
        "volume_in_m3": total_in, "volume_stored_m3": stored, "volume_stored_cells_m3": vol_cells,
        "volume_out_m3": out_total, "spills": n_spills,
        "budget_relative_error": abs(resid) / max(total_in, 1e-300),
        "stored_vs_cells_relative_error": abs(stored - vol_cells) / max(stored, 1e-300),
        "lake_area_m2": float((depth > 0).sum() * cell_area),
    }


@dataclass(frozen=True)
class LakeMaps:
    depth: np.ndarray  # float64 water depth per cell (0 where dry)
    level: np.ndarray  # float64 water level per cell, NaN where dry
    lake_id: np.ndarray  # int32 connected lake label, 0 where dry
    stats: dict


def lake_maps(env, land, filled: np.ndarray, code: np.ndarray, rain: np.ndarray, params) -> LakeMaps:
    """The stage's step 4 on the OpenCL device `env` (the stage's ctx.cl): every catchment's basins receive
    lake_runoff_depth_m of water scaled by the local rain relative to the
    mean; no lakes when params.lakes is off."""
    import functools

    from pipeline.errors import StageError
    from worldlib.flow import device as dev

    if not params.lakes:
        return no_lakes(land.shape)
    data, cell_area = land.data, land.cell_area
    code_raw = dev.d8(env, np.where(data, land.h, np.float32(0)), land.kind, land.dx)
    mean_rain = math.fsum(rain[data].tolist()) / int(data.sum())  # correctly rounded sum: tiling cannot change it
    mean_rain = mean_rain if mean_rain > 0 else 1.0
    lake_in = params.lake_runoff_depth_m * cell_area * rain / mean_rain
    lk = solve_lakes(land.h, land.kind, filled, code, code_raw, lake_in, cell_area,
                     functools.partial(dev.accumulate, env), functools.partial(dev.merge_sweep, env))
    if lk.stats["budget_relative_error"] > 1e-6:
        raise StageError(f"hydrology: lake volume budget off by {lk.stats['budget_relative_error']:.2e} (relative)")
    return LakeMaps(lk.depth, lk.level, lk.lake_id, lk.stats)
