"""The erosion's coarse grids: on cells finer than storm_cell_m (the storm)
or geological_cell_m (geological time) that process runs on blocks of f x f
cells (f the largest whole factor with f dx <= the cell size that divides
both sides), and its result comes back to the fine cells by a prolongation
that keeps every block's volume.

Why: the storm's explicit step is CFL-bound, dt ~ dx / wave speed, so on a
grid k times finer it takes k times the steps over k^2 the cells (cost per
cell and simulated hour grows as 1 / dx). Geological time has no step limit,
but its processes (rivers incise by their flow per incision_width_m of width,
hillslopes creep and slide over many metres) have nothing to resolve below a
few metres, and its implicit solve is one sweep over the whole world. On the
coarse grid the step count and the cells are those of the coarse cell size
whatever the terrain's cells: the cost per fine cell falls as the terrain
gets finer, and the coarse world (1/f^2 of the cells) is small enough for one
process while the fine terrain is baked in tiles. This is the coarse-flow /
fine-terrain split of multi-resolution erosion (the solve on a coarser grid,
the change carried back to the fine heights). What it costs: gullies and
valleys narrower than the coarse cell are not resolved; the fine grid
receives the block's change spread smoothly (C1 cubic; water and sediment
bilinear, which stays non-negative) and corrected so each block keeps its
coarse volume (float64, to round-off), so the budgets of the coarse run hold
on the fine grid.

A prolongation is computed once on the coarse grid (Prolongation: a coarse
field to interpolate and a per-block scale and offset) and evaluated on any
window of fine cells (Prolongation.window) with the same operations for a
cell whatever the window: a tiled bake's tiles get the whole map's bits.

With f = 1 (cells already >= the coarse cell size, or it is 0) nothing here runs."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from worldlib.terrain.blocks import block_mean, coarse_factor

# smooth residual corrections before the exact per-block one (Prolongation.conserving): the block means of the
# cubic keep 0.40 .. 1 of a residual (the checkerboard the least), so a gain of 1.4 shrinks every part at least
# 0.44x per sweep and 20 sweeps leave 1e-7 of it: the last per-block step is far below what a hillshade shows
PROLONG_SWEEPS = 20
PROLONG_GAIN = 1.4


storm_factor = coarse_factor  # the storm's: storm_cell_m


def _cubic_weights(t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Catmull-Rom weights of the taps i - 1, i, i + 1, i + 2 at t in [0, 1) past tap i."""
    t2, t3 = t * t, t * t * t
    return (0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0), 0.5 * (-3.0 * t3 + 4.0 * t2 + t),
            0.5 * (t3 - t2))


