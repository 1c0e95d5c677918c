"""The longest upstream flow path of every cell of a D8 tree (Hack's
mainstream length: the longest path from a head cell's centre down to the
cell), whole or in tiles, the same numbers either way.

A path's length is counted, not summed: a cardinal steps and b diagonal
steps, length a dx + b dx sqrt(2) evaluated once. Counts add exactly in
any order, so a path cut by tile borders has the length of the whole path;
a running float sum along it would round differently with every cut. Two
different counts never compare equal here: |a - a' + (b - b') sqrt(2)|
stays above 1e-5 while the counts stay below 10^4 (sqrt(2)'s continued
fraction), far above float64's rounding of lengths of that size.

Tiles follow Barnes (2017)'s three passes with (max, +) in place of (+, +):
1. tile_paths: the tile's longest paths with nothing flowing in, and per
   perimeter cell where its path leaves the tile and the counts to there;
2. solve_entries: over the perimeter cells of all tiles, the longest path
   arriving at each entry cell from other tiles (Kahn's order over exits);
3. finish_tile: the tile again, each entry cell starting from its arrival.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import reference as ref
from .reference import topological_levels
from .tiled_accum import (Perimeter, _local_receivers, _path_ends, exit_fronts, per_tile, perimeter_cells,
                          perimeter_graph, perimeter_position)

SQRT2 = math.sqrt(2.0)


def steps(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cardinal, diagonal) int64 counts of each cell's own step (0, 0 where it has no receiver)."""
    code = np.asarray(code).ravel()
    moves = code >= 0
    diag = moves & (np.clip(code, 0, 7) % 2 == 1)
    return (moves & ~diag).astype(np.int64), diag.astype(np.int64)


def length_m(a: np.ndarray, b: np.ndarray, dx: float) -> np.ndarray:
    """The length (m) of a cardinal and b diagonal steps of a dx grid."""
    return a * dx + b * (dx * SQRT2)


