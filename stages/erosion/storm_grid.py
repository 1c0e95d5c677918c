"""The storm's own grid: on cells finer than storm_cell_m the shallow-water
storm runs on blocks of f x f cells (f the largest whole factor with f dx <=
storm_cell_m that divides both sides), and its terrain change, water and
sediment come back to the fine cells by a mass-conserving prolongation.

Why: the storm's explicit step is CFL-bound, dt ~ dx / wave speed, so on a
grid k times finer it takes k times the steps over k^2 the cells (cost per
cell and simulated hour grows as 1 / dx). On the storm's grid the step count
and the cells are those of storm_cell_m whatever the terrain's cells: the
cost per fine cell falls as the terrain gets finer. This is the coarse-flow /
fine-terrain split of multi-resolution shallow-water erosion (the hydraulic
solve on a coarser grid, the change carried back to the fine heights). What
it costs: gullies narrower than storm_cell_m are not resolved; the fine grid
receives the block's change spread smoothly (bilinear) and corrected so each
block keeps exactly its coarse volume (float64), so the terrain + sediment
and water budgets of the coarse run hold on the fine grid.

With f = 1 (cells already >= storm_cell_m, or storm_cell_m = 0) nothing here runs."""
from __future__ import annotations

import math

import numpy as np


PROLONG_SWEEPS = 6  # smooth residual corrections before the exact per-block one (prolong_conserving)
# over-relaxed: block-mean-of-bilinear keeps 0.35 .. 1 of a residual, so a gain of 1.5 shrinks the slowest
# (block-to-block alternating) part about 2x per sweep, the smooth part at once
PROLONG_GAIN = 1.5


def storm_factor(rows: int, cols: int, dx: float, storm_cell_m: float) -> int:
    """Cells per block side of the storm's grid: the largest f <= storm_cell_m / dx
    (with a 1e-9 tolerance) dividing rows and cols; 1 when storm_cell_m is 0 or <= dx."""
    if storm_cell_m <= 0:
        return 1
    most = int(math.floor(storm_cell_m / dx * (1.0 + 1e-9)))
    for f in range(min(most, rows, cols), 1, -1):
        if rows % f == 0 and cols % f == 0:
            return f
    return 1


def block_mean(a: np.ndarray, f: int) -> np.ndarray:
    """The mean over each f x f block (float64)."""
    rows, cols = a.shape
    return np.asarray(a, np.float64).reshape(rows // f, f, cols // f, f).mean(axis=(1, 3))


def _linear_1d(c: np.ndarray, f: int, axis: int) -> np.ndarray:
    """Cell-centred linear interpolation along one axis to f times the cells,
    held constant beyond the outer cell centres."""
    n = c.shape[axis]
    x = np.clip((np.arange(n * f) + 0.5) / f - 0.5, 0.0, n - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    w = x - i0
    shape = [1, 1]
    shape[axis] = n * f
    w = w.reshape(shape)
    return np.take(c, i0, axis=axis) * (1.0 - w) + np.take(c, i1, axis=axis) * w


def prolong_linear(c: np.ndarray, f: int) -> np.ndarray:
    """Bilinear (cell-centred) interpolation to f times the cells per side, float64."""
    c = np.asarray(c, np.float64)
    return _linear_1d(_linear_1d(c, f, 0), f, 1)


def prolong_conserving(c: np.ndarray, f: int, positive: bool = False) -> np.ndarray:
    """Bilinear interpolation corrected so that every f x f block's mean is
    exactly the coarse value (float64, to round-off): the volume of each
    block, so of the whole map, is kept. positive: a non-negative field (water,
    sediment) is corrected by scaling, so it stays non-negative (a block whose
    interpolation sums to nothing gets its value uniformly); else by
    PROLONG_SWEEPS smooth corrections (the residual's own bilinear
    interpolation) and then the block's last residual added to its cells."""
    c = np.asarray(c, np.float64)
    fine = prolong_linear(c, f)
    if not positive:
        # a constant correction per block prints the blocks where the change varies fast: first
        # take the residual back smoothly, sweep by sweep (it shrinks each time), then what is left
        for _ in range(PROLONG_SWEEPS):
            fine += PROLONG_GAIN * prolong_linear(c - block_mean(fine, f), f)
    rows, cols = fine.shape
    blocks = fine.reshape(rows // f, f, cols // f, f)
    mean = blocks.mean(axis=(1, 3))
    if positive:
        ok = mean > 0
        scale = np.where(ok, c / np.where(ok, mean, 1.0), 0.0)
        blocks = blocks * scale[:, None, :, None]
        blocks += np.where(ok, 0.0, c)[:, None, :, None]
    else:
        blocks = blocks + (c - mean)[:, None, :, None]
    return blocks.reshape(rows, cols)