def _linear_weights(t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Linear weights of the same four taps (the outer two unused)."""
    return (0.0 * t, 1.0 - t, t, 0.0 * t)


def _block_mean_1d(c: np.ndarray, f: int, axis: int, weights) -> np.ndarray:
    """Along one axis, the block means of the interpolation of c with these
    tap weights, the outer cells repeated beyond the map (as both
    interpolations hold them): a 5-tap stencil from the f cells' weights."""
    taps = np.zeros(5)
    x = (np.arange(f) + 0.5) / f - 0.5
    i = np.floor(x).astype(int)
    for k, w in enumerate(weights(x - i)):
        np.add.at(taps, i + k + 1, w / f)  # tap i - 1 + k of cell 0 sits at index i + k + 1 of taps[-2 .. 2]
    pad = [(0, 0)] * c.ndim
    pad[axis] = (2, 2)
    e = np.pad(c, pad, mode="edge")
    n = c.shape[axis]
    return sum(taps[d] * np.take(e, np.arange(d, d + n), axis=axis) for d in range(5))


def block_mean_of_linear(c: np.ndarray, f: int) -> np.ndarray:
    """block_mean(prolong_linear(c, f), f), computed on the coarse grid."""
    c = np.asarray(c, np.float64)
    return _block_mean_1d(_block_mean_1d(c, f, 0, _linear_weights), f, 1, _linear_weights)


def block_mean_of_cubic(c: np.ndarray, f: int) -> np.ndarray:
    """block_mean(Prolongation(c, cubic).whole(), f), computed on the coarse grid."""
    c = np.asarray(c, np.float64)
    return _block_mean_1d(_block_mean_1d(c, f, 0, _cubic_weights), f, 1, _cubic_weights)


def _cubic_1d(c: np.ndarray, f: int, axis: int, start: int, count: int, n: int, c_start: int) -> np.ndarray:
    """Cell-centred Catmull-Rom interpolation along one axis (C1: a hillshade
    shows no kinks at the coarse cells), the outer cells repeated beyond the
    map: fine cells [start, start + count) of a map of n coarse cells, from c
    holding coarse cells [c_start, ...) on that axis."""
    x = (np.arange(start, start + count) + 0.5) / f - 0.5
    i = np.floor(x).astype(np.int64)
    shape = [1, 1]
    shape[axis] = count
    out = None
    for k, w in enumerate(_cubic_weights(x - i)):
        term = np.take(c, np.clip(i - 1 + k, 0, n - 1) - c_start, axis=axis) * w.reshape(shape)
        out = term if out is None else out + term
    return out


def _linear_1d(c: np.ndarray, f: int, axis: int, start: int, count: int, n: int, c_start: int) -> np.ndarray:
    """Cell-centred linear interpolation along one axis, held constant beyond
    the outer cell centres: fine cells [start, start + count) of a map of n
    coarse cells, from c holding coarse cells [c_start, ...) on that axis."""
    x = np.clip((np.arange(start, start + count) + 0.5) / f - 0.5, 0.0, n - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    w = x - i0
    shape = [1, 1]
    shape[axis] = count
    w = w.reshape(shape)
    return np.take(c, i0 - c_start, axis=axis) * (1.0 - w) + np.take(c, i1 - c_start, axis=axis) * w


def coarse_span(start: int, count: int, f: int, n: int, cubic: bool = False) -> tuple[int, int]:
    """The coarse cells [lo, hi) that fine cells [start, start + count) read
    (_linear_1d: cells i0 and i0 + 1 of each, the second even at weight 0;
    _cubic_1d: i - 1 .. i + 2)."""
    if cubic:
        first, last = (start + 0.5) / f - 0.5, (start + count - 0.5) / f - 0.5
        return max(0, int(math.floor(first)) - 1), min(n, max(0, int(math.floor(last)) + 3))
    first = min(max((start + 0.5) / f - 0.5, 0.0), n - 1)
    last = min(max((start + count - 0.5) / f - 0.5, 0.0), n - 1)
    return int(math.floor(first)), min(n, int(math.floor(last)) + 2)


@dataclass(frozen=True)
class Prolongation:
    """Fine cells = interpolation(field) * scale[block] + offset[block], f
    fine cells per coarse cell, the interpolation bilinear or (cubic)
    Catmull-Rom; the arrays may be a window of the coarse map starting at
    coarse cell `origin` of a map of `shape` coarse cells."""

    f: int
    field: np.ndarray
    scale: np.ndarray | None
    offset: np.ndarray | None
    shape: tuple[int, int]
    origin: tuple[int, int] = (0, 0)
    cubic: bool = False

    @classmethod
    def linear(cls, c: np.ndarray, f: int) -> "Prolongation":
        """Bilinear (cell-centred) interpolation."""
        c = np.asarray(c, np.float64)
        return cls(f, c, None, None, c.shape)

    @classmethod
    def conserving(cls, c: np.ndarray, f: int) -> "Prolongation":
        """Catmull-Rom, corrected so every block's mean is c: PROLONG_SWEEPS
        smooth corrections (the residual's own interpolation; the
        interpolation is linear in its field, so the sweeps run on the
        coarse field), then each block's last residual (1e-7 of the first)
        added to its cells. Bilinear would print the coarse cells on a
        hillshade (its gradient jumps at every coarse cell centre)."""
        c = np.asarray(c, np.float64)
        a = c.copy()
        for _ in range(PROLONG_SWEEPS):
            a += PROLONG_GAIN * (c - block_mean_of_cubic(a, f))
        return cls(f, a, None, c - block_mean_of_cubic(a, f), c.shape, cubic=True)

    @classmethod
    def positive(cls, c: np.ndarray, f: int) -> "Prolongation":
        """For a non-negative field (water, sediment): bilinear scaled per
        block to the block's mean, so it stays non-negative (a block whose
        interpolation sums to nothing gets its value uniformly)."""
        c = np.asarray(c, np.float64)
        mean = block_mean_of_linear(c, f)
        ok = mean > 0
        return cls(f, c, np.where(ok, c / np.where(ok, mean, 1.0), 0.0), np.where(ok, 0.0, c), c.shape)

    def part(self, row0: int, col0: int, rows: int, cols: int) -> "Prolongation":
        """The coarse data fine cells [row0, +rows) x [col0, +cols) read (what a tile is sent)."""
        f, (n_r, n_c) = self.f, self.shape
        r_lo, r_hi = coarse_span(row0, rows, f, n_r, self.cubic)
        c_lo, c_hi = coarse_span(col0, cols, f, n_c, self.cubic)
        b_lo, b_hi, d_lo, d_hi = row0 // f, -(-(row0 + rows) // f), col0 // f, -(-(col0 + cols) // f)
        r_lo, r_hi, c_lo, c_hi = min(r_lo, b_lo), max(r_hi, b_hi), min(c_lo, d_lo), max(c_hi, d_hi)
        cut = lambda a: None if a is None else np.ascontiguousarray(  # noqa: E731
            a[r_lo - self.origin[0]:r_hi - self.origin[0], c_lo - self.origin[1]:c_hi - self.origin[1]])
        return Prolongation(f, cut(self.field), cut(self.scale), cut(self.offset), self.shape, (r_lo, c_lo), self.cubic)

    def window(self, row0: int, col0: int, rows: int, cols: int) -> np.ndarray:
        """The fine cells [row0, +rows) x [col0, +cols), float64."""
        f, (n_r, n_c), (o_r, o_c) = self.f, self.shape, self.origin
        along = _cubic_1d if self.cubic else _linear_1d
        fine = along(along(self.field, f, 0, row0, rows, n_r, o_r), f, 1, col0, cols, n_c, o_c)
        if self.scale is None and self.offset is None:
            return fine
        br = np.arange(row0, row0 + rows) // f - o_r
        bc = np.arange(col0, col0 + cols) // f - o_c
        if self.scale is not None:
            fine = fine * self.scale[np.ix_(br, bc)]
        return fine + self.offset[np.ix_(br, bc)]

    def whole(self) -> np.ndarray:
        return self.window(0, 0, self.shape[0] * self.f, self.shape[1] * self.f)


def prolong_linear(c: np.ndarray, f: int) -> np.ndarray:
    """Bilinear (cell-centred) interpolation to f times the cells per side, float64."""
    return Prolongation.linear(c, f).whole()


def prolong_conserving(c: np.ndarray, f: int, positive: bool = False) -> np.ndarray:
    """The whole map's Prolongation.conserving (or .positive)."""
    return (Prolongation.positive(c, f) if positive else Prolongation.conserving(c, f)).whole()
