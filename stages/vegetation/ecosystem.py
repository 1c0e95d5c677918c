"""The ecosystem simulation (seed 003 ch. 3; Deussen et al. 1998; Benes 2002)
on a grid of cells that hold at most one plant each, so one step costs
O(cells) and the run scales to millions of plants.

A step of `step_years` from year t (all in kernels.cl, mirrored in reference.py):
1. seed rain: mature plants (age >= maturity) of each species counted in a
   square window of half-width dispersal_m (integer box sums);
2. ageing and death: a plant dies past its own lifespan (lifespan_years
   +- spread), or with probability dt * stress_mortality * (1 - suitability);
3. establishment on free cells: species s lands with probability
   suit_s * lam / (1 + lam), lam = dt * (seed_rate * mature count / window
   cells + background); several landing: an exponential race (the smallest
   u / p wins);
4. self-thinning: spheres of influence R(age) = radius * min(1, 0.1 + 0.9 age /
   maturity) around jittered positions; where two overlap, the weaker plant
   (strength = height(age) * vitality * (0.25 + 0.75 suitability), height
   growing from height_m * scale_range[0] to height_m * scale_range[1] at
   maturity, vitality = 0.5 + 0.5 tent(age / life), Benes's mid-life peak) is
   shaded (dominated) and survives only with its shade tolerance (per year,
   compounded over the step). Taller species shade lower ones, as in Lane and
   Prusinkiewicz's multilevel communities: trees over shrubs. Resolved in
   parallel rounds: local maxima of strength among the overlapping plants win,
   the plants they overlap are dominated, the rest compete again (this is
   exactly the sequential strongest-first result, independent of order).

The start: initial_density_per_ha plants (at most one per cell) of a
species drawn in proportion to suitability, of uniformly random age; it
thins itself. Seed rain from far away is background_seed_per_ha per year.

Outputs: the final plants; per species its relative yield (de Wit): the
number of its plants within share_radius_m in the mixture, over the number
the species reaches alone on the same sites (a small calibration run of the
same simulation with that species only, at suitability levels 1/8 .. 1, on
the same grid, for the same years). It is 1 where the species holds the
ground alone and falls where others win; species of different layers (trees
over shade-tolerant shrubs) can each keep a large share. The ratio of two
counts on the same grid cancels most of the grid's one-plant-per-cell limit,
which is what makes the result converge as sim_cell_m shrinks (see the
benchmark). And the stability record: population per step and species,
plateau and share entropy.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from worldlib.terrain.blocks import block_mean, coarse_factor

from . import reference as ref
from .params import VegetationParams

F = np.float32


@dataclass
class SimGrid:
    nx: int
    nz: int
    g: float  # cell size, m


@dataclass
class SimResult:
    grid: SimGrid
    names: list[str]
    sp: np.ndarray  # (nz, nx) int32, -1 empty
    birth: np.ndarray  # (nz, nx) int32
    year: int
    radius_m: np.ndarray  # (nz, nx) float64 radius of influence of each plant (0 empty)
    history: list[dict] = field(default_factory=list)  # per step: year, counts per species
    stats: dict = field(default_factory=dict)


def sim_grid(cols: int, rows: int, dx: float, g: float) -> SimGrid:
    return SimGrid(max(1, math.ceil(cols * dx / g - 1e-9)), max(1, math.ceil(rows * dx / g - 1e-9)), g)


def block_factor(rows: int, cols: int, dx: float, grid: SimGrid) -> int:
    """f when the simulation cell is f x f whole terrain cells tiling the
    terrain exactly (f >= 2), else 0."""
    f = coarse_factor(rows, cols, dx, grid.g)
    exact = f >= 2 and abs(f * dx - grid.g) <= 1e-9 * grid.g and grid.nx * f == cols and grid.nz * f == rows
    return f if exact else 0


def to_sim_grid(a: np.ndarray, dx: float, grid: SimGrid) -> np.ndarray:
    """Terrain-grid fields (..., rows, cols) sampled at the simulation cell
    centres (area mean when the simulation cell is coarser). When it is f x f
    whole terrain cells, the means are worldlib's block means (a fixed
    order: a tile's blocks have the whole map's bits); otherwise a box
    filter of the cell's size read at each centre (the same area)."""
    rows, cols = a.shape[-2:]
    f = block_factor(rows, cols, dx, grid)
    if f:
        lead = a.reshape((-1, rows, cols))
        return np.ascontiguousarray(np.stack([block_mean(x, f) for x in lead]).reshape(
            a.shape[:-2] + (grid.nz, grid.nx)).astype(F))
    k = grid.g / dx
    if k > 1.5:
        size = (1,) * (a.ndim - 2) + (int(round(k)),) * 2
        a = ndimage.uniform_filter(a.astype(np.float64), size=size, mode="nearest")
    ci = np.minimum(((np.arange(grid.nx) + 0.5) * grid.g / dx).astype(np.int64), cols - 1)
    ri = np.minimum(((np.arange(grid.nz) + 0.5) * grid.g / dx).astype(np.int64), rows - 1)
    return np.ascontiguousarray(a[..., ri[:, None], ci[None, :]].astype(F))


