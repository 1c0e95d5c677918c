"""Exact depression filling of a world split into tiles (Barnes 2016,
"Parallel Priority-Flood depression filling for trillion cell digital
elevation models on desktops or clusters", Computers & Geosciences 96),
bitwise equal to the untiled plain Priority-Flood fill (device.fill with
eps=False, the hydrology stage's `filled`).

Three passes, the first and last per tile, each seeing one tile only:

1. fill_tile: fill the tile with its perimeter as an open boundary (the
   project's own fill), split it into watersheds, each a set of cells that
   reach one perimeter seed (or, label OCEAN, a world outlet: a map border
   cell or a cell next to no-data) without rising above their own filled
   height, and note the lowest spill height between adjacent watersheds.
2. solve_levels: on the small graph of every tile's watersheds, the
   perimeter crossings between tiles and the outlets, the minimax height at
   which each watershed is reached from the outlets (Barnes' level).
3. finish_tile: each cell's fill is max(its tile-local fill, its
   watershed's level).

Every value is a selection of the input heights (min and max only), so the
result is exact for any tiling. Why max(local, level) is the whole-world
fill: a cell's true fill W is at least its tile-local fill (the last stretch
of any outlet path lies in the tile and starts on its perimeter) and at
least its level (every cell on the optimal path has a tile-local fill <= W,
so every label change along it is a graph edge <= W); and W is at most
max(local, level), a path the labels' construction provides. That holds for
any labelling in which each cell reaches its label's seed without rising
above its own tile-local fill, which the one here (equal-height components
linked downhill) is.

The epsilon fill (device.fill eps=True, the stage's routing surface) does
not split this way: its increments count cells along the path, so crossing a
tile from one perimeter cell to another is not one spill height but a set of
(height, path length) trade-offs. It is exact too, given its perimeter's
final values (finish_tile_eps, eps_round_tile); tiled_fill_eps finds those by
rounds of neighbour perimeters, a number of rounds that depends on the
terrain instead of Barnes' fixed three passes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import reference as ref

OCEAN = 0  # the label of cells that drain to a world outlet inside the tile
NO_LABEL = -1  # no-data cells
PAIR_OFFSETS = ((0, 1), (1, 0), (1, 1), (1, -1))  # each 8-neighbour pair once


def tile_slices(shape: tuple[int, int], tile: int) -> list[list[tuple[slice, slice]]]:
    """The row-major grid of tile windows; edge tiles are smaller when the
    world is not a multiple of `tile`."""
    rows, cols = shape
    if tile < 1:
        raise ValueError(f"tile size {tile} below 1")
    return [[(slice(r, min(r + tile, rows)), slice(c, min(c + tile, cols))) for c in range(0, cols, tile)]
            for r in range(0, rows, tile)]


def tile_kind(h_halo: np.ndarray) -> np.ndarray:
    """ref.cell_kinds of a tile from its canonical heights with a one-cell
    halo (NaN beyond the world's border): equal to the whole world's kinds
    cut to the tile, since a kind looks at the 8 neighbours only."""
    return ref.cell_kinds(h_halo)[1:-1, 1:-1]


def eps_unsettled(z_halo: np.ndarray, kind: np.ndarray) -> int:
    """How many interior cells of a tile (z_halo: the surface with a
    one-cell halo, NaN beyond the world; kind its cells' kinds) stand less
    than one epsilon step (ref.step_up) above every neighbour. None: the
    surface is its own epsilon fill (each interior cell at or above a
    neighbour's step up, a fixed point, and the fill is the least one
    above the surface), so the rounds of an epsilon fill can be skipped."""
    rows, cols = kind.shape
    z = z_halo[1:-1, 1:-1]
    above = np.zeros((rows, cols), bool)
    for dr, dc in zip(ref.DR, ref.DC):
        n = z_halo[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols]
        with np.errstate(invalid="ignore"):
            above |= np.isfinite(n) & (z >= ref.step_up(n))
    return int(((kind == ref.INTERIOR) & ~above).sum())


def _pairs_where(test, *arrays) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (a, b) of the 8-adjacent cell pairs, each once, for
    which test(x_a, x_b, y_a, y_b, ...) holds on the arrays' shifted views."""
    rows, cols = arrays[0].shape
    a_out, b_out = [], []
    for dr, dc in PAIR_OFFSETS:
        va = (slice(0, rows - dr), slice(max(0, -dc), cols - max(0, dc)))
        vb = (slice(dr, rows), slice(max(0, dc), cols - max(0, -dc)))
        r, c = np.nonzero(test(*[v for x in arrays for v in (x[va], x[vb])]))
        a_out.append(r.astype(np.int64) * cols + c + max(0, -dc))
        b_out.append((r.astype(np.int64) + dr) * cols + c + max(0, dc))
    return np.concatenate(a_out), np.concatenate(b_out)


def min_per_pair(a: np.ndarray, b: np.ndarray, z: np.ndarray, n: int):
    """Undirected edges (a, b, z) reduced to one per node pair, the lowest z."""
    lo, hi = np.minimum(a, b).astype(np.int64), np.maximum(a, b).astype(np.int64)
    key = lo * n + hi
    order = np.argsort(key, kind="stable")
    key = key[order]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if key.size else np.zeros(0, np.int64)
    zmin = np.minimum.reduceat(z[order], start) if key.size else z[:0]
    return lo[order][start], hi[order][start], zmin


def _lower_neighbour(F: np.ndarray, data: np.ndarray) -> np.ndarray:
    """Flat index of each cell's lowest 8-neighbour (no-data never), -1
    where no neighbour is strictly lower."""
    rows, cols = F.shape
    Fp = np.pad(np.where(data, F, np.float32(np.inf)), 1, constant_values=np.inf)
    best = np.where(data, F, np.float32(-np.inf))
    arg = np.full(F.shape, -1, np.int64)
    for k, (dr, dc) in enumerate(zip(ref.DR, ref.DC)):
        nb = Fp[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols]
        lower = nb < best
        best = np.where(lower, nb, best)
        arg[lower] = k
    idx = np.arange(F.size, dtype=np.int64).reshape(F.shape)
    k = np.maximum(arg, 0)
    return np.where(arg >= 0, idx + ref.DR[k] * cols + ref.DC[k], -1).ravel()


@dataclass(frozen=True)
class Perimeter:
    """What the global pass needs of one tile: the tile-local fill and label
    of its four sides (corners in the rows), its label count and its
    internal spill edges (label a, label b, lowest spill height)."""
    top: tuple[np.ndarray, np.ndarray]  # (filled, label) of the first row
    bottom: tuple[np.ndarray, np.ndarray]
    left: tuple[np.ndarray, np.ndarray]  # first column
    right: tuple[np.ndarray, np.ndarray]
    n_labels: int  # labels 1..n_labels; 0 is OCEAN
    spill: tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class TileFill:
    """A tile after pass 1: its tile-local fill (NaN on no-data), watershed
    labels (OCEAN, 1..n_labels, NO_LABEL on no-data) and perimeter summary."""
    filled: np.ndarray
    labels: np.ndarray
    perimeter: Perimeter


def _watersheds(F: np.ndarray, seed: np.ndarray, outlet: np.ndarray, data: np.ndarray) -> tuple[np.ndarray, int]:
    """Labels such that each cell reaches its label's seed without rising
    above its own height in F (a filled surface whose every undrained flat
    touches a seed): 8-connected equal-height components, each linked to a
    strictly lower neighbour's component until one holding a seed."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = F.size
    d = data.ravel()
    A, B = _pairs_where(lambda fa, fb, da, db: da & db & (fa == fb), F, data)
    ncomp, comp = connected_components(coo_matrix((np.ones(A.size, np.int8), (A, B)), shape=(n, n)), directed=False)
    has_seed = np.zeros(ncomp, bool)
    has_seed[comp[seed.ravel() & d]] = True
    down = _lower_neighbour(F, data)
    src = np.flatnonzero((down >= 0) & ~has_seed[comp])
    parent = np.arange(ncomp)
    parent[comp[src]] = comp[down[src]]
    data_comp = np.zeros(ncomp, bool)
    data_comp[comp[d]] = True
    if ((parent == np.arange(ncomp)) & data_comp & ~has_seed).any():
        raise ValueError("tiled fill: a flat without a seed or a lower neighbour (the surface is not filled)")
    while True:  # pointer jumping: each component to the seed component it drains to
        up = parent[parent]
        if np.array_equal(up, parent):
            break
        parent = up
    ocean_root = np.zeros(ncomp, bool)
    ocean_root[comp[outlet.ravel()]] = True
    label_of = np.full(ncomp, NO_LABEL, np.int64)
    used = np.zeros(ncomp, bool)
    used[parent[comp[d]]] = True
    roots = np.flatnonzero(used)
    inland = roots[~ocean_root[roots]]
    label_of[inland] = np.arange(1, inland.size + 1)
    label_of[roots[ocean_root[roots]]] = OCEAN
    labels = np.where(d, label_of[parent[comp]], NO_LABEL).reshape(F.shape)
    return labels.astype(np.int32), int(inland.size)


def _spill_edges(F: np.ndarray, labels: np.ndarray, n_labels: int):
    """The lowest spill height max(F[a], F[b]) over 8-adjacent cells of
    two different labels, per label pair."""
    A, B = _pairs_where(lambda la, lb: (la != lb) & (la != NO_LABEL) & (lb != NO_LABEL), labels)
    z = np.maximum(F.ravel()[A], F.ravel()[B])
    return min_per_pair(labels.ravel()[A], labels.ravel()[B], z, n_labels + 1)


def _open_kind(kind: np.ndarray) -> np.ndarray:
    """The tile's kinds with its perimeter opened: every data cell on it an outlet."""
    k = kind.copy()
    ring = np.zeros(k.shape, bool)
    ring[0, :] = ring[-1, :] = ring[:, 0] = ring[:, -1] = True
    k[ring & (k == ref.INTERIOR)] = ref.EDGE
    return k


def _local_fill(env, h: np.ndarray, kind: np.ndarray, eps: bool) -> np.ndarray:
    """The project's fill of one tile: on the OpenCL device, or the numpy reference when env is None."""
    if env is None:
        return ref.priority_flood(h, eps, kind)
    from . import device as dev

    return dev.fill(env, h, kind, eps)


def fill_tile(h: np.ndarray, kind: np.ndarray, env=None) -> TileFill:
    """Pass 1 on one tile: canonical float32 heights (NaN on no-data) and
    the tile's kinds (tile_kind: world outlets, not the tile's perimeter)."""
    h = np.ascontiguousarray(h, np.float32)
    open_kind = _open_kind(kind)
    F = _local_fill(env, h, open_kind, eps=False)
    data = kind != ref.NODATA
    labels, n_labels = _watersheds(F, open_kind == ref.EDGE, kind == ref.EDGE, data)
    sides = [(F[s].copy(), labels[s].copy()) for s in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1])]
    perim = Perimeter(*sides, n_labels, _spill_edges(F, labels, n_labels))
    return TileFill(F, labels, perim)


