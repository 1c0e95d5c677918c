"""The terrain surface as a triangle mesh: the one definition of "on the
terrain" that every stage placing things on the ground must share.

Vertices sit on a regular lattice spanning the cell centres of the height
grid (first to last), heights bilinearly interpolated; each lattice quad is
split along the same diagonal (north-west to south-east) into two triangles
wound counter-clockwise seen from above (+Y), as USD's rightHanded
orientation expects.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.grid import Grid


@dataclass(frozen=True)
class TerrainMesh:
    points: np.ndarray  # (n, 3) float32 x east, y up, z south, metres
    normals: np.ndarray  # (n, 3) float32 unit, per vertex
    st: np.ndarray  # (n, 2) float32 texture coordinates (t = 1 at the north edge)
    face_vertex_indices: np.ndarray  # (3 * faces,) int32
    lattice_shape: tuple[int, int]  # vertices per column, per row

    @property
    def extent(self) -> np.ndarray:
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)])


def lattice_coordinates(n_cells: int, n_vertices: int) -> np.ndarray:
    """Fractional cell indices (0 = centre of the first cell) of n_vertices
    lattice lines spread evenly from the first to the last cell centre."""
    if n_vertices >= n_cells:
        return np.arange(n_cells, dtype=np.float64)
    return np.linspace(0.0, n_cells - 1, n_vertices)


def lattice_shape(rows: int, cols: int, max_vertices_per_side: int) -> tuple[int, int]:
    """Vertices along the rows and the columns: the longer side gets at most
    max_vertices_per_side, the shorter side as many as keep the same spacing
    in metres (a rectangular world's triangles stay near square), each side
    at most one vertex per cell."""
    longer = max(rows, cols)
    n_long = min(longer, max_vertices_per_side)
    spacing = (longer - 1) / max(n_long - 1, 1)  # cells between lattice lines

    def side(n: int) -> int:
        return n_long if n == longer else min(n, max(2, int(round((n - 1) / spacing)) + 1))
    return side(rows), side(cols)


def bilinear(values: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """values sampled at fractional (row, col) cell indices (outer product)."""
    r0 = np.clip(np.floor(rows).astype(np.int64), 0, max(values.shape[0] - 2, 0))
    c0 = np.clip(np.floor(cols).astype(np.int64), 0, max(values.shape[1] - 2, 0))
    r1 = np.minimum(r0 + 1, values.shape[0] - 1)
    c1 = np.minimum(c0 + 1, values.shape[1] - 1)
    fr = (rows - r0)[:, None]
    fc = (cols - c0)[None, :]
    v = values.astype(np.float64)
    top = v[np.ix_(r0, c0)] * (1 - fc) + v[np.ix_(r0, c1)] * fc
    bottom = v[np.ix_(r1, c0)] * (1 - fc) + v[np.ix_(r1, c1)] * fc
    return top * (1 - fr) + bottom * fr


def build_terrain_mesh(height: Grid, max_vertices_per_side: int) -> TerrainMesh:
    h = height.channel(height.channels[0])
    rows, cols = h.shape
    if rows < 2 or cols < 2:
        raise ValueError(f"a terrain mesh needs at least 2x2 cells, the grid is {rows}x{cols}")
    dx = height.cell_size_m
    nr, nc = lattice_shape(rows, cols, max_vertices_per_side)
    ri = lattice_coordinates(rows, nr)
    ci = lattice_coordinates(cols, nc)
    hv = bilinear(h, ri, ci)
    x = height.origin_m[0] + (ci + 0.5) * dx
    z = height.origin_m[1] + (ri + 0.5) * dx
    nr, nc = hv.shape
    X, Z = np.meshgrid(x, z)
    points = np.stack([X, hv, Z], axis=-1).reshape(-1, 3)

    # Normals from central differences of the lattice heights, in metres.
    dh_dx = np.gradient(hv, x, axis=1)
    dh_dz = np.gradient(hv, z, axis=0)
    n = np.stack([-dh_dx, np.ones_like(hv), -dh_dz], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)

    width, depth = height.size_m
    s = (X - height.origin_m[0]) / width
    t = 1.0 - (Z - height.origin_m[1]) / depth
    st = np.stack([s, t], axis=-1).reshape(-1, 2)

    idx = np.arange(nr * nc, dtype=np.int32).reshape(nr, nc)
    a, b = idx[:-1, :-1], idx[:-1, 1:]
    d, e = idx[1:, :-1], idx[1:, 1:]
    tris = np.stack([a, d, b, b, d, e], axis=-1).reshape(-1)
    return TerrainMesh(points.astype(np.float32), n.reshape(-1, 3).astype(np.float32), st.astype(np.float32),
                       tris.astype(np.int32), (nr, nc))


def height_on_mesh(mesh: TerrainMesh, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The height of the mesh surface at (x, z): barycentric interpolation on
    the triangle that contains the point, so instances sit exactly on it."""
    nr, nc = mesh.lattice_shape
    P = mesh.points.reshape(nr, nc, 3).astype(np.float64)
    xs, zs = P[0, :, 0], P[:, 0, 2]
    j = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, nc - 2)
    i = np.clip(np.searchsorted(zs, z, side="right") - 1, 0, nr - 2)
    u = (x - xs[j]) / (xs[j + 1] - xs[j])  # 0..1 east within the quad
    v = (z - zs[i]) / (zs[i + 1] - zs[i])  # 0..1 south within the quad
    ha, hb = P[i, j, 1], P[i, j + 1, 1]
    hd, he = P[i + 1, j, 1], P[i + 1, j + 1, 1]
    upper = u + v <= 1.0  # triangle (a, d, b); otherwise (b, d, e)
    return np.where(upper, ha + u * (hb - ha) + v * (hd - ha), he + (1 - u) * (hd - he) + (1 - v) * (hb - he))
