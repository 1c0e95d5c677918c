"""Placement: target density maps, variable-radius Poisson-disk sampling by
grid phases, exact counts per block, and the instance attributes.

Target density of species s (plants per m^2) on the terrain grid:
    n_s = density_per_ha / 1e4 * suitability_s * yield_s * clump_s
yield_s, the relative yield from the ecosystem simulation (its density among
the other species over its density alone), clump_s a mean-1 value noise (clustering), capped at what
min_spacing_m allows. Border cells (half outside the terrain mesh) get 0.

Sampling a species (placement.py drives the kernel poisson_phase):
- radius field r = clamp(sqrt(KAPPA * FILL / n_s), r_lo, 2 r_lo) with r_lo =
  max(min_spacing, sqrt(KAPPA * FILL / max n_s)): a saturated Poisson-disk
  set of radius r holds KAPPA / r^2 points per m^2, 1 / FILL times the target;
- a grid of cell c = r_lo / sqrt(2) (at most one point per cell), passes of
  one dart per free cell over 16 phases ((x mod 4, z mod 4)): darts of one
  phase are farther apart than any radius, so they are tested in parallel
  and the result does not depend on order; a dart is kept when no point is
  closer than max(r, r_q) (+2 mm) and no plant of a species placed earlier
  closer than the sum of the collision radii;
- selection: per block of density_block_m, the target count E_b = sum of
  n_s * cell area is rounded stochastically (floor(E_b + u_b)) and that many
  candidates are kept by weighted sampling (weight = expected keep rate at
  the candidate), all when there are fewer (a shortfall, reported). Removing points keeps every distance.
Species are placed in order of decreasing collision radius (then name): a
species never depends on those placed after it.
"""
from __future__ import annotations

import math
import time
import zlib
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from worldlib.terrain.blocks import block_sum
from worldlib.terrain.stats import exact_mean, exact_sum

from . import reference as ref
from .params import FILL, KAPPA, VegetationParams

F = np.float32
MARGIN_M = 0.002  # extra distance the sampler keeps, so float32 world coordinates still respect the radii
BANK_MARGIN_M = 0.5  # a stem stands this far clear of the water's edge


