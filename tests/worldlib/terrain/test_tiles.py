"""Terrain tiles and their LODs (worldlib.terrain.mesh): each LOD a valid
mesh covering its tile, its border the full lattice's, the error measure
against brute force."""
from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from pipeline.grid import Grid
from worldlib.terrain.mesh import (build_terrain_mesh, lod_error_m, terrain_tile, tile_edges, tile_lod_triangles)


def _mesh(rows=40, cols=53, cell=25.0):
    r, c = np.mgrid[0:rows, 0:cols]
    h = 800 + 300 * np.sin(c / 6.0) * np.cos(r / 9.0) + 2.0 * r
    return build_terrain_mesh(Grid(h.astype(np.float32), cell), 10_000)


def test_tile_edges_split_evenly_and_a_small_side_is_one_tile():
    assert tile_edges(1025, 256).tolist() == [0, 256, 512, 768, 1024]
    assert tile_edges(10, 256).tolist() == [0, 9]
    e = tile_edges(301, 64)  # 300 quads in 5 tiles of 60
    assert e.tolist() == [0, 60, 120, 180, 240, 300]
    assert np.diff(tile_edges(1000, 7)).max() <= 7 and np.diff(tile_edges(1000, 7)).min() >= 6


@pytest.mark.parametrize("rows,cols", [(1, 1), (1, 9), (2, 2), (3, 7), (5, 5), (8, 8), (13, 6), (16, 17), (33, 2)])
@pytest.mark.parametrize("stride", [1, 2, 4, 8])
def test_every_lod_is_a_watertight_cover_of_its_tile_with_a_full_border(rows, cols, stride):
    t = tile_lod_triangles(rows, cols, stride)
    r, c = np.divmod(t, cols + 1)
    # counter-clockwise seen from +Y (x = col east, z = row south), none degenerate, covering the tile once
    cross_y = (r[:, 1] - r[:, 0]) * (c[:, 2] - c[:, 0]) - (c[:, 1] - c[:, 0]) * (r[:, 2] - r[:, 0])
    assert (cross_y > 0).all()
    assert cross_y.sum() / 2 == rows * cols
    directed = Counter((int(a), int(b)) for tri in t for a, b in zip(tri, np.roll(tri, -1)))
    assert max(directed.values()) == 1  # consistently wound, no edge used twice the same way
    boundary = {e for e in directed if (e[1], e[0]) not in directed}
    ring = ([(0, q) for q in range(cols + 1)] + [(q, cols) for q in range(1, rows + 1)]
            + [(rows, q) for q in range(cols - 1, -1, -1)] + [(q, 0) for q in range(rows - 1, 0, -1)])
    ids = [a * (cols + 1) + b for a, b in ring]
    # the open edges are exactly the border's full-resolution segments (clockwise in row-col = ccw from above)
    want = {(ids[(k + 1) % len(ids)], ids[k]) for k in range(len(ids))}
    assert boundary == want
    if stride == 1:
        assert len(t) == 2 * rows * cols


def test_tiles_share_border_vertices_bitwise_and_lods_keep_the_border():
    m = _mesh()
    nc = m.lattice_shape[1]
    rows, cols = tile_edges(m.lattice_shape[0], 13), tile_edges(nc, 13)
    for s_a in (1, 2, 4):
        for s_b in (1, 2, 4):
            west = terrain_tile(m, (rows[1], rows[2]), (cols[0], cols[1]), s_a)
            east = terrain_tile(m, (rows[1], rows[2]), (cols[1], cols[2]), s_b)
            on_w = np.flatnonzero(west.lattice_ids % nc == cols[1])
            on_e = np.flatnonzero(east.lattice_ids % nc == cols[1])
            assert len(on_w) == len(on_e) == rows[2] - rows[1] + 1
            for attr in ("points", "normals", "st"):
                a, b = getattr(west, attr)[on_w], getattr(east, attr)[on_e]
                assert a.tobytes() == b.tobytes(), (attr, s_a, s_b)


def test_full_lod_tiles_are_the_single_mesh():
    m = _mesh()
    rows, cols = tile_edges(m.lattice_shape[0], 16), tile_edges(m.lattice_shape[1], 16)
    ids, tris = [], []
    for j in range(len(rows) - 1):
        for i in range(len(cols) - 1):
            t = terrain_tile(m, (rows[j], rows[j + 1]), (cols[i], cols[i + 1]))
            np.testing.assert_array_equal(t.points, m.points[t.lattice_ids])
            ids.append(t.lattice_ids)
            tris.append(t.lattice_ids[t.face_vertex_indices.reshape(-1, 3)])
    assert np.array_equal(np.unique(np.concatenate(ids)), np.arange(len(m.points)))
    got = {tuple(x) for x in np.concatenate(tris).tolist()}
    assert got == {tuple(x) for x in m.face_vertex_indices.reshape(-1, 3).tolist()}


