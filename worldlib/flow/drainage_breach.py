"""Complete breaching, the same bit for bit on a world split into tiles.

Complete breaching (Lindsay 2016) lowers the cells on a path out of each
pit (an interior cell with no strictly lower neighbour), one float32 step
per cell, until the path descends: no cell is raised and every cell
drains. reference.breach takes the path the Priority-Flood of the whole
map reached the pit by, an order of one global heap that no tiling
reproduces. Here the paths (carve_codes) are two local parts of it:

- on the depression cells (filled above the terrain), the flood from the
  rims (flood_codes): a depression's cells are flooded from its outlet,
  lowest ground first, as in Lindsay's heap, so a carve follows the
  valleys inside it and crosses its inner ridges at their saddles. The
  depression cells are gathered from the tiles and flooded on their own,
  like the lakes';
- elsewhere, the drainage of the epsilon-filled surface (its D8 codes).

With step(x) one float32 step toward -inf (ordered: the denormals left out):

    B(c)       = min(z(c), min over carving u with path to c of step(B(u)))
    carving(c) = pit(c) or B(c) < z(c)

A carve stops at the first cell already below it, as Lindsay's does. The
breached surface drains everywhere: a pit or a lowered cell is above the
next cell on its path, any other cell above its own lower neighbour, and
reference.d8 on it finds no pit. Its steps are float32 ulps, finer than the
epsilon fill's below 1 m (reference.step_up), so the hydrology
epsilon-fills it after, as it did Lindsay's.

On tiles (the three passes of tiled_accum, Barnes 2017): heights as ordered
integers (a step is -1), a carve that enters a tile at cell e with value v
lowers the k-th cell of e's in-tile path iff v - k < z_k for every cell up
to it, so it crosses the tile iff v < T(e) = min_k (z_k + k), and leaves it
at its exit d(e) + 1 steps lower. Where carves meet, the cell takes the
lowest, and a carve that stops there goes on only as a higher one would:
the minimum over carves, taken in any order (no float arithmetic), is the
untiled B.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from . import reference as ref
from .tiled_accum import (Perimeter, _local_receivers, exit_fronts, per_tile, perimeter_cells, perimeter_graph,
                          perimeter_position)

TINY_BITS = 0x00800000  # the bits of the least normal float32, 2^-126
NONE = np.iinfo(np.int64).max  # no carve arrives (an ordered height above every float32)


def ordered(z: np.ndarray) -> np.ndarray:
    """Canonical float32 heights (reference.canonical: no denormals, one
    zero) as int64 in their order, adjacent floats one apart, the denormals
    left out: a carve through 0 steps to -2^-126, as no device flushes it
    (NaN and the infinities above and below every height)."""
    bits = np.ascontiguousarray(z, np.float32).view(np.int32).astype(np.int64)
    magnitude = bits & 0x7FFFFFFF
    o = np.where(magnitude == 0, 0, magnitude - (TINY_BITS - 1))
    return np.where(bits >= 0, o, -o)


def from_ordered(o: np.ndarray) -> np.ndarray:
    """The inverse of ordered."""
    o = np.asarray(o, np.int64)
    m = np.abs(o)
    bits = np.where(m == 0, 0, m + (TINY_BITS - 1)) | np.where(o < 0, 0x80000000, 0)
    return bits.astype(np.uint32).view(np.float32)


def carve(z_ord: np.ndarray, receiver: np.ndarray, pit: np.ndarray,
          inflow: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """B (ordered) and carving of flat cells (module docstring): z_ord the
    ordered heights, receiver each cell's flat receiver (-1: none in the
    array), pit the pits, inflow the ordered value of carves arriving at a
    cell from outside the array (NONE: none). Carves advance a cell per
    round from the cells whose B went down (a Bellman-Ford on a forest):
    as many rounds as the longest carve, each on its front only."""
    incoming = np.full(z_ord.size, NONE, np.int64) if inflow is None else np.array(inflow, np.int64)
    b = np.minimum(z_ord, incoming)
    carving = pit | (incoming < z_ord)
    front = np.flatnonzero(carving & (receiver >= 0))
    while front.size:
        tgt, val = receiver[front], b[front] - 1
        order = np.lexsort((val, tgt))
        tgt, val = tgt[order], val[order]
        first = np.r_[True, tgt[1:] != tgt[:-1]]
        tgt, val = tgt[first], val[first]  # the lowest carve arriving at each cell
        lower = val < incoming[tgt]
        tgt, val = tgt[lower], val[lower]
        incoming[tgt] = val
        before = b[tgt]
        b[tgt] = np.minimum(z_ord[tgt], val)
        went_down = b[tgt] < before  # only then is the cell carving (val < z) and its own carve lower
        carving[tgt[went_down]] = True
        nxt = tgt[went_down]
        front = nxt[receiver[nxt] >= 0]
    return b, carving


def _pits_of_halo(halo: np.ndarray, kind: np.ndarray) -> np.ndarray:
    """reference.pits of the cells inside a one-cell halo (their kinds: kind)."""
    kk = np.full(halo.shape, ref.EDGE, np.uint8)
    kk[1:-1, 1:-1] = kind
    return ref.pits(halo, kk)[1:-1, 1:-1]


def depression_sets(h: np.ndarray, filled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The depression cells (filled above the terrain) and the cells off
    them next to one (their rims, where a flood from outside enters), of
    arrays that may carry a one-cell halo the caller cuts off."""
    with np.errstate(invalid="ignore"):
        inside = filled > h
    rows, cols = h.shape
    near = np.zeros((rows, cols), bool)
    padded = np.pad(inside, 1)
    for dr, dc in zip(ref.DR, ref.DC):
        near |= padded[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols]
    return inside, near & ~inside & np.isfinite(h)


