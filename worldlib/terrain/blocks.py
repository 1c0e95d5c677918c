"""Blocks of f x f cells: the coarse grids a process runs on when the
terrain's cells are finer than it needs (the erosion's storm and geological
time, the vegetation's simulation), and their means summed in a fixed order
so a tile's blocks have the whole map's bits."""
from __future__ import annotations

import math

import numpy as np


def coarse_factor(rows: int, cols: int, dx: float, coarse_cell_m: float) -> int:
    """Cells per block side of a coarse grid: the largest f <= coarse_cell_m / dx
    (with a 1e-9 tolerance) dividing rows and cols; 1 when coarse_cell_m is 0 or <= dx."""
    if coarse_cell_m <= 0:
        return 1
    most = int(math.floor(coarse_cell_m / dx * (1.0 + 1e-9)))
    for f in range(min(most, rows, cols), 1, -1):
        if rows % f == 0 and cols % f == 0:
            return f
    return 1


BLOCK_ROWS_AT_ONCE = 1 << 20  # about this many cells summed at a time (bounds the block-major copy)
SMALL_BLOCK = 64  # blocks up to this side are summed by strided adds, larger ones by a cumulative sum


def block_sum(a: np.ndarray, f: int) -> np.ndarray:
    """The sum over each f x f block (float64), in a fixed order (the
    block's rows top first, each left to right, added one by one from 0):
    the same bits for a block whatever the array around it, so a tile's
    block sums are the whole map's. A cumulative sum is sequential (numpy's
    reductions sum pairwise, whose order depends on the length), so with
    each block's cells laid out in that order its last term is their sum."""
    a = np.asarray(a, np.float64)
    nr, nc = a.shape[0] // f, a.shape[1] // f
    if f <= SMALL_BLOCK:  # few cells a block: one strided add per cell of the block is quicker
        total = np.zeros((nr, nc))
        for i in range(f):
            for j in range(f):
                total += a[i:nr * f:f, j:nc * f:f]
        return total
    total = np.empty((nr, nc))
    step = max(1, BLOCK_ROWS_AT_ONCE // max(1, f * f * nc))
    for r0 in range(0, nr, step):
        r1 = min(nr, r0 + step)
        blocks = a[r0 * f:r1 * f, :nc * f].reshape(r1 - r0, f, nc, f).transpose(0, 2, 1, 3).reshape(r1 - r0, nc, f * f)
        total[r0:r1] = np.cumsum(blocks, axis=2)[:, :, -1]
    return total


def block_mean(a: np.ndarray, f: int) -> np.ndarray:
    """block_sum's means."""
    return block_sum(a, f) / (f * f)
