"""Sites: what the terrain's shape and its water make of a place beyond
the local attributes (host numpy; whole-map operations: distance
transforms, flow lines), and how they change each species' suitability.

- Effective altitude (tree line by aspect): altitude - shift / 2 * cos(aspect
  - equator azimuth) * steepness, shift = treeline_aspect_shift_m and
  steepness a smoothstep of the slope over 0 .. ASPECT_FULL_SLOPE_DEG. Every
  species' altitude range is judged on it, so a steep sun-facing slope
  carries each zone shift / 2 higher and a shaded one shift / 2 lower
  (Holtmeier 2009, Koerner 2012: tree lines on sunny slopes typically
  100-200 m higher).
- Riparian index (banks and flood-prone valley floors), 0..1: for every cell
  the nearest water cell (river or lake, Euclidean), its water level (lake
  level; the river cell's ground) and distance from its edge (river: minus
  half its width); index = (1 - S(height above / riparian_height_m)) x
  (1 - S(distance / riparian_distance_m)), S the smoothstep on [0, 1]:
  a height above the nearest drainage (HAND, Renno et al. 2008) limited to
  the water's neighbourhood. 1 on the water.
- Avalanche paths: release cells where altitude >= avalanche_release_min_m,
  the slope is within avalanche_release_slope_{min,max}_deg and a
  counter-based patch noise is in its top avalanche_release_share (whole
  patches release, so a planar face sends a band, not a comb of lines); each
  avalanche runs down the steepest descent (D8) while the line falling at
  avalanche_alpha_deg from its release height stays above the ground (the
  alpha angle of Lied and Bakkehoi 1980); over a flat straight on. A cell
  keeps the highest line per direction of arrival (RunOut), so the result
  is exact and does not depend on order: tiles spread in rounds give the
  whole world's. The track is the path
  widened to avalanche_track_width_m with a soft edge.
- Clearings: a three-octave counter-based value noise of wavelength
  clearing_size_m in its top clearing_share (the noise's quantile measured on
  a fixed reference sample, so the share does not depend on the world's
  size), with a soft edge.
Trees (species with tree = true) get suitability x (1 - avalanche) x (1 -
clearing); every species gets its riparian preference factor.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from . import reference as ref
from .params import VegetationParams

F = np.float32
ASPECT_FULL_SLOPE_DEG = 20.0  # flat ground faces nowhere: the aspect shift grows to its full size by this slope
CLEARING_OCTAVES = 3  # irregular outlines
CLEARING_EDGE = 0.06  # soft edge of a clearing, in units of its noise (which spans about -1 .. 1)
SLOPE_CLASSES_DEG = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 90.0)  # the forest-by-slope table's classes
CHANNELS = ("site.other", "site.riparian", "site.avalanche", "site.clearing", "altitude.effective")  # the sites grid
D8 = ((-1, 0), (0, 1), (1, 0), (0, -1), (-1, -1), (-1, 1), (1, 1), (1, -1))  # row, col: a fixed order (ties)


@dataclass(frozen=True)
class Sites:
    altitude: np.ndarray  # float32 effective altitude (m) the altitude preferences judge
    riparian: np.ndarray  # float32 0..1
    avalanche: np.ndarray  # float32 0..1 (1 in the track)
    clearing: np.ndarray  # float32 0..1
    stats: dict = field(default_factory=dict)

    def channels(self) -> tuple[np.ndarray, tuple[str, ...]]:
        """The sites grid: the three site weights, the rest (1 - their
        largest) and the effective altitude."""
        rest = 1.0 - np.maximum(np.maximum(self.riparian, self.avalanche), self.clearing)
        data = np.stack([rest, self.riparian, self.avalanche, self.clearing, self.altitude], -1)
        return data.astype(F), CHANNELS


def smooth01(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def effective_altitude(h: np.ndarray, slope_deg: np.ndarray, aspect_deg: np.ndarray, shift_m: float,
                       latitude_deg: float) -> np.ndarray:
    """The altitude the species' ranges judge: lower on sun-facing slopes."""
    equator = 180.0 if latitude_deg >= 0.0 else 0.0
    sunward = np.cos(np.radians(aspect_deg.astype(np.float64) - equator))
    steep = smooth01(slope_deg.astype(np.float64) / ASPECT_FULL_SLOPE_DEG)
    return (h.astype(np.float64) - 0.5 * shift_m * sunward * steep).astype(F)


