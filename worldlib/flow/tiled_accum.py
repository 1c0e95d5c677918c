"""Exact D8 flow directions and D8 accumulation of a world split into tiles
(Barnes 2017, "Parallel non-divergent flow accumulation for trillion cell
digital elevation models on desktops or clusters", Environmental Modelling &
Software 92), bitwise equal to device.d8 and device.accumulate on the whole
world, for cell counts (uint32) and for integer weights (int64).

Directions are local: tile_d8 sees the tile's routing surface with a
one-cell halo. Accumulation has three passes, the first and last per tile:

1. accumulate_tile: the tile's own accumulation, flow from other tiles
   taken as zero; for each perimeter cell, where its path leaves the tile
   (Barnes' link: the perimeter cell whose code points out, or none when
   the path ends inside) and its local sum. Output grows with the perimeter.
2. solve_inflow: over the perimeter cells of all tiles only, each exit's
   total (its local sum plus the inflow of the entries whose paths reach
   it), passed on to the entry cell of the neighbouring tile it flows into;
   the result is the inflow each entry cell receives from other tiles.
3. finish_tile: the tile's accumulation again, each entry cell weighing its
   own weight plus its inflow.

The sums are integers, so no order matters and the result is the untiled
one bit for bit: a cell's accumulation is the sum of the weights upstream,
those in its tile reached inside the tile (pass 3's own weights) and those
in other tiles arriving through the entry cells on its path (the inflows).

Fixed-point weights (device.quantize) need the world's total weight for
their scale; exact_sum gives each tile's sum as an exact integer, so the
world's total is exact and independent of the tiling (math.fsum's value,
the correctly rounded sum), and quantize_scale finishes the scale with
per-tile integer sums (tile_quantized_sums).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import reference as ref
from .device import first_scale
from .tiled_fill import tile_kind, tile_slices

EXACT_UNIT = 1126  # exact_sum counts units of 2^-1126: the subnormal 2^-1074 is a 53-bit mantissa times 2^-1126
Q_LIMIT = 2 ** 62  # device.quantize's bound on the total of the integer weights


def tile_d8(z_halo: np.ndarray, kind: np.ndarray, dx: float, env=None) -> np.ndarray:
    """D8 codes of one tile from its routing surface with a one-cell halo
    (NaN beyond the world) and its kinds (tiled_fill.tile_kind): a code
    reads the cell's 8 neighbours only, in the same float32 operations, so
    it is the whole world's code cut to the tile."""
    kk = np.full(z_halo.shape, ref.EDGE, np.uint8)  # halo cells' own codes are thrown away
    kk[1:-1, 1:-1] = kind
    z = np.ascontiguousarray(z_halo, np.float32)
    if env is None:
        return ref.d8(z, kk, dx)[1:-1, 1:-1]
    from . import device as dev

    return np.ascontiguousarray(dev.d8(env, z, kk, dx)[1:-1, 1:-1])


def perimeter_cells(nr: int, nc: int) -> np.ndarray:
    """Tile-local flat indices (row * nc + col) of the perimeter cells, in
    raster order (tiles of 1 or 2 rows or columns: every cell)."""
    ring = np.zeros((nr, nc), bool)
    ring[0, :] = ring[-1, :] = ring[:, 0] = ring[:, -1] = True
    return np.flatnonzero(ring)


def perimeter_position(lr, lc, nr, nc):
    """The inverse of perimeter_cells, vectorised over cells of tiles of
    different shapes: the position of local cell (lr, lc) in its tile's list."""
    lr, lc, nr, nc = (np.asarray(x, np.int64) for x in (lr, lc, nr, nc))
    full = (nr <= 2) | (nc <= 2)
    middle = nc + 2 * (lr - 1) + (lc == nc - 1)
    ring = np.where(lr == 0, lc, np.where(lr == nr - 1, nc + 2 * (nr - 2) + lc, middle))
    return np.where(full, lr * nc + lc, ring)


