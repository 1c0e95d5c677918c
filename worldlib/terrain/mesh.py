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


def lattice_taps(n_cells: int, coords: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two cells (first, second) and the weight of the second of
    bilinear sampling at fractional cell indices coords along a side of n_cells."""
    i0 = np.clip(np.floor(coords).astype(np.int64), 0, max(n_cells - 2, 0))
    return i0, np.minimum(i0 + 1, n_cells - 1), coords - i0


def bilinear_taps(values: np.ndarray, rt: tuple, ct: tuple, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """bilinear() from its taps (lattice_taps) on values that hold the
    world's cells from (row, col) = origin on: the same numbers from a
    window of the world as from the whole."""
    (r0, r1, fr), (c0, c1, fc) = rt, ct
    r0, r1, c0, c1 = r0 - origin[0], r1 - origin[0], c0 - origin[1], c1 - origin[1]
    fr, fc = fr[:, None], fc[None, :]
    v = values.astype(np.float64)
    top = v[np.ix_(r0, c0)] * (1 - fc) + v[np.ix_(r0, c1)] * fc
    bottom = v[np.ix_(r1, c0)] * (1 - fc) + v[np.ix_(r1, c1)] * fc
    return top * (1 - fr) + bottom * fr


def bilinear(values: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """values sampled at fractional (row, col) cell indices (outer product)."""
    return bilinear_taps(values, lattice_taps(values.shape[0], rows), lattice_taps(values.shape[1], cols))


def lattice_of(rows: int, cols: int, max_vertices_per_side: int) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's lattice lines as fractional cell indices (rows, cols) of a rows x cols grid."""
    if rows < 2 or cols < 2:
        raise ValueError(f"a terrain mesh needs at least 2x2 cells, the grid is {rows}x{cols}")
    nr, nc = lattice_shape(rows, cols, max_vertices_per_side)
    return lattice_coordinates(rows, nr), lattice_coordinates(cols, nc)


def build_terrain_mesh(height: Grid, max_vertices_per_side: int) -> TerrainMesh:
    h = height.channel(height.channels[0])
    ri, ci = lattice_of(*h.shape, max_vertices_per_side)
    return mesh_from_lattice(bilinear(h, ri, ci), ri, ci, height.cell_size_m, height.origin_m, height.size_m)


def lattice_heights(read, shape: tuple[int, int], ri: np.ndarray, ci: np.ndarray, band_rows: int = 512) -> np.ndarray:
    """bilinear(h, ri, ci) of a rows x cols grid read by window (read(row0,
    col0, rows, cols) -> that window of h), band by band of cell rows: the
    same numbers as from the whole grid, which is never whole here."""
    rt, ct = lattice_taps(shape[0], ri), lattice_taps(shape[1], ci)
    c_lo, c_hi = int(ct[0].min()), int(ct[1].max()) + 1
    hv = np.zeros((len(ri), len(ci)))
    for b0 in range(0, shape[0], band_rows):
        rs = np.flatnonzero((rt[0] >= b0) & (rt[0] < b0 + band_rows))
        if not len(rs):
            continue
        r_hi = int(rt[1][rs].max()) + 1  # a tap's second cell may be the next band's
        h = read(b0, c_lo, r_hi - b0, c_hi - c_lo)
        hv[rs] = bilinear_taps(h, tuple(x[rs] for x in rt), ct, origin=(b0, c_lo))
    return hv


def terrain_mesh_by_window(read, shape: tuple[int, int], dx: float, origin_m: tuple[float, float],
                           max_vertices_per_side: int, band_rows: int = 512) -> TerrainMesh:
    """build_terrain_mesh of a height grid read by window (lattice_heights)."""
    ri, ci = lattice_of(*shape, max_vertices_per_side)
    size = (shape[1] * dx, shape[0] * dx)
    return mesh_from_lattice(lattice_heights(read, shape, ri, ci, band_rows), ri, ci, dx, tuple(origin_m), size)


def mesh_from_lattice(hv: np.ndarray, ri: np.ndarray, ci: np.ndarray, dx: float, origin_m: tuple[float, float],
                      size_m: tuple[float, float]) -> TerrainMesh:
    """The mesh of the lattice heights hv (float64) at lattice lines ri, ci (lattice_of)."""
    x = origin_m[0] + (ci + 0.5) * dx
    z = origin_m[1] + (ri + 0.5) * dx
    nr, nc = hv.shape
    X, Z = np.meshgrid(x, z)
    points = np.stack([X, hv, Z], axis=-1).reshape(-1, 3)

    # Normals from central differences of the lattice heights, in metres.
    dh_dx = np.gradient(hv, x, axis=1)
    dh_dz = np.gradient(hv, z, axis=0)
    n = np.stack([-dh_dx, np.ones_like(hv), -dh_dz], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)

    width, depth = size_m
    s = (X - origin_m[0]) / width
    t = 1.0 - (Z - origin_m[1]) / depth
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


# Terrain tiles: the lattice cut into tiles of at most tile_quads quads a side, each tile drawn at LOD strides
# (every stride-th lattice line). A coarse LOD keeps its tile's border at full resolution and fans the ring of
# coarse quads along the border onto it, so every LOD of a tile has the same border vertices as the full lattice:
# neighbouring tiles at any LODs meet without cracks, and no skirts are needed.
LOD_STRIDES = {"full": 1, "half": 2, "quarter": 4}


@dataclass(frozen=True)
class TileMesh:
    """A part of a TerrainMesh: its vertices (the lattice's own values,
    bitwise, but where carve_lod lowered them) and triangles indexing them."""
    points: np.ndarray  # (n, 3) float32
    normals: np.ndarray  # (n, 3) float32
    st: np.ndarray  # (n, 2) float32
    face_vertex_indices: np.ndarray  # (3 * faces,) int32, into points
    lattice_ids: np.ndarray  # (n,) int64: each vertex's index in the whole lattice (row-major)

    @property
    def extent(self) -> np.ndarray:
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)])


