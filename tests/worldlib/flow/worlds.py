"""Test worlds shared by the tiled flow tests (tiled fill, tiled D8)."""
from __future__ import annotations

import numpy as np

from worldlib.flow import reference as ref


def fractal(n: int, seed: int, beta: float = 2.2) -> np.ndarray:
    """Spectral-synthesis fractal terrain (power ~ k^-beta), 0..1000 m."""
    rng = np.random.default_rng(seed)
    k2 = np.fft.fftfreq(n)[:, None] ** 2 + np.fft.fftfreq(n)[None, :] ** 2
    k2[0, 0] = 1.0
    spec = (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))) / k2 ** (beta / 4)
    h = np.real(np.fft.ifft2(spec))
    return ((h - h.min()) / (h.max() - h.min()) * 1000).astype(np.float32)


def random_small_worlds(seed: int, count: int, max_side: int):
    """(trial, h, tile): small random worlds 1..max_side cells a side,
    every third with integer heights (flats), every fourth with 10 % NaN
    cells, canonical float32, and a random tile size of 1..11 cells."""
    rng = np.random.default_rng(seed)
    for trial in range(count):
        rows, cols = (int(x) for x in rng.integers(1, max_side, 2))
        h = (rng.random((rows, cols)) * 10).astype(np.float32)
        if trial % 3 == 0:
            h = np.round(h)
        if trial % 4 == 0:
            h[rng.random(h.shape) < 0.1] = np.nan
        yield trial, ref.canonical(h), int(rng.integers(1, 12))
