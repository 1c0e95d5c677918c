"""The ground's detail layer: per ground type a tiling albedo + normal
texture at millimetres to centimetres per texel, and their blend by the
splat weights, projected three ways (triplanar) so steep ground does not
streak. One definition for the world stage (which writes the textures and
bakes the blend near a point) and the renderer (which samples it per pixel).

- Textures: DETAIL_TEXELS^2 per type over tile_m metres (DETAIL_SETS), made
  from periodic counter-based noise (worldlib.hashing.mix32 on a lattice
  whose indices wrap), so every texture tiles seamlessly and the same seed
  gives the same bytes. Their mean linear albedo is the ground type's
  colour (GROUND_COLOURS), so far views (the 1 m bake) and near views agree.
- Coordinates: texture column = x / tile_m, texture row = z / tile_m (x
  east, z south, rows top first), i.e. st = (x, -z) / tile_m; normals are
  tangent space (x along s = east, y along t = north), encoded 0..1.
- Triplanar: each of the three axis projections is weighted |n_axis|^p
  (TRIPLANAR_SHARPNESS), so on a 60 degree slope the top projection, which
  stretches texels 2x along the fall line, has 10 % of the weight.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worldlib.ground import GROUND_COLOURS, GROUND_TYPES
from worldlib.hashing import U32, mix32

DETAIL_TEXELS = 512


@dataclass(frozen=True)
class DetailSet:
    tile_m: float  # metres one texture covers
    bump_m: float  # height of the relief the normal map encodes (amplitude, m)


# one set per ground type, by name (GROUND_TYPES order)
DETAIL_SETS = {"rock": DetailSet(4.0, 0.06), "scree": DetailSet(3.0, 0.05), "grass": DetailSet(2.0, 0.02),
               "dry_grass": DetailSet(2.0, 0.02), "mud": DetailSet(3.0, 0.015), "snow": DetailSet(4.0, 0.01)}
TRIPLANAR_SHARPNESS = 4.0
# axis projections: (world axis of the projection, texture s axis, texture t axis) as unit vectors;
# texture column follows +s, row follows -t (rows top first)
PROJECTIONS = (
    ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, -1.0)),  # top: s east, t north
    ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),  # facing x: s north, t up
    ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),  # facing z: s east, t up
)


# --- periodic counter-based noise --------------------------------------------------------------------------------

def lattice01(i, j, key: int) -> np.ndarray:
    """Uniform [0, 1) per integer lattice point and key (mix32, counter-based)."""
    with np.errstate(over="ignore"):
        h = mix32(np.asarray(i, np.int64).astype(U32) * U32(0x8DA6B343) ^ np.asarray(j, np.int64).astype(U32)
                  * U32(0xD8163841) ^ U32(key & 0xFFFFFFFF) * U32(0xCB1AB31F))
    return (h >> U32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def _coords(n: int, cells: int):
    g = (np.arange(n) + 0.5) * cells / n
    i = np.floor(g).astype(np.int64)
    return i, (g - i).astype(np.float32)


def value_noise(n: int, cells: int, key: int) -> np.ndarray:
    """(n, n) smooth noise in [0, 1] over a cells x cells lattice that wraps,
    so the texture tiles."""
    i, f = _coords(n, cells)
    f = f * f * (3 - 2 * f)
    lat = lattice01(*np.meshgrid(np.arange(cells), np.arange(cells)), key)  # [row j, col i]
    i1 = (i + 1) % cells
    top = lat[i][:, i] * (1 - f) + lat[i][:, i1] * f
    bot = lat[i1][:, i] * (1 - f) + lat[i1][:, i1] * f
    return top * (1 - f)[:, None] + bot * f[:, None]


def fbm(n: int, cells: int, octaves: int, key: int, gain: float = 0.5) -> np.ndarray:
    """Octaves of value_noise (cells doubling), normalised to [0, 1]."""
    total, amp, norm = np.zeros((n, n), np.float32), 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(n, cells << o, key * 31 + o)
        norm += amp
        amp *= gain
    return total / norm


def cells_nearest(n: int, cells: int, key: int, stretch: float = 1.0):
    """Worley noise over a wrapping lattice, one feature point per cell:
    (F1, F2) distances in cell units and the nearest point's id hash in
    [0, 1). stretch > 1 makes each cell's metric an ellipse along a hashed
    direction (blades of grass)."""
    i, f = _coords(n, cells)
    cx, cy = np.meshgrid(i, i)
    fx, fy = np.meshgrid(f, f)
    f1 = np.full((n, n), np.inf, np.float32)
    f2 = np.full((n, n), np.inf, np.float32)
    ident = np.zeros((n, n), np.float32)
    for dj in (-1, 0, 1):
        for di in (-1, 0, 1):
            gi, gj = (cx + di) % cells, (cy + dj) % cells
            px = di + lattice01(gi, gj, key) - fx
            py = dj + lattice01(gi, gj, key + 1) - fy
            if stretch != 1.0:
                a = lattice01(gi, gj, key + 2) * np.float32(np.pi)
                ca, sa = np.cos(a), np.sin(a)
                px, py = (px * ca + py * sa) / stretch, (-px * sa + py * ca)
            d = np.sqrt(px * px + py * py)
            closer = d < f1
            f2 = np.where(closer, f1, np.minimum(f2, d))
            ident = np.where(closer, lattice01(gi, gj, key + 3), ident)
            f1 = np.where(closer, d, f1)
    return f1, f2, ident


# --- the textures of each ground type ------------------------------------------------------------------------------

def _mix(a, b, t):
    t = np.clip(t, 0.0, 1.0)[..., None]
    return np.asarray(a, np.float32) * (1 - t) + np.asarray(b, np.float32) * t


def _rock(n, key):
    grain = fbm(n, 8, 6, key)
    f1, f2, ident = cells_nearest(n, 5, key + 100)
    # 0 on the cell borders: joints between blocks, open only where a coarse noise says so
    crack = np.maximum(np.clip((f2 - f1) / 0.05, 0, 1), np.clip((fbm(n, 3, 3, key + 4) - 0.45) / 0.1, 0, 1))
    h = 0.6 * grain + 0.4 * ident * crack
    lichen = np.clip((fbm(n, 6, 4, key + 7) - 0.62) / 0.08, 0, 1)
    c = _mix((0.8, 0.78, 0.75), (1.25, 1.2, 1.12), grain * 0.7 + 0.3 * ident)
    c = _mix(c, (1.2, 1.25, 0.8), lichen * 0.6)
    return c * (0.35 + 0.65 * crack)[..., None], h * (0.2 + 0.8 * crack)


def _scree(n, key):
    f1, f2, ident = cells_nearest(n, 14, key)
    edge = f2 - f1  # 0 on the borders between stones: a cushion per cell, gaps along the borders
    stone = np.sqrt(np.clip(edge / 0.4, 0, 1)) * np.clip((edge - 0.03) / 0.05, 0, 1)
    grain = fbm(n, 16, 4, key + 5)
    tint = _mix((0.75, 0.73, 0.7), (1.3, 1.25, 1.15), ident)
    c = _mix((0.35, 0.32, 0.3), tint * (0.8 + 0.4 * grain)[..., None], np.clip(stone * 3, 0, 1))
    return c, stone * (0.8 + 0.2 * grain)


def _blades(n, key, layers=6):
    """Top-down grass: thin ellipses along hashed directions (blades about
    a tenth of the tile long), the higher layer wins."""
    h = np.zeros((n, n), np.float32)
    shade = np.zeros((n, n), np.float32)
    for k in range(layers):
        f1, _, ident = cells_nearest(n, 10 + 5 * k, key + 10 * k, stretch=5.5)
        blade = np.clip(1 - f1 / 0.13, 0, 1)
        top = blade * (0.4 + 0.6 * k / max(layers - 1, 1)) > h
        h = np.where(top, blade * (0.4 + 0.6 * k / max(layers - 1, 1)), h)
        shade = np.where(top, ident, shade)
    return h, shade


def _grass(n, key, dry=False):
    h, shade = _blades(n, key)
    patch = fbm(n, 4, 3, key + 3)
    green = ((0.9, 1.1, 0.7), (1.3, 1.2, 0.9)) if not dry else ((1.0, 0.95, 0.85), (1.25, 1.2, 1.1))
    c = _mix(green[0], green[1], 0.6 * shade + 0.4 * patch)
    soil = (0.45, 0.4, 0.35) if not dry else (0.55, 0.5, 0.42)
    return _mix(soil, c, np.clip(h * 3.0, 0, 1)), h


def _mud(n, key):
    base = fbm(n, 6, 6, key)
    wet = np.clip((fbm(n, 6, 3, key + 9) - 0.55) / 0.1, 0, 1)
    f1, f2, ident = cells_nearest(n, 24, key + 20)
    pebble = np.clip(1 - f1 / 0.25, 0, 1) * (ident > 0.7)
    c = _mix((1.1, 1.05, 1.0), (0.82, 0.8, 0.78), wet) * (0.85 + 0.3 * base)[..., None]
    c = _mix(c, (1.5, 1.5, 1.45), pebble)
    return c, base * (1 - 0.7 * wet) + 0.3 * pebble


def _snow(n, key):
    drift = fbm(n, 3, 5, key)
    sparkle = (lattice01(*np.meshgrid(np.arange(n), np.arange(n)), key + 1) > 0.995).astype(np.float32)
    c = _mix((0.94, 0.96, 1.02), (1.02, 1.01, 1.0), drift) + 0.05 * sparkle[..., None]
    return c, drift


_RECIPES = {"rock": _rock, "scree": _scree, "grass": _grass, "dry_grass": lambda n, k: _grass(n, k, dry=True),
            "mud": _mud, "snow": _snow}


def normal_from_height(h: np.ndarray, texel_m: float) -> np.ndarray:
    """Tangent-space normals (x along s = +column, y along t = -row), encoded
    0..1, from a wrapping height field in metres (central differences)."""
    dx = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) / (2 * texel_m)
    dz = (np.roll(h, -1, 0) - np.roll(h, 1, 0)) / (2 * texel_m)  # rows grow with -t
    n = np.stack([-dx, dz, np.ones_like(h)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return (0.5 * n + 0.5).astype(np.float32)


def detail_texture(ground_type: str, seed: int, n: int = DETAIL_TEXELS) -> tuple[np.ndarray, np.ndarray]:
    """(albedo linear RGB (n, n, 3) with mean GROUND_COLOURS of the type,
    normal encoded 0..1 (n, n, 3)) of one ground type; periodic over n."""
    k = GROUND_TYPES.index(ground_type)
    colour, h = _RECIPES[ground_type](n, (seed * 16 + k) * 1000 + 17)
    target = GROUND_COLOURS[k].astype(np.float64)
    albedo = colour.astype(np.float64)
    for _ in range(3):  # scale to the type's mean colour; the clip to 1 moves the mean a little, so again
        albedo = np.clip(albedo * (target / np.maximum(albedo.reshape(-1, 3).mean(0), 1e-6)), 0.0, 1.0)
    s = DETAIL_SETS[ground_type]
    h = (h - h.mean()) / max(float(np.ptp(h)), 1e-6) * 2 * s.bump_m
    return albedo.astype(np.float32), normal_from_height(h.astype(np.float32), s.tile_m / n)


def detail_textures(seed: int, n: int = DETAIL_TEXELS) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {t: detail_texture(t, seed, n) for t in GROUND_TYPES}


# --- sampling and the blend ----------------------------------------------------------------------------------------

class MipTexture:
    """A wrapping texture with box MIP levels, sampled bilinear per level and
    linearly between levels (trilinear)."""

    def __init__(self, rgb: np.ndarray):
        from worldlib.images import box_mip_chain

        self.levels = box_mip_chain(np.asarray(rgb, np.float32))
        self.flat = [a.reshape(-1, a.shape[2]) for a in self.levels]  # rows of texels, for np.take
        self.size = self.levels[0].shape[0]

    def _bilinear(self, level: int, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        a = self.flat[level]
        n = self.levels[level].shape[0]
        c, r = col * n - 0.5, row * n - 0.5
        c0, r0 = np.floor(c), np.floor(r)
        fc, fr = (c - c0).astype(np.float32)[:, None], (r - r0).astype(np.float32)[:, None]
        c0, r0 = c0.astype(np.int64) % n, r0.astype(np.int64) % n
        c1, r1 = (c0 + 1) % n, (r0 + 1) % n
        r0 *= n
        r1 *= n
        top = np.take(a, r0 + c0, axis=0) * (1 - fc) + np.take(a, r0 + c1, axis=0) * fc
        bottom = np.take(a, r1 + c0, axis=0) * (1 - fc) + np.take(a, r1 + c1, axis=0) * fc
        return top * (1 - fr) + bottom * fr

    def sample(self, col: np.ndarray, row: np.ndarray, lod: np.ndarray) -> np.ndarray:
        """col, row in texture widths (wrapping); lod the MIP level (0 the finest, fractional)."""
        lod = np.clip(np.asarray(lod, np.float64), 0, len(self.levels) - 1)
        l0 = np.floor(lod).astype(np.int64)
        out = np.zeros((len(col), self.levels[0].shape[2]), np.float32)
        for level in np.unique(l0):
            m = l0 == level
            every = bool(m.all())  # one level for all (a bake at one texel size): no gathers by mask
            cm, rm, f = (col, row, lod - level) if every else (col[m], row[m], lod[m] - level)
            f = f.astype(np.float32)[:, None]
            lo = self._bilinear(int(level), cm, rm)
            hi = self._bilinear(min(int(level) + 1, len(self.levels) - 1), cm, rm)
            if every:
                return lo * (1 - f) + hi * f
            out[m] = lo * (1 - f) + hi * f
        return out


def triplanar_weights(normal: np.ndarray, sharpness: float = TRIPLANAR_SHARPNESS) -> np.ndarray:
    """(n, 3) weights of the top, x-facing and z-facing projections, |n_axis|^p normalised."""
    a = np.abs(np.asarray(normal, np.float64)[:, [1, 0, 2]]) ** sharpness
    return a / np.maximum(a.sum(1, keepdims=True), 1e-12)


def weighted_stretch(normal: np.ndarray, sharpness: float = TRIPLANAR_SHARPNESS) -> np.ndarray:
    """How much the blended projections stretch texels along the surface:
    each projection stretches by 1 / |n_axis| along the fall line, weighted
    by its triplanar weight (1 on ground facing an axis; a planar top
    projection gives 1 / cos(slope), 2 at 60 degrees)."""
    n = np.asarray(normal, np.float64)
    w = triplanar_weights(n, sharpness)
    a = np.maximum(np.abs(n[:, [1, 0, 2]]), 1e-6)
    return (w / a).sum(1)


@dataclass
class DetailLayer:
    """The six ground types' textures, ready to sample, and their tile sizes."""

    albedo: list  # MipTexture per type (linear RGB)
    normal: list  # MipTexture per type (tangent-space, -1..1)
    tile_m: np.ndarray  # (types,)

    @staticmethod
    def from_textures(textures: dict, tile_m: dict | None = None) -> "DetailLayer":
        tile = tile_m or {t: DETAIL_SETS[t].tile_m for t in GROUND_TYPES}
        return DetailLayer([MipTexture(textures[t][0]) for t in GROUND_TYPES],
                           [MipTexture(2.0 * textures[t][1] - 1.0) for t in GROUND_TYPES],
                           np.array([tile[t] for t in GROUND_TYPES], np.float64))


