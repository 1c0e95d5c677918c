"""The landscape lattice and its tiles, pure numpy.

The world's grid is pixel-is-area: cell (r, c) holds the height at its
centre. The landscape is pixel-is-point: vertex (J, I) of the lattice sits at
x = x0 + I * dl, z = z0 + J * dl with (x0, z0) the centre of the world's first
cell, so at the world's own cell (dl = dx) vertex (J, I) is cell (J, I)
exactly. Tile (col, row) holds vertices row * stride .. row * stride + N - 1
(and the same in columns): stride = N - 1 when tiles share their border row
and column (World Composition, Gaea, World Machine), N when they abut (the
tiled "Import from File" of Unreal 5 places tile x at x * N).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Unreal's landscape: quads per section and sections per component (1 = 1x1, 2 = 2x2)
SECTION_QUADS = (7, 15, 31, 63, 127, 255)
SECTIONS = (1, 2)
# the sizes (vertices per side) Unreal's Landscape Technical Guide recommends for a landscape or tile
RECOMMENDED_VERTICES = (127, 253, 505, 1009, 2017, 4033, 8129)

PNG_MAX = 65535  # the 16-bit heightmap's largest value
WEIGHT_MAX = 255  # an 8-bit weightmap's full weight
UNREAL_MID = 32768  # the 16-bit value Unreal puts at the landscape actor's Z
UNREAL_Z_STEPS = 128.0  # Unreal: one 16-bit step is Z scale / 128 cm


@dataclass(frozen=True)
class Layout:
    """Where the landscape's vertices are and how they are cut into tiles."""

    vertices: int  # N, per tile side
    stride: int  # N - 1 (shared borders) or N
    tiles: tuple[int, int]  # (columns, rows) of tiles
    cell_m: float  # dl, the lattice spacing
    origin_m: tuple[float, float]  # world x, z of lattice vertex (0, 0)
    valid: tuple[int, int]  # lattice vertices (columns, rows) inside the world; the rest is edge clamped
    world_cell_m: float
    world_shape: tuple[int, int]  # (rows, cols) of the world's grid

    @property
    def lattice(self) -> tuple[int, int]:
        """Vertices (columns, rows) of the whole lattice."""
        extra = self.vertices - self.stride
        return self.tiles[0] * self.stride + extra, self.tiles[1] * self.stride + extra

    def tile_origin(self, col: int, row: int) -> tuple[float, float]:
        """World x, z of the tile's first vertex."""
        return (self.origin_m[0] + col * self.stride * self.cell_m, self.origin_m[1] + row * self.stride * self.cell_m)

    def tile_valid(self, col: int, row: int) -> tuple[int, int]:
        """The tile's vertices (columns, rows) inside the world: the others are padding."""
        return (max(0, min(self.vertices, self.valid[0] - col * self.stride)),
                max(0, min(self.vertices, self.valid[1] - row * self.stride)))


def _tile_count(inside: int, vertices: int, stride: int) -> int:
    """Tiles along one axis so that `inside` lattice vertices are covered."""
    return max(1, math.ceil((inside - (vertices - stride)) / stride))


def plan_layout(world_shape: tuple[int, int], world_cell_m: float, world_origin_m: tuple[float, float],
                vertices: int, share_borders: bool, cell_m: float | None, fit: str) -> Layout:
    """The lattice and tiles for a world of `world_shape` (rows, cols) cells.

    fit "pad": the lattice at `cell_m` (default the world's cell) from the
    first cell centre; the last tiles reach past the world and are padded by
    edge clamping. fit "resample": the largest cell at most `cell_m` whose
    tiles span the world's cell centres exactly along its limiting axis (the
    other axis is padded by less than a tile)."""
    rows, cols = world_shape
    stride = vertices - 1 if share_borders else vertices
    wanted = float(cell_m) if cell_m else float(world_cell_m)
    spans = ((cols - 1) * world_cell_m, (rows - 1) * world_cell_m)  # cell centre to cell centre, x and z
    if fit == "resample":
        # at least ceil(span / wanted) quads per axis, so the cell is at most the one wanted
        counts = [_tile_count(math.ceil(s / wanted - 1e-9) + 1, vertices, stride) for s in spans]
        quads = [k * stride + (vertices - stride) - 1 for k in counts]  # the lattice's quads per axis
        dl = max(s / q for s, q in zip(spans, quads)) or wanted
    else:
        dl = wanted
    inside = tuple(int(math.floor(s / dl + 1e-9)) + 1 for s in spans)
    tiles = tuple(_tile_count(n, vertices, stride) for n in inside)
    origin = (world_origin_m[0] + 0.5 * world_cell_m, world_origin_m[1] + 0.5 * world_cell_m)
    return Layout(vertices=vertices, stride=stride, tiles=tiles, cell_m=dl, origin_m=origin, valid=inside,
                  world_cell_m=float(world_cell_m), world_shape=(rows, cols))