def riparian_index(h: np.ndarray, water: np.ndarray, level: np.ndarray, half_width: np.ndarray, dx: float,
                   height_m: float, distance_m: float) -> np.ndarray:
    """0..1: near the water and little above it (1 on the water)."""
    if not water.any():
        return np.zeros(h.shape, F)
    dist, (ri, ci) = ndimage.distance_transform_edt(~water, return_indices=True)
    above = h.astype(np.float64) - level[ri, ci]
    away = np.maximum(dist * dx - half_width[ri, ci], 0.0)
    out = (1.0 - smooth01(above / height_m)) * (1.0 - smooth01(away / distance_m))
    return np.where(water, 1.0, out).astype(F)


def water_mask(depth: np.ndarray | None, mask: np.ndarray | None, shape) -> np.ndarray:
    """Where lakes (depth > 0) or rivers (mask > 0.5) are: nothing grows there.
    depth, mask: float64 with NaN as 0, or None without the input."""
    water = np.zeros(shape, bool)
    if depth is not None:
        water |= depth > 0
    if mask is not None:
        water |= mask > 0.5
    return water


def water_levels(h: np.ndarray, depth: np.ndarray | None, level: np.ndarray | None) -> np.ndarray:
    """Per cell the level of its water for the riparian index: a lake's
    level where it is deeper than 0, else the ground."""
    out = h.astype(np.float64).copy()
    if depth is not None and level is not None:
        out = np.where((depth > 0) & np.isfinite(level), level, out)
    return out


def half_widths(water: np.ndarray, width: np.ndarray | None) -> np.ndarray:
    """Half a river cell's bankfull width (width: NaN as 0), 0 elsewhere and on lakes' cells without one."""
    if width is None:
        return np.zeros(water.shape)
    return np.where(water, 0.5 * np.maximum(width, 0.0), 0.0)


def avalanche_stats(release_cells: int, path_cells: int, track_cells: int, cells: int) -> dict:
    """avalanche_tracks' statistics from its counts (a tiled run's tiles add them up)."""
    if not release_cells:
        return {"release_share": 0.0, "path_share": 0.0, "track_share": 0.0}
    return {"release_share": release_cells / cells, "path_share": path_cells / cells, "track_share": track_cells / cells}


def site_stats(avalanche: dict, land_cells: int, riparian_cells: int, clearing_cells: int,
               shift_min: float | None, shift_max: float | None) -> dict:
    """The sites' statistics from counts and the altitude shift's extremes over the land (None: no land)."""
    n = max(land_cells, 1)
    return {"avalanche": avalanche, "riparian_share": riparian_cells / n, "clearing_share": clearing_cells / n,
            "altitude_shift_range_m": [round(shift_min, 2) if shift_min is not None else 0.0,
                                       round(shift_max, 2) if shift_max is not None else 0.0]}


def riparian_halo(dx: float, params: VegetationParams, max_half_width_m: float) -> int:
    """The cells around a tile its riparian index reads: beyond
    riparian_distance_m plus the widest river's half width the index is 0
    whichever water is nearest, so a tile read with this halo gets the whole
    world's values (the nearest water cell it finds is the world's wherever
    the index is not 0)."""
    return int(math.ceil((params.riparian_distance_m + max_half_width_m) / dx)) + 2