def blend(layer: DetailLayer, weights: np.ndarray, pos: np.ndarray, normal: np.ndarray,
          footprint_m: np.ndarray, min_weight: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """At points pos (n, 3) with surface normals (n, 3), splat weights
    (n, types) and a footprint (the surface length one pixel or texel
    covers, m): the linear albedo (n, 3), sum over types and projections of
    weight x projection weight x the type's albedo, and the normal (n, 3),
    the surface normal tilted by the same blend of tangent-space detail
    normals (each projection's s and t axes). MIP level: footprint over
    texel size, along the projection (footprint / |n_axis|)."""
    pos = np.asarray(pos, np.float64)
    n = np.asarray(normal, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    w = np.asarray(weights, np.float64)
    w = w / np.maximum(w.sum(1, keepdims=True), 1e-12)
    tw = triplanar_weights(n)
    albedo = np.zeros((len(pos), 3))
    tilt = np.zeros((len(pos), 3))
    for p, (axis, s_axis, t_axis) in enumerate(PROJECTIONS):
        s_coord, t_coord = pos @ np.asarray(s_axis), pos @ np.asarray(t_axis)
        along = np.maximum(np.abs(n @ np.asarray(axis)), 1e-3)
        for k in range(len(layer.albedo)):
            m = (w[:, k] * tw[:, p]) > min_weight
            if not m.any():
                continue
            m = slice(None) if m.all() else m  # one type and projection everywhere: no gathers by mask
            tile = layer.tile_m[k]
            texel = tile / layer.albedo[k].size
            lod = np.log2(np.maximum(footprint_m[m] / along[m] / texel, 1.0))
            col, row = s_coord[m] / tile, -t_coord[m] / tile
            share = (w[m, k] * tw[m, p])[:, None]
            albedo[m] += share * layer.albedo[k].sample(col, row, lod)
            tn = layer.normal[k].sample(col, row, lod)
            tilt[m] += share * (tn[:, :1] * np.asarray(s_axis) + tn[:, 1:2] * np.asarray(t_axis))
    # the share of weight skipped (below min_weight) is made up so the albedo keeps its level
    total = (w[:, :, None] * tw[:, None, :])
    kept = np.where(total > min_weight, total, 0.0).sum((1, 2))[:, None]
    albedo /= np.maximum(kept, 1e-12)
    tilt /= np.maximum(kept, 1e-12)
    tilt -= (tilt * n).sum(1, keepdims=True) * n  # along the surface only
    out = n + tilt
    return albedo.astype(np.float32), (out / np.linalg.norm(out, axis=1, keepdims=True)).astype(np.float32)


def splat_bilinear(splat: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(n, types) splat weights at fractional cell indices (0 = first cell
    centre), bilinear, clamped to the grid."""
    nr, nc = splat.shape[:2]
    r = np.clip(rows, 0, nr - 1)
    c = np.clip(cols, 0, nc - 1)
    r0 = np.minimum(np.floor(r).astype(np.int64), max(nr - 2, 0))
    c0 = np.minimum(np.floor(c).astype(np.int64), max(nc - 2, 0))
    r1, c1 = np.minimum(r0 + 1, nr - 1), np.minimum(c0 + 1, nc - 1)
    fr, fc = (r - r0)[:, None], (c - c0)[:, None]
    return ((splat[r0, c0] * (1 - fc) + splat[r0, c1] * fc) * (1 - fr)
            + (splat[r1, c0] * (1 - fc) + splat[r1, c1] * fc) * fr)