def _crossings(za, la, oa: int, zb, lb, ob: int, offsets: tuple[int, ...]):
    """Spill edges between two facing tile sides (cell i of side a next to
    cell i + d of side b), in global label numbers (OCEAN stays 0)."""
    a_out, b_out, z_out = [], [], []
    for d in offsets:
        i = np.arange(max(0, -d), min(za.size, zb.size - d))
        if not i.size:
            continue
        x, y = la[i].astype(np.int64), lb[i + d].astype(np.int64)  # global numbers may pass 2^31
        ok = (x != NO_LABEL) & (y != NO_LABEL)
        a_out.append(np.where(x[ok] == OCEAN, 0, x[ok] + oa))
        b_out.append(np.where(y[ok] == OCEAN, 0, y[ok] + ob))
        z_out.append(np.maximum(za[i][ok], zb[i + d][ok]))
    if not a_out:
        return []
    return [(np.concatenate(a_out), np.concatenate(b_out), np.concatenate(z_out))]


def _all_edges(perims: list[list[Perimeter]], offsets: np.ndarray) -> list:
    """Every tile's internal spill edges and every crossing between 8-adjacent tiles."""
    ty, tx = len(perims), len(perims[0])
    edges = []
    for i in range(ty):
        for j in range(tx):
            p, o = perims[i][j], int(offsets[i, j])
            a, b, z = p.spill
            edges.append((np.where(a == OCEAN, 0, a + o), np.where(b == OCEAN, 0, b + o), z))
            if j + 1 < tx:
                q = perims[i][j + 1]
                edges += _crossings(*p.right, o, *q.left, int(offsets[i, j + 1]), (-1, 0, 1))
            if i + 1 < ty:
                q, oq = perims[i + 1][j], int(offsets[i + 1, j])
                edges += _crossings(*p.bottom, o, *q.top, oq, (-1, 0, 1))
                if j + 1 < tx:  # the corner below right
                    q, oq = perims[i + 1][j + 1], int(offsets[i + 1, j + 1])
                    edges += _crossings(p.bottom[0][-1:], p.bottom[1][-1:], o, q.top[0][:1], q.top[1][:1], oq, (0,))
                if j > 0:  # the corner below left
                    q, oq = perims[i + 1][j - 1], int(offsets[i + 1, j - 1])
                    edges += _crossings(p.bottom[0][:1], p.bottom[1][:1], o, q.top[0][-1:], q.top[1][-1:], oq, (0,))
    return edges


