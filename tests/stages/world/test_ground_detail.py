"""The ground's detail layer in the world stage: the files, the USD wiring a
DCC rebuilds (inputs, colour spaces, scale and bias of normal maps), the
near square's subset and its bake against the blend it bakes."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline import usdio
from pipeline.contract import RunContext
from pipeline.grid import Grid
from stages.world import STAGE
from worldlib import ground_detail
from worldlib.ground import GROUND_TYPES, SPLAT_CHANNELS

FAST = dict(mesh_max_vertices=17, terrain_tile_quads=4, texture_size=32, ground_texel_m=2.0, ground_tile_texels=256,
            ground_detail_texels=64, ground_near_m=100.0, ground_near_texels=96)


def _terrain(rows=33, cols=40, cell=25.0):
    r, c = np.mgrid[0:rows, 0:cols]
    h = 800 + 300 * np.sin(c / 6.0) * np.cos(r / 9.0) + 2.0 * r
    return Grid(h.astype(np.float32), cell)


def _splat(rows, cols, seed=3):
    rng = np.random.default_rng(seed)
    w = rng.random((rows, cols, len(SPLAT_CHANNELS))).astype(np.float32) ** 3
    w /= w.sum(axis=-1, keepdims=True)
    return Grid(w, 25.0, SPLAT_CHANNELS)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from pipeline.opencl import get_cl

    out_dir = tmp_path_factory.mktemp("ground_detail")
    terrain = _terrain()
    splat = _splat(*terrain.shape)
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="k", out_dir=out_dir, seed=0,
                     provenance={"stage": "world", "key": "k"}, project_root=out_dir)
    out = STAGE.run(ctx, {"terrain": terrain, "splat": splat}, STAGE.params(**FAST))
    return out_dir, out, ctx, terrain, splat


def test_detail_files_are_written_and_the_layer_validates(world):
    out_dir, out, ctx, _, _ = world
    assert usdio.validate(out["world.root"]) == []
    import OpenImageIO as oiio

    for t in GROUND_TYPES:
        for kind in ("albedo", "normal"):
            spec = oiio.ImageInput.open(str(out_dir / "detail" / f"{t}_{kind}.png")).spec()
            assert (spec.width, spec.height, spec.format) == (64, 64, oiio.UINT8)
    for f in ("splat_a.exr", "splat_b.exr", "near_albedo.png", "near_normal.png"):
        assert (out_dir / f).is_file()
    near = ctx.metrics["ground_detail"]["near"]
    # 100 m rounded to whole quads of the 17-vertex mesh (975 m / 16 = 61 m): 2 quads a side, 96 texels at most
    x0, x1, z0, z1 = near["square"]
    assert x1 - x0 == pytest.approx(2 * 975 / 16) and z1 - z0 == pytest.approx(2 * 975 / 16, rel=0.02)
    assert near["texel_m"] == pytest.approx(max(x1 - x0, z1 - z0) / 96)


def test_detail_network_wiring(world):
    from pxr import Gf, Usd, UsdShade

    from stages.world.ground_near import DETAIL_GRAPH, SPLAT_FILES

    _, out, _, _, _ = world
    stage = Usd.Stage.Open(str(out["world.root"]))
    graph = UsdShade.NodeGraph(stage.GetPrimAtPath(DETAIL_GRAPH))
    assert graph and graph.GetPrim().GetParent().GetPath() == "/World/Terrain/Looks/Ground"
    for t in GROUND_TYPES:
        albedo = UsdShade.Shader(graph.GetOutput(f"{t}_albedo").GetConnectedSource()[0].GetPrim())
        normal = UsdShade.Shader(graph.GetOutput(f"{t}_normal").GetConnectedSource()[0].GetPrim())
        assert albedo.GetIdAttr().Get() == normal.GetIdAttr().Get() == "UsdUVTexture"
        assert albedo.GetInput("file").Get().path == f"./detail/{t}_albedo.png"
        assert albedo.GetInput("sourceColorSpace").Get() == "sRGB"
        assert normal.GetInput("sourceColorSpace").Get() == "raw"
        assert normal.GetInput("scale").Get() == Gf.Vec4f(2, 2, 2, 1)
        assert normal.GetInput("bias").Get() == Gf.Vec4f(-1, -1, -1, 0)
        assert not albedo.GetInput("scale")  # albedo as stored
        for tex in (albedo, normal):
            assert tex.GetInput("wrapS").Get() == tex.GetInput("wrapT").Get() == "repeat"
            xf = UsdShade.Shader(tex.GetInput("st").GetConnectedSource()[0].GetPrim())
            assert xf.GetIdAttr().Get() == "UsdTransform2d"
            assert xf.GetInput("scale").Get()[0] == pytest.approx(1.0 / ground_detail.DETAIL_SETS[t].tile_m)
            reader = UsdShade.Shader(xf.GetInput("in").GetConnectedSource()[0].GetPrim())
            assert reader.GetInput("varname").Get() == "st_detail"
    # each weight reads its splat texture's channel: rock, scree, grass from splat_a's r, g, b ...
    for name, types in SPLAT_FILES:
        for channel, t in zip("rgb", types):
            src, out_name, _ = graph.GetOutput(f"{t}_weight").GetConnectedSource()
            tex = UsdShade.Shader(src.GetPrim())
            assert out_name == channel and tex.GetInput("file").Get().path == "./" + name
            assert tex.GetInput("sourceColorSpace").Get() == "raw"


def test_st_detail_is_metres_and_the_near_subset_is_bound(world):
    """On every terrain tile (4 x 4 quads here, so the near square spans several)."""
    from pxr import Gf, Usd, UsdGeom, UsdShade

    from stages.world.ground_near import NEAR_MATERIAL, NEAR_SUBSET_NAME
    from stages.world.terrain_tiles import tile_prims

    _, out, ctx, _, _ = world
    stage = Usd.Stage.Open(str(out["world.root"]))
    x0, x1, z0, z1 = ctx.metrics["ground_detail"]["near"]["square"]
    area, subsets = 0.0, []
    for prim in tile_prims(stage):
        mesh = UsdGeom.Mesh(prim)
        pts = np.asarray(mesh.GetPointsAttr().Get())
        st = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st_detail").Get())
        np.testing.assert_allclose(st, np.stack([pts[:, 0], -pts[:, 2]], -1), rtol=1e-6)
        subset = UsdGeom.Subset(prim.GetChild(NEAR_SUBSET_NAME))
        if not subset:
            continue
        subsets.append(subset)
        assert subset.GetFamilyNameAttr().Get() == "materialBind"
        # Near and Rest (the tile's other triangles, bound to the ground: Blender would draw them with Near's)
        assert UsdGeom.Subset.GetFamilyType(mesh, "materialBind") == "partition"
        assert UsdGeom.Subset.ValidateFamily(mesh, "face", "materialBind")[0]
        rest = prim.GetChild("Rest")
        assert UsdShade.MaterialBindingAPI(rest).ComputeBoundMaterial()[0].GetPath() == "/World/Terrain/Looks/Ground"
        faces = np.asarray(subset.GetIndicesAttr().Get())
        corners = pts[np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)[faces]]
        assert len(faces) and (corners[..., 0] >= x0 - 1e-3).all() and (corners[..., 0] <= x1 + 1e-3).all()
        assert (corners[..., 2] >= z0 - 1e-3).all() and (corners[..., 2] <= z1 + 1e-3).all()
        area += 0.5 * np.abs(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])[:, 1]).sum()
        st_near = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st_near").Get())
        inside = st_near[np.unique(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)[faces])]
        assert inside.min() >= -1e-6 and inside.max() <= 1 + 1e-6
    # the subsets' quads are the whole square: (x1 - x0) (z1 - z0) of area, over more than one tile
    assert len(subsets) > 1
    assert area == pytest.approx((x1 - x0) * (z1 - z0), rel=1e-4)
    subset = subsets[0]
    material, _ = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()
    assert material.GetPath() == NEAR_MATERIAL
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    albedo = UsdShade.Shader(surface.GetInput("diffuseColor").GetConnectedSource()[0].GetPrim())
    normal = UsdShade.Shader(surface.GetInput("normal").GetConnectedSource()[0].GetPrim())
    assert albedo.GetInput("sourceColorSpace").Get() == "sRGB" and albedo.GetInput("file").Get().path == "./near_albedo.png"
    assert normal.GetInput("sourceColorSpace").Get() == "raw" and normal.GetInput("scale").Get() == Gf.Vec4f(2, 2, 2, 1)
    assert normal.GetInput("bias").Get() == Gf.Vec4f(-1, -1, -1, 0)
    reader = UsdShade.Shader(albedo.GetInput("st").GetConnectedSource()[0].GetPrim())
    assert reader.GetInput("varname").Get() == "st_near"


def test_near_bake_is_the_blend_at_its_texels(world):
    """Texels of the written near albedo against ground_detail.blend at their
    points (8-bit sRGB: within 1.5 levels)."""
    import OpenImageIO as oiio

    from pipeline.exr import linear_from_srgb
    from worldlib.terrain.mesh import build_terrain_mesh, height_on_mesh

    out_dir, _, ctx, terrain, splat = world
    near = ctx.metrics["ground_detail"]["near"]
    x0, x1, z0, z1 = near["square"]
    img = np.asarray(oiio.ImageBuf(str(out_dir / "near_albedo.png")).get_pixels(oiio.FLOAT))
    n = img.shape[0]
    mesh = build_terrain_mesh(terrain, FAST["mesh_max_vertices"])
    layer = ground_detail.DetailLayer.from_textures(ground_detail.detail_textures(0, 64))
    rows, cols = np.array([3, 40, 77, n - 1]), np.array([0, 17, 50, n - 5])
    X = x0 + (cols + 0.5) * (x1 - x0) / n
    Z = z0 + (rows + 0.5) * (z1 - z0) / n
    h = terrain.channel("height").astype(np.float64)
    gz, gx = np.gradient(h, 25.0)
    r, c = Z / 25.0 - 0.5, X / 25.0 - 0.5
    normal = ground_detail.splat_bilinear(np.stack([-gx, np.ones_like(gx), -gz], -1), r, c)
    w = ground_detail.splat_bilinear(np.stack([splat.channel(ch) for ch in SPLAT_CHANNELS], -1), r, c)
    pos = np.stack([X, height_on_mesh(mesh, X, Z), Z], -1)
    want, _ = ground_detail.blend(layer, w, pos, normal, np.full(len(X), near["texel_m"]))
    got = linear_from_srgb(img[rows, cols, :3])
    np.testing.assert_allclose(got, want, atol=0.012, rtol=0.03)


def test_no_detail_layer_when_switched_off(tmp_path):
    from pipeline.opencl import get_cl
    from pxr import Usd

    terrain = _terrain(9, 10)
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="k", out_dir=tmp_path, seed=0,
                     provenance={"stage": "world", "key": "k"}, project_root=tmp_path)
    out = STAGE.run(ctx, {"terrain": terrain, "splat": _splat(9, 10)},
                    STAGE.params(**dict(FAST, ground_detail=False)))
    stage = Usd.Stage.Open(str(out["world.root"]))
    assert not stage.GetPrimAtPath("/World/Terrain/Looks/Ground/Detail")
    assert not (tmp_path / "detail").exists() and not (tmp_path / "near_albedo.png").exists()
