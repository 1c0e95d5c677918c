"""The erosion's coarse grids: on cells finer than storm_cell_m (the storm)
or geological_cell_m (geological time) that process runs on blocks of f x f
cells (f the largest whole factor with f dx <= the cell size that divides
both sides), and its result comes back to the fine cells by a prolongation
that keeps the map's volume.

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
receives the change spread smoothly (the cubic B-spline, which keeps the
map's volume exactly but each block's only up to its curvature: see
SMOOTH_TAPS; water and sediment bilinear scaled per block, which stays
non-negative and keeps each block's), so the budgets of the coarse run hold
on the fine grid.

A prolongation is computed once on the coarse grid (Prolongation: a coarse
field to interpolate, and for water and sediment a per-block scale and
offset) and evaluated on any window of fine cells (Prolongation.window) with
the same operations for a cell whatever the window: a tiled bake's tiles get
the whole map's bits.

With f = 1 (cells already >= the coarse cell size, or it is 0) nothing here runs."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from worldlib.terrain.blocks import block_mean, coarse_factor

# The smooth prolongation (Prolongation.conserving) is the cubic B-spline with the coarse values as its
# coefficients: C2, non-negative, linear ramps come back exactly, and with the coarse map mirrored at its edges
# (half a cell out) the fine map holds exactly the coarse map's volume. It is an approximation, not an
# interpolation: a block's fine cells hold its volume only up to the change of slope across it (a smoothing of
# about half a coarse cell). That is the point: a prolongation that gives every block exactly its coarse volume
# must put the coarse grid's checkerboard on the fine cells, so every interpolating or volume-matching one
# (Catmull-Rom, or the B-spline corrected per block) prints the coarse grid's wavenumbers, and their images
# along the axes and diagonals, on the fine slopes. The B-spline damps what lies past the coarse cells' own
# wavenumbers as sinc^4: on 1 m cells under an 8 m geology the 2-to-16-cell grid anisotropy of a threshold
# landscape was 1.51 with Catmull-Rom corrected per block, 1.85 with the B-spline so corrected.
SMOOTH_TAPS = range(-1, 3)


storm_factor = coarse_factor  # the storm's: storm_cell_m


def _smooth_weights(t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Cubic B-spline weights of the taps i - 1 .. i + 2 at t in [0, 1) past tap i."""
    t2, t3 = t * t, t * t * t
    return ((1.0 - t) ** 3 / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0, (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
            t3 / 6.0)


def _mirrored(i: np.ndarray, n: int) -> np.ndarray:
    """Coarse cell indices beyond [0, n) mirrored half a cell past the edge (-1 -> 0, -2 -> 1, n -> n - 1)."""
    i = np.where(i < 0, -1 - i, i)
    return np.where(i >= n, 2 * n - 1 - i, i)


LINEAR_TAPS = range(0, 2)


def _linear_weights(t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Linear weights of the taps i, i + 1 at t in [0, 1) past tap i."""
    return (1.0 - t, t)


def _block_mean_1d(c: np.ndarray, f: int, axis: int, weights, taps_of, mode: str) -> np.ndarray:
    """Along one axis, the block means of the interpolation of c with these
    tap weights (of the taps i + taps_of past coarse cell i), the map
    continued past its edges by np.pad's mode (as the interpolation holds
    it): a short stencil from the f cells' weights."""
    reach = max(-taps_of[0], taps_of[-1]) + 1  # a block's cells lie within half a coarse cell of its centre
    taps = np.zeros(2 * reach + 1)
    x = (np.arange(f) + 0.5) / f - 0.5
    i = np.floor(x).astype(int)
    for k, w in zip(taps_of, weights(x - i)):
        np.add.at(taps, i + k + reach, w / f)  # tap i + k of cell 0 sits at index i + k + reach of taps[-reach ..]
    pad = [(0, 0)] * c.ndim
    pad[axis] = (reach, reach)
    e = np.pad(c, pad, mode=mode)
    n = c.shape[axis]
    return sum(taps[d] * np.take(e, np.arange(d, d + n), axis=axis) for d in range(taps.size))


def block_mean_of_linear(c: np.ndarray, f: int) -> np.ndarray:
    """block_mean(prolong_linear(c, f), f), computed on the coarse grid."""
    c = np.asarray(c, np.float64)
    along = lambda a, axis: _block_mean_1d(a, f, axis, _linear_weights, LINEAR_TAPS, "edge")  # noqa: E731
    return along(along(c, 0), 1)


def block_mean_of_smooth(c: np.ndarray, f: int) -> np.ndarray:
    """block_mean(Prolongation(c, smooth).whole(), f), computed on the coarse grid."""
    c = np.asarray(c, np.float64)
    along = lambda a, axis: _block_mean_1d(a, f, axis, _smooth_weights, SMOOTH_TAPS, "symmetric")  # noqa: E731
    return along(along(c, 0), 1)


def _smooth_1d(c: np.ndarray, f: int, axis: int, start: int, count: int, n: int, c_start: int) -> np.ndarray:
    """Cell-centred cubic B-spline along one axis (C2: a hillshade shows no
    kinks at the coarse cells), the map mirrored past its edges: fine cells
    [start, start + count) of a map of n coarse cells, from c holding coarse
    cells [c_start, ...) on that axis."""
    x = (np.arange(start, start + count) + 0.5) / f - 0.5
    i = np.floor(x).astype(np.int64)
    shape = [1, 1]
    shape[axis] = count
    out = None
    for k, w in zip(SMOOTH_TAPS, _smooth_weights(x - i)):
        term = np.take(c, _mirrored(i + k, n) - c_start, axis=axis) * w.reshape(shape)
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


def coarse_span(start: int, count: int, f: int, n: int, smooth: bool = False) -> tuple[int, int]:
    """The coarse cells [lo, hi) that fine cells [start, start + count) read
    (_linear_1d: cells i0 and i0 + 1 of each, the second even at weight 0;
    _smooth_1d: i - 1 .. i + 2, mirrored into the map)."""
    if smooth:
        first, last = (start + 0.5) / f - 0.5, (start + count - 0.5) / f - 0.5
        return (max(0, int(math.floor(first)) + SMOOTH_TAPS[0]),
                min(n, max(0, int(math.floor(last)) + SMOOTH_TAPS[-1] + 1)))
    first = min(max((start + 0.5) / f - 0.5, 0.0), n - 1)
    last = min(max((start + count - 0.5) / f - 0.5, 0.0), n - 1)
    return int(math.floor(first)), min(n, int(math.floor(last)) + 2)


@dataclass(frozen=True)
class Prolongation:
    """Fine cells = interpolation(field) * scale[block] + offset[block], f
    fine cells per coarse cell, the interpolation bilinear or (smooth) the
    cubic B-spline; the arrays may be a window of the coarse map starting at
    coarse cell `origin` of a map of `shape` coarse cells."""

    f: int
    field: np.ndarray
    scale: np.ndarray | None
    offset: np.ndarray | None
    shape: tuple[int, int]
    origin: tuple[int, int] = (0, 0)
    smooth: bool = False

    @classmethod
    def linear(cls, c: np.ndarray, f: int) -> "Prolongation":
        """Bilinear (cell-centred) interpolation."""
        c = np.asarray(c, np.float64)
        return cls(f, c, None, None, c.shape)

    @classmethod
    def conserving(cls, c: np.ndarray, f: int) -> "Prolongation":
        """The cubic B-spline with c as its coefficients, the map mirrored
        past its edges: smooth (a hillshade shows no 8 m grid), the map's
        volume exactly, a block's up to the change of slope across it.
        Bilinear would print the coarse cells on a hillshade (its gradient
        jumps at every coarse cell centre)."""
        return cls(f, np.asarray(c, np.float64), None, None, np.shape(c), smooth=True)

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
        r_lo, r_hi = coarse_span(row0, rows, f, n_r, self.smooth)
        c_lo, c_hi = coarse_span(col0, cols, f, n_c, self.smooth)
        b_lo, b_hi, d_lo, d_hi = row0 // f, -(-(row0 + rows) // f), col0 // f, -(-(col0 + cols) // f)
        r_lo, r_hi, c_lo, c_hi = min(r_lo, b_lo), max(r_hi, b_hi), min(c_lo, d_lo), max(c_hi, d_hi)
        cut = lambda a: None if a is None else np.ascontiguousarray(  # noqa: E731
            a[r_lo - self.origin[0]:r_hi - self.origin[0], c_lo - self.origin[1]:c_hi - self.origin[1]])
        return Prolongation(f, cut(self.field), cut(self.scale), cut(self.offset), self.shape, (r_lo, c_lo),
                            self.smooth)

    def window(self, row0: int, col0: int, rows: int, cols: int) -> np.ndarray:
        """The fine cells [row0, +rows) x [col0, +cols), float64."""
        f, (n_r, n_c), (o_r, o_c) = self.f, self.shape, self.origin
        along = _smooth_1d if self.smooth else _linear_1d
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
