"""worldlib.render.world_view on a tiny world.usda written here: a textured
ground (UDIM tiles), one PointInstancer of a prototype (a green textured card
tree) with per-instance tints; the picture shows the ground's texture, the
instances as billboards, each in its own tint."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib.render import Camera, world_view


def _write_tile(path, rgb):
    import OpenImageIO as oiio

    assert oiio.ImageBuf(np.ascontiguousarray(rgb, np.float32)).write(str(path))


@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory):
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

    d = tmp_path_factory.mktemp("world")
    # two UDIM tiles side by side: west red-brown, east blue-grey (linear EXR data)
    _write_tile(d / "ground.1001.exr", np.full((8, 8, 3), (0.4, 0.1, 0.05)))
    _write_tile(d / "ground.1002.exr", np.full((8, 8, 3), (0.1, 0.1, 0.4)))
    import OpenImageIO as oiio

    leaf = np.zeros((16, 16, 4), np.float32)
    leaf[2:16, 3:13] = (0.2, 0.8, 0.2, 1.0)  # a green blob on a transparent card
    oiio.ImageBuf(leaf).write(str(d / "leaf.exr"))
    stage = Usd.Stage.CreateNew(str(d / "world.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    ground = UsdGeom.Mesh.Define(stage, "/World/Ground")
    ground.CreatePointsAttr([(-20, 0, -10), (20, 0, -10), (20, 0, 10), (-20, 0, 10)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
    pv = UsdGeom.PrimvarsAPI(ground)
    pv.CreatePrimvar("st_udim", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec2fArray([(0, 1), (2, 1), (2, 0), (0, 0)]))

    def material(path, file, st_name, alpha):
        mat = UsdShade.Material.Define(stage, path)
        surf = UsdShade.Shader.Define(stage, path + "/Surface")
        surf.CreateIdAttr("UsdPreviewSurface")
        rd = UsdShade.Shader.Define(stage, path + "/St")
        rd.CreateIdAttr("UsdPrimvarReader_float2")
        rd.CreateInput("varname", Sdf.ValueTypeNames.String).Set(st_name)
        tex = UsdShade.Shader.Define(stage, path + "/Tex")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(rd.ConnectableAPI(), "result")
        surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), "rgb")
        if alpha:
            surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(tex.ConnectableAPI(), "a")
        mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
        return mat

    UsdShade.MaterialBindingAPI.Apply(ground.GetPrim()).Bind(material("/World/Looks/Ground", "./ground.<UDIM>.exr",
                                                                      "st_udim", False))
    pi = UsdGeom.PointInstancer.Define(stage, "/World/Trees")
    card = UsdGeom.Mesh.Define(stage, "/World/Trees/Prototypes/tree/Card")
    card.CreatePointsAttr([(-1, 0, 0), (1, 0, 0), (1, 4, 0), (-1, 4, 0)])
    card.CreateFaceVertexCountsAttr([4])
    card.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdGeom.PrimvarsAPI(card).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec2fArray([(0, 0), (1, 0), (1, 1), (0, 1)]))
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(material("/World/Looks/Leaf", "./leaf.exr", "st", True))
    pi.CreatePrototypesRel().SetTargets([Sdf.Path("/World/Trees/Prototypes/tree")])
    pi.CreatePositionsAttr(Vt.Vec3fArray([(-10, 0, 0), (10, 0, 0), (0, 0, 0)]))
    pi.CreateProtoIndicesAttr(Vt.IntArray([0, 0, 0]))
    pi.CreateScalesAttr(Vt.Vec3fArray([(1, 1, 1), (1, 1, 1), (0.1, 0.1, 0.1)]))  # the third is too small to draw
    UsdGeom.PrimvarsAPI(pi).CreatePrimvar("tint", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray([(1.0, 1.0, 1.0), (1.5, 0.5, 0.5), (1, 1, 1)]))
    stage.GetRootLayer().Save()
    return d / "world.usda"


def test_world_scene_holds_ground_and_billboards(cl_env, tiny_world):
    scene, summary = world_view.build_world_scene(cl_env, tiny_world, min_instance_height_m=1.0, progress=lambda m: None)
    assert summary["instances"] == {"tree": 2} and summary["skipped_small"] == {"tree": 1}
    assert scene.n_triangles == 2 + 2 * 6  # the ground quad, three quads per drawn instance
    assert summary["bounds"][0][0] == -20 and summary["bounds"][1][0] == 20


def test_world_picture_shows_ground_texture_trees_and_tints(cl_env, tiny_world):
    from worldlib.render import Prepared, Settings

    scene, _ = world_view.build_world_scene(cl_env, tiny_world, min_instance_height_m=1.0, progress=lambda m: None)
    top = Camera((0.0, 50.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0), ortho_height_m=20.0)
    img = Prepared(cl_env, scene).render(top, Settings(80, 40, samples=1))
    west, east = img.albedo[20, 5], img.albedo[20, 75]
    assert west[0] > 2 * west[2] and east[2] > 2 * east[0]  # the UDIM tiles where they belong
    side = Camera((0.0, 2.0, 40.0), (0.0, 0.0, -1.0), ortho_height_m=8.0)
    img = Prepared(cl_env, scene).render(side, Settings(200, 40, samples=1))
    row = img.albedo[18]
    plain, tinted = row[50], row[150]  # x = -10 and x = +10
    assert plain[1] > 2 * plain[0]  # a green tree
    assert tinted[0] / tinted[1] > 2.5 * plain[0] / plain[1]  # the tint (1.5, 0.5, 0.5) reddens the second
    rgba = world_view.render_world(cl_env, tiny_world, 80, 40, camera=top, samples=1, ao_rays=0, progress=lambda m: None)
    assert rgba.shape == (40, 80, 4) and rgba.dtype == np.uint8 and (rgba[..., 3] == 255).all()


def test_meshes_under_an_instanceable_prim_are_read():
    """The world's instancer prototypes are instanceable prims of one asset
    per species: their meshes are instance proxies, read all the same."""
    from pxr import Usd, UsdGeom

    from worldlib.render.usd_asset import subtree_scene

    stage = Usd.Stage.CreateInMemory()
    mesh = UsdGeom.Mesh.Define(stage, "/Asset/Geom")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    inst = stage.DefinePrim("/Instance")
    inst.GetReferences().AddInternalReference("/Asset")
    inst.SetInstanceable(True)
    assert inst.IsInstance()
    scenes = subtree_scene(inst, None, {})
    assert sum(s.n_triangles for s in scenes) == 1
