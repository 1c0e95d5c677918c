"""USD writing: one asset file per species and the top layer.

<species>.usdc, defaultPrim /<species> (Xform, kind component):
    variantSet "lod" = LOD0 .. LODn (selection LOD0); each variant holds
      /<species>/Geom/Wood    the watertight woody solid (trees, shrubs)
      /<species>/Geom/Leaves  leaves and needles (doubleSided)
      /<species>/Geom/Blades  grass blades (doubleSided), /Geom/Cards the slice tuft
      and the model's extentsHint for that level;
    /<species>/Looks/Bark, /Looks/FoliageCards, /Looks/Blades: UsdPreviewSurface
      reading textures/ (UsdUVTexture: albedo PNG sRGB, its alpha as opacity
      with opacityThreshold 0.5 on cards through a second reader, OpacityTexture,
      tangent-space normal EXR raw stored 0..1 with scale 2 and bias -1); the
      foliage looks' AlbedoTexture carries the species' translucency gain
      (scale g, g, g, 1; customData worldbake:translucency_gain), the light
      through the leaves that UsdPreviewSurface cannot transmit;
      /Looks/GrassSlices: the slice tuft's atlas (cards.bake_grass_slices);
      /Looks/Foliage reads primvars:displayColor (untextured species);
      the foliage looks (FoliageCards, Blades, GrassSlices) also hold a
      Tint reader of the instancers' per-instance primvars:tint, and the
      cards a TranslucencyTexture and a ThicknessTexture (data EXRs), with
      customData worldbake:tint / worldbake:translucency / worldbake:thickness
      saying how to wire what UsdPreviewSurface has no input for;
    every mesh: subdivisionScheme none, normals (primvars:normals), primvars:st,
      extent, and the wind primvars (vertex interpolation):
        primvars:wind:branchWeight  bend weight, 0 at the root of the plant, 1 at the outermost tips
        primvars:wind:flutterWeight 0 on wood; 0 at a leaf's stalk / blade root, 1 at its tip
        primvars:wind:phase         per branch / leaf / blade random phase in [0, 1)
        primvars:wind:pivot         the point the part swings about: branch base, leaf stalk, blade root
    customData worldbake:lods: per level its triangles, Hausdorff error (m and
      fraction of the bounding-box diagonal) and simplification time;
    customData worldbake:measures: foliage and wood area, leaf area index,
      crown opacity (LOD0 and per level), card coverage (measure.py).
plants.usda (the stage's artifact), defaultPrim /Plants (kind group), one
  child per built species referencing "./<species>.usdc": the prototypes a
  world layer's PointInstancers point to.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline import usdio
from worldlib import materials
from worldlib.plant_asset import PLANTS_ROOT, plant_asset_prim

from .mesh import Part


def _material(stage, path: str, colour, roughness: float, read_display_color: bool):
    from pxr import Gf, Sdf, UsdShade

    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    col = surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    col.Set(Gf.Vec3f(*map(float, colour)))
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
    surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    if read_display_color:
        rd = UsdShade.Shader.Define(stage, f"{path}/DisplayColor")
        rd.CreateIdAttr("UsdPrimvarReader_float3")
        rd.CreateInput("varname", Sdf.ValueTypeNames.String).Set("displayColor")
        rd.CreateInput("fallback", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(*map(float, colour)))
        col.ConnectToSource(rd.ConnectableAPI(), "result")
        rd.CreateOutput("result", Sdf.ValueTypeNames.Float3)
    return mat


# How the foliage materials carry what UsdPreviewSurface has no input for
# (written into the material's customData, so a technical artist wiring a
# renderer's own surface finds it):
TINT_SCHEME = ("diffuseColor = AlbedoTexture.outputs:rgb * Tint.outputs:result: Tint reads primvars:tint, a linear "
               "colour factor per instance authored on the PointInstancers (interpolation vertex) and 1 elsewhere; "
               "UsdPreviewSurface cannot multiply, so its diffuseColor shows the untinted albedo")
TRANSLUCENCY_SCHEME = {
    "translucency": "TranslucencyTexture.outputs:r: share of light the foliage passes at each texel (0..1, linear "
                    "EXR data); a renderer's diffuse transmission / translucency weight (e.g. Karma or OmniPBR "
                    "translucency, MaterialX subsurface), tinted by the albedo",
    "thickness": "ThicknessTexture.outputs:r: metres of foliage along the card normal (linear EXR data), for a "
                 "thickness / subsurface-radius input",
}


def _textured_material(stage, path: str, look: dict, roughness: float):
    """UsdPreviewSurface reading its textures through UsdUVTexture: diffuse
    colour from an 8-bit sRGB PNG (sourceColorSpace sRGB), opacity from that
    PNG's alpha with opacityThreshold (the alpha test of foliage cards),
    normal from a linear EXR tangent-space normal map (sourceColorSpace raw,
    stored as 0.5 n + 0.5, so scale 2 and bias -1). `look`: albedo, normal
    (paths relative to the layer), wrap ("repeat" for bark, "clamp" for
    cards), alpha_test (bool), tint (bool: read the per-instance tint),
    translucency, thickness (optional data EXRs, see TRANSLUCENCY_SCHEME),
    gain (the foliage's translucency gain on the colour, see
    materials.bake_translucency)."""
    from pxr import Gf, Sdf, UsdShade

    mat, surf, texture_at = materials.textured_preview_surface(stage, path, roughness)

    def texture(name: str, file: str, colour_space: str):
        return texture_at(name, file, colour_space, look["wrap"])

    albedo = texture("AlbedoTexture", look["albedo"], "sRGB")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        albedo.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    if look.get("gain", 1.0) != 1.0:
        materials.bake_translucency(albedo, look["gain"])
    if look.get("alpha_test"):
        # a second reader of the PNG: its alpha is the cut-out whatever scale the colour reader carries
        cutout = texture("OpacityTexture", look["albedo"], "sRGB")
        surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(
            cutout.CreateOutput("a", Sdf.ValueTypeNames.Float))
        surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    if look.get("tint"):
        # the per-instance tint the PointInstancers carry (primvars:tint, one colour per instance); UsdPreviewSurface
        # has no multiply node, so the reader is wired by the scheme in customData worldbake:tint
        tint = UsdShade.Shader.Define(stage, f"{path}/Tint")
        tint.CreateIdAttr("UsdPrimvarReader_float3")
        tint.CreateInput("varname", Sdf.ValueTypeNames.String).Set("tint")
        tint.CreateInput("fallback", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(1.0, 1.0, 1.0))
        tint.CreateOutput("result", Sdf.ValueTypeNames.Float3)
        mat.GetPrim().SetCustomDataByKey("worldbake:tint", TINT_SCHEME)
    for key, shader_name in (("translucency", "TranslucencyTexture"), ("thickness", "ThicknessTexture")):
        if look.get(key):
            data = texture(shader_name, look[key], "raw")
            data.CreateOutput("r", Sdf.ValueTypeNames.Float)
            mat.GetPrim().SetCustomDataByKey(f"worldbake:{key}", TRANSLUCENCY_SCHEME[key])
    if look.get("normal"):
        materials.connect_normal_map(surf, texture("NormalTexture", look["normal"], "raw"))
    return mat


def _extent(pos: np.ndarray):
    from pxr import Gf, Vt

    lo, hi = pos.min(0), pos.max(0)
    return Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))])


def write_mesh(stage, path: str, part: Part, material, double_sided: bool, colour_root, colour_tip=None):
    """A UsdGeom.Mesh from a Part: welded points, normals and st as indexed
    faceVarying primvars where vertices are split (uv seams), vertex ones
    otherwise; wind primvars per point."""
    from pxr import Sdf, UsdGeom, UsdShade, Vt

    pos, faces = part.welded()
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateDoubleSidedAttr(bool(double_sided))
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pos, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.ravel(), np.int32)))
    mesh.CreateExtentAttr(_extent(pos))
    pv = UsdGeom.PrimvarsAPI(mesh)
    split = len(part.weld) != len(pos)
    v = part.verts
    if split:
        interp = UsdGeom.Tokens.faceVarying
        idx = Vt.IntArray.FromNumpy(np.ascontiguousarray(part.tris.ravel(), np.int32))
        n = pv.CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, interp)
        n.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(v[:, 3:6], np.float32)))
        n.SetIndices(idx)
        st = pv.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, interp)
        st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(v[:, 6:8], np.float32)))
        st.SetIndices(idx)
        first = np.full(len(pos), len(v), np.int64)
        np.minimum.at(first, part.weld, np.arange(len(v)))
        pt = v[first]
    else:
        interp = UsdGeom.Tokens.vertex
        order = np.empty(len(v), np.int64)
        order[part.weld] = np.arange(len(v))
        pt = v[order]
        pv.CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, interp).Set(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pt[:, 3:6], np.float32)))
        pv.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, interp).Set(
            Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(pt[:, 6:8], np.float32)))
    V = UsdGeom.Tokens.vertex
    pv.CreatePrimvar("wind:branchWeight", Sdf.ValueTypeNames.FloatArray, V).Set(
        Vt.FloatArray.FromNumpy(np.ascontiguousarray(pt[:, 8], np.float32)))
    pv.CreatePrimvar("wind:flutterWeight", Sdf.ValueTypeNames.FloatArray, V).Set(
        Vt.FloatArray.FromNumpy(np.ascontiguousarray(pt[:, 9], np.float32)))
    pv.CreatePrimvar("wind:phase", Sdf.ValueTypeNames.FloatArray, V).Set(
        Vt.FloatArray.FromNumpy(np.ascontiguousarray(pt[:, 10], np.float32)))
    pv.CreatePrimvar("wind:pivot", Sdf.ValueTypeNames.Point3fArray, V).Set(
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pt[:, 11:14], np.float32)))
    root = np.asarray(colour_root, np.float32)
    if colour_tip is None:
        dc = pv.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.constant)
        dc.Set(Vt.Vec3fArray.FromNumpy(root[None, :]))
    else:
        t = np.clip(pt[:, 9:10], 0, 1)
        cols = (1 - t) * root[None] + t * np.asarray(colour_tip, np.float32)[None]
        pv.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, V).Set(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(cols, np.float32)))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    return mesh


def write_species(path: Path, name: str, spec, lods: list[dict[str, Part]], lod_info: list[dict], provenance: dict,
                  looks: dict | None = None, measures: dict | None = None) -> None:
    """lods[k] maps 'Wood' / 'Leaves' / 'Blades' / 'Cards' to a Part; looks
    names the textures of 'bark', 'foliage' (cards) and 'blades' (see
    _textured_material); measures goes into customData worldbake:measures."""
    looks = looks or {}
    from pxr import UsdGeom

    stage, root = usdio.create_stage(path, provenance, root=f"/{name}", kind="component")
    UsdGeom.Scope.Define(stage, f"/{name}/Looks")
    has_wood = any(parts.get("Wood") is not None and parts["Wood"].n_tris for parts in lods)
    bark = None
    if has_wood:
        bark = (_textured_material(stage, f"/{name}/Looks/Bark", looks["bark"], spec.roughness) if "bark" in looks
                else _material(stage, f"/{name}/Looks/Bark", spec.bark_color, spec.roughness, False))
    plain = _material(stage, f"/{name}/Looks/Foliage", spec.leaf_color, spec.roughness, True)
    foliage = (_textured_material(stage, f"/{name}/Looks/FoliageCards", dict(looks["foliage"], tint=True),
                                  spec.roughness) if "foliage" in looks else plain)
    blades = (_textured_material(stage, f"/{name}/Looks/Blades", dict(looks["blades"], tint=True), spec.roughness)
              if "blades" in looks else plain)
    slices = (_textured_material(stage, f"/{name}/Looks/GrassSlices", dict(looks["slices"], tint=True), spec.roughness)
              if "slices" in looks else plain)
    material_of = {"Leaves": foliage, "Blades": blades, "Cards": slices}
    vset = root.GetVariantSets().AddVariantSet("lod")
    for k, parts in enumerate(lods):
        vname = f"LOD{k}"
        vset.AddVariant(vname)
        vset.SetVariantSelection(vname)
        with vset.GetVariantEditContext():
            UsdGeom.Xform.Define(stage, f"/{name}/Geom")
            allpos = []
            for pname, part in parts.items():
                if part.n_tris == 0:
                    continue
                wood = pname == "Wood"
                write_mesh(stage, f"/{name}/Geom/{pname}", part, bark if wood else material_of.get(pname, plain), not wood,
                           spec.bark_color if wood else spec.leaf_color, None if wood else spec.leaf_tip_color)
                allpos.append(part.welded()[0])
            if allpos:
                UsdGeom.ModelAPI(root).SetExtentsHint(_extent(np.concatenate(allpos)))
    vset.SetVariantSelection("LOD0")
    root.SetCustomDataByKey("worldbake:lods", json.dumps(lod_info, sort_keys=True))
    if measures is not None:
        root.SetCustomDataByKey("worldbake:measures", json.dumps(measures, sort_keys=True))
    stage.GetRootLayer().Save()


def write_top(path: Path, species_files: dict[str, str], provenance: dict, summary: dict) -> None:
    from pxr import UsdGeom

    stage, root = usdio.create_stage(path, provenance, root=PLANTS_ROOT, kind="group")
    for name, rel in species_files.items():
        prim = UsdGeom.Xform.Define(stage, plant_asset_prim(name)).GetPrim()
        prim.GetReferences().AddReference(rel)
    root.SetCustomDataByKey("worldbake:species", json.dumps(summary, sort_keys=True))
    stage.GetRootLayer().Save()
