"""Grass: a density field, a height field and jittered-grid tufts (seeds 000, 001, 004).

density = suitability of the grass species x the grassy share of the ground
          (splat grass + dry grass) x (1 - grass_canopy_shade x tree canopy
          cover) x clumping noise, in [0, 1]: the probability a tuft is kept
          (seed 000: P(keep) = density);
height  = height_m x scale, scale from scale_range by moisture (lush where
          wet, seed 004), 0 where there is no grass.
Tufts: one candidate per cell of a grid of spacing 100 / sqrt(density_per_ha)
metres (grown to stay under grass_max_tufts), jittered inside the middle
`grass_jitter` of its cell (so tufts are at least (1 - jitter) x spacing
apart), kept with the density of the terrain cell it lands in.
"""
from __future__ import annotations

import math

import numpy as np

from worldlib.terrain.stats import exact_mean, exact_sum

from . import reference as ref
from .params import VegetationParams
from .placement import Domain, Placed, quaternions, value_noise, world_positions, Instances

F = np.float32


def canopy_cover(params: VegetationParams, names: list[str], n_t: np.ndarray) -> np.ndarray:
    """Share of the ground under tree and shrub crowns: 1 - exp(-sum n pi R^2)
    (crowns of radius radius_m, placed at random)."""
    lam = np.zeros(n_t.shape[1:])
    for s, name in enumerate(names):
        lam += n_t[s] * math.pi * params.species[name].radius_m ** 2
    return 1.0 - np.exp(-lam)


def grass_maps(params: VegetationParams, name: str | None, suit: np.ndarray | None, splat: np.ndarray,
               cover: np.ndarray, moisture: np.ndarray, dx: float, origin, seed: int, first=(0, 0)):
    """(density 0..1, height m) float32 fields; first: the arrays' first
    cell in the world (a window has the world's bits)."""
    shape = splat.shape[:2]
    if name is None:
        return np.zeros(shape, F), np.zeros(shape, F)
    e = params.species[name]
    grassy = splat[..., 2].astype(np.float64) + splat[..., 3]
    d = suit.astype(np.float64) * grassy * (1.0 - params.grass_canopy_shade * cover)
    if e.clustering > 0:
        d = d * np.maximum(0.0, 1.0 + e.clustering * value_noise(shape, dx, origin, e.cluster_size_m,
                                                                    ref.stream_key(seed, "clump", name), first))
    d = np.clip(d, 0.0, 1.0)
    m = np.clip(moisture.astype(np.float64), 0.0, 1.0)
    vigour = m * m * (3 - 2 * m)
    s0, s1 = e.scale_range
    height = np.where(d > 0, e.height_m * (s0 + (s1 - s0) * vigour), 0.0)
    return d.astype(F), height.astype(F)


def tuft_spacing(params: VegetationParams, name: str, density: np.ndarray, dx: float) -> tuple[float, float]:
    """(spacing m, expected tufts): the species' spacing, grown so the
    expected count stays under grass_max_tufts."""
    return tuft_spacing_of(params, name, exact_sum(density), dx)


def tuft_spacing_of(params: VegetationParams, name: str, density_sum: int, dx: float) -> tuple[float, float]:
    """tuft_spacing from the density's exact_sum integer (a tiled run's
    tiles' sums add up to it)."""
    sp = 100.0 / math.sqrt(params.species[name].density_per_ha)
    expected = exact_mean(density_sum, 1) * dx * dx / sp ** 2
    if params.grass_max_tufts == 0:
        return math.inf, 0.0
    if expected > params.grass_max_tufts:
        sp *= math.sqrt(expected / params.grass_max_tufts) * 1.0001
        expected = params.grass_max_tufts
    return sp, expected


def place_tufts(params: VegetationParams, name: str | None, density: np.ndarray, dom: Domain, seed: int,
                backend, local=None) -> tuple[Placed | None, dict]:
    if name is None or not density.any() or params.grass_max_tufts == 0:
        return None, {"tufts": 0}
    sp, expected = tuft_spacing(params, name, density, dom.dx)
    nx, nz = int(dom.width // sp) + 1, int(dom.depth // sp) + 1
    key = ref.stream_key(seed, "tufts", name)
    out = backend.grass_tufts(density, dom.dx, nx, nz, sp, params.grass_jitter, dom.width, dom.depth, key, local=local)
    idx = np.nonzero(out[:, 3] > 0)[0]
    pts = out[idx]
    min_dist = (1.0 - params.grass_jitter) * sp
    p = Placed(name, pts[:, 0].copy(), pts[:, 1].copy(), np.full(len(idx), min_dist, F), idx.astype(np.int64),
               {"tuft_spacing_m": sp, "expected_tufts": expected, "tufts": int(len(idx)), "candidates": nx * nz})
    return p, p.stats


def tuft_instances(p: Placed, params: VegetationParams, height: np.ndarray, dom: Domain, mesh, seed: int) -> Instances:
    import zlib

    e = params.species[p.name]
    key = ref.stream_key(seed, "instance", p.name)
    u = [ref.uniform(key, p.cell, k, 0).astype(np.float64) for k in range(4)]
    tr, tc = dom.cell_of(p.x, p.z)
    scale = height[tr, tc].astype(np.float64) / e.height_m * (0.9 + 0.2 * u[0])
    q = quaternions(2 * np.pi * u[1], np.radians(e.tilt_deg) * u[2], 2 * np.pi * u[3])
    ids = (np.int64(zlib.crc32(p.name.encode()) & 0x7FFFFFFF) << np.int64(32)) | p.cell
    rnd = ref.uniform(key, p.cell, 9, 0)
    return Instances(p.name, world_positions(p.x, p.z, dom, mesh), q.astype(np.float16),
                     np.repeat(scale[:, None], 3, 1).astype(F), np.ones(len(p.x), F), rnd.astype(F), ids, p.r)
