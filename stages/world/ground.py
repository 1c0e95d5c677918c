"""The ground material from the vegetation stage's splat weights: one
definition of rock, scree, grass, dry grass, mud and snow for the whole world.

- Albedo: per texel, the splat weights (bilinear between cell centres, so at
  a cell centre they are the splat map's and everywhere they sum to 1, as the
  splat maps do) blend one colour per ground type, each modulated by its own
  detail pattern (value noise from a counter-based hash, several octaves
  down to 1 m, periodic over DETAIL_PERIOD_M like a detail texture), so the
  ground has structure closer than a cell.
- Tiles: the world is cut into T x T UDIM tiles (USD `<UDIM>`, tile 1001 at
  the south-west corner, u east, v north) of tile_texels^2 texels each,
  T = ceil(size / (texel_m * tile_texels)) (at most 10 per row, UDIM's
  limit), so a texel is texel_m or finer where the camera is near.
- Normal map: tangent space, from the final height at its own resolution,
  relative to the terrain mesh (which already carries the coarse normals):
  the slope of height minus the mesh surface, so the 8 m detail the
  513-vertex mesh drops is still lit.
"""
from __future__ import annotations

import math

import numpy as np

from worldlib.ground import GROUND_COLOURS, SPLAT_CHANNELS  # noqa: F401 (GROUND_COLOURS: the kernel's)

SPLAT_ORDER = SPLAT_CHANNELS
# detail contrast per type (relative brightness swing) and its coarsest wavelength in metres
DETAIL_CONTRAST = np.array([0.45, 0.35, 0.30, 0.30, 0.25, 0.06], np.float32)
DETAIL_WAVELENGTH_M = np.array([16.0, 4.0, 8.0, 8.0, 6.0, 32.0])
DETAIL_OCTAVES = 4
UDIM_MAX_COLUMNS = 10


