"""Textures by the UsdPreviewSurface spec and how the USD reader of the
renderer reads them: normal maps stored 0..1 and decoded by scale and bias,
a colour texture's scale applied as authored, the foliage translucency gain
(which the display light models itself) divided back out."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib import materials
from worldlib.render.usd_asset import load_plant, read_image


def test_normal_encoding_round_trips_and_stays_in_0_1():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n = np.concatenate([n, [[1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1]]])
    t = materials.encode_normal(n)
    assert t.min() >= 0.0 and t.max() <= 1.0
    assert np.allclose(materials.decode_normal(t), n, atol=1e-6)
    # the spec's decoding is the scale and bias the shaders author
    assert np.allclose(t * np.array(materials.NORMAL_SCALE[:3]) + np.array(materials.NORMAL_BIAS[:3]), n, atol=1e-6)
    assert materials.NORMAL_SCALE[3] == 1.0 and materials.NORMAL_BIAS[3] == 0.0
    # the flat normal is the familiar normal-map blue
    assert np.allclose(materials.encode_normal([0.0, 0.0, 1.0]), [0.5, 0.5, 1.0])


def test_normal_encoding_survives_a_half_float_exr(tmp_path):
    from stages.impostors import images

    rng = np.random.default_rng(4)
    n = rng.normal(size=(16, 16, 3))
    n[..., 2] = np.abs(n[..., 2])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    images.write_exr(tmp_path / "n.exr", [materials.encode_normal(n)], ("R", "G", "B"), {})
    texels = read_image(str(tmp_path / "n.exr"), "raw")[..., :3]
    assert texels.min() >= 0.0 and texels.max() <= 1.0
    assert np.abs(materials.decode_normal(texels) - n).max() < 2e-3  # half precision near 1


def _quad_layer(tmp_path, scale=None, bias=None, gain=None):
    """/Plants/quad: one textured quad (a grey PNG) whose AlbedoTexture
    carries `scale`, `bias` and the translucency `gain` if given."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

    from pipeline import exr

    tmp_path.mkdir(parents=True, exist_ok=True)
    exr.write_png(tmp_path / "grey.png", np.full((4, 4, 3), 128, np.uint8))
    stage = Usd.Stage.CreateNew(str(tmp_path / "quad.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    mesh = UsdGeom.Mesh.Define(stage, "/Plants/quad/Geom/Leaves")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, "vertex").Set(
        [(0, 0), (1, 0), (1, 1), (0, 1)])
    mat, surf, texture = materials.textured_preview_surface(stage, "/Plants/quad/Looks/Leaf", 0.8)
    tex = texture("AlbedoTexture", "./grey.png", "sRGB", "clamp")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    if gain is not None:
        materials.bake_translucency(tex, gain)
    if scale is not None:
        tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*scale))
    if bias is not None:
        tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*bias))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    stage.GetRootLayer().Save()
    return tmp_path / "quad.usda"


def test_a_colour_scale_is_applied_as_authored(tmp_path):
    plain = load_plant(_quad_layer(tmp_path / "a"), "/Plants/quad").scene
    scaled = load_plant(_quad_layer(tmp_path / "b", scale=(2.0, 1.0, 0.5, 1.0)), "/Plants/quad").scene
    assert np.allclose(plain.tint, 1.0)
    assert np.allclose(scaled.tint, [2.0, 1.0, 0.5])
    assert np.allclose(scaled.textures, plain.textures)


def test_the_translucency_gain_is_divided_back_out(tmp_path):
    """The display light passes the transmitted light itself: a gain-baked
    foliage colour reads as the albedo, so our pictures do not change."""
    plain = load_plant(_quad_layer(tmp_path / "a"), "/Plants/quad").scene
    baked = load_plant(_quad_layer(tmp_path / "b", gain=1.37), "/Plants/quad").scene
    assert np.allclose(baked.tint, plain.tint) and np.allclose(baked.textures, plain.textures)
    from pxr import Usd

    stage = Usd.Stage.Open(str(tmp_path / "b" / "quad.usda"))
    tex = stage.GetPrimAtPath("/Plants/quad/Looks/Leaf/AlbedoTexture")
    assert tuple(tex.GetAttribute("inputs:scale").Get()) == pytest.approx((1.37, 1.37, 1.37, 1.0))


def test_a_colour_bias_is_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match="AlbedoTexture.*bias"):
        load_plant(_quad_layer(tmp_path, bias=(0.1, 0.0, 0.0, 0.0)), "/Plants/quad")