def _axis(layout: Layout, tile: int, n_cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along one axis of a tile: the lower source cell, the upper one and the
    fraction between them of each vertex, clamped to the world's edge. The
    position comes from the vertex's global index, so two tiles sharing a
    vertex compute it identically; at the world's cell the fraction is 0."""
    j = tile * layout.stride + np.arange(layout.vertices, dtype=np.float64)
    ratio = layout.cell_m / layout.world_cell_m  # exactly 1.0 at the world's cell
    f = np.clip(j * ratio, 0.0, n_cells - 1.0)
    i0 = np.minimum(np.floor(f).astype(np.int64), max(n_cells - 2, 0))
    i1 = np.minimum(i0 + 1, n_cells - 1)
    return i0, i1, f - i0


def sample_tile(data: np.ndarray, layout: Layout, col: int, row: int, band: slice = slice(None)) -> np.ndarray:
    """Bilinear samples (float64) of `data` ((rows, cols) or (rows, cols, k))
    at the tile's vertices (its vertex rows `band`), reading only the window
    of cells they cover."""
    x0, x1, fx = _axis(layout, col, data.shape[1])
    z0, z1, fz = (a[band] for a in _axis(layout, row, data.shape[0]))
    r_lo, r_hi, c_lo, c_hi = int(z0.min()), int(z1.max()) + 1, int(x0.min()), int(x1.max()) + 1
    win = np.asarray(data[r_lo:r_hi, c_lo:c_hi], np.float64)
    z0, z1, x0, x1 = z0 - r_lo, z1 - r_lo, x0 - c_lo, x1 - c_lo
    fx = fx.reshape((1, -1) + (1,) * (data.ndim - 2))
    fz = fz.reshape((-1, 1) + (1,) * (data.ndim - 2))
    top, bottom = win[z0], win[z1]
    top = (1.0 - fx) * top[:, x0] + fx * top[:, x1]
    bottom = (1.0 - fx) * bottom[:, x0] + fx * bottom[:, x1]
    return (1.0 - fz) * top + fz * bottom


def quantise_heights(h: np.ndarray, lo: float, span: float) -> np.ndarray:
    """Heights in metres to the 16-bit values 0..65535 over [lo, lo + span]."""
    v = np.rint((np.asarray(h, np.float64) - lo) * (PNG_MAX / span))
    return np.clip(v, 0, PNG_MAX).astype(np.uint16)


def decode_heights(v: np.ndarray, lo: float, span: float) -> np.ndarray:
    """The 16-bit values back to metres (what a reader of the sidecar does)."""
    return lo + np.asarray(v, np.float64) * (span / PNG_MAX)


def quantise_weights(w: np.ndarray) -> np.ndarray:
    """Weights (..., k) to 8-bit values summing to exactly 255 wherever the
    weights sum to more than 0 (they are normalised first): the floors, then
    one more for the largest remainders (ties to the first ground type),
    Hamilton's method; all 0 where no weight is set."""
    w = np.clip(np.nan_to_num(np.asarray(w, np.float64)), 0.0, None)
    total = w.sum(axis=-1, keepdims=True)
    share = np.divide(w, total, out=np.zeros_like(w), where=total > 0) * WEIGHT_MAX
    base = np.floor(share)
    left = np.rint(WEIGHT_MAX - base.sum(axis=-1)).astype(np.int64) * (total[..., 0] > 0)
    order = np.argsort(-(share - base), axis=-1, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.arange(w.shape[-1]), axis=-1)
    return (base + (rank < left[..., None])).astype(np.uint8)


def unreal_settings(layout: Layout, col: int, row: int, lo: float, span: float,
                    quads_per_section: int, sections_per_component: int) -> dict:
    """Unreal's import settings for one tile (centimetres): the lattice as a
    landscape of components, its scale and the actor location that puts the
    16-bit values back at their heights: h = lo + v * step, and Unreal's
    h = Z + (v - 32768) * Zscale / 128, so Zscale = 128 step and
    Z = lo + 32768 step (step = span / 65535; the rule of thumb
    Zscale = span * 100 / 512 is the same to 0.002 %)."""
    step_cm = 100.0 * span / PNG_MAX
    x, z = layout.tile_origin(col, row)
    component_quads = quads_per_section * sections_per_component
    return {
        "resolution": [layout.vertices, layout.vertices],
        "quads_per_section": quads_per_section,
        "sections_per_component": f"{sections_per_component}x{sections_per_component}",
        "component_size_quads": component_quads,
        "components": [(layout.vertices - 1) // component_quads] * 2,
        "scale_cm": [100.0 * layout.cell_m, 100.0 * layout.cell_m, UNREAL_Z_STEPS * step_cm],
        "location_cm": [100.0 * x, 100.0 * z, 100.0 * lo + UNREAL_MID * step_cm],
        "axes": "Unreal X = world x (east), Unreal Y = world z (south, the image's rows)",
    }