def _local_receivers(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-tile flat receiver of each cell (-1 where the path ends or leaves)
    and the mask of cells whose receiver is outside the tile."""
    rows, cols = code.shape
    it = np.int32 if code.size < 2 ** 31 else np.int64  # half the memory traffic of int64 on a tile
    k = np.clip(code, 0, 7)
    rr = np.arange(rows, dtype=it)[:, None] + ref.DR.astype(it)[k]
    cc = np.arange(cols, dtype=it)[None, :] + ref.DC.astype(it)[k]
    moves = code >= 0
    inside = moves & (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
    return np.where(inside, rr * it(cols) + cc, it(-1)).ravel(), moves & ~inside


def _open_code(code: np.ndarray, leaves: np.ndarray) -> np.ndarray:
    """The tile's codes with every move out of the tile made an outlet."""
    return np.where(leaves, np.int8(ref.OUTLET), code).astype(np.int8)


def _path_ends(rl: np.ndarray) -> np.ndarray:
    """The last in-tile cell of each cell's path, by pointer jumping
    (log2 of the longest in-tile path rounds of one gather each)."""
    nxt = np.where(rl >= 0, rl, np.arange(rl.size, dtype=rl.dtype))
    while True:
        jump = nxt[nxt]
        if np.array_equal(jump, nxt):
            return nxt
        nxt = jump


def path_ends(code: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For tile-local flat `cells` of a tile's codes: the last in-tile cell
    of each one's path (tile-local flat) and whether the path leaves the tile there."""
    rl, leaves = _local_receivers(np.ascontiguousarray(code, np.int8))
    end = _path_ends(rl)[np.asarray(cells, np.int64)].astype(np.int64)
    return end, leaves.ravel()[end]


def _accumulate(code: np.ndarray, weights: np.ndarray | None, env) -> np.ndarray:
    """The project's accumulation of one array: the device's, or the numpy
    reference when env is None (the same integers; counts as uint32)."""
    if env is not None:
        from . import device as dev

        return dev.accumulate(env, code, weights)
    out = ref.accumulate(code, weights)
    return out.astype(np.uint32) if weights is None else out


@dataclass(frozen=True)
class Perimeter:
    """What the global pass needs of one tile: where it lies, and per
    perimeter cell (perimeter_cells order) its code, the position of the
    perimeter cell where its path leaves the tile (-1: it ends inside) and
    its tile-local accumulation."""
    origin: tuple[int, int]  # world row and column of the tile's first cell
    shape: tuple[int, int]
    code: np.ndarray  # int8
    exit: np.ndarray  # int32
    local_sum: np.ndarray  # int64


def accumulate_tile(code: np.ndarray, origin: tuple[int, int], weights: np.ndarray | None = None,
                    env=None) -> Perimeter:
    """Pass 1 on one tile: its codes (and integer weights, None for cell
    counts), where it lies in the world. The tile-local accumulation is not
    kept: pass 3 recomputes it (Barnes' evict strategy, memory per tile only
    while it runs)."""
    code = np.ascontiguousarray(code, np.int8)
    rl, leaves = _local_receivers(code)
    local = _accumulate(_open_code(code, leaves), weights, env)
    cells = perimeter_cells(*code.shape)
    end = _path_ends(rl)[cells]
    leaving = leaves.ravel()[end]
    er, ec = np.divmod(end, code.shape[1])
    pos = perimeter_position(er, ec, *code.shape)
    return Perimeter((int(origin[0]), int(origin[1])), code.shape, code.ravel()[cells].copy(),
                     np.where(leaving, pos, -1).astype(np.int32), local.ravel()[cells].astype(np.int64))


def _tile_of(starts: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Index of the tile row (or column) holding world row (or column) x."""
    return np.searchsorted(starts, x, side="right") - 1


def perimeter_graph(perims: list[list[Perimeter]]):
    """Every tile's perimeter cells as nodes of one graph: offsets of the
    tiles' node numbers, each node's local sum, its exit node (-1) and, for
    exit nodes, the node of the entry cell its code points to (-1)."""
    flat = [p for row in perims for p in row]
    counts = np.array([p.code.size for p in flat], np.int64)
    offsets = np.cumsum(counts) - counts
    n = int(counts.sum())
    local = np.concatenate([p.local_sum for p in flat])
    exit_node = np.concatenate([np.where(p.exit >= 0, p.exit + o, -1) for p, o in zip(flat, offsets)])
    row_starts = np.array([row[0].origin[0] for row in perims], np.int64)
    col_starts = np.array([p.origin[1] for p in perims[0]], np.int64)
    shapes = np.array([p.shape for p in flat], np.int64)
    origins = np.array([p.origin for p in flat], np.int64)
    tile_of_node = np.repeat(np.arange(len(flat)), counts)
    is_exit = exit_node == np.arange(n)
    e = np.flatnonzero(is_exit)
    t = tile_of_node[e]
    cells = np.concatenate([perimeter_cells(*p.shape) for p in flat])[e]
    lr, lc = np.divmod(cells, shapes[t, 1])
    k = np.concatenate([p.code for p in flat])[e].astype(np.int64)
    yr, yc = origins[t, 0] + lr + ref.DR[k], origins[t, 1] + lc + ref.DC[k]
    ti, tj = _tile_of(row_starts, yr), _tile_of(col_starts, yc)
    u = ti * len(col_starts) + tj
    pos = perimeter_position(yr - origins[u, 0], yc - origins[u, 1], shapes[u, 0], shapes[u, 1])
    to = np.full(n, -1, np.int64)
    to[e] = offsets[u] + pos
    return offsets, counts, local, exit_node, to


def exit_fronts(to: np.ndarray, exit_node: np.ndarray, what: str):
    """Kahn's order over the exit nodes of perimeter_graph: yields fronts
    (exits f, and the exit nxt each one's water reaches next) whose every
    upstream exit came in an earlier front, so a caller that passes each
    exit's total on to nxt before the next front sees final totals only.
    The number of fronts is the most tiles one path crosses."""
    e = np.flatnonzero(to >= 0)
    nxt = np.full(to.size, -1, np.int64)
    nxt[e] = exit_node[to[e]]  # the exit the water of exit e reaches next (-1: its path ends there)
    has = e[nxt[e] >= 0]
    indeg = np.bincount(nxt[has], minlength=to.size)
    front = e[indeg[e] == 0]
    done = 0
    while front.size:
        done += front.size
        f = front[nxt[front] >= 0]
        yield f, nxt[f]
        np.subtract.at(indeg, nxt[f], 1)
        front = np.unique(nxt[f][indeg[nxt[f]] == 0])
    if done != e.size:
        raise ValueError(f"{what}: the receiver graph has a cycle across tiles")


def per_tile(values: np.ndarray, offsets: np.ndarray, counts: np.ndarray, tiles_per_row: int) -> list[list[np.ndarray]]:
    """Per-node values of perimeter_graph cut back into the grid of tiles."""
    out = [values[o:o + c] for o, c in zip(offsets.tolist(), counts.tolist())]
    return [out[i:i + tiles_per_row] for i in range(0, len(out), tiles_per_row)]


def solve_inflow(perims: list[list[Perimeter]]) -> list[list[np.ndarray]]:
    """Pass 2 over the perimeter graph: per tile (the grid of tiles, row
    major, as tiled_fill.tile_slices), the int64 inflow from other tiles at
    each of its perimeter cells (0 where none enters), in exit_fronts' order."""
    offsets, counts, total, exit_node, to = perimeter_graph(perims)
    for f, nxt in exit_fronts(to, exit_node, "tiled accumulation"):
        np.add.at(total, nxt, total[f])
    e = np.flatnonzero(to >= 0)
    inflow = np.zeros(total.size, np.int64)
    np.add.at(inflow, to[e], total[e])
    return per_tile(inflow, offsets, counts, len(perims[0]))


def finish_tile(code: np.ndarray, inflow: np.ndarray, weights: np.ndarray | None = None, env=None) -> np.ndarray:
    """Pass 3 on one tile: its accumulation with each perimeter cell
    weighing its own weight plus its inflow (pass 2); uint32 counts when
    weights is None (modulo 2^32 like the untiled kernel), else int64."""
    code = np.ascontiguousarray(code, np.int8)
    _, leaves = _local_receivers(code)
    w = (code != ref.NODATA_CODE).astype(np.int64) if weights is None else np.array(weights, np.int64)
    if not inflow.any():
        return _accumulate(_open_code(code, leaves), weights, env)
    w.ravel()[perimeter_cells(*code.shape)] += inflow
    out = _accumulate(_open_code(code, leaves), w, env)
    return out.astype(np.uint32) if weights is None else out


def _halo(a: np.ndarray, rs: slice, cs: slice) -> np.ndarray:
    """Tile (rs, cs) of the world a, padded by one NaN cell beyond the world, with its one-cell halo."""
    rows, cols = a.shape
    r0, r1, c0, c1 = rs.start - 1, rs.stop + 1, cs.start - 1, cs.stop + 1
    out = np.full((r1 - r0, c1 - c0), np.nan, np.float32)
    out[max(0, -r0):out.shape[0] - max(0, r1 - rows), max(0, -c0):out.shape[1] - max(0, c1 - cols)] = \
        a[max(r0, 0):min(r1, rows), max(c0, 0):min(c1, cols)]
    return out


def tiled_d8(z: np.ndarray, dx: float, tile: int, env=None) -> np.ndarray:
    """D8 codes of the routing surface z (NaN on no-data), one tile at a
    time, kinds from each tile's own halo (the tests' and bench's driver)."""
    out = np.empty(z.shape, np.int8)
    for row in tile_slices(z.shape, tile):
        for rs, cs in row:
            zh = _halo(z, rs, cs)
            out[rs, cs] = tile_d8(zh, tile_kind(zh), dx, env)
    return out


def tiled_accumulate(code: np.ndarray, tile: int, weights: np.ndarray | None = None, env=None) -> np.ndarray:
    """The three passes one tile after another in one process (the tests'
    and bench's driver): device.accumulate's result, tile by tile; only the
    perimeters meet in pass 2."""
    grid = tile_slices(code.shape, tile)
    wt = (lambda rs, cs: None) if weights is None else (lambda rs, cs: weights[rs, cs])
    perims = [[accumulate_tile(code[rs, cs], (rs.start, cs.start), wt(rs, cs), env) for rs, cs in row]
              for row in grid]
    inflow = solve_inflow(perims)
    out = np.empty(code.shape, np.uint32 if weights is None else np.int64)
    for row, irow in zip(grid, inflow):
        for (rs, cs), fin in zip(row, irow):
            out[rs, cs] = finish_tile(code[rs, cs], fin, wt(rs, cs), env)
    return out


# --------------------------------------------------------------------------- fixed-point weights across tiles


def _clean(weights: np.ndarray) -> np.ndarray:
    """device.quantize's cleaning: float64, NaN and +inf 0, negatives 0."""
    w = np.nan_to_num(np.asarray(weights, np.float64), nan=0.0, posinf=0.0)
    return np.maximum(w, 0.0)


def exact_sum(weights: np.ndarray) -> int:
    """A tile's weights (as quantize cleans them) summed exactly: an integer
    count of 2^-EXACT_UNIT. Integers add in any order, so the world's sum
    is the tiles' sum whatever the tiling."""
    m, e = np.frexp(_clean(weights).ravel())
    mant = (m * 2.0 ** 53).astype(np.int64)  # exact: 53-bit mantissas
    e = e.astype(np.int64) - 53 + EXACT_UNIT
    total = 0
    for ex in np.unique(e[mant != 0]).tolist():
        sel = mant[e == ex]
        hi, lo = int((sel >> 26).sum()), int((sel & (2 ** 26 - 1)).sum())  # no int64 overflow below 2^37 cells
        total += ((hi << 26) + lo) << ex
    return total


def exact_total(sums: list[int]) -> float:
    """The world's total weight from its tiles' exact_sum, correctly
    rounded to float64 (Python's int division rounds correctly): math.fsum
    of every weight."""
    return sum(sums) / (1 << EXACT_UNIT) if sum(sums) else 0.0


def tile_quantized_sums(weights: np.ndarray, scale: float) -> tuple[int, int]:
    """A tile's integer weight sums at scale and at scale / 2: device.quantize
    halves its scale at most once (the rounding adds at most half a unit
    per cell, far below 2^61), so these settle the scale in one pass."""
    w = _clean(weights)
    return tuple(int(np.rint(w * s).astype(np.int64).sum()) for s in (scale, scale / 2))


def quantize_scale(total: float, sums: list[tuple[int, int]]) -> float:
    """The final scale from first_scale(total) and every tile's
    tile_quantized_sums at it."""
    scale = first_scale(total)
    if total > 0 and sum(s[0] for s in sums) >= Q_LIMIT:
        scale /= 2
        if sum(s[1] for s in sums) >= Q_LIMIT:
            raise ValueError("quantize: the total weight does not fit 2^62 after halving the scale")
    return scale


def quantize_tile(weights: np.ndarray, scale: float) -> np.ndarray:
    """A tile's int64 fixed-point weights at the world's scale."""
    return np.rint(_clean(weights) * scale).astype(np.int64)


def tiled_quantize(weights: np.ndarray, tile: int) -> tuple[np.ndarray, float]:
    """device.quantize tile by tile (the tests' driver): two per-tile passes
    of small output (exact sums, then integer sums at the candidate scales)."""
    grid = [x for row in tile_slices(np.shape(weights), tile) for x in row]
    total = exact_total([exact_sum(weights[rs, cs]) for rs, cs in grid])
    scale = first_scale(total)
    scale = quantize_scale(total, [tile_quantized_sums(weights[rs, cs], scale) for rs, cs in grid])
    q = np.empty(np.shape(weights), np.int64)
    for rs, cs in grid:
        q[rs, cs] = quantize_tile(weights[rs, cs], scale)
    return q, scale
