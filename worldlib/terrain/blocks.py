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


def block_sum(a: np.ndarray, f: int) -> np.ndarray:
    """The sum over each f x f block (float64), in a fixed order (block row
    by block row, cell by cell): the same bits for a block whatever the
    array around it, so a tile's block sums are the whole map's."""
    a = np.asarray(a, np.float64)
    total = np.zeros((a.shape[0] // f, a.shape[1] // f))
    for i in range(f):
        for j in range(f):
            total += a[i::f, j::f]
    return total


def block_mean(a: np.ndarray, f: int) -> np.ndarray:
    """block_sum's means."""
    return block_sum(a, f) / (f * f)