def _brute_error(m, t) -> float:
    """Per lattice vertex, the triangle (by a loop) containing it in xz."""
    nc = m.lattice_shape[1]
    r, c = np.divmod(t.lattice_ids, nc)
    worst = 0.0
    tri = t.points[t.face_vertex_indices.reshape(-1, 3)].astype(np.float64)
    for rr in range(r.min(), r.max() + 1):
        for cc in range(c.min(), c.max() + 1):
            p = m.points[rr * nc + cc].astype(np.float64)
            for a, b, d in tri:
                e1, e2, v = b - a, d - a, p - a
                det = e1[0] * e2[2] - e1[2] * e2[0]
                u = (v[0] * e2[2] - v[2] * e2[0]) / det
                w = (e1[0] * v[2] - e1[2] * v[0]) / det
                if u >= -1e-9 and w >= -1e-9 and u + w <= 1 + 1e-9:
                    worst = max(worst, abs(a[1] + u * e1[1] + w * e2[1] - p[1]))
                    break
    return worst


def test_lod_error_matches_brute_force():
    m = _mesh(20, 20)
    for stride in (1, 2, 4):
        t = terrain_tile(m, (0, 13), (3, 19), stride)
        assert lod_error_m(m, t) == pytest.approx(_brute_error(m, t), abs=1e-3)
    assert lod_error_m(m, terrain_tile(m, (0, 13), (3, 19), 1)) < 1e-3
    assert lod_error_m(m, terrain_tile(m, (0, 13), (3, 19), 4)) > 1.0  # the sine's curvature shows


def test_a_plane_has_no_lod_error():
    r, c = np.mgrid[0:30, 0:30]
    m = build_terrain_mesh(Grid((100 + 3.0 * r - 2.0 * c).astype(np.float32), 10.0), 1000)
    for stride in (2, 4, 8):
        assert lod_error_m(m, terrain_tile(m, (0, 29), (0, 29), stride)) < 1e-3


def _surface_at(tile, x, z):
    """The tile mesh's height at (x, z), by brute force over its triangles (seen from above)."""
    p = tile.points.astype(np.float64)
    out = np.full(len(x), np.nan)
    for a, b, c in tile.face_vertex_indices.reshape(-1, 3):
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = p[a], p[b], p[c]
        det = (bx - ax) * (cz - az) - (cx - ax) * (bz - az)
        u = ((x - ax) * (cz - az) - (cx - ax) * (z - az)) / det
        v = ((bx - ax) * (z - az) - (x - ax) * (bz - az)) / det
        inside = (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9)
        out[inside] = (ay + u * (by - ay) + v * (cy - ay))[inside]
    return out


def test_a_carved_coarse_lod_keeps_the_river_in_sight_and_its_border():
    """A V valley along the rows, its floor between the quarter LOD's
    lattice lines: the coarse surface spans the valley above the river;
    carved, it lies WATER depth under the water at every river point of the
    inner quads, and the border ring is the lattice's own, bit for bit."""
    from worldlib.terrain.mesh import carve_lod

    c = np.arange(41, dtype=np.float64)
    h = np.tile(10.0 * np.abs(c - 18.0), (41, 1)).astype(np.float32)  # the floor on column 18 (x = 18.5 m)
    mesh = build_terrain_mesh(Grid(h, 1.0), 41)
    river = np.stack([np.full(25, 18.5), np.full(25, 0.4), np.linspace(8.5, 31.5, 25)], -1)  # x, y 0.4 m deep, z
    tile = terrain_tile(mesh, (0, 40), (0, 40), 4)
    before = _surface_at(tile, river[:, 0], river[:, 2])
    assert (before > 15.0).all()  # the quarter LOD buries the river under 20 m of valley
    carved, lowered = carve_lod(mesh, tile, (0, 40), (0, 40), 4, river, 0.3)
    after = _surface_at(carved, river[:, 0], river[:, 2])
    assert np.all(after <= river[:, 1] - 0.3 + 1e-4) and lowered > 0
    moved = carved.points[:, 1] != tile.points[:, 1]
    r, col = np.divmod(tile.lattice_ids, 41)
    border = (r == 0) | (r == 40) | (col == 0) | (col == 40)
    assert not moved[border].any() and np.array_equal(carved.points[border], tile.points[border])
    assert set(col[moved]) <= {16, 20}  # only the lines either side of the river
    assert carve_lod(mesh, terrain_tile(mesh, (0, 40), (0, 40), 1), (0, 40), (0, 40), 1, river, 0.3)[1] == 0
    # the error the DCC selection reads is the carved surface's: the lowered lattice lines sit 19.9 m under the lattice
    assert lod_error_m(mesh, carved) >= 19.9