def d8_receivers(h: np.ndarray, dx: float) -> np.ndarray:
    """Per cell (flat index) the D8 index of the steepest lower neighbour
    (-1: none, a flat or a pit)."""
    hp = np.pad(h.astype(np.float64), 1, constant_values=np.inf)
    rows, cols = h.shape
    best = np.zeros(h.shape)
    way = np.full(h.shape, -1, np.int64)
    for k, (dr, dc) in enumerate(D8):
        drop = (h - hp[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols]) / (dx * math.hypot(dr, dc))
        better = drop > best
        best = np.where(better, drop, best)
        way = np.where(better, k, way)
    return way.ravel()


def run_out(h: np.ndarray, release: np.ndarray, dx: float, alpha_deg: float) -> np.ndarray:
    """bool: the cells avalanches from `release` reach (RunOut: each runs
    down the D8 steepest descent, over a flat straight on where that does
    not climb, while its alpha line is at or above the ground)."""
    run = RunOut(h, d8_receivers(h, dx), dx, alpha_deg)
    run.spread(run.seed(np.flatnonzero(release.ravel()), np.full(int(release.sum()), NO_HEADING),
                        h.astype(np.float64).ravel()[release.ravel()]))
    return run.path()


NO_HEADING = 8  # the state slot of a line that keeps no direction (a release, or a cell with a lower neighbour)