def _minimax_from_ocean(n: int, a: np.ndarray, b: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Each node's minimax height from node 0 (-inf there): the highest
    edge on its path through the minimum spanning tree. The tree is built on
    the ranks of z (exact, and never 0, which scipy reads as no edge)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    a, b, z = min_per_pair(a, b, z, n)
    values, rank = np.unique(z, return_inverse=True)
    tree = minimum_spanning_tree(coo_matrix((rank + 1.0, (a, b)), shape=(n, n)).tocsr()).tocoo()
    order, pred = breadth_first_order(tree.tocsr(), 0, directed=False, return_predecessors=True)
    if order.size != n:
        raise ValueError(f"tiled fill: {n - order.size} watersheds reach no outlet (broken invariant)")
    child = order[1:]
    tkey = np.minimum(tree.row, tree.col).astype(np.int64) * n + np.maximum(tree.row, tree.col)
    sort = np.argsort(tkey)
    ckey = np.minimum(pred[child], child).astype(np.int64) * n + np.maximum(pred[child], child)
    weight = tree.data[sort][np.searchsorted(tkey[sort], ckey)].astype(np.int64)
    best = np.zeros(n, np.int64)  # rank + 1 of the highest edge so far; 0 at the ocean
    for node, up, w in zip(child.tolist(), pred[child].tolist(), weight.tolist()):
        best[node] = max(best[up], w)
    level = np.full(n, -np.inf, np.float32)
    level[best > 0] = values[best[best > 0] - 1]
    return level


def solve_levels(perims: list[list[Perimeter]]) -> list[list[np.ndarray]]:
    """Pass 2 over the perimeter graph: per tile, the level of each of its
    labels (index = label; -inf at OCEAN)."""
    counts = np.array([[p.n_labels for p in row] for row in perims], np.int64)
    offsets = (np.cumsum(counts.ravel()) - counts.ravel()).reshape(counts.shape)
    n = int(counts.sum()) + 1
    edges = _all_edges(perims, offsets)
    a = np.concatenate([e[0] for e in edges]).astype(np.int64)
    b = np.concatenate([e[1] for e in edges]).astype(np.int64)
    z = np.concatenate([e[2] for e in edges]).astype(np.float32)
    level = _minimax_from_ocean(n, a, b, z)
    return [[np.concatenate([[np.float32(-np.inf)], level[o + 1:o + 1 + c]]).astype(np.float32)
             for o, c in zip(orow, crow)] for orow, crow in zip(offsets.tolist(), counts.tolist())]


def finish_tile(filled: np.ndarray, labels: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Pass 3 on one tile: max(tile-local fill, its label's level); NaN on no-data."""
    lv = level[np.maximum(labels, 0)]
    return np.where(labels == NO_LABEL, np.float32(np.nan), np.maximum(filled, lv)).astype(np.float32)


def finish_tile_eps(h: np.ndarray, kind: np.ndarray, perimeter_final: np.ndarray, env=None) -> np.ndarray:
    """The epsilon fill of one tile once the final values of its perimeter
    cells are known (an array of the tile's shape, read on the perimeter
    only): the perimeter becomes an outlet at those values. Exact, because
    an optimal path's last stretch inside the tile starts at a perimeter
    cell, and the path's value there can be replaced by that cell's own."""
    open_kind = _open_kind(kind)
    hp = np.array(h, np.float32)
    ring = (open_kind == ref.EDGE) & (kind == ref.INTERIOR)
    hp[ring] = perimeter_final[ring]
    return _local_fill(env, hp, open_kind, eps=True)


def eps_round_tile(h: np.ndarray, kind: np.ndarray, ring: np.ndarray, env=None) -> np.ndarray:
    """One round of the epsilon fill on one tile: `ring` is the tile's
    shape plus one cell each side, its outer ring the neighbours' current
    values (inf where not yet known, NaN on no-data and beyond the world);
    those cells are outlets at their values. Exact once they are final."""
    hh = np.array(ring, np.float32)
    hh[1:-1, 1:-1] = h
    kk = np.where(np.isnan(hh), ref.NODATA, ref.EDGE).astype(np.uint8)
    kk[1:-1, 1:-1] = kind
    return _local_fill(env, hh, kk, eps=True)[1:-1, 1:-1]


def tiled_fill_eps(h: np.ndarray, tile: int, env=None, max_rounds: int = 10_000) -> tuple[np.ndarray, int]:
    """The epsilon fill (device.fill eps=True) by rounds of eps_round_tile,
    each tile reading its neighbours' perimeters of the round before, until
    no perimeter changes (values only fall, to the unique answer). Returns
    the fill and the rounds run: about the most tiles an optimal path
    crosses, not a constant as in the plain fill's three passes."""
    h = ref.canonical(h)
    padded = np.pad(h, 1, constant_values=np.nan)
    grid = tile_slices(h.shape, tile)
    kinds = [[tile_kind(padded[rs.start:rs.stop + 2, cs.start:cs.stop + 2]) for rs, cs in row] for row in grid]
    est = np.pad(np.where(np.isnan(h), np.float32(np.nan), np.float32(np.inf)), 1, constant_values=np.nan)
    out = np.empty(h.shape, np.float32)
    active = np.ones((len(grid), len(grid[0])), bool)
    for rounds in range(1, max_rounds + 1):
        new = est.copy()
        for i, row in enumerate(grid):
            for j, (rs, cs) in enumerate(row):
                if active[i, j]:
                    ring = est[rs.start:rs.stop + 2, cs.start:cs.stop + 2]
                    out[rs, cs] = eps_round_tile(h[rs, cs], kinds[i][j], ring, env)
                    new[rs.start + 1:rs.stop + 1, cs.start + 1:cs.stop + 1] = out[rs, cs]
        changed = ~((new == est) | (np.isnan(new) & np.isnan(est)))
        if not changed.any():
            return out, rounds
        active = _tiles_near(changed[1:-1, 1:-1], grid)
        est = new
    raise ValueError(f"tiled epsilon fill: no fixed point after {max_rounds} rounds")


def _tiles_near(changed: np.ndarray, grid) -> np.ndarray:
    """Tiles with a changed cell in themselves or an 8-neighbour tile."""
    hit = np.array([[changed[rs, cs].any() for rs, cs in row] for row in grid])
    near = np.pad(hit, 1)
    out = np.zeros_like(hit)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            out |= near[1 + dr:1 + dr + hit.shape[0], 1 + dc:1 + dc + hit.shape[1]]
    return out


def tiled_fill(h: np.ndarray, tile: int, env=None) -> np.ndarray:
    """The three passes one tile after another in one process (the tests'
    and bench's driver): canonical heights in, the plain fill out. It keeps
    every tile's pass-1 result until pass 3, as Barnes' "retain" strategy
    does; only the perimeters meet in pass 2."""
    h = ref.canonical(h)
    padded = np.pad(h, 1, constant_values=np.nan)
    grid = tile_slices(h.shape, tile)
    tiles = []
    for row in grid:
        tiles.append([])
        for rs, cs in row:
            halo = padded[rs.start:rs.stop + 2, cs.start:cs.stop + 2]
            tiles[-1].append(fill_tile(h[rs, cs], tile_kind(halo), env))
    levels = solve_levels([[t.perimeter for t in row] for row in tiles])
    out = np.empty(h.shape, np.float32)
    for row, trow, lrow in zip(grid, tiles, levels):
        for (rs, cs), t, lv in zip(row, trow, lrow):
            out[rs, cs] = finish_tile(t.filled, t.labels, lv)
    return out