def _value(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a + b * SQRT2


def longest(rcv: np.ndarray, da: np.ndarray, db: np.ndarray, seed_a: np.ndarray | None = None,
            seed_b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Step counts (a, b) of the longest path down to each cell of the
    receiver forest rcv (flat, -1 none; da, db each cell's own step),
    starting from the seeds (0, 0 by default), sources first."""
    a = np.zeros(rcv.size, np.int64) if seed_a is None else np.array(seed_a, np.int64)
    b = np.zeros(rcv.size, np.int64) if seed_b is None else np.array(seed_b, np.int64)
    v = _value(a, b)
    for lev in topological_levels(rcv):
        t = rcv[lev]
        ok = t >= 0
        src, t = lev[ok], t[ok]
        if not t.size:
            continue
        ca, cb = a[src] + da[src], b[src] + db[src]
        cv = _value(ca, cb)
        np.maximum.at(v, t, cv)
        win = cv == v[t]  # the longest: equal values are equal counts
        a[t[win]], b[t[win]] = ca[win], cb[win]
    return a, b


def longest_whole(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """longest() on a whole world's D8 codes: (a, b) per cell, flat."""
    da, db = steps(code)
    return longest(ref.receivers(code), da, db)


@dataclass(frozen=True)
class TilePaths:
    """Pass 1's answer for one tile, per perimeter cell (perimeter_cells order)."""
    origin: tuple[int, int]
    shape: tuple[int, int]
    code: np.ndarray  # int8
    exit: np.ndarray  # int32 position of the perimeter cell where its path leaves the tile, -1: it ends inside
    a: np.ndarray  # int64 the tile-local longest path down to it (cardinal, diagonal steps)
    b: np.ndarray
    to_exit_a: np.ndarray  # int64 the steps from it to that exit cell
    to_exit_b: np.ndarray


def _local(code: np.ndarray):
    code = np.ascontiguousarray(code, np.int8)
    rl, leaves = _local_receivers(code)
    rl = rl.astype(np.int64)
    da, db = steps(code)
    return rl, leaves, da, db


def tile_paths(code: np.ndarray, origin: tuple[int, int]) -> TilePaths:
    """Pass 1 on one tile."""
    rl, leaves, da, db = _local(code)
    a, b = longest(rl, da, db)
    cells = perimeter_cells(*code.shape)
    end = _path_ends(rl)[cells]
    # steps from each cell to its path's in-tile end, by pointer jumping over exact integer counts
    nxt = np.where(rl >= 0, rl, np.arange(rl.size))
    sa, sb = np.where(rl >= 0, da, 0), np.where(rl >= 0, db, 0)
    while not np.array_equal(nxt[nxt], nxt):
        sa, sb, nxt = sa + sa[nxt], sb + sb[nxt], nxt[nxt]
    er, ec = np.divmod(end, code.shape[1])
    pos = perimeter_position(er, ec, *code.shape)
    return TilePaths((int(origin[0]), int(origin[1])), code.shape, np.ascontiguousarray(code, np.int8).ravel()[cells],
                     np.where(leaves.ravel()[end], pos, -1).astype(np.int32), a[cells], b[cells], sa[cells],
                     sb[cells])


def solve_entries(tiles: list[list[TilePaths]]) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Pass 2: per tile (row-major grid), the step counts (a, b) of the
    longest path arriving at each perimeter cell from other tiles (0, 0 where none)."""
    perims = [[Perimeter(t.origin, t.shape, t.code, t.exit, np.zeros(t.code.size, np.int64)) for t in row]
              for row in tiles]
    offsets, counts, _, exit_node, to = perimeter_graph(perims)
    flat = [t for row in tiles for t in row]
    a = np.concatenate([t.a for t in flat])
    b = np.concatenate([t.b for t in flat])
    ta_, tb_ = np.concatenate([t.to_exit_a for t in flat]), np.concatenate([t.to_exit_b for t in flat])
    da, db = steps(np.concatenate([t.code for t in flat]))
    v = _value(a, b)
    for f, x in exit_fronts(to, exit_node, "tiled longest paths"):
        y = to[f]
        ca, cb = a[f] + da[f] + ta_[y], b[f] + db[f] + tb_[y]
        cv = _value(ca, cb)
        np.maximum.at(v, x, cv)
        win = cv == v[x]
        a[x[win]], b[x[win]] = ca[win], cb[win]
    e = np.flatnonzero(to >= 0)
    ia, ib = np.zeros(a.size, np.int64), np.zeros(a.size, np.int64)
    iv = np.zeros(a.size)
    ca, cb = a[e] + da[e], b[e] + db[e]
    cv = _value(ca, cb)
    np.maximum.at(iv, to[e], cv)
    win = cv == iv[to[e]]
    ia[to[e][win]], ib[to[e][win]] = ca[win], cb[win]
    tx = len(tiles[0])
    return [list(zip(ra, rb)) for ra, rb in zip(per_tile(ia, offsets, counts, tx), per_tile(ib, offsets, counts, tx))]


def finish_tile(code: np.ndarray, entry_a: np.ndarray, entry_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pass 3: the tile's (a, b) per cell (flat), its perimeter cells starting from their arrivals."""
    rl, _, da, db = _local(code)
    sa, sb = np.zeros(rl.size, np.int64), np.zeros(rl.size, np.int64)
    cells = perimeter_cells(*code.shape)
    sa[cells], sb[cells] = entry_a, entry_b
    return longest(rl, da, db, sa, sb)


def tiled_longest(code: np.ndarray, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """The three passes one tile after another in one process (the tests'
    driver): longest_whole's counts, (rows, cols) each."""
    from .tiled_fill import tile_slices

    grid = tile_slices(code.shape, tile)
    parts = [[tile_paths(code[rs, cs], (rs.start, cs.start)) for rs, cs in row] for row in grid]
    entries = solve_entries(parts)
    a, b = np.empty(code.shape, np.int64), np.empty(code.shape, np.int64)
    for row, erow in zip(grid, entries):
        for (rs, cs), (ea, eb) in zip(row, erow):
            ta_, tb_ = finish_tile(code[rs, cs], ea, eb)
            shape = (rs.stop - rs.start, cs.stop - cs.start)
            a[rs, cs], b[rs, cs] = ta_.reshape(shape), tb_.reshape(shape)
    return a, b
