"""Microrelief: the relief finer than geological time's own cells, as land
at 1 m has it (the pits and mounds of uprooted trees, burrows, boulders).

Small disturbances move soil a short way at random places and times, and
hillslope creep flattens each of them as it ages; in steady state the
surface is the Edwards-Wilkinson one with conserved noise,
dh/dt = D lap h - div(xi). A disturbance of size s0 that has aged t has
spread to s^2 = s0^2 + 2 D t, so summed over its ages the power spectrum is

    S(k) = C (exp(-k^2 s0^2) - exp(-k^2 s1^2)) = C int_{s0^2}^{s1^2} k^2 exp(-k^2 u) du,

flat between 1/s1 and 1/s0. Only C = (rate x moment^2) / D matters there,
so the process is set by what a survey measures: the relief's RMS height
(microrelief_rms_m) and its disturbances' size s0 (microrelief_size_m; a
root plate is 1 to 1.5 m across its half-width). Older, broader relief is
the geology's: s1 is half the geology's cell, whose solve holds everything
wider. So the microrelief exists only where geological time runs on blocks
of several cells (on its own cells nothing finer is left to add).

The field is the sum over CLASSES_PER_OCTAVE classes per octave of u of
div(G_s * xi) for independent white vector noise xi (|FT(d/dx G_s)|^2 +
|FT(d/dy G_s)|^2 = k^2 exp(-k^2 s^2)), each class weighted by its share of
the integral; its RMS is exactly the asked one in the continuum. The noise
is counter-based per world cell (worldlib.hashing.uniform), one uniform
scaled to unit variance (no transcendental function, so the same bits on
every machine), and the separable Gaussian-derivative filters add their
taps in a fixed order: a window's cells get the same bits whatever window
holds them, so tiles are the whole world's. The filters run in float32
(half the memory traffic of float64): a relief of decimetres carries
rounding of about 1e-7 m."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from worldlib.hashing import stream_key, uniform

CLASSES_PER_OCTAVE = 2  # classes of the disturbances' squared size per doubling of it
KERNEL_RADIUS_SIGMAS = 4.0  # each class's Gaussian cut 4 sigma out (its tail holds 3e-4 of its weight)
ROWS_AT_ONCE = 512  # rows of output computed at a time (bounds the memory of a whole-world window)


@dataclass(frozen=True)
class MicroRelief:
    """The microrelief of one world (seed, its shape in cells, cell size dx)."""

    seed: int
    shape: tuple[int, int]
    dx: float
    rms_m: float
    sizes_m: tuple[float, ...]  # each class's sigma
    weights: tuple[float, ...]  # each class's amplitude (m^2: sqrt(C du) times the noise's dx)
    periodic: bool = False

    @classmethod
    def of(cls, seed: int, shape: tuple[int, int], dx: float, geology_cell_m: float, rms_m: float, size_m: float,
           periodic: bool = False) -> "MicroRelief | None":
        """The world's microrelief, or None where there is none: no RMS asked,
        or the geology's half cell (s1) not above the disturbances' size (s0,
        at least one cell: finer relief is not on the grid)."""
        s0, s1 = max(size_m, dx), 0.5 * geology_cell_m
        if rms_m <= 0.0 or s1 <= s0:
            return None
        u0, u1 = s0 * s0, s1 * s1
        n = max(1, math.ceil(CLASSES_PER_OCTAVE * math.log2(u1 / u0)))
        edges = [u0 * (u1 / u0) ** (i / n) for i in range(n + 1)]
        mids = [math.sqrt(a * b) for a, b in zip(edges, edges[1:])]
        du = [b - a for a, b in zip(edges, edges[1:])]
        # variance of one class of unit C: du int k^2 exp(-k^2 u) d^2k / (2 pi)^2 = du / (4 pi u^2)
        variance = sum(d / (4.0 * math.pi * u * u) for d, u in zip(du, mids))
        c = rms_m * rms_m / variance
        # white noise of unit spectral density on cells of dx: unit-variance values times 1 / dx, each
        # summed with weight dx^2, i.e. the unit values times dx
        weights = tuple(math.sqrt(c * d) * dx for d in du)
        return cls(int(seed), (int(shape[0]), int(shape[1])), float(dx), float(rms_m),
                   tuple(math.sqrt(u) for u in mids), weights, bool(periodic))

    @property
    def halo(self) -> int:
        """Cells of noise read beyond a window on each side."""
        return max(_radius(s, self.dx) for s in self.sizes_m)

    def field(self, window: tuple[int, int, int, int]) -> np.ndarray:
        """The microrelief (m, float32) on the window (row0, col0, rows, cols) of the world's cells."""
        r0, c0, rows, cols = window
        out = np.zeros((rows, cols), np.float32)
        for at in range(0, rows, ROWS_AT_ONCE):
            band = min(ROWS_AT_ONCE, rows - at)
            for k, (s, w) in enumerate(zip(self.sizes_m, self.weights)):
                out[at:at + band] += np.float32(w) * self._class(k, s, (r0 + at, c0, band, cols))
        return out

    def _class(self, k: int, s: float, window: tuple[int, int, int, int]) -> np.ndarray:
        """div(G_s * xi) of class k on the window, unit noise per cell (per cell^2 of the filters)."""
        r0, c0, rows, cols = window
        rad = _radius(s, self.dx)
        g, dg = _taps(s, self.dx, rad)
        rr = np.arange(r0 - rad, r0 + rows + rad, dtype=np.int64)
        cc = np.arange(c0 - rad, c0 + cols + rad, dtype=np.int64)
        # xi_x differentiated along the columns (east), smoothed along the rows; xi_y the other way round
        xi_x, xi_y = (self._noise(2 * k + comp, rr, cc) for comp in (0, 1))
        return (_along(_along(xi_x, dg, 1, cols), g, 0, rows) + _along(_along(xi_y, g, 1, cols), dg, 0, rows))

    def _noise(self, stream: int, rr: np.ndarray, cc: np.ndarray) -> np.ndarray:
        """Unit-variance white noise (uniform, zero mean, float32) at world rows rr x columns cc."""
        if self.periodic:
            rr, cc = rr % self.shape[0], cc % self.shape[1]
        u = uniform(stream_key(self.seed, "microrelief", str(stream)), rr[:, None], cc[None, :], 0)
        return (u - np.float32(0.5)) * np.float32(math.sqrt(12.0))


def _radius(s: float, dx: float) -> int:
    return max(1, math.ceil(KERNEL_RADIUS_SIGMAS * s / dx))


def _taps(s: float, dx: float, rad: int) -> tuple[np.ndarray, np.ndarray]:
    """The 1-D Gaussian of sigma s (1/m) and its derivative (1/m^2) at the taps -rad .. rad (cells of dx)."""
    x = np.arange(-rad, rad + 1, dtype=np.float64) * dx
    g = np.exp(-0.5 * (x / s) ** 2) / (math.sqrt(2.0 * math.pi) * s)
    # the filter is a correlation (the output at i reads i + t), so the derivative's taps are mirrored
    return g.astype(np.float32), (x / (s * s) * g).astype(np.float32)


def _along(a: np.ndarray, taps: np.ndarray, axis: int, n_out: int) -> np.ndarray:
    """sum_t taps[t] a[i + t] along `axis`, the taps added in order: n_out values from len(taps) - 1 more."""
    out = np.zeros(a.shape[:axis] + (n_out,) + a.shape[axis + 1:], np.float32)
    for t, w in enumerate(taps):
        out += w * (a[:, t:t + n_out] if axis == 1 else a[t:t + n_out])
    return out