def flood_codes(cells: np.ndarray, key: np.ndarray, inside: np.ndarray, cols: int, n_cells: int) -> np.ndarray:
    """The D8 code (toward the cell it was flooded from) of every depression
    cell among `cells` (flat indices, ascending; inside: a depression cell,
    else a rim cell): Priority-Flood from the rims, the lowest key first,
    ties by flat index. A depression cell's key is its height, as in
    Lindsay's breaching (a depression fills from its outlet before any
    higher rim opens, its paths along its lowest ground); a rim's is its
    epsilon-filled height, so every depression is entered from the rim its
    epsilon-filled cells drain to, whose own path leads away, never back
    (the lowest epsilon-filled rim is below every cell of the depression,
    which the epsilon fill raised above a neighbour). int8, -1 at the rim
    cells. Serial: one heap over the gathered cells."""
    nbr = ref.sparse_neighbours(cells, cols, n_cells)
    zl = np.asarray(key, np.float64).tolist()
    heap = [(zl[i], i) for i in np.flatnonzero(~inside).tolist()]  # cells ascend: position order is flat order
    heapq.heapify(heap)
    done = bytearray((~np.asarray(inside, bool)).astype(np.uint8).tobytes())
    back = np.full(len(zl), -1, np.int64)
    while heap:
        _, i = heapq.heappop(heap)
        for j in nbr[i].tolist():
            if j >= 0 and not done[j]:
                done[j] = 1
                back[j] = i
                heapq.heappush(heap, (zl[j], j))
    if not all(done):
        raise ValueError("breaching: a depression cell is not reached from any rim")
    code = np.full(len(zl), -1, np.int8)
    d = np.flatnonzero(back >= 0)
    r, c = np.divmod(np.asarray(cells, np.int64)[d], cols)
    br, bc = np.divmod(np.asarray(cells, np.int64)[back[d]], cols)
    lookup = np.full((3, 3), -1, np.int8)
    lookup[ref.DR + 1, ref.DC + 1] = np.arange(8)
    code[d] = lookup[br - r + 1, bc - c + 1]
    return code


def carve_codes(h: np.ndarray, filled: np.ndarray, routing: np.ndarray, code: np.ndarray) -> np.ndarray:
    """The paths the carves take: flood_codes on the depression cells,
    elsewhere code, the D8 codes of routing (h's epsilon-filled surface).
    Whole arrays."""
    inside, rim = depression_sets(h, filled)
    cells = np.flatnonzero(inside | rim)
    if not cells.size:
        return code
    out = np.array(code, np.int8)
    d = inside.ravel()[cells]
    key = np.where(d, h.ravel()[cells], routing.ravel()[cells])
    got = flood_codes(cells, key, d, h.shape[1], h.size)
    out.ravel()[cells[got >= 0]] = got[got >= 0]
    return out


def breach(h: np.ndarray, kind: np.ndarray, code: np.ndarray) -> np.ndarray:
    """The breached surface of canonical heights h (NaN on no-data; their
    reference.cell_kinds kind) along code, carve_codes' paths:
    float32, NaN where h is. The world as one tile, nothing arriving."""
    b = _carve_halo(np.pad(h, 1, constant_values=np.nan), kind, code)[0]
    return from_ordered(b).reshape(h.shape)


@dataclass(frozen=True)
class CarvePerimeter:
    """Pass 1's answer for one tile: its perimeter cells' codes and exits
    (perimeter.local_sum: the ordered value the exit's own carves send out
    of the tile, NONE where it does not carve), and per perimeter cell the
    largest ordered value a carve entering there can have and still cross
    the tile (threshold), and its path's steps to the exit (steps)."""
    perimeter: Perimeter
    threshold: np.ndarray  # int64
    steps: np.ndarray  # int64