def species_table(params: VegetationParams, names: list[str], g: float, seed: int) -> tuple[np.ndarray, int]:
    """The kernel's species table (SPW floats per species) and the
    neighbourhood NB (cells) that covers every possible overlap."""
    dt = params.step_years
    tab = np.zeros((len(names), ref.SPW), F)
    rmax = 0.0
    for s, name in enumerate(names):
        sp = params.species[name]
        w = max(1, int(round(sp.dispersal_m / g)))
        key = ref.stream_key(seed, "ecosystem", name)
        tab[s, 0] = sp.maturity_years
        tab[s, 1] = 1.0 / sp.maturity_years
        tab[s, 2] = sp.lifespan_years
        tab[s, 3] = sp.lifespan_spread
        tab[s, 4] = sp.radius_m / g
        tab[s, 5] = sp.shade_tolerance ** dt
        tab[s, 6] = dt * sp.seed_rate / float((2 * w + 1) ** 2)
        tab[s, 7] = dt * params.background_seed_per_ha * g * g / 1e4
        tab[s, 8] = w
        tab[s, 9] = np.array([key], np.uint32).view(F)[0]
        tab[s, 10] = sp.height_m * sp.scale_range[0]
        tab[s, 11] = sp.height_m * (sp.scale_range[1] - sp.scale_range[0])
        rmax = max(rmax, float(tab[s, 4]))
    nb = max(1, math.ceil(2.0 * rmax))
    return tab.reshape(-1), nb


def initial_state(suit: np.ndarray, params: VegetationParams, names: list[str], seed: int, g: float):
    """initial_density_per_ha plants (at most one per cell): species drawn in
    proportion to suitability, age uniform in [0, lifespan)."""
    nsp, nz, nx = suit.shape
    cell = np.arange(nx * nz, dtype=np.int64).reshape(nz, nx)
    key = ref.stream_key(seed, "ecosystem-start")
    sp = np.full((nz, nx), -1, np.int32)
    birth = np.zeros((nz, nx), np.int32)
    total = suit.astype(np.float64).sum(axis=0)
    if nsp == 0:
        return sp, birth
    fill = min(1.0, params.initial_density_per_ha * g * g / 1e4)
    occupied = (ref.uniform(key, cell, 0, 0) < fill) & (total > 0)
    pick = ref.uniform(key, cell, 1, 0).astype(np.float64) * total
    cum = np.cumsum(suit.astype(np.float64), axis=0)
    choice = np.minimum((cum <= pick[None]).sum(axis=0), nsp - 1).astype(np.int32)
    # a species with zero suitability is never chosen: step past it
    for s in range(nsp):
        bad = occupied & (choice == s) & (suit[s] <= 0)
        if bad.any():
            alt = np.argmax(suit, axis=0).astype(np.int32)
            choice = np.where(bad, alt, choice)
    sp[occupied] = choice[occupied]
    life = np.array([params.species[n].lifespan_years for n in names])
    u_age = ref.uniform(key, cell, 2, 0).astype(np.float64)
    birth = np.where(occupied, -np.floor(u_age * life[np.maximum(sp, 0)]), 0).astype(np.int32)
    return sp, birth


