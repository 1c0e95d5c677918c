"""UsdPreviewSurface materials that read textures, shared by the stages
whose assets carry them (plants, impostors, the ground)."""
from __future__ import annotations


def textured_preview_surface(stage, path: str, roughness: float):
    """A Material at `path` with a UsdPreviewSurface (`Surface`, not metallic)
    and a `st` primvar reader, for the stages whose assets read textures:
    returns (material, surface shader, texture), where texture(name, file,
    colour_space, wrap) defines a UsdUVTexture reading `file` at `st`."""
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