def _carve_halo(halo: np.ndarray, kind: np.ndarray, code: np.ndarray, inflow: np.ndarray | None = None):
    """carve on a tile: its canonical heights with a one-cell halo (NaN
    beyond the world; the halo only says which cells are pits), its kinds
    and carve_codes' paths; inflow as carve's, at the tile's cells. Returns
    B and carving, the heights (ordered, flat), the in-tile receivers and
    the cells whose path leaves the tile."""
    rl, leaves = _local_receivers(np.ascontiguousarray(code, np.int8))
    rl = rl.astype(np.int64)
    z = ordered(np.where(kind == ref.NODATA, np.float32(np.nan), halo[1:-1, 1:-1])).ravel()
    b, carving = carve(z, rl, _pits_of_halo(halo, kind).ravel(), inflow)
    return b, carving, z, rl, leaves


def carve_tile(halo: np.ndarray, kind: np.ndarray, code: np.ndarray, origin: tuple[int, int]) -> CarvePerimeter:
    """Pass 1 on one tile: its canonical heights with a one-cell halo (NaN
    beyond the world), its kinds and carve_codes' paths, where it lies.
    Thresholds and steps by pointer jumping over (min, +) pairs: a cell's
    (T, d) over its path up to the cell nxt, then to nxt's."""
    b, carving, z, rl, leaves = _carve_halo(halo, kind, code)
    ends = rl < 0
    nxt = np.where(ends, np.arange(rl.size), rl)
    thr, d = z.copy(), np.where(ends, 0, 1).astype(np.int64)
    while True:
        thr, d = np.minimum(thr, thr[nxt] + d), d + d[nxt]
        jump = nxt[nxt]
        if np.array_equal(jump, nxt):
            break
        nxt = jump
    cells = perimeter_cells(*code.shape)
    end = nxt[cells]
    leaving = leaves.ravel()[end]
    er, ec = np.divmod(end, code.shape[1])
    pos = perimeter_position(er, ec, *code.shape)
    out = np.where(carving[cells], b[cells] - 1, NONE)
    per = Perimeter((int(origin[0]), int(origin[1])), code.shape, np.ascontiguousarray(code, np.int8).ravel()[cells],
                    np.where(leaving, pos, -1).astype(np.int32), out.astype(np.int64))
    return CarvePerimeter(per, thr[cells], d[cells])


def solve_carves(tiles: list[list[CarvePerimeter]]) -> list[list[np.ndarray]]:
    """Pass 2 over the perimeter graph: per tile (row-major grid), the
    ordered value of the carves arriving at each perimeter cell from other
    tiles (NONE where none does)."""
    offsets, counts, out, exit_node, to = perimeter_graph([[t.perimeter for t in row] for row in tiles])
    flat = [t for row in tiles for t in row]
    thr = np.concatenate([t.threshold for t in flat])
    steps = np.concatenate([t.steps for t in flat])
    for f, x in exit_fronts(to, exit_node, "tiled breaching"):
        v, y = out[f], to[f]
        crosses = (v != NONE) & (v < thr[y])
        np.minimum.at(out, x[crosses], v[crosses] - steps[y[crosses]] - 1)
    e = np.flatnonzero(to >= 0)
    inflow = np.full(out.size, NONE, np.int64)
    np.minimum.at(inflow, to[e], out[e])
    return per_tile(inflow, offsets, counts, len(tiles[0]))


def finish_tile(halo: np.ndarray, kind: np.ndarray, code: np.ndarray, inflow: np.ndarray) -> np.ndarray:
    """Pass 3 on one tile: its breached surface (float32), the carves
    arriving at its perimeter cells (pass 2) carving on in it."""
    arriving = np.full(code.size, NONE, np.int64)
    arriving[perimeter_cells(*code.shape)] = inflow
    b = _carve_halo(halo, kind, code, arriving)[0]
    return from_ordered(b).reshape(code.shape)


def tiled_breach(h: np.ndarray, code: np.ndarray, tile: int) -> np.ndarray:
    """The three passes one tile after another in one process (the tests'
    driver): breach's result, tile by tile; only the perimeters meet."""
    from .tiled_accum import _halo
    from .tiled_fill import tile_kind, tile_slices

    grid = tile_slices(h.shape, tile)

    def parts(rs, cs):
        halo = _halo(h, rs, cs)
        return halo, tile_kind(halo), code[rs, cs]

    firsts = [[carve_tile(*parts(rs, cs), (rs.start, cs.start)) for rs, cs in row] for row in grid]
    out = np.empty(h.shape, np.float32)
    for row, irow in zip(grid, solve_carves(firsts)):
        for (rs, cs), arriving in zip(row, irow):
            out[rs, cs] = finish_tile(*parts(rs, cs), arriving)
    return out