def plant_radius(sp: np.ndarray, birth: np.ndarray, year: int, params: VegetationParams, names: list[str]) -> np.ndarray:
    """Radius of influence (m) of each plant at `year` (0 where empty), the
    kernel's R(age) in float64."""
    out = np.zeros(sp.shape)
    for s, name in enumerate(names):
        m = sp == s
        if m.any():
            e = params.species[name]
            age = (year - birth[m]).astype(np.float64)
            out[m] = e.radius_m * np.minimum(1.0, 0.1 + 0.9 * age / e.maturity_years)
    return out


def simulate(suit: np.ndarray, grid: SimGrid, params: VegetationParams, names: list[str], seed: int,
             backend, local=None, progress=None) -> SimResult:
    """Run the simulation on `backend` (the device module or reference)."""
    t0 = time.perf_counter()
    tab, nb = species_table(params, names, grid.g, seed)
    sp0, birth0 = initial_state(suit, params, names, seed, grid.g)
    sim = backend.Sim(sp0, birth0, suit, tab, nb, local=local)
    key = ref.stream_key(seed, "ecosystem-stress")
    dt = params.step_years
    stress = min(1.0, dt * params.stress_mortality)
    history = []
    rounds_total = 0
    max_rounds = 64

    def thin(t):
        nonlocal rounds_total
        sim.thin_init(t)
        for rnd in range(max_rounds):
            rounds_total += 1
            if sim.thin_round(t, rnd) == 0:
                return rnd + 1
        return max_rounds

    def record(t, rounds):
        s_, _ = sim.read()
        counts = np.bincount(s_[s_ >= 0].ravel(), minlength=len(names))[: len(names)]
        history.append({"year": int(t), "rounds": int(rounds), **{n: int(c) for n, c in zip(names, counts)}})

    record(0, 0)  # the start, before thinning
    record(0, thin(0))
    steps = params.years // dt
    for k in range(1, steps + 1):
        t = k * dt
        sim.seed_counts(t)
        sim.update(t, stress, key)
        record(t, thin(t))
        if progress and (k % 4 == 0 or k == steps):
            progress(k / steps, f"ecosystem year {t}")
    sp, birth = sim.read()
    year = steps * dt
    res = SimResult(grid, list(names), sp, birth, year, plant_radius(sp, birth, year, params, names), history)
    res.stats = stability(history, names)
    res.stats.update(seconds=time.perf_counter() - t0, steps=steps, thinning_rounds=rounds_total,
                     neighbourhood_cells=nb, cells=grid.nx * grid.nz, cell_size_m=grid.g)
    return res


def stability(history: list[dict], names: list[str]) -> dict:
    """Population plateau and species shares of a run."""
    tot = np.array([sum(h[n] for n in names) for h in history], np.float64)
    out: dict = {"population_start": int(tot[0]) if len(tot) else 0,
                 "population_after_first_thinning": int(tot[1]) if len(tot) > 1 else 0,
                 "population_end": int(tot[-1]) if len(tot) else 0}
    if len(tot) > 4 and tot[-1] > 0:
        q = max(2, int(round(0.75 * (len(tot) - 2))) + 1)
        last = tot[q:]
        out["plateau_relative_change"] = float(abs(tot[-1] - tot[q]) / tot[-1])
        out["plateau_relative_std"] = float(last.std() / last.mean()) if last.mean() > 0 else 0.0
    end = np.array([history[-1][n] for n in names], np.float64) if history else np.zeros(len(names))
    shares = end / end.sum() if end.sum() > 0 else end
    out["species_shares"] = {n: float(s) for n, s in zip(names, shares)}
    nz = shares[shares > 0]
    ent = float(-(nz * np.log(nz)).sum()) if len(nz) else 0.0
    out["share_entropy"] = ent
    out["share_evenness"] = ent / math.log(len(names)) if len(names) > 1 else 1.0
    return out