@dataclass
class Domain:
    """The placement domain: the terrain mesh footprint, from the first to
    the last cell centre. x, z in metres from its origin."""

    rows: int
    cols: int
    dx: float
    origin_m: tuple[float, float]

    @property
    def width(self) -> float:
        return (self.cols - 1) * self.dx

    @property
    def depth(self) -> float:
        return (self.rows - 1) * self.dx

    @property
    def x0(self) -> float:
        return self.origin_m[0] + 0.5 * self.dx

    @property
    def z0(self) -> float:
        return self.origin_m[1] + 0.5 * self.dx

    def world_cell(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of the terrain cell containing world positions (n, 3):
        floor((x - origin) / dx), the definition the checks use."""
        p = positions.astype(np.float64)
        tc = np.clip(np.floor((p[:, 0] - self.origin_m[0]) / self.dx).astype(np.int64), 0, self.cols - 1)
        tr = np.clip(np.floor((p[:, 2] - self.origin_m[1]) / self.dx).astype(np.int64), 0, self.rows - 1)
        return tr, tc

    def cell_of(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of the terrain cell containing domain coordinates, as the kernels compute it."""
        tc = np.minimum(np.floor(x.astype(F) / F(self.dx) + F(0.5)).astype(np.int64), self.cols - 1)
        tr = np.minimum(np.floor(z.astype(F) / F(self.dx) + F(0.5)).astype(np.int64), self.rows - 1)
        return tr, tc


def value_noise(shape: tuple[int, int], dx: float, origin: tuple[float, float], wavelength: float, key: int,
                first=(0, 0)) -> np.ndarray:
    """Zero-mean value noise in [-1, 1] (lattice of spacing `wavelength`,
    smoothstep interpolation) at the cell centres. first: the (row, col) of
    the array's first cell in the world whose origin is `origin`."""
    rows, cols = shape
    x = (origin[0] + (first[1] + np.arange(cols) + 0.5) * dx) / wavelength
    z = (origin[1] + (first[0] + np.arange(rows) + 0.5) * dx) / wavelength
    ix, iz = np.floor(x).astype(np.int64), np.floor(z).astype(np.int64)
    fx, fz = x - ix, z - iz
    sx, sz = fx * fx * (3 - 2 * fx), fz * fz * (3 - 2 * fz)

    def v(a, b):
        return 2.0 * ref.uniform(key, a[None, :] & 0xFFFFFFFF, b[:, None] & 0xFFFFFFFF, 0).astype(np.float64) - 1.0
    v00, v10, v01, v11 = v(ix, iz), v(ix + 1, iz), v(ix, iz + 1), v(ix + 1, iz + 1)
    top = v00 + (v10 - v00) * sx[None, :]
    bot = v01 + (v11 - v01) * sx[None, :]
    return top + (bot - top) * sz[:, None]


def target_density(params: VegetationParams, names: list[str], suit: np.ndarray, share: np.ndarray,
                   dx: float, origin: tuple[float, float], seed: int) -> tuple[np.ndarray, dict]:
    """(nsp, rows, cols) plants per m^2, and per species how much was capped."""
    out = np.zeros(suit.shape)
    info = {}
    for s, name in enumerate(names):
        out[s], excess = species_target(params, name, suit[s], share[s], dx, origin, seed)
        info[name] = {"capped_plants": exact_mean(excess, 1) * dx * dx}
    return out, info


def species_target(params: VegetationParams, name: str, suit: np.ndarray, share: np.ndarray, dx: float,
                   origin: tuple[float, float], seed: int, first=(0, 0), world=None) -> tuple[np.ndarray, int]:
    """One species' target (plants per m^2) on the world's cells, or on a
    window of them from cell `first` of a `world` (rows, cols): the world's
    bits. 0 on the world's border cells (half outside the terrain mesh).
    With it the density over the min_spacing_m cap, an exact_sum integer
    (windows' add up to the world's)."""
    e = params.species[name]
    rows, cols = suit.shape
    world = (rows, cols) if world is None else world
    n = e.density_per_ha / 1e4 * suit.astype(np.float64) * share
    if e.clustering > 0:
        n = n * np.maximum(0.0, 1.0 + e.clustering * value_noise(
            (rows, cols), dx, origin, e.cluster_size_m, ref.stream_key(seed, "clump", name), first))
    cap = KAPPA * FILL / e.min_spacing_m ** 2
    excess = exact_sum(np.maximum(n - cap, 0))
    n = np.minimum(n, cap)
    r = first[0] + np.arange(rows)
    c = first[1] + np.arange(cols)
    n[(r == 0) | (r == world[0] - 1), :] = 0.0
    n[:, (c == 0) | (c == world[1] - 1)] = 0.0
    return n, excess


def placement_order(params: VegetationParams, names: list[str]) -> list[str]:
    return sorted(names, key=lambda n: (-params.species[n].collision_radius_m, n))


@dataclass
class Placed:
    """The plants of one species, in domain coordinates."""

    name: str
    x: np.ndarray  # float32 m from the domain origin
    z: np.ndarray
    r: np.ndarray  # Poisson radius (minimum distance to another plant of the species)
    cell: np.ndarray  # int64 Poisson cell index (stable id within the species)
    stats: dict


class Obstacles(NamedTuple):
    """The plants placed before, as a CSR grid of cells of oc metres over
    the domain (onx x onz cells), or over the window of it that one tile's
    darts can reach: onwx x onwz cells from cell (ox0, oz0). start has one
    entry per window cell and one more; pts are float4 (x, z, clearance, 0)."""

    start: np.ndarray
    pts: np.ndarray
    onx: int
    onz: int
    oc: float
    ox0: int = 0
    oz0: int = 0
    onwx: int = 0
    onwz: int = 0


NO_OBSTACLES = Obstacles(np.zeros(2, np.int32), np.zeros((1, 4), F), 0, 0, 1.0)


def _obstacles(prev: list[tuple[Placed, float]], coll: float, dom: Domain, c: float,
               window_m: tuple[float, float, float, float] | None = None) -> Obstacles:
    """The Obstacles of the plants placed before, over the domain or, given
    window_m = (x0, x1, z0, z1) metres (where darts may fall), over the cells
    a dart there looks at: a tile's task gets its share, not the world's."""
    if not prev or not sum(len(p.x) for p, _ in prev):
        return NO_OBSTACLES
    xs = np.concatenate([p.x for p, _ in prev])
    zs = np.concatenate([p.z for p, _ in prev])
    cl = np.concatenate([np.full(len(p.x), cq + coll, F) for p, cq in prev])
    oc = max(c, float(cl.max()) + 2 * MARGIN_M + 1e-3)
    onx, onz = int(dom.width // oc) + 1, int(dom.depth // oc) + 1
    ox = np.minimum((xs / F(oc)).astype(np.int64), onx - 1)
    oz = np.minimum((zs / F(oc)).astype(np.int64), onz - 1)
    ox0, oz0, onwx, onwz = 0, 0, onx, onz
    if window_m is not None:
        # a dart looks one cell around its own; two more cover its float32 cell against this float64 one
        x0, x1, z0, z1 = window_m
        ox0, oz0 = max(int(x0 // oc) - 3, 0), max(int(z0 // oc) - 3, 0)
        onwx, onwz = min(int(x1 // oc) + 4, onx) - ox0, min(int(z1 // oc) + 4, onz) - oz0
        inside = (ox >= ox0) & (ox < ox0 + onwx) & (oz >= oz0) & (oz < oz0 + onwz)
        xs, zs, cl, ox, oz = xs[inside], zs[inside], cl[inside], ox[inside], oz[inside]
    cell = (oz - oz0) * onwx + (ox - ox0)
    order = np.argsort(cell, kind="stable")
    start = np.zeros(onwx * onwz + 1, np.int64)
    np.add.at(start, cell + 1, 1)
    start = np.cumsum(start)
    pts = np.stack([xs[order], zs[order], cl[order], np.zeros(len(xs), F)], -1).astype(F).reshape(-1, 4)
    if not len(pts):
        pts = np.zeros((1, 4), F)
    return Obstacles(start.astype(np.int32), pts, onx, onz, oc, ox0, oz0, onwx, onwz)


POISSON_ROUND_HALO = ref.PN * (ref.PN + 1) ** 2  # Poisson cells a window needs around a tile for one pass


def point_window(x0: int, z0: int, wnx: int, wnz: int, c: float, dom: Domain) -> tuple[ref.PointWindow, tuple]:
    """The PointWindow of Poisson cells [x0, x0 + wnx) x [z0, z0 + wnz) and
    the terrain cells (row slice, col slice) its darts can land in (the
    radius field's window)."""
    def span(first, n, cells):
        lo = max(int(math.floor(first * c / dom.dx)) - 1, 0)
        hi = min(int(math.ceil((first + n) * c / dom.dx)) + 2, cells)
        return slice(lo, hi)
    rs, cs = span(z0, wnz, dom.rows), span(x0, wnx, dom.cols)
    return ref.PointWindow(x0, z0, wnx, wnz, rs.start, cs.start, dom.rows, dom.cols), (rs, cs)


def poisson_sample(rad: np.ndarray, r_lo: float, dom: Domain, passes: int, key: int, backend, obstacles=None,
                   local=None) -> tuple[np.ndarray, dict]:
    """Candidates (n, 4: x, z, r, key) and their Poisson cell index, from a
    radius field on the terrain grid (0: nothing grows there)."""
    c = r_lo / math.sqrt(2.0)
    nx, nz = int(dom.width // c) + 1, int(dom.depth // c) + 1
    sampler = backend.Poisson(nx, nz, c, dom.width, dom.depth, rad, dom.dx, MARGIN_M,
                              *(NO_OBSTACLES if obstacles is None else obstacles), local=local)
    t0 = time.perf_counter()
    P = ref.PN + 1
    for k in range(passes):
        for pz in range(P):
            for px in range(P):
                sampler.phase(px, pz, k, key)
    pts = sampler.read()
    seconds = time.perf_counter() - t0
    idx = np.nonzero(pts[:, 2] > 0)[0]
    return pts[idx], idx.astype(np.int64), {"poisson_cells": nx * nz, "poisson_cell_m": c, "poisson_seconds": seconds}


def select_counts(pts: np.ndarray, cells: np.ndarray, n_t: np.ndarray, dom: Domain, block: int, key: int,
                  first=(0, 0)):
    """Keep floor(E_b + u_b) candidates per block, E_b the target count of
    the block, chosen by weighted sampling without replacement (Efraimidis
    and Spirakis: the smallest -ln(u) / w), w = the candidate's expected keep
    rate n_t r^2 / KAPPA, so the kept points follow the target inside the
    block too. n_t: the world's target, or a window of whole blocks of it
    from terrain cell `first` (row, col), with the candidates landing in it:
    blocks are numbered and summed as the world's, so a window's choice is
    the world's. Returns (kept mask, stats, the target count as
    worldlib.terrain.stats.exact_sum's integer: windows' add up exactly)."""
    rows, cols = n_t.shape
    r0, c0 = first
    if r0 % block or c0 % block or (rows % block and r0 + rows != dom.rows) or (cols % block and c0 + cols != dom.cols):
        raise ValueError(f"select_counts: a window of {rows}x{cols} cells from {first} cuts blocks of {block}")
    nbr, nbc = -(-rows // block), -(-cols // block)
    pad = np.zeros((nbr * block, nbc * block))
    pad[:rows, :cols] = n_t * dom.dx * dom.dx
    expect = block_sum(pad, block).ravel()
    world_nbc = -(-dom.cols // block)
    bid = ((r0 // block + np.arange(nbr, dtype=np.int64))[:, None] * world_nbc
           + (c0 // block + np.arange(nbc, dtype=np.int64))[None, :]).ravel()
    want = np.floor(expect + ref.uniform(key, bid, 0, 0).astype(np.float64)).astype(np.int64)
    tr, tc = dom.cell_of(pts[:, 0], pts[:, 1])
    tr, tc = tr - r0, tc - c0
    b = (tr // block) * nbc + (tc // block)
    have = np.bincount(b, minlength=nbr * nbc)
    w = n_t[tr, tc] * pts[:, 2].astype(np.float64) ** 2 / KAPPA
    u = np.maximum(pts[:, 3].astype(np.float64), 2.0 ** -25)
    rank_key = -np.log(u) / np.maximum(w, 1e-12)
    order = np.lexsort((cells, rank_key, b))
    sb = b[order]
    start = np.searchsorted(sb, sb, side="left")
    rank = np.empty(len(b), np.int64)
    rank[order] = np.arange(len(b)) - start
    kept = rank < want[b]
    short = np.maximum(want - have, 0)
    target = exact_sum(expect)
    stats = {"target_plants": exact_mean(target, 1), "candidates": int(len(b)), "placed": int(kept.sum()),
             "shortfall_plants": int(short.sum()), "blocks_short": int((short > 0).sum())}
    return kept, stats, target


def lowest_radius(e, nmax: float) -> float:
    """A species' smallest Poisson radius: its min_spacing_m, or the spacing
    its densest target fills if wider."""
    return max(e.min_spacing_m, math.sqrt(KAPPA * FILL / nmax))


def radius_field(n: np.ndarray, r_lo: float) -> np.ndarray:
    """float32 Poisson radius per terrain cell from the target n (plants per
    m^2): the spacing that fills it, within [r_lo, 2 r_lo]; 0 where n is 0."""
    with np.errstate(divide="ignore"):
        rad = np.where(n > 0, np.clip(np.sqrt(KAPPA * FILL / np.where(n > 0, n, 1.0)), r_lo, 2.0 * r_lo), 0.0)
    return rad.astype(F)


def place_species(params: VegetationParams, names: list[str], n_t: np.ndarray, dom: Domain, seed: int, backend,
                  local=None, progress=None) -> dict[str, Placed]:
    """Every plant species, in placement order, on the terrain grid's domain."""
    order = placement_order(params, names)
    done: dict[str, Placed] = {}
    prev: list[tuple[Placed, float]] = []
    block = max(1, int(round(params.density_block_m / dom.dx)))
    for k, name in enumerate(order):
        s = names.index(name)
        e = params.species[name]
        n = n_t[s]
        t0 = time.perf_counter()
        nmax = float(n.max()) if n.size else 0.0
        if nmax <= 0:
            done[name] = Placed(name, np.zeros(0, F), np.zeros(0, F), np.zeros(0, F), np.zeros(0, np.int64),
                                {"target_plants": 0.0, "candidates": 0, "placed": 0, "shortfall_plants": 0})
            prev.append((done[name], e.collision_radius_m))
            continue
        r_lo = lowest_radius(e, nmax)
        rad = radius_field(n, r_lo)
        c = r_lo / math.sqrt(2.0)
        obstacles = _obstacles(prev, e.collision_radius_m, dom, c)
        pts, cells, pinfo = poisson_sample(rad, r_lo, dom, params.poisson_passes,
                                           ref.stream_key(seed, "poisson", name), backend, obstacles, local)
        kept, stats, _ = select_counts(pts, cells, n, dom, block, ref.stream_key(seed, "select", name))
        stats.update(pinfo, r_lo_m=r_lo, seconds=time.perf_counter() - t0,
                     obstacles=int(len(obstacles[1])) if obstacles[2] else 0)
        done[name] = Placed(name, pts[kept, 0], pts[kept, 1], pts[kept, 2], cells[kept], stats)
        prev.append((done[name], e.collision_radius_m))
        if progress:
            progress((k + 1) / len(order), f"placed {name}")
    return done


# --------------------------------------------------------------------------- instance attributes

def quaternions(yaw: np.ndarray, tilt: np.ndarray, tilt_dir: np.ndarray) -> np.ndarray:
    """(n, 4) float64 (i, j, k, real): a turn `yaw` about +Y, then a lean of
    `tilt` about the horizontal axis at azimuth `tilt_dir` (radians)."""
    qy = np.stack([np.zeros_like(yaw), np.sin(yaw / 2), np.zeros_like(yaw), np.cos(yaw / 2)], -1)
    ax, az = np.cos(tilt_dir), np.sin(tilt_dir)
    st = np.sin(tilt / 2)
    qt = np.stack([ax * st, np.zeros_like(tilt), az * st, np.cos(tilt / 2)], -1)
    # q = qt * qy (Hamilton product, vector part first)
    v1, w1 = qt[:, :3], qt[:, 3:]
    v2, w2 = qy[:, :3], qy[:, 3:]
    v = w1 * v2 + w2 * v1 + np.cross(v1, v2)
    w = w1 * w2 - (v1 * v2).sum(-1, keepdims=True)
    return np.concatenate([v, w], -1)


@dataclass
class Instances:
    """Instances of one species, ready for USD."""

    name: str
    positions: np.ndarray  # (n, 3) float32 world x, y, z
    orientations: np.ndarray  # (n, 4) float16 (i, j, k, real)
    scales: np.ndarray  # (n, 3) float32
    age: np.ndarray  # (n,) float32 years
    random: np.ndarray  # (n,) float32 in [0, 1)
    ids: np.ndarray  # (n,) int64
    radius: np.ndarray  # (n,) float32 minimum distance to another instance of the species (m)

    def __len__(self):
        return len(self.positions)

    def subset(self, keep: np.ndarray) -> "Instances":
        return Instances(self.name, self.positions[keep], self.orientations[keep], self.scales[keep], self.age[keep],
                         self.random[keep], self.ids[keep], self.radius[keep])


def keep_allowed(inst: Instances, allowed: np.ndarray, dom: Domain) -> tuple[Instances, int]:
    """Drop the (rare) instances whose float32 world position falls, by a
    rounding, into a neighbouring cell where the species may not grow."""
    tr, tc = dom.world_cell(inst.positions)
    keep = allowed[tr, tc]
    return (inst if keep.all() else inst.subset(keep)), int((~keep).sum())


def keep_out_of_water(inst: Instances, water: np.ndarray, half_m: np.ndarray, dom: Domain,
                      margin_m: float) -> tuple[Instances, int]:
    """The instances not in_water, and how many were."""
    wet = in_water(inst, water, half_m, dom, margin_m)
    return (inst, 0) if not wet.any() else (inst.subset(~wet), int(wet.sum()))


def in_water(inst: Instances, water: np.ndarray, half_m: np.ndarray, dom: Domain, margin_m: float,
             first=(0, 0)) -> np.ndarray:
    """bool per instance: standing in a river. A cell of a wide river's bank
    is allowed, but the river's ribbon covers part of it. The ribbon is
    taken as half_m (a water cell's half bankfull width, the hydrology
    stage's) either side of the segments joining the centres of 8-adjacent
    water cells (the larger half width of the two ends); an instance within
    it plus margin_m is in. water, half_m: the world's, or a window of it
    from cell `first` holding the cells within the widest half width of
    every instance (a tile's instances and that halo: the world's answer)."""
    if not len(inst) or not water.any():
        return np.zeros(len(inst), bool)
    from scipy import ndimage

    rows, cols = water.shape
    reach = int(np.ceil((float(half_m.max()) + margin_m) / dom.dx)) + 1
    near = ndimage.binary_dilation(water, np.ones((2 * reach + 1, 2 * reach + 1), bool))
    tr, tc = dom.world_cell(inst.positions)
    tr, tc = tr - first[0], tc - first[1]
    cand = np.nonzero(near[tr, tc])[0]
    # positions in cells from the candidate's own cell centre: exact segment distances on a small lattice
    fx = (inst.positions[cand, 0].astype(np.float64) - dom.origin_m[0]) / dom.dx - (tc[cand] + first[1] + 0.5)
    fz = (inst.positions[cand, 2].astype(np.float64) - dom.origin_m[1]) / dom.dx - (tr[cand] + first[0] + 0.5)
    wet = np.zeros(len(cand), bool)
    at = lambda r, c: (np.clip(r, 0, rows - 1), np.clip(c, 0, cols - 1), (r >= 0) & (r < rows) & (c >= 0) & (c < cols))
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            r, c, inside = at(tr[cand] + dr, tc[cand] + dc)
            start = inside & water[r, c]
            for sr, sc in ((0, 0), (0, 1), (1, 1), (1, 0), (1, -1)):  # the cell itself, then its segments
                r2, c2, inside2 = at(r + sr, c + sc)
                seg = start & inside2 & water[r2, c2]
                if not seg.any():
                    continue
                # distance (cells) from the instance to the segment from (dc, dr) to (dc + sc, dr + sr)
                t = np.clip(((fx - dc) * sc + (fz - dr) * sr) / max(sc * sc + sr * sr, 1), 0.0, 1.0)
                d = np.hypot(fx - dc - t * sc, fz - dr - t * sr) * dom.dx
                wet |= seg & (d < np.maximum(half_m[r, c], half_m[r2, c2]) + margin_m)
    out = np.zeros(len(inst), bool)
    out[cand[wet]] = True
    return out


def world_positions(x: np.ndarray, z: np.ndarray, dom: Domain, mesh) -> np.ndarray:
    """float32 world positions on the terrain mesh: x, z rounded to float32
    first, then the height of the mesh triangle under that exact point."""
    from worldlib.terrain.mesh import height_on_mesh

    wx = (dom.x0 + x.astype(np.float64)).astype(F)
    wz = (dom.z0 + z.astype(np.float64)).astype(F)
    wy = height_on_mesh(mesh, wx.astype(np.float64), wz.astype(np.float64)).astype(F)
    return np.stack([wx, wy, wz], -1)


def plant_ages(p: Placed, s: int, sim, dom: Domain, params: VegetationParams, seed: int) -> np.ndarray:
    """The age of the simulated plant of the same species nearest in grid
    terms (the instance's own simulation cell, then its 5 x 5 neighbours in a
    fixed order); without one, a random age up to maturity."""
    e = params.species[p.name]
    n = len(p.x)
    key = ref.stream_key(seed, "age", p.name)
    fallback = (ref.uniform(key, p.cell, 0, 0).astype(np.float64) * e.maturity_years)
    if sim is None or n == 0:
        return fallback
    g = sim.grid.g
    ix = np.minimum(((dom.x0 - dom.origin_m[0] + p.x.astype(np.float64)) / g).astype(np.int64), sim.grid.nx - 1)
    iz = np.minimum(((dom.z0 - dom.origin_m[1] + p.z.astype(np.float64)) / g).astype(np.int64), sim.grid.nz - 1)
    age = np.full(n, np.nan)
    offs = sorted(((a, b) for a in range(-2, 3) for b in range(-2, 3)), key=lambda o: (o[0] ** 2 + o[1] ** 2, o))
    for dz, dxx in offs:
        zz, xx = iz + dz, ix + dxx
        ok = (zz >= 0) & (zz < sim.grid.nz) & (xx >= 0) & (xx < sim.grid.nx) & np.isnan(age)
        if not ok.any():
            continue
        zc, xc = np.clip(zz, 0, sim.grid.nz - 1), np.clip(xx, 0, sim.grid.nx - 1)
        match = ok & (sim.sp[zc, xc] == s)
        age[match] = sim.year - sim.birth[zc, xc][match]
    return np.where(np.isnan(age), fallback, age)


def instances(p: Placed, s: int, params: VegetationParams, dom: Domain, mesh, sim, seed: int) -> Instances:
    e = params.species[p.name]
    n = len(p.x)
    key = ref.stream_key(seed, "instance", p.name)
    u = [ref.uniform(key, p.cell, k, 0).astype(np.float64) for k in range(5)]
    age = plant_ages(p, s, sim, dom, params, seed)
    grow = np.minimum(1.0, 0.1 + 0.9 * age / e.maturity_years)
    s0, s1 = e.scale_range
    scale = (s0 + (s1 - s0) * grow) * (0.92 + 0.16 * u[0])
    q = quaternions(2 * np.pi * u[1], np.radians(e.tilt_deg) * u[2], 2 * np.pi * u[3])
    pos = world_positions(p.x, p.z, dom, mesh) if n else np.zeros((0, 3), F)
    ids = (np.int64(zlib.crc32(p.name.encode()) & 0x7FFFFFFF) << np.int64(32)) | p.cell.astype(np.int64)
    return Instances(p.name, pos, q.astype(np.float16), np.repeat(scale[:, None], 3, 1).astype(F),
                     age.astype(F), u[4].astype(F), ids, p.r.astype(F))


# --------------------------------------------------------------------------- checks

WINDOW_M = 512.0  # the density check's window, in metres (64 cells of the default world's 8 m)
WINDOW_FLOOR_PLANTS = 200.0  # windows whose target count is below this are not judged


def density_error(x: np.ndarray, z: np.ndarray, n_t: np.ndarray, dom: Domain, window: int | None = None,
                  floor: float = WINDOW_FLOOR_PLANTS) -> dict:
    """Placed count against the target count over non-overlapping windows of
    window x window terrain cells (default WINDOW_M; whole windows only)
    whose target count is at least `floor`: the largest and the mean
    relative error."""
    w = density_window(dom, window)
    expect, got = density_windows(x, z, n_t, dom, w)
    return density_error_of(expect.ravel(), got.ravel(), w, floor)


def density_window(dom: Domain, window: int | None = None) -> int:
    """The check's window in cells: WINDOW_M of this world's cells unless
    given, so at 1 m as at 8 m a window holds enough plants to judge."""
    cells = window if window is not None else max(1, int(round(WINDOW_M / dom.dx)))
    return min(cells, dom.rows, dom.cols)


def density_windows(x: np.ndarray, z: np.ndarray, n_t: np.ndarray, dom: Domain, w: int,
                    first=(0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """Target and placed counts of the whole w x w windows in n_t (the
    world's, or the windows of a part from cell `first`, a multiple of w)
    whose cells all lie in the world; x, z: the plants in that part."""
    tr, tc = dom.cell_of(np.asarray(x), np.asarray(z))
    return density_windows_of_cells(tr, tc, n_t, dom, w, first)


def density_windows_of_cells(tr: np.ndarray, tc: np.ndarray, n_t: np.ndarray, dom: Domain, w: int,
                             first=(0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """density_windows from the plants' terrain cells (Domain.cell_of)."""
    rows, cols = n_t.shape
    nr = max(min(rows, dom.rows // w * w - first[0]) // w, 0)
    nc = max(min(cols, dom.cols // w * w - first[1]) // w, 0)
    expect = block_sum(n_t[: nr * w, : nc * w] * dom.dx * dom.dx, w) if nr and nc else np.zeros((nr, nc))
    tr, tc = tr - first[0], tc - first[1]
    inside = (tr >= 0) & (tc >= 0) & (tr < nr * w) & (tc < nc * w)
    got = np.zeros((nr, nc))
    np.add.at(got, (tr[inside] // w, tc[inside] // w), 1)
    return expect, got


def density_error_of(expect: np.ndarray, got: np.ndarray, w: int, floor: float = WINDOW_FLOOR_PLANTS) -> dict:
    """density_error's statistics from the windows' counts (in any order:
    exact sums)."""
    judged = expect >= floor
    rel = np.abs(got - expect)[judged] / expect[judged]
    total_expect, total_got = exact_mean(exact_sum(expect), 1), exact_mean(exact_sum(got), 1)
    return {"windows": int(judged.sum()), "window_cells": w, "floor_plants": floor,
            "max_relative_error": float(rel.max()) if rel.size else 0.0,
            "mean_relative_error": exact_mean(exact_sum(rel), rel.size) if rel.size else 0.0,
            "total_relative_error": float(abs(total_got - total_expect) / total_expect) if total_expect > 0 else 0.0}