def tile_edges(n_vertices: int, tile_quads: int) -> np.ndarray:
    """Lattice lines where tiles meet along one side, first and last
    included: ceil(quads / tile_quads) tiles of as even a size as whole
    quads allow (one tile when the side is at most tile_quads quads)."""
    quads = n_vertices - 1
    n = max(1, -(-quads // max(tile_quads, 1)))
    return np.array([k * quads // n for k in range(n + 1)], np.int64)


def _lod_lines(n: int, stride: int) -> list[int]:
    lines = list(range(0, n, stride))
    return lines + [n] if lines[-1] != n else lines


def _coarse_quad(a: int, b: int, c: int, d: int, rows: int, cols: int) -> list[tuple[int, int, int]]:
    """Triangles (corners as (row, col) flattened by the caller) of the coarse
    quad rows a..b, cols c..d of a tile of rows x cols quads whose border
    lines keep every vertex: the quad's outline (its border sides at full
    resolution) fanned from a corner both of whose sides are plain, else
    from the quad's centre vertex, else (a one-quad-wide strip between two
    borders) its fine quads. Counter-clockwise seen from +Y."""
    def side(start: tuple[int, int], end: tuple[int, int], on_border: bool) -> list[tuple[int, int]]:
        """The vertices from start up to (not including) end along a row or column: every one on a border."""
        n = max(abs(end[0] - start[0]), abs(end[1] - start[1]))
        steps = range(n) if on_border else range(1)
        return [(start[0] + (end[0] - start[0]) * k // n, start[1] + (end[1] - start[1]) * k // n) for k in steps]

    west, south, east, north = c == 0, b == rows, d == cols, a == 0
    # the outline NW -> SW -> SE -> NE (counter-clockwise from above: x east, z south)
    ring = (side((a, c), (b, c), west) + side((b, c), (b, d), south) + side((b, d), (a, d), east)
            + side((a, d), (a, c), north))
    plain = {(a, c): not (west and b - a > 1) and not (north and d - c > 1),
             (b, c): not (west and b - a > 1) and not (south and d - c > 1),
             (b, d): not (east and b - a > 1) and not (south and d - c > 1),
             (a, d): not (east and b - a > 1) and not (north and d - c > 1)}
    corner = next((p for p in ((b, d), (a, c), (b, c), (a, d)) if plain[p]), None)
    if corner is not None:
        k = ring.index(corner)
        ring = ring[k:] + ring[:k]
        return [(ring[0], ring[i], ring[i + 1]) for i in range(1, len(ring) - 1)]
    if b - a >= 2 and d - c >= 2:
        centre = ((a + b) // 2, (c + d) // 2)
        return [(centre, ring[i], ring[(i + 1) % len(ring)]) for i in range(len(ring))]
    return [t for r in range(a, b) for q in range(c, d)
            for t in (((r, q), (r + 1, q), (r, q + 1)), ((r, q + 1), (r + 1, q), (r + 1, q + 1)))]


def tile_lod_triangles(rows: int, cols: int, stride: int) -> np.ndarray:
    """(faces, 3) local vertex indices (row-major over the tile's
    (rows + 1) x (cols + 1) vertices) of a tile of rows x cols quads at a
    LOD stride: stride 1 the lattice's own triangles (build_terrain_mesh's
    diagonal), coarser ones every stride-th line inside with the border at
    full resolution (_coarse_quad)."""
    if stride <= 1:
        idx = np.arange((rows + 1) * (cols + 1), dtype=np.int64).reshape(rows + 1, cols + 1)
        a, b, d, e = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        return np.stack([a, d, b, b, d, e], axis=-1).reshape(-1, 3)
    rr, cc = _lod_lines(rows, stride), _lod_lines(cols, stride)
    tris = []
    for i in range(len(rr) - 1):
        for j in range(len(cc) - 1):
            a, b, c, d = rr[i], rr[i + 1], cc[j], cc[j + 1]
            if a > 0 and b < rows and c > 0 and d < cols:  # inside the border ring: two triangles
                tris += [((a, c), (b, c), (a, d)), ((a, d), (b, c), (b, d))]
            else:
                tris += _coarse_quad(a, b, c, d, rows, cols)
    t = np.asarray(tris, np.int64)  # (faces, 3, 2)
    return t[..., 0] * (cols + 1) + t[..., 1]


def terrain_tile(mesh: TerrainMesh, rows: tuple[int, int], cols: tuple[int, int], stride: int = 1) -> TileMesh:
    """The tile of the mesh's lattice between lattice lines rows (r0, r1)
    and cols (c0, c1), inclusive, at a LOD stride (tile_lod_triangles): its
    vertices are the lattice's own, so tiles sharing a border share its
    vertices bitwise."""
    nr, nc = mesh.lattice_shape
    (r0, r1), (c0, c1) = rows, cols
    if not (0 <= r0 < r1 < nr and 0 <= c0 < c1 < nc):
        raise ValueError(f"tile rows {rows} cols {cols} outside the {nr}x{nc} lattice")
    local = tile_lod_triangles(r1 - r0, c1 - c0, stride)
    used, faces = np.unique(local, return_inverse=True)
    lr, lc = np.divmod(used, c1 - c0 + 1)
    ids = (lr + r0) * nc + (lc + c0)
    return TileMesh(mesh.points[ids], mesh.normals[ids], mesh.st[ids], faces.reshape(-1).astype(np.int32), ids)


def carve_lod(mesh: TerrainMesh, tile: TileMesh, rows: tuple[int, int], cols: tuple[int, int], stride: int,
              water: np.ndarray, depth_m: float) -> tuple[TileMesh, int]:
    """The tile's LOD at a stride (terrain_tile) with the vertices of its
    inner quads lowered where its surface would rise above points on the
    water surface (x, y, z) less depth_m: a coarse LOD spans a narrow valley
    above its river and would bury it. Each point's triangle's three
    vertices go down by the largest rise of the points it holds, so the
    surface at every point ends depth_m under the water. The border ring
    (its vertices shared with the neighbours) stays as it is. Returns the
    tile and how many vertices it lowered."""
    if stride <= 1 or not len(water):
        return tile, 0
    nr, nc = mesh.lattice_shape
    lattice = mesh.points.reshape(nr, nc, 3)
    xs, zs = lattice[0, :, 0].astype(np.float64), lattice[:, 0, 2].astype(np.float64)
    ci = (water[:, 0] - xs[0]) / (xs[-1] - xs[0]) * (nc - 1)  # the lattice is evenly spaced
    ri = (water[:, 2] - zs[0]) / (zs[-1] - zs[0]) * (nr - 1)
    rr = np.asarray(_lod_lines(rows[1] - rows[0], stride)) + rows[0]
    cc = np.asarray(_lod_lines(cols[1] - cols[0], stride)) + cols[0]
    qi = np.searchsorted(rr, ri, side="right") - 1
    qj = np.searchsorted(cc, ci, side="right") - 1
    inner = (qi >= 1) & (qi <= len(rr) - 3) & (qj >= 1) & (qj <= len(cc) - 3)  # tile_lod_triangles' plain quads
    if not inner.any():
        return tile, 0
    qi, qj, ri, ci, y = qi[inner], qj[inner], ri[inner], ci[inner], water[inner, 1]
    a, b, c, d = rr[qi], rr[qi + 1], cc[qj], cc[qj + 1]
    u, v = (ci - c) / (d - c), (ri - a) / (b - a)
    upper = u + v <= 1.0  # triangle (a c, b c, a d); otherwise (a d, b c, b d): the lattice's diagonal
    corners = np.stack([np.where(upper, a * nc + c, a * nc + d), b * nc + c, np.where(upper, a * nc + d, b * nc + d)], 1)
    weights = np.stack([np.where(upper, 1.0 - u - v, 1.0 - v), np.where(upper, v, 1.0 - u),
                        np.where(upper, u, u + v - 1.0)], 1)
    at = np.searchsorted(tile.lattice_ids, corners)  # the tile's vertices (lattice_ids is sorted)
    points = tile.points.astype(np.float64)
    rise = (weights * points[at, 1]).sum(1) - (y - depth_m)
    drop = np.zeros(len(points))
    np.maximum.at(drop, at.ravel(), np.repeat(np.maximum(rise, 0.0), 3))
    if not (drop > 0).any():
        return tile, 0
    points[:, 1] -= drop
    return (TileMesh(points.astype(np.float32), tile.normals, tile.st, tile.face_vertex_indices, tile.lattice_ids),
            int((drop > 0).sum()))


def lod_error_m(mesh: TerrainMesh, tile: TileMesh) -> float:
    """Largest vertical distance between the full lattice's vertices inside
    the tile and the tile's surface (0 for the full LOD): each triangle
    against the lattice vertices in its box, in lattice coordinates (the
    lattice is evenly spaced, so they are the plane's own)."""
    nc = mesh.lattice_shape[1]
    heights = mesh.points[:, 1].astype(np.float64)
    r, c = np.divmod(tile.lattice_ids, nc)
    tri = tile.face_vertex_indices.reshape(-1, 3)
    tr, tc, ty = r[tri].astype(np.float64), c[tri].astype(np.float64), tile.points[:, 1].astype(np.float64)[tri]
    r0, c0 = r[tri].min(1), c[tri].min(1)
    span = int(max((r[tri].max(1) - r0).max(), (c[tri].max(1) - c0).max())) + 1
    dr, dc = (a.reshape(-1) for a in np.mgrid[0:span, 0:span])
    qr, qc = r0[:, None] + dr[None], c0[:, None] + dc[None]  # (faces, span^2) candidate vertices
    e1r, e1c, e2r, e2c = tr[:, 1] - tr[:, 0], tc[:, 1] - tc[:, 0], tr[:, 2] - tr[:, 0], tc[:, 2] - tc[:, 0]
    det = (e1c * e2r - e1r * e2c)[:, None]
    vr, vc = qr - tr[:, :1], qc - tc[:, :1]
    u = (vc * e2r[:, None] - vr * e2c[:, None]) / det
    w = (e1c[:, None] * vr - e1r[:, None] * vc) / det
    inside = (u >= -1e-9) & (w >= -1e-9) & (u + w <= 1 + 1e-9)
    y = ty[:, :1] + u * (ty[:, 1] - ty[:, 0])[:, None] + w * (ty[:, 2] - ty[:, 0])[:, None]
    ids = (qr * nc + qc)[inside]
    err = np.abs(y[inside] - heights[np.clip(ids, 0, len(heights) - 1)])
    return float(err.max()) if len(err) else 0.0


def weld_lattice(points: np.ndarray, normals: np.ndarray) -> TerrainMesh | None:
    """The lattice (row-major: z rows, x columns) of a terrain given in
    tiles (their full LOD: every lattice vertex, each border vertex in
    several tiles, bitwise equal); None unless the points make a whole
    lattice. No triangles or st: a TerrainMesh for height_on_mesh."""
    p = np.asarray(points, np.float32)
    key = np.stack([p[:, 2], p[:, 0]], -1)
    _, first = np.unique(key, axis=0, return_index=True)  # sorted by z, then x: row-major
    xs, zs = np.unique(p[:, 0]), np.unique(p[:, 2])
    if len(first) != len(xs) * len(zs):
        return None
    return TerrainMesh(p[first], np.asarray(normals, np.float32)[first], np.zeros((len(first), 2), np.float32),
                       np.zeros(0, np.int32), (len(zs), len(xs)))