class RunOut:
    """Avalanche lines on a grid (the world, or a tile and a one-cell halo).

    A line falls tan(alpha) per metre of run from its release height and
    goes on while at or above the ground. From a cell with a lower neighbour
    it moves to the steepest (d8_receivers); from a flat it goes straight on
    in the direction it came from, where that does not climb. So a cell's
    lines differ only by that direction: the state is the highest line per
    (cell, slot), slot the direction of arrival on a flat and NO_HEADING
    elsewhere. Each state's value is the highest over every path reaching
    it, each path's value its release height less its steps' falls, in the
    path's order: the states are the same, bit for bit, in whatever order
    lines are spread, so a world spread tile by tile (its lines crossing
    into neighbours in rounds) equals the world spread whole.

    own: the cells lines spread from (a tile's; default all); a line
    reaching another cell is settled there and reported by spread() as a
    crossing, for the neighbour that owns it."""

    def __init__(self, h: np.ndarray, way: np.ndarray, dx: float, alpha_deg: float, own: np.ndarray | None = None):
        self.shape = h.shape
        self.hf = h.astype(np.float64).ravel()
        self.way = way
        self.own = np.ones(self.hf.size, bool) if own is None else own.ravel()
        self.off = np.asarray(D8, np.int64)
        self.fall = math.tan(math.radians(alpha_deg)) * dx * np.hypot(self.off[:, 0], self.off[:, 1])
        self.line = np.full((self.hf.size, NO_HEADING + 1), -np.inf)

    def slot(self, cells: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """Where a line arriving with `heading` is kept: its heading on a flat."""
        return np.where(self.way[cells] >= 0, NO_HEADING, heading)

    def seed(self, cells: np.ndarray, slots: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raise states to `values` (a maximum: any order); the states raised."""
        flat = cells * (NO_HEADING + 1) + slots
        line = self.line.ravel()
        before = line[flat]
        np.maximum.at(line, flat, values)
        raised = np.unique(flat[line[flat] > before])
        return np.divmod(raised, NO_HEADING + 1)

    def spread(self, active: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Move the active states' lines on until none moves; the lines
        reaching cells not owned (cell, heading, value), for their owner's
        seed(cells, slot(cells, headings), values)."""
        rows, cols = self.shape
        out_cells, out_headings, out_values = [], [], []
        cells, slots = active
        while cells.size:
            keep = self.own[cells]
            cells, slots = cells[keep], slots[keep]
            k = np.where(self.way[cells] >= 0, self.way[cells], np.where(slots < NO_HEADING, slots, -1))
            r, c = np.divmod(cells, cols)
            kk = np.maximum(k, 0)
            r2, c2 = r + self.off[kk, 0], c + self.off[kk, 1]
            inside = (k >= 0) & (r2 >= 0) & (r2 < rows) & (c2 >= 0) & (c2 < cols)
            nxt = np.where(inside, r2 * cols + c2, 0)
            e = self.line[cells, slots] - self.fall[kk]
            ok = inside & (e >= self.hf[nxt]) & ((self.way[cells] >= 0) | (self.hf[nxt] <= self.hf[cells]))
            nxt, e, k = nxt[ok], e[ok], k[ok]
            away = ~self.own[nxt]  # the owner keeps its slot (this grid may not see the cell's neighbours)
            out_cells.append(nxt[away]), out_headings.append(k[away]), out_values.append(e[away])
            cells, slots = self.seed(nxt, self.slot(nxt, k), e)
        cat = np.concatenate
        return (cat(out_cells) if out_cells else np.zeros(0, np.int64), cat(out_headings) if out_headings else
                np.zeros(0, np.int64), cat(out_values) if out_values else np.zeros(0))

    def path(self) -> np.ndarray:
        """bool: where a line is at or above the ground."""
        return (self.line.max(axis=1) >= self.hf).reshape(self.shape)


def _lattice_noise(x: np.ndarray, z: np.ndarray, key: int) -> np.ndarray:
    """Value noise in [-1, 1] on the unit lattice at points (x, z):
    counter-based values at the lattice corners, smoothstep blending."""
    ix, iz = np.floor(x), np.floor(z)
    fx, fz = smooth01(x - ix), smooth01(z - iz)
    ix, iz = ix.astype(np.int64), iz.astype(np.int64)
    x0, z0 = int(ix.min()), int(iz.min())
    nx, nz = int(ix.max()) - x0 + 2, int(iz.max()) - z0 + 2
    if nx * nz <= ix.size:  # hash each lattice corner once (the same values)
        gz, gx = np.meshgrid(np.arange(z0, z0 + nz), np.arange(x0, x0 + nx), indexing="ij")
        table = 2.0 * ref.uniform(key, gx & 0xFFFFFFFF, gz & 0xFFFFFFFF, 0).astype(np.float64) - 1.0

        def v(a, b):
            return table[b - z0, a - x0]
    else:
        def v(a, b):
            return 2.0 * ref.uniform(key, a & 0xFFFFFFFF, b & 0xFFFFFFFF, 0).astype(np.float64) - 1.0
    top = v(ix, iz) + (v(ix + 1, iz) - v(ix, iz)) * fx
    bot = v(ix, iz + 1) + (v(ix + 1, iz + 1) - v(ix, iz + 1)) * fx
    return top + (bot - top) * fz


def noise(shape, dx: float, origin, wavelength: float, key: int, octaves: int, first=(0, 0)) -> np.ndarray:
    """Value noise at the cell centres in world coordinates: octaves at
    wavelength / 2.3^k with amplitude 0.5^k, each on a lattice turned by its
    own angle (no axis-aligned blocks), divided by the amplitudes' sum.
    first: the (row, col) of the array's first cell in the world whose
    origin is `origin` (a window of it has the world's bits)."""
    rows, cols = shape
    x = (origin[0] + (first[1] + np.arange(cols) + 0.5) * dx)[None, :]
    z = (origin[1] + (first[0] + np.arange(rows) + 0.5) * dx)[:, None]
    total, amp, out = 0.0, 1.0, np.zeros(shape)
    for k in range(octaves):
        a, w = 0.6 + 1.1 * k, wavelength / 2.3 ** k
        u, t = (x * math.cos(a) - z * math.sin(a)) / w, (x * math.sin(a) + z * math.cos(a)) / w
        out += amp * _lattice_noise(u, t, (key + 0x9E3779B9 * k) & 0xFFFFFFFF)
        total += amp
        amp *= 0.5
    return out / total


@functools.lru_cache(maxsize=64)
def noise_threshold(share: float, octaves: int) -> float:
    """The noise value exceeded on `share` of the land: its quantile on a
    fixed reference sample (512 x 512 points over 64 x 64 wavelengths)."""
    sample = noise((512, 512), 1.0 / 8.0, (0.0, 0.0), 1.0, ref.stream_key(0, "noise-quantile"), octaves)
    return float(np.quantile(sample, 1.0 - share))


def release_cells(h, slope, blocked, params: VegetationParams, dx: float, origin, seed: int,
                  first=(0, 0)) -> np.ndarray:
    """bool: where avalanches release (see the module's doc); first: the
    array's first cell in the world (noise)."""
    p = params
    ok = ((h >= p.avalanche_release_min_m) & (slope >= p.avalanche_release_slope_min_deg)
          & (slope <= p.avalanche_release_slope_max_deg) & ~blocked)
    if p.avalanche_release_share <= 0.0 or not ok.any():
        return np.zeros(h.shape, bool)
    if p.avalanche_release_share < 1.0:
        n = noise(h.shape, dx, origin, p.avalanche_release_patch_m, ref.stream_key(seed, "avalanche-release"), 1,
                  first)
        ok &= n > noise_threshold(p.avalanche_release_share, 1)
    return ok


def avalanche_tracks(h, slope, blocked, params: VegetationParams, dx: float, origin,
                     seed: int) -> tuple[np.ndarray, dict]:
    """0..1 track weight (1 on the flow lines, 0.5 at half the track width
    from them) and statistics."""
    release = release_cells(h, slope, blocked, params, dx, origin, seed)
    if not release.any():
        return np.zeros(h.shape, F), avalanche_stats(0, 0, 0, h.size)
    path = run_out(h, release, dx, params.avalanche_alpha_deg)
    half = 0.5 * params.avalanche_track_width_m
    if half > 0.0:
        d = ndimage.distance_transform_edt(~path) * dx
        track = 1.0 - smooth01((d - 0.5 * half) / half)
    else:
        track = path.astype(np.float64)
    return track.astype(F), avalanche_stats(int(release.sum()), int(path.sum()), int((track >= 0.5).sum()), h.size)


def clearings(shape, params: VegetationParams, dx: float, origin, seed: int, first=(0, 0)) -> np.ndarray:
    """0..1 clearing weight: the noise over its threshold, with a soft edge;
    first: the array's first cell in the world."""
    if params.clearing_share <= 0.0:
        return np.zeros(shape, F)
    n = noise(shape, dx, origin, params.clearing_size_m, ref.stream_key(seed, "clearing"), CLEARING_OCTAVES, first)
    t = noise_threshold(params.clearing_share, CLEARING_OCTAVES)
    return smooth01((n - t) / CLEARING_EDGE + 0.5).astype(F)


def compute(h, attributes: dict, water: np.ndarray, blocked: np.ndarray, level: np.ndarray,
            half_width: np.ndarray, params: VegetationParams, dx: float, origin, seed: int) -> Sites:
    """Every site field of the terrain (see the module's doc)."""
    p = params
    alt = effective_altitude(h, attributes["slope"], attributes["aspect"], p.treeline_aspect_shift_m, p.latitude_deg)
    rip = riparian_index(h, water, level, half_width, dx, p.riparian_height_m, p.riparian_distance_m)
    ava, astats = avalanche_tracks(h, attributes["slope"], blocked, p, dx, origin, seed)
    clr = clearings(h.shape, p, dx, origin, seed)
    land = ~blocked
    shift = (h - alt)[land]
    stats = site_stats(astats, int(land.sum()), int(((rip >= 0.5) & land).sum()), int(((clr >= 0.5) & land).sum()),
                       float(shift.min()) if shift.size else None, float(shift.max()) if shift.size else None)
    return Sites(alt, rip, np.where(blocked, F(0), ava).astype(F), clr, stats)


def preference_factor(x: np.ndarray, pref) -> np.ndarray:
    """The suitability kernel's soft range (ramp up from min, down to max)."""
    def ramp(d):
        if pref.edge > 0:
            return smooth01(d / pref.edge)
        return (d > 0).astype(np.float64)
    x = x.astype(np.float64)
    return ramp(x - pref.min) * ramp(pref.max - x)


def apply(suit: np.ndarray, names: list[str], params: VegetationParams, sites: Sites) -> np.ndarray:
    """Suitability x each species' riparian factor, and x (1 - avalanche)
    x (1 - clearing) for trees."""
    out = suit.astype(np.float64)
    open_ground = (1.0 - sites.avalanche.astype(np.float64)) * (1.0 - sites.clearing)
    for s, name in enumerate(names):
        e = params.species[name]
        out[s] *= preference_factor(sites.riparian, e.riparian)
        if e.tree:
            out[s] *= open_ground
    return out.astype(F)


def slope_class(slope: np.ndarray) -> np.ndarray:
    """The forest-by-slope table's class of each slope (deg)."""
    edges = np.asarray(SLOPE_CLASSES_DEG)
    return np.clip(np.digitize(slope, edges[1:-1]), 0, len(edges) - 2)


def forest_by_slope(slope: np.ndarray, land: np.ndarray, trees: list[tuple[np.ndarray, np.ndarray]], dx: float) -> dict:
    """Per slope class: its share of the land, its share of the trees
    (instances of tree species; their cell's slope) and trees per hectare
    of the class's land."""
    nclass = len(SLOPE_CLASSES_DEG) - 1
    cls = slope_class(slope)
    counts = np.zeros(nclass, np.int64)
    for tr, tc in trees:
        counts += np.bincount(cls[tr, tc], minlength=nclass)
    return forest_table(np.bincount(cls[land], minlength=nclass), counts, dx)


def forest_table(land_cells: np.ndarray, tree_counts: np.ndarray, dx: float) -> dict:
    """forest_by_slope's table from the land cells and the trees per class
    (integers: a tiled run's tiles add them up)."""
    edges = np.asarray(SLOPE_CLASSES_DEG)
    nclass = len(edges) - 1
    land_cells, counts = np.asarray(land_cells, np.float64), np.asarray(tree_counts, np.float64)
    total_land, total_trees = max(land_cells.sum(), 1.0), max(counts.sum(), 1.0)
    labels = [f"{edges[k]:g}-{edges[k + 1]:g}" if k < nclass - 1 else f">{edges[k]:g}" for k in range(nclass)]
    return {"classes_deg": labels,
            "land_share": [round(float(v / total_land), 5) for v in land_cells],
            "tree_share": [round(float(v / total_trees), 5) for v in counts],
            "trees_per_ha": [round(float(counts[k] / (land_cells[k] * dx * dx / 1e4)), 3) if land_cells[k] else 0.0
                             for k in range(nclass)],
            "trees": int(counts.sum())}


BANK_INDEX = 0.5  # the banks of plants_on_banks: riparian index at least this


def plants_on_banks(riparian: np.ndarray, land: np.ndarray, cells: dict, dx: float) -> dict:
    """Per plant species its instances per hectare of land on the banks
    (riparian index >= BANK_INDEX) and elsewhere: the banks' own mix."""
    banks = land & (riparian >= BANK_INDEX)
    rest = land & ~banks
    species = sorted(cells)
    on = [int(banks[tr, tc].sum()) for tr, tc in (cells[n] for n in species)]
    off = [int(rest[tr, tc].sum()) for tr, tc in (cells[n] for n in species)]
    return banks_table(int(banks.sum()), int(rest.sum()), species, on, off, dx)


def banks_table(bank_cells: int, rest_cells: int, species: list[str], on: list[int], off: list[int],
                dx: float) -> dict:
    """plants_on_banks' table from cell and instance counts (a tiled run's
    tiles add them up)."""
    ha_banks, ha_rest = bank_cells * dx * dx / 1e4, rest_cells * dx * dx / 1e4
    return {"species": species, "bank_ha": round(float(ha_banks), 3), "elsewhere_ha": round(float(ha_rest), 3),
            "banks_per_ha": [round(k / ha_banks, 3) if ha_banks else 0.0 for k in on],
            "elsewhere_per_ha": [round(k / ha_rest, 3) if ha_rest else 0.0 for k in off]}