"""UsdPreviewSurface materials that read textures, shared by the stages
whose assets carry them (plants, impostors, the ground), and the water of
rivers and lakes."""
from __future__ import annotations


# A normal map's texels by the UsdPreviewSurface spec: a tangent-space unit
# normal n stored as 0.5 n + 0.5 (every channel in 0..1, as 8-bit files and
# DCC normal-map nodes expect), read back through the UsdUVTexture's
# scale and bias: n = 2 texel - 1.
NORMAL_SCALE = (2.0, 2.0, 2.0, 1.0)
NORMAL_BIAS = (-1.0, -1.0, -1.0, 0.0)


def encode_normal(n):
    """Unit normals (..., 3), components -1..1, as normal-map texels 0..1."""
    import numpy as np

    return np.clip(0.5 * np.asarray(n, np.float32) + 0.5, 0.0, 1.0)


def decode_normal(texels, scale=NORMAL_SCALE, bias=NORMAL_BIAS):
    """What a UsdUVTexture with this scale and bias outputs for the texels
    (..., 3): texel * scale + bias (the spec's decoding)."""
    import numpy as np

    t = np.asarray(texels, np.float32)
    return t * np.asarray(scale[:3], np.float32) + np.asarray(bias[:3], np.float32)


def connect_normal_map(surf, tex) -> None:
    """The UsdUVTexture `tex` (a normal map stored by encode_normal, read
    raw) decoded by the spec's scale and bias into the surface's normal."""
    from pxr import Gf, Sdf

    tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*NORMAL_SCALE))
    tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*NORMAL_BIAS))
    surf.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))


# Foliage's light through the leaf (our renderer's display light passes a share of the sun through surfaces
# facing away from it) has no UsdPreviewSurface input: the diffuse colour's UsdUVTexture carries it as a gain
# (scale g, g, g, 1), recorded under this customData key on that texture so a reader that models the
# transmitted light itself (worldlib.render.usd_asset) divides it back out.
TRANSLUCENCY_GAIN = "worldbake:translucency_gain"


def bake_translucency(tex, gain: float) -> None:
    """The diffuse-colour UsdUVTexture `tex` brightened by `gain` (>= 1),
    the light a DCC's opaque diffuse misses; its opacity must come from
    another UsdUVTexture (Blender's importer wires a scaled texture's alpha
    from the scaled colour)."""
    from pxr import Gf, Sdf

    g = float(gain)
    tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(g, g, g, 1.0))
    tex.GetPrim().SetCustomDataByKey(TRANSLUCENCY_GAIN, g)


def textured_preview_surface(stage, path: str, roughness: float):
    """A Material at `path` with a UsdPreviewSurface (`Surface`, not metallic)
    and a `st` primvar reader, for the stages whose assets read textures:
    returns (material, surface shader, texture), where texture(name, file,
    colour_space, wrap) defines a UsdUVTexture reading `file` at `st`
    (colour_space: "sRGB" for 8-bit colour, "raw" for data and linear EXR)."""
    from pxr import Sdf, UsdShade

    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
    surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    st = UsdShade.Shader.Define(stage, f"{path}/TexCoord")
    st.CreateIdAttr("UsdPrimvarReader_float2")
    st.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    st_out = st.CreateOutput("result", Sdf.ValueTypeNames.Float2)

    def texture(name: str, file: str, colour_space: str, wrap: str):
        tex = UsdShade.Shader.Define(stage, f"{path}/{name}")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(file))
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(colour_space)
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(wrap)
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set(wrap)
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_out)
        return tex

    return mat, surf, texture


# Open water (linear RGB): deep clear mountain water seen from above is dark blue-green; glossy, partly
# see-through over a shallow bed; ior of water 1.33.
WATER_COLOUR = (0.05, 0.16, 0.22)


def water_preview_surface(stage, path: str, colour=WATER_COLOUR, opacity: float = 0.75, roughness: float = 0.05,
                          ior: float = 1.33):
    """A Material at `path` with a UsdPreviewSurface (`Surface`) for rivers
    and lakes: constant diffuseColor, low roughness, not metallic, opacity
    below 1 (the spec has no transmission: opacity is its see-through) and
    the ior of water, so any DCC renders it as water. Returns the material."""
    from pxr import Gf, Sdf, UsdShade

    material = UsdShade.Material.Define(stage, path)
    surface = UsdShade.Shader.Define(stage, path + "/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, colour)))
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    surface.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(float(opacity))
    surface.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(float(ior))
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    return material