LEVELS = 8  # suitability levels of the calibration run
CAL_SIDE = 40  # cells per side of each level's patch


def alone_density(params: VegetationParams, names: list[str], g: float, seed: int, backend, local=None) -> np.ndarray:
    """(nsp, LEVELS + 1) plants per cell each species reaches alone at
    suitability 0, 1/8, ..., 1: the simulation of that species only on
    patches of uniform suitability (the inner part of each patch counted)."""
    out = np.zeros((len(names), LEVELS + 1))
    levels = np.arange(1, LEVELS + 1) / LEVELS
    for s, name in enumerate(names):
        suit = np.repeat(levels, CAL_SIDE)[:, None] * np.ones((1, CAL_SIDE))
        res = simulate(suit[None].astype(F), SimGrid(CAL_SIDE, CAL_SIDE * LEVELS, g), params, [name],
                       ref.stream_key(seed, "alone"), backend, local)
        m = 4
        for k in range(LEVELS):
            band = res.sp[k * CAL_SIDE + m:(k + 1) * CAL_SIDE - m, m:-m]
            out[s, k + 1] = float((band >= 0).mean())
    return out


def alone_at_full(alone: np.ndarray, names: list[str], g: float) -> dict:
    """alone_density's plants per ha at suitability 1, per species (stats.json)."""
    return {n: float(alone[s, -1] * 1e4 / g ** 2) for s, n in enumerate(names)}


def relative_yield(res: SimResult, params: VegetationParams, suit_sim: np.ndarray, alone: np.ndarray, dx: float,
                   shape: tuple[int, int], first=(0, 0), cells=None) -> np.ndarray:
    """Per species (nsp, rows, cols) on the terrain grid: plants of the
    species within share_radius_m over the number it reaches alone on the
    same cells (alone density interpolated at each cell's suitability),
    clipped to [0, 1]; 0 where it cannot grow. shape: the terrain's; the
    cells of a window of it: `cells` (rows, cols) from its cell `first`
    (row, col), the whole terrain's values there bit for bit."""
    return yield_on_terrain(sim_yield(res, params, suit_sim, alone), res.grid.g, dx, shape, first, cells)


def sim_yield(res: SimResult, params: VegetationParams, suit_sim: np.ndarray, alone: np.ndarray) -> np.ndarray:
    """(nsp, nz, nx) the relative yield on the simulation grid (0..1)."""
    names, g = res.names, res.grid.g
    k = 2 * int(round(params.share_radius_m / g)) + 1
    levels = np.arange(LEVELS + 1) / LEVELS
    out = np.zeros((len(names), res.grid.nz, res.grid.nx))
    for s in range(len(names)):
        have = (res.sp == s).astype(np.float64)
        want = np.interp(suit_sim[s].astype(np.float64), levels, alone[s])
        if k > 1:
            have = ndimage.uniform_filter(have, size=k, mode="constant")
            want = ndimage.uniform_filter(want, size=k, mode="constant")
        ry = np.where(want > 1e-9, have / np.where(want > 1e-9, want, 1.0), 0.0)
        out[s] = np.clip(ry, 0.0, 1.0)
    return out


def yield_on_terrain(ry: np.ndarray, g: float, dx: float, shape: tuple[int, int], first=(0, 0),
                     cells=None) -> np.ndarray:
    """sim_yield's (nsp, nz, nx) read bilinearly at terrain cell centres:
    the whole terrain of `shape`, or `cells` (rows, cols) from its cell
    `first` (coordinates from world indices: a window has the world's bits)."""
    rows, cols = shape if cells is None else cells
    xc = (first[1] + np.arange(cols) + 0.5) * dx / g - 0.5
    zc = (first[0] + np.arange(rows) + 0.5) * dx / g - 0.5
    Z, X = np.meshgrid(zc, xc, indexing="ij")
    out = np.zeros((len(ry), rows, cols))
    for s in range(len(ry)):
        out[s] = ndimage.map_coordinates(ry[s], [Z, X], order=1, mode="nearest")
    return np.clip(out, 0.0, 1.0)
