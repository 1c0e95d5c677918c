"""Plain numpy implementation of kernels.cl, for tests on small grids.

Every operation is float32 and in the same order as the kernel (the kernel
switches off fma contraction), so on a conforming OpenCL device the two agree
to the last bit or within a few ulps.
"""
from __future__ import annotations

import numpy as np

from worldlib.hashing import mix32

from .noise import TerrainSpec

F = np.float32
GA1, GB1, GA2, GB2 = F(0.98078528), F(0.19509032), F(0.83146961), F(0.55557023)
NOISE_SCALE = F(1.41421356)
HX, HZ = np.uint32(0x8DA6B343), np.uint32(0xD8163841)


def grad(h: np.ndarray, fx: np.ndarray, fz: np.ndarray) -> np.ndarray:
    """dot(g, (fx, fz)) for one of 16 unit gradients at 11.25 + k 22.5 degrees."""
    b8, b4 = (h & np.uint32(8)) != 0, (h & np.uint32(4)) != 0
    ga, gb = np.where(b8, GA2, GA1), np.where(b8, GB2, GB1)
    gx, gz = np.where(b4, gb, ga), np.where(b4, ga, gb)
    gx = np.where((h & np.uint32(1)) != 0, -gx, gx)
    gz = np.where((h & np.uint32(2)) != 0, -gz, gz)
    return gx * fx + gz * fz


def fade(t: np.ndarray) -> np.ndarray:
    return t * t * t * (t * (t * F(6) - F(15)) + F(10))


def gnoise(px: np.ndarray, pz: np.ndarray, period: int, seed: int) -> np.ndarray:
    """Gradient noise in [-1, 1] at lattice positions (float32 arrays)."""
    flx, flz = np.floor(px), np.floor(pz)
    fx, fz = px - flx, pz - flz
    ix0, iz0 = flx.astype(np.int64), flz.astype(np.int64)
    ix1, iz1 = ix0 + 1, iz0 + 1
    if period > 0:
        ix0, iz0, ix1, iz1 = (np.mod(i, period) for i in (ix0, iz0, ix1, iz1))
    u32 = lambda i: (i & 0xFFFFFFFF).astype(np.uint32)  # noqa: E731  two's complement bits of an int
    s = np.uint32(seed & 0xFFFFFFFF)
    hx0, hx1 = u32(ix0) * HX, u32(ix1) * HX
    hz0, hz1 = u32(iz0) * HZ + s, u32(iz1) * HZ + s
    fx1, fz1 = fx - F(1), fz - F(1)
    d00 = grad(mix32(hx0 ^ hz0), fx, fz)
    d10 = grad(mix32(hx1 ^ hz0), fx1, fz)
    d01 = grad(mix32(hx0 ^ hz1), fx, fz1)
    d11 = grad(mix32(hx1 ^ hz1), fx1, fz1)
    u, v = fade(fx), fade(fz)
    a = d00 + u * (d10 - d00)
    b = d01 + u * (d11 - d01)
    return (a + v * (b - a)) * NOISE_SCALE


def _octave(spec: TerrainSpec, i: int, X: np.ndarray, Z: np.ndarray) -> np.ndarray:
    scale, ox, oz, _ = spec.octf[i]
    period, seed = int(spec.octi[i, 0]), int(spec.octi[i, 1])
    return gnoise(X * scale + ox, Z * scale + oz, period, seed)


def fbm(spec: TerrainSpec, X: np.ndarray, Z: np.ndarray, first: int, n: int) -> np.ndarray:
    total = np.zeros_like(X)
    for i in range(first, first + n):
        total = total + spec.octf[i, 3] * _octave(spec, i, X, Z)
    return total


def ridged(spec: TerrainSpec, X: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """Musgrave's ridged multifractal."""
    total = np.zeros_like(X)
    weight = np.ones_like(X)
    for i in range(spec.n_main):
        s = spec.ridge_offset - np.abs(_octave(spec, i, X, Z))
        s = s * s
        s = s * weight
        total = total + s * spec.octf[i, 3]
        weight = np.clip(s * spec.ridge_gain, F(0), F(1))
    return total


def evaluate(spec: TerrainSpec, window: tuple[int, int, int, int]) -> np.ndarray:
    """Heights (float32, (rows, cols)) of the window = (col0, row0, cols, rows)."""
    col0, row0, cols, rows = window
    X0 = (np.arange(col0, col0 + cols)).astype(F) + F(0.5)
    Z0 = (np.arange(row0, row0 + rows)).astype(F) + F(0.5)
    X, Z = np.meshgrid(X0, Z0)
    value = np.zeros_like(X)
    if spec.fault:  # smooth steps across the fault lines (see noise.fault_table)
        for a, b, d, w in spec.faults:
            t = np.clip(a * X + (b * Z - d), F(0), F(1))
            S = t * t * (F(3) - F(2) * t)
            value = value + w * (S + S - F(1))
    if spec.warp:
        wx = fbm(spec, X, Z, spec.n_main, spec.n_warp)
        wz = fbm(spec, X, Z, spec.n_main + spec.n_warp, spec.n_warp)
        X = X + spec.warp_cells * wx
        Z = Z + spec.warp_cells * wz
    if spec.ridged:
        value = value + ridged(spec, X, Z)
    else:
        value = value + fbm(spec, X, Z, 0, spec.n_main)
    return (spec.hb + spec.hs * value).astype(F)