def _hash01(ix: np.ndarray, iz: np.ndarray, key: int) -> np.ndarray:
    """Uniform [0, 1) per integer lattice point (counter-based, splitmix64)."""
    with np.errstate(over="ignore"):
        x = (ix.astype(np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             ^ iz.astype(np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ np.uint64(key) * np.uint64(0x165667B19E3779F9))
        x ^= x >> np.uint64(30)
        x *= np.uint64(0xBF58476D1CE4E5B9)
        x ^= x >> np.uint64(27)
        x *= np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return (x >> np.uint64(40)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def _bilinear_taps(pos: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lower and upper cell index and the upper cell's share at fractional
    cell indices pos (0 = first cell centre), clamped to the grid."""
    p = np.clip(np.asarray(pos, np.float64), 0, n - 1)
    i0 = np.minimum(np.floor(p).astype(np.int64), max(n - 2, 0))
    return i0, np.minimum(i0 + 1, n - 1), (p - i0).astype(np.float32)


def texel_weights(splat: np.ndarray, rows: np.ndarray, cols: np.ndarray, types_first: bool = False) -> np.ndarray:
    """Splat weights at fractional cell indices (0 = first cell centre),
    bilinear between cell centres, clamped at the edges: (len(rows),
    len(cols), channels), or (channels, len(rows), len(cols)) with
    types_first. Convex combinations of the splat maps' rows, so they sum to
    1 wherever the maps do, and at a cell centre exactly the map's value.
    Separable: along the rows first (only the columns the tile needs), then
    along the columns, so a tile of 1 m texels over 8 m cells costs two
    blends of whole rows, not four gathers per texel."""
    nr, nc = splat.shape[:2]
    r0, r1, fr = _bilinear_taps(rows, nr)
    c0, c1, fc = _bilinear_taps(cols, nc)
    lo, hi = int(c0.min()), int(c1.max()) + 1
    s = np.moveaxis(np.asarray(splat, np.float32)[:, lo:hi], -1, 0)  # (types, rows, needed cols)
    along = s[:, r0] * (1 - fr)[None, :, None] + s[:, r1] * fr[None, :, None]
    w = along[:, :, c0 - lo] * (1 - fc) + along[:, :, c1 - lo] * fc
    return w if types_first else np.moveaxis(w, 0, -1)


DETAIL_PERIOD_M = 512  # the detail patterns repeat every this many metres (a whole number of every octave)


def detail_tables(seed: int, texel_m: float) -> np.ndarray:
    """Each type's detail over one period, sampled every texel_m:
    (types, P, P) with P = DETAIL_PERIOD_M / texel_m; periodic because every
    octave's wavelength divides the period (hash lattice indices wrap)."""
    p = max(1, int(round(DETAIL_PERIOD_M / texel_m)))
    c = (np.arange(p) + 0.5) * texel_m
    X, Z = np.meshgrid(c, c)
    return np.stack([_periodic_detail(X, Z, k, seed) for k in range(len(GROUND_COLOURS))])


def _periodic_detail(x_m, z_m, ground_type, seed):
    total = np.zeros(x_m.shape, np.float32)
    amp, norm = 1.0, 0.0
    for o in range(DETAIL_OCTAVES):
        w = DETAIL_WAVELENGTH_M[ground_type] / 2 ** o
        period = int(round(DETAIL_PERIOD_M / w))
        gx, gz = x_m / w, z_m / w
        ix, iz = np.floor(gx), np.floor(gz)
        fx, fz = (gx - ix).astype(np.float32), (gz - iz).astype(np.float32)
        fx, fz = fx * fx * (3 - 2 * fx), fz * fz * (3 - 2 * fz)
        key = seed * 64 + ground_type * 8 + o
        i0, j0 = ix.astype(np.int64) % period, iz.astype(np.int64) % period
        i1, j1 = (i0 + 1) % period, (j0 + 1) % period
        # the hash once per lattice point of the period, then looked up at each texel's four corners
        li, lj = np.meshgrid(np.arange(period), np.arange(period))
        lattice = _hash01(li, lj, key)
        a, b = lattice[j0, i0], lattice[j0, i1]
        c, d = lattice[j1, i0], lattice[j1, i1]
        total += amp * ((a * (1 - fx) + b * fx) * (1 - fz) + (c * (1 - fx) + d * fx) * fz - 0.5)
        norm += amp
        amp *= 0.6
    return 1.0 + DETAIL_CONTRAST[ground_type] * 2.0 * total / np.float32(norm)


def udim_layout(size_m: float, texel_m: float, tile_texels: int) -> tuple[int, int]:
    """(tiles per side, texels per tile side): texel_m or finer unless the
    UDIM row limit forces more texels per tile."""
    tiles = max(1, math.ceil(size_m / (texel_m * tile_texels) - 1e-9))
    if tiles > UDIM_MAX_COLUMNS:
        tiles = UDIM_MAX_COLUMNS
        tile_texels = math.ceil(size_m / (texel_m * tiles))
    return tiles, tile_texels


def tile_positions(cell_m: float, shape: tuple[int, int], tiles: int, tile_texels: int, u: int,
                   v: int) -> tuple[np.ndarray, np.ndarray]:
    """Metres from the grid's corner of the texel centres of UDIM tile (u, v)
    (u east, v north from the south-west corner): x per texel column, z per
    texel row (row 0 at the tile's north edge, as USD reads textures; z
    grows south)."""
    rows, cols = shape
    s = (u + (np.arange(tile_texels) + 0.5) / tile_texels) / tiles  # 0..1 east
    t = (v + 1 - (np.arange(tile_texels) + 0.5) / tile_texels) / tiles  # 0..1 north, row 0 at the top
    return s * (cols * cell_m), (1.0 - t) * (rows * cell_m)


def axis_taps(pos_m: np.ndarray, origin_m: float, cell_m: float, n: int, texel_m: float,
              period: int) -> tuple[np.ndarray, np.ndarray]:
    """Per texel along one axis: (lower cell, upper cell, detail texel) as
    int32 and the upper cell's share, as texel_weights and albedo compute
    them; the kernel takes these (the tile is separable)."""
    i0, i1, f = _bilinear_taps(pos_m / cell_m - 0.5, n)
    detail = np.floor((origin_m + pos_m) / texel_m).astype(np.int64) % period
    return np.stack([i0, i1, detail], axis=1).astype(np.int32), f


def normal_map(height: np.ndarray, mesh_height: np.ndarray, cell_m: float) -> np.ndarray:
    """Tangent-space normals (x along +s = east, y along +t = north, z out),
    encoded 0..1, from the slope of height minus the mesh surface at the
    cell centres; image row 0 is the north edge."""
    r = np.asarray(height, np.float64) - np.asarray(mesh_height, np.float64)
    dr_dz, dr_dx = np.gradient(r, cell_m) if min(r.shape) > 1 else (np.zeros_like(r), np.zeros_like(r))
    n = np.stack([-dr_dx, dr_dz, np.ones_like(r)], axis=-1)  # d/dt = -d/dz (t grows north)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return (0.5 * n + 0.5).astype(np.float32)
