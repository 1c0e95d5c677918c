"""The world assembly on synthetic terrain: valid USD, mesh conventions, mesh-surface queries."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline import exr, usdio
from worldlib import images
from pipeline.contract import RunContext
from pipeline.grid import Grid
from stages.world import STAGE
from worldlib.terrain.mesh import build_terrain_mesh, height_on_mesh
from pipeline.opencl import get_cl


def _terrain(rows=33, cols=40, cell=25.0):
    r, c = np.mgrid[0:rows, 0:cols]
    h = 800 + 300 * np.sin(c / 6.0) * np.cos(r / 9.0) + 2.0 * r
    return Grid(h.astype(np.float32), cell)


def _run(tmp_path, grid, **params):
    cl_env = get_cl()  # the device a bake would use (an every_device test's, when it runs)
    ctx = RunContext(cl=cl_env, stage=STAGE, key="k", out_dir=tmp_path, seed=0,
                     provenance={"stage": "world", "key": "k"}, project_root=tmp_path)
    out = STAGE.run(ctx, {"terrain": grid}, STAGE.params(**params))
    return ctx, out


def test_world_layers_validate_and_follow_conventions(tmp_path):
    from pxr import Usd, UsdGeom, UsdShade

    ctx, out = _run(tmp_path, _terrain(), mesh_max_vertices=17, texture_size=32)
    assert usdio.validate(out["world.root"]) == []
    stage = Usd.Stage.Open(str(out["world.root"]))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/World"
    assert Usd.ModelAPI(stage.GetDefaultPrim()).GetKind() == "assembly"
    # a world smaller than a terrain tile is one tile
    assert [p.GetName() for p in stage.GetPrimAtPath("/World/Terrain/Ground").GetChildren()] == ["Tile_x0_y0"]
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Terrain/Ground/Tile_x0_y0"))
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    pts = np.array(mesh.GetPointsAttr().Get())
    # 17 vertices along the 40 columns; along the 33 rows the same spacing (39 / 16 cells) gives 14
    assert len(pts) == 14 * 17
    spacing = np.diff(np.unique(pts[:, 0])).mean(), np.diff(np.unique(pts[:, 2])).mean()
    assert abs(spacing[0] / spacing[1] - 1) < 0.02
    normals = np.array(mesh.GetNormalsAttr().Get())
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-5) and (normals[:, 1] > 0).all()
    ext = np.array(mesh.GetExtentAttr().Get())
    assert np.allclose(ext[0], pts.min(0)) and np.allclose(ext[1], pts.max(0))
    assert UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").IsDefined()
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert material.GetPath() == "/World/Terrain/Looks/Ground"
    tex = stage.GetPrimAtPath("/World/Terrain/Looks/Ground/Albedo").GetAttribute("inputs:file").Get()
    assert tex.resolvedPath and tex.resolvedPath.endswith("albedo.exr")
    attrs = exr.read_attributes(out["world.albedo"])
    assert attrs["oiio:miplevels"] > 1 and attrs["worldbake:stage"] == "world"


def test_triangles_face_up_and_cover_the_grid(tmp_path):
    g = _terrain()
    m = build_terrain_mesh(g, 1000)
    tri = m.points[m.face_vertex_indices.reshape(-1, 3)].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (n[:, 1] > 0).all()  # counter-clockwise seen from +Y: rightHanded faces up
    assert m.lattice_shape == g.shape  # full resolution when allowed
    assert np.allclose(m.points[:, 1].reshape(g.shape), g.data, atol=1e-3)


def test_height_on_mesh_lies_on_its_triangles():
    g = _terrain()
    m = build_terrain_mesh(g, 12)
    rng = np.random.default_rng(1)
    lo, hi = m.extent
    x = rng.uniform(lo[0], hi[0], 2000)
    z = rng.uniform(lo[2], hi[2], 2000)
    y = height_on_mesh(m, x, z)
    # at the lattice vertices the surface passes through the points
    assert np.allclose(height_on_mesh(m, m.points[:, 0].astype(np.float64), m.points[:, 2].astype(np.float64)),
                       m.points[:, 1], atol=1e-3)
    # every query point lies in the plane of one of the mesh's triangles (brute force)
    tri = m.points[m.face_vertex_indices.reshape(-1, 3)].astype(np.float64)
    for xi, zi, yi in zip(x[:200], z[:200], y[:200]):
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        v0, v1 = b - a, c - a
        det = v0[:, 0] * v1[:, 2] - v0[:, 2] * v1[:, 0]
        u = ((xi - a[:, 0]) * v1[:, 2] - (zi - a[:, 2]) * v1[:, 0]) / det
        w = (v0[:, 0] * (zi - a[:, 2]) - v0[:, 2] * (xi - a[:, 0])) / det
        inside = (u >= -1e-9) & (w >= -1e-9) & (u + w <= 1 + 1e-9)
        k = np.flatnonzero(inside)[0]
        y_ref = a[k, 1] + u[k] * v0[k, 1] + w[k] * v1[k, 1]
        assert abs(y_ref - yi) < 1e-3


def test_too_small_terrain_is_refused(tmp_path):
    from pipeline.errors import InputError
    with pytest.raises(InputError, match="at least 2x2"):
        _run(tmp_path, Grid(np.zeros((1, 5), np.float32), 1.0))


def _splat(rows, cols, seed=3):
    from stages.world import ground

    rng = np.random.default_rng(seed)
    w = rng.random((rows, cols, len(ground.SPLAT_ORDER))).astype(np.float32) ** 3
    w /= w.sum(axis=-1, keepdims=True)
    return Grid(w, 25.0, tuple(sorted(ground.SPLAT_ORDER)))  # the EXR's order (sorted), not the blend order


def test_ground_weights_equal_the_splat_maps_and_sum_to_one():
    from stages.world import ground

    s = _splat(9, 13).data
    # at the cell centres the texel weights are the splat maps' own
    w = ground.texel_weights(s, np.arange(9), np.arange(13))
    np.testing.assert_array_equal(w, s)
    # between them (and beyond the edge) they are convex blends: within [0, 1], summing to 1
    w = ground.texel_weights(s, np.linspace(-1, 9, 57), np.linspace(-2, 14, 61))
    assert w.min() >= 0 and w.max() <= 1
    np.testing.assert_allclose(w.sum(axis=-1), 1.0, atol=1e-6)


def test_ground_material_udim_tiles_and_normal_map(cl_env, tmp_path):
    from pxr import Usd, UsdShade

    from stages.world import ground, reference

    terrain = _terrain()
    splat = _splat(*terrain.shape)
    ctx = RunContext(cl=cl_env, stage=STAGE, key="k", out_dir=tmp_path, seed=0, provenance={"stage": "world", "key": "k"},
                     project_root=tmp_path)
    out = STAGE.run(ctx, {"terrain": terrain, "splat": splat},
                    STAGE.params(mesh_max_vertices=17, texture_size=32, ground_texel_m=2.0, ground_tile_texels=256,
                                 ground_detail_texels=32, ground_near_texels=32))
    assert usdio.validate(out["world.root"]) == []
    # 40 x 25 m = 1000 m wide at 2 m per texel in 256-texel tiles: 2 x 2 tiles
    assert ctx.metrics["ground_udim_tiles"] == 4 and ctx.metrics["ground_texel_m"] <= 2.0
    for n in (1001, 1002, 1011, 1012):
        assert (tmp_path / f"ground.{n}.exr").is_file()
    stage = Usd.Stage.Open(str(out["world.root"]))
    looks = "/World/Terrain/Looks/Ground"
    assert stage.GetPrimAtPath(f"{looks}/Albedo").GetAttribute("inputs:file").Get().path == "./ground.<UDIM>.exr"
    assert stage.GetPrimAtPath(f"{looks}/Normal").GetAttribute("inputs:file").Get().path == "./normal.exr"
    surface = UsdShade.Shader(stage.GetPrimAtPath(f"{looks}/Surface"))
    assert surface.GetInput("normal").HasConnectedSource()
    s = np.stack([splat.channel(c) for c in ground.SPLAT_ORDER], -1)
    tables = ground.detail_tables(0, 1000.0 / 512)
    a = reference.tile_albedo(s, 25.0, (0.0, 0.0), 2, 256, 0, 0, tables, 1000.0 / 512)
    import OpenImageIO as oiio
    written = np.asarray(oiio.ImageBuf(str(tmp_path / "ground.1001.exr")).get_pixels(oiio.FLOAT))
    np.testing.assert_allclose(written, a, atol=1e-3)  # the device's tile, stored as half floats
    # a flat terrain has an upright normal map
    flat = ground.normal_map(np.zeros((5, 6)), np.zeros((5, 6)), 10.0)
    np.testing.assert_allclose(flat, np.broadcast_to([0.5, 0.5, 1.0], flat.shape))
    # a slope rising east that the mesh does not have tilts the normal west (x < 0.5)
    ramp = ground.normal_map(np.tile(np.arange(6.0), (5, 1)), np.zeros((5, 6)), 10.0)
    assert (ramp[..., 0] < 0.5).all() and np.allclose(ramp[..., 1], 0.5)


def test_the_ground_textures_are_reused_while_terrain_and_splat_do_not_change(cl_env, tmp_path):
    """A world re-made for its plants (another layer changed, same terrain
    and splat) links the ground textures from the run that baked them: the
    same bytes as a clean run; a new splat bakes them again."""
    from pipeline.store import Store
    from pipeline.units import Units

    terrain, splat = _terrain(), _splat(*_terrain().shape)
    params = STAGE.params(mesh_max_vertices=17, texture_size=32, ground_texel_m=2.0, ground_tile_texels=256,
                          ground_detail_texels=32, ground_near_texels=32)

    def run(out, build, splat_grid, roughness=0.9):
        store = Store(build)
        ctx = RunContext(cl=cl_env, stage=STAGE, key="k", out_dir=out, seed=0, provenance={"stage": "world", "key": "k"},
                         project_root=tmp_path, units=Units(store.units, store.tmp, "world", {"stage": "world"}))
        out.mkdir(parents=True)
        STAGE.run(ctx, {"terrain": terrain, "splat": splat_grid}, params.model_copy(update={"roughness": roughness}))
        return ctx.metrics["ground_reused"], {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*"))
                                              if p.suffix in (".exr", ".png")}

    first = run(tmp_path / "a", tmp_path / "build", splat)
    again = run(tmp_path / "b", tmp_path / "build", splat, roughness=0.5)  # only the layer changes
    clean = run(tmp_path / "c", tmp_path / "clean", splat, roughness=0.5)
    assert (first[0], again[0], clean[0]) == (False, True, False)
    # overview, normal map, 4 UDIM tiles; the detail layer: 2 splat textures, 2 near textures, 6 x 2 detail maps
    assert again[1] == clean[1] == first[1] and len(first[1]) == 6 + 2 + 2 + 12
    other = run(tmp_path / "d", tmp_path / "build", _splat(*terrain.shape, seed=4))
    assert other[0] is False and other[1]["ground.1001.exr"] != first[1]["ground.1001.exr"]


def test_mipmapped_texture_levels_are_box_means(tmp_path):
    import OpenImageIO as oiio

    rng = np.random.default_rng(1)
    rgb = rng.random((8, 6, 3)).astype(np.float32)
    images.write_mipmapped_texture(tmp_path / "t.exr", rgb, {"stage": "world"})
    inp = oiio.ImageInput.open(str(tmp_path / "t.exr"))
    levels = []
    while inp.seek_subimage(0, len(levels)):
        levels.append(inp.read_image(oiio.FLOAT))
    inp.close()
    # OpenEXR's round-down chain 8x6, 4x3, 2x1, 1x1; half-float texels
    assert [lv.shape[:2] for lv in levels] == [(8, 6), (4, 3), (2, 1), (1, 1)]
    np.testing.assert_allclose(levels[0], rgb, atol=1e-3)
    box = rgb.reshape(4, 2, 3, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(levels[1], box, atol=1e-3)
    np.testing.assert_allclose(levels[2][:, 0], box[:, :2].reshape(2, 2, 2, 3).mean(axis=(1, 2)), atol=1e-3)


def test_a_texture_written_band_by_band_is_the_whole_ones_bytes(tmp_path):
    rng = np.random.default_rng(2)
    rgb = rng.random((201, 77, 3)).astype(np.float32)  # odd rows and columns: the MIP levels drop them
    images.write_mipmapped_texture(tmp_path / "whole.exr", rgb, {"stage": "world"})
    with images.MipmappedWriter(tmp_path / "bands.exr", 201, 77, 3, {"stage": "world"}) as out:
        for r0 in range(0, 201, 64):
            out.write_rows(rgb[r0:r0 + 64])
    assert (tmp_path / "bands.exr").read_bytes() == (tmp_path / "whole.exr").read_bytes()
    with pytest.raises(ValueError, match="whole 64-row tiles"):
        with images.MipmappedWriter(tmp_path / "bad.exr", 201, 77, 3) as out:
            out.write_rows(rgb[:10])
