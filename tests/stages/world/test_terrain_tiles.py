"""The terrain in tiles (stages/world/terrain_tiles.py): payloads a DCC can
leave unloaded, `lod` variants, borders shared bitwise at any LODs, the
full LOD the single lattice mesh."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline import usdio
from pipeline.contract import RunContext
from pipeline.grid import Grid
from stages.world import STAGE
from worldlib.ground import SPLAT_CHANNELS
from worldlib.terrain.mesh import LOD_STRIDES, build_terrain_mesh

PARAMS = dict(mesh_max_vertices=1000, terrain_tile_quads=16, texture_size=32, ground_texel_m=8.0,
              ground_tile_texels=128, ground_detail_texels=32, ground_near_m=200.0, ground_near_texels=64)
PRIMVARS = ("st", "st_udim", "st_detail")


def _terrain(rows=40, cols=53, cell=25.0):
    r, c = np.mgrid[0:rows, 0:cols]
    h = 800 + 300 * np.sin(c / 6.0) * np.cos(r / 9.0) + 2.0 * r
    return Grid(h.astype(np.float32), cell)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from pipeline.opencl import get_cl

    out_dir = tmp_path_factory.mktemp("terrain_tiles")
    terrain = _terrain()
    rng = np.random.default_rng(3)
    w = rng.random((*terrain.shape, len(SPLAT_CHANNELS))).astype(np.float32)
    w /= w.sum(axis=-1, keepdims=True)
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="k", out_dir=out_dir, seed=0,
                     provenance={"stage": "world", "key": "k"}, project_root=out_dir)
    out = STAGE.run(ctx, {"terrain": terrain, "splat": Grid(w, 25.0, SPLAT_CHANNELS)}, STAGE.params(**PARAMS))
    return out, ctx, terrain


def _stage(out, load=True):
    from pxr import Usd

    return Usd.Stage.Open(str(out["world.root"]), Usd.Stage.LoadAll if load else Usd.Stage.LoadNone)


def _get(prim, name):
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(prim)
    if name == "points":
        return np.asarray(mesh.GetPointsAttr().Get())
    if name == "normals":
        return np.asarray(mesh.GetNormalsAttr().Get())
    return np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar(name).Get())


def test_tiles_are_payloads_a_viewer_can_leave_unloaded(world):
    from pxr import UsdGeom, UsdShade

    from stages.world.terrain_tiles import tile_prims

    out, ctx, _ = world
    assert usdio.validate(out["world.root"]) == []
    # 40 x 53 cells at one vertex a cell: 39 x 52 quads in tiles of at most 16: 3 x 4 tiles
    assert ctx.metrics["terrain_tiles"] == [3, 4]
    stage = _stage(out, load=False)
    tiles = tile_prims(stage)
    assert len(tiles) == 12 and all(not p.IsLoaded() for p in tiles)
    for p in tiles:
        mesh = UsdGeom.Mesh(p)
        assert mesh.GetPointsAttr().Get() is None  # no geometry until loaded
        assert mesh.GetExtentAttr().Get() is not None  # but its bounds, for a viewer to pick it by
        vset = p.GetVariantSets().GetVariantSet("lod")
        assert set(vset.GetVariantNames()) == set(LOD_STRIDES) and vset.GetVariantSelection() == "full"
        assert UsdShade.MaterialBindingAPI(p).ComputeBoundMaterial()[0].GetPath() == "/World/Terrain/Looks/Ground"
    one = tiles[5]
    stage.Load(one.GetPath())
    assert one.IsLoaded() and sum(p.IsLoaded() for p in tiles) == 1
    pts = _get(one, "points")
    span = one.GetCustomDataByKey("worldbake:tile")
    assert len(pts) == (span["rows"][1] - span["rows"][0] + 1) * (span["cols"][1] - span["cols"][0] + 1)
    lo, hi = np.asarray(UsdGeom.Mesh(one).GetExtentAttr().Get())
    assert np.allclose(pts.min(0), lo) and np.allclose(pts.max(0), hi)
    # the tile files are declared beside terrain.usdc (an undeclared file fails the bake)
    beside = next(a for a in STAGE.outputs if a.name == "world.terrain").beside
    files = sorted(p.relative_to(out["world.terrain"].parent).as_posix()
                   for p in (out["world.terrain"].parent / "terrain").iterdir())
    assert len(files) == 12 and all(any(__import__("fnmatch").fnmatch(f, b) for b in beside) for f in files)


def _select(stage, prim, lod):
    from pxr import Usd

    with Usd.EditContext(stage, stage.GetSessionLayer()):
        prim.GetVariantSets().GetVariantSet("lod").SetVariantSelection(lod)


@pytest.mark.parametrize("lod_a,lod_b", [("full", "full"), ("full", "quarter"), ("half", "quarter")])
def test_neighbours_share_their_border_bitwise_at_any_lods(world, lod_a, lod_b):
    out, _, _ = world
    stage = _stage(out)
    g = stage.GetPrimAtPath("/World/Terrain/Ground")
    pairs = [("Tile_x1_y1", "Tile_x2_y1", 0), ("Tile_x1_y0", "Tile_x1_y1", 2)]  # east, south neighbours
    for a_name, b_name, axis in pairs:
        a, b = g.GetChild(a_name), g.GetChild(b_name)
        _select(stage, a, lod_a)
        _select(stage, b, lod_b)
        pa, pb = _get(a, "points"), _get(b, "points")
        line = pa[:, axis].max()
        assert pb[:, axis].min() == line
        on_a, on_b = np.flatnonzero(pa[:, axis] == line), np.flatnonzero(pb[:, axis] == line)
        other = 2 - axis
        on_a, on_b = on_a[np.argsort(pa[on_a, other])], on_b[np.argsort(pb[on_b, other])]
        assert len(on_a) == len(on_b) == 14  # the whole border (13 quads), every vertex, at any LOD
        for name in ("points", "normals") + PRIMVARS:
            assert _get(a, name)[on_a].tobytes() == _get(b, name)[on_b].tobytes(), (a_name, b_name, name)


def test_every_lod_variant_is_a_mesh_covering_its_tile(world):
    from pxr import UsdGeom

    from stages.world.terrain_tiles import tile_prims

    out, _, _ = world
    stage = _stage(out)
    for prim in tile_prims(stage):
        b = prim.GetCustomDataByKey("worldbake:tile")["bounds_xz_m"]
        vertices = []
        for lod in LOD_STRIDES:
            _select(stage, prim, lod)
            mesh = UsdGeom.Mesh(prim)
            pts = _get(prim, "points").astype(np.float64)
            idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
            assert (np.asarray(mesh.GetFaceVertexCountsAttr().Get()) == 3).all() and idx.max() < len(pts)
            for name in ("normals",) + PRIMVARS:
                assert len(_get(prim, name)) == len(pts)
            tri = pts[idx]
            ny = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 1]
            assert (ny > 0).all()
            assert 0.5 * ny.sum() == pytest.approx((b[2] - b[0]) * (b[3] - b[1]), rel=1e-6)
            assert pts[:, 0].min() == pytest.approx(b[0]) and pts[:, 2].max() == pytest.approx(b[3])
            vertices.append(len(pts))
        assert vertices[0] > vertices[1] > vertices[2]


def test_the_composed_full_lod_is_the_single_lattice_mesh(world):
    from stages.world.terrain_tiles import tile_prims

    out, ctx, terrain = world
    stage = _stage(out)
    single = build_terrain_mesh(terrain, PARAMS["mesh_max_vertices"])
    tiles = tile_prims(stage)
    pts = np.concatenate([_get(p, "points") for p in tiles])
    normals = np.concatenate([_get(p, "normals") for p in tiles])
    st = np.concatenate([_get(p, "st") for p in tiles])
    welded, first = np.unique(pts, axis=0, return_index=True)
    want = np.unique(single.points, axis=0)
    np.testing.assert_array_equal(welded, want)
    # the same normal and st at each welded vertex as the single mesh's
    order = np.lexsort(single.points.T[::-1])
    np.testing.assert_array_equal(normals[first], single.normals[order])
    np.testing.assert_array_equal(st[first], single.st[order])
    faces = sum(len(_get(p, "points")) and len(np.asarray(p.GetAttribute("faceVertexIndices").Get())) for p in tiles)
    assert faces == len(single.face_vertex_indices)
    assert ctx.metrics["mesh_triangles"] == len(single.face_vertex_indices) // 3


def test_the_renderers_detail_view_welds_the_tiles_into_the_lattice(world):
    """worldlib.render.ground_detail reads the ground's lattice from every tile (at full LOD: dcc.usdc muted)."""
    from worldlib.render.ground_detail import load_detail_view

    out, _, terrain = world
    view = load_detail_view(out["world.root"])
    single = build_terrain_mesh(terrain, PARAMS["mesh_max_vertices"])
    assert view is not None and view.lattice.lattice_shape == single.lattice_shape
    np.testing.assert_array_equal(view.lattice.points, single.points)
    np.testing.assert_array_equal(view.lattice.normals, single.normals)
    assert view.covered is None  # no other mesh: the tiles do not cover one another
