"""The impostors layer (impostors.usda): overs on the plants layer's
/Plants/<species>, composed by the world over each prototype (the plants
stage's own files are never modified).

over /Plants/<species> (GeomModelAPI)
    model:cardGeometry = "box", model:cardTexture{X,Y,Z}{Pos,Neg}: six
      orthographic views along the axes (card_views), so USD's viewers draw
      textured cards when model:drawMode = "cards" is asked for;
    model:applyDrawMode = true;
    customData worldbake:impostor (the atlas: files, layout, frames, the
      bounding sphere, the held-out error), worldbake:lod_switch_m (the
      distance in metres from which each LOD is used, derived from its
      measured error: the mesh LODs' Hausdorff error, the impostors'
      held-out silhouette error and texel size; ladder_m for an engine
      that draws the atlas, variant_m for the `lod` variants a USD
      consumer switches, whose `impostor` is the slices);
    over Geom (purpose render, proxyPrim -> Impostor): the mesh of every
      LODk variant;
    def Xform Impostor: the slice billboards (Mesh Slices, or Tuft and
      TuftTop for grass) with their UsdPreviewSurface (albedo PNG sRGB
      with the plant's foliage translucency gain, alpha-tested at 0.5,
      tangent-space normal PNG stored 0..1 with scale 2 and bias -1);
    variantSet lod: every existing LODk variant sets Impostor's purpose to
      proxy (drawn in viewports beside the render-purpose mesh); the new
      variant `impostor` holds no mesh and draws Impostor as the model
      itself (purpose default).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline import usdio
from worldlib import materials
from worldlib.render import Camera, Prepared, Settings
from worldlib.plant_asset import PLANTS_ROOT, plant_asset_prim

from .screen import switch_distance_m

# the six cards views: (name, view direction toward the viewer, camera up), the
# orientation UsdImaging's cards draw mode maps each texture with
CARD_AXES = (
    ("xpos", (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)), ("xneg", (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ("ypos", (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), ("yneg", (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    ("zpos", (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)), ("zneg", (0.0, 0.0, -1.0), (0.0, -1.0, 0.0)),
)
CARD_ATTR = {"xpos": "XPos", "xneg": "XNeg", "ypos": "YPos", "yneg": "YNeg", "zpos": "ZPos", "zneg": "ZNeg"}


def card_views(prepared: Prepared, lo: np.ndarray, hi: np.ndarray, size: int, samples: int) -> dict:
    """Per axis (straight linear RGB padded, alpha): the plant seen along the
    axis, the picture stretched over the box face (the model's extent)."""
    from scipy import ndimage

    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre, span = 0.5 * (lo + hi), np.maximum(hi - lo, 1e-6)
    out = {}
    for name, view, up in CARD_AXES:
        v, u = np.asarray(view), np.asarray(up)
        right = np.cross(-v, u)
        width = float(np.abs(right) @ span)
        height = float(np.abs(u) @ span)
        eye = centre + v * (float(np.abs(v) @ span) + 1.0)
        img = prepared.render(Camera(tuple(eye), tuple(-v), tuple(u), ortho_height_m=height, ortho_width_m=width),
                              Settings(size, size, samples=samples))
        rgb = img.albedo / np.maximum(img.alpha, 1e-6)[..., None]
        empty = img.alpha <= 0
        if empty.any() and not empty.all():
            _, (iy, ix) = ndimage.distance_transform_edt(empty, return_indices=True)
            rgb = rgb[iy, ix]
        out[name] = (np.clip(rgb, 0, 1), img.alpha)
    return out


def _material(stage, path: str, albedo: str, normal: str | None, gain: float = 1.0):
    """Albedo PNG (sRGB) as diffuseColor, brightened by the plant's foliage
    translucency gain (materials.bake_translucency: the DCC look of LOD0's
    foliage), its alpha cut out at 0.5 through a second reader of the PNG,
    and the tangent-space normal PNG (raw, 0..1, the spec's scale and bias)."""
    from pxr import Sdf

    mat, surf, texture_at = materials.textured_preview_surface(stage, path, roughness=0.8)

    def texture(name, file, space):
        return texture_at(name, file, space, "clamp")

    colour = texture("AlbedoTexture", albedo, "sRGB")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        colour.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    if gain != 1.0:
        materials.bake_translucency(colour, gain)
    cutout = texture("OpacityTexture", albedo, "sRGB")
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(cutout.CreateOutput("a", Sdf.ValueTypeNames.Float))
    surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    if normal:
        materials.connect_normal_map(surf, texture("NormalTexture", normal, "raw"))
    return mat


def foliage_gain(plants_layer: Path | None, name: str) -> float:
    """The translucency gain the plant asset's foliage colour carries (the
    largest materials.TRANSLUCENCY_GAIN under its prim; 1 without)."""
    from pxr import Usd

    if plants_layer is None:
        return 1.0
    stage = Usd.Stage.Open(str(plants_layer))
    prim = stage.GetPrimAtPath(plant_asset_prim(name))
    gains = [float(p.GetCustomDataByKey(materials.TRANSLUCENCY_GAIN)) for p in Usd.PrimRange(prim)
             if p.GetCustomDataByKey(materials.TRANSLUCENCY_GAIN) is not None] if prim else []
    return max(gains, default=1.0)


def _billboards(stage, path: str, sheet, material) -> None:
    from pxr import Gf, Sdf, UsdGeom, UsdShade, Vt

    p, st, tris, _ = sheet.mesh()
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateDoubleSidedAttr(sheet.name != "slices")  # tree slabs: one quad per side, each its own render
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(p, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(tris.ravel(), np.int32)))
    n = np.cross(p[1::4] - p[0::4], p[2::4] - p[0::4])
    n = np.repeat(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12), 4, 0)
    pv = UsdGeom.PrimvarsAPI(mesh)
    pv.CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(n, np.float32)))
    pv.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(st, np.float32)))
    lo, hi = p.min(0), p.max(0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)


def _mesh_lods(plants_layer: Path, name: str) -> tuple[list[str], list[dict]]:
    from pxr import Usd

    stage = Usd.Stage.Open(str(plants_layer))
    prim = stage.GetPrimAtPath(plant_asset_prim(name))
    variants = list(prim.GetVariantSets().GetVariantSet("lod").GetVariantNames())
    lods = prim.GetCustomDataByKey("worldbake:lods")
    return variants, (json.loads(lods) if lods else [])


def lod_ladder(own: dict[str, float]) -> dict[str, float]:
    """The LODs in order (meshes, impostor, slices), each used from its own
    distance, where a later representation whose distance is smaller takes
    over the earlier ones it beats (they are dropped); increasing."""
    ladder: list[tuple[str, float]] = []
    for name, d in own.items():
        while ladder and ladder[-1][1] >= d and ladder[-1][0] != "LOD0":
            ladder.pop()
        ladder.append((name, max(d, ladder[-1][1]) if ladder else 0.0))
    return {name: round(d, 3) for name, d in ladder}


def write(path: Path, provenance: dict, baked: list[dict], plants_layer: Path | None, params) -> dict:
    from pxr import Gf, Sdf, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = stage.OverridePrim(PLANTS_ROOT)
    stage.SetDefaultPrim(root)
    usdio.set_provenance(stage.GetRootLayer(), provenance)
    switches = {}
    for b in baked:
        name = b["name"]
        base = plant_asset_prim(name)
        prim = stage.OverridePrim(base)
        model = UsdGeom.ModelAPI.Apply(prim)
        model.CreateModelCardGeometryAttr("box")
        model.CreateModelApplyDrawModeAttr(True)
        for axis, file in b["card_files"].items():
            getattr(model, f"CreateModelCardTexture{CARD_ATTR[axis]}Attr")(Sdf.AssetPath(f"./textures/{file}"))
        geom = stage.OverridePrim(f"{base}/Geom")
        UsdGeom.Imageable(geom).CreatePurposeAttr(UsdGeom.Tokens.render)
        UsdGeom.Imageable(geom).CreateProxyPrimRel().SetTargets([Sdf.Path(f"{base}/Impostor")])
        imp = UsdGeom.Xform.Define(stage, f"{base}/Impostor")
        UsdGeom.Scope.Define(stage, f"{base}/Impostor/Looks")
        gain = foliage_gain(plants_layer, name)
        for sheet in b["sheets"]:
            files = b["sheet_files"][sheet.name]
            prim_name = {"slices": "Slices", "tuft": "Tuft", "tuft_top": "TuftTop"}[sheet.name]
            mat = _material(stage, f"{base}/Impostor/Looks/{prim_name}", f"./textures/{files['albedo']}",
                            f"./textures/{files['normal']}", gain)
            _billboards(stage, f"{base}/Impostor/{prim_name}", sheet, mat)
        lo, hi = b["lo"], b["hi"]
        UsdGeom.ModelAPI(imp).SetExtentsHint([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))])
        variants, lods = _mesh_lods(plants_layer, name) if plants_layer is not None else (["LOD0"], [])
        vset = prim.GetVariantSets().AddVariantSet("lod")
        for v in variants:
            vset.AddVariant(v)
            vset.SetVariantSelection(v)
            with vset.GetVariantEditContext():
                UsdGeom.Imageable(stage.OverridePrim(f"{base}/Impostor")).CreatePurposeAttr(UsdGeom.Tokens.proxy)
        vset.AddVariant("impostor")
        vset.SetVariantSelection("impostor")
        with vset.GetVariantEditContext():
            UsdGeom.Imageable(stage.OverridePrim(f"{base}/Impostor")).CreatePurposeAttr(UsdGeom.Tokens.default_)
        vset.ClearVariantSelection()  # the plant asset's selection (LOD0) stands
        # each representation's own distance: from where its measured error is at most error_px
        own = {f"LOD{e['level']}": switch_distance_m(float(e.get("hausdorff_m", 0.0)), params) for e in lods}
        own["impostor"] = b["switch_m"]["impostor"]
        own["slices"] = b["switch_m"]["slices"]
        switch = lod_ladder(own)
        switches[name] = switch
        # what a USD consumer can switch: the mesh LODs and the `impostor` variant, which draws the slices
        # (the atlas needs an engine's shader), each from its own distance
        variant_m = lod_ladder({**{k: v for k, v in own.items() if k.startswith("LOD")}, "impostor": own["slices"]})
        info = dict(b["info"])
        info["files"] = {k: f"./textures/{v}" for k, v in b["files"].items()}
        info["slice_files"] = {k: {kk: f"./textures/{vv}" for kk, vv in v.items()} for k, v in b["sheet_files"].items()}
        prim.SetCustomDataByKey("worldbake:impostor", json.dumps(info, sort_keys=True))
        prim.SetCustomDataByKey("worldbake:lod_switch_m", json.dumps(
            {"ladder_m": switch, "variant_m": variant_m, "own_distance_m": {k: round(v, 3) for k, v in own.items()},
             "screen_px": params.screen_px, "fov_deg": params.screen_fov_deg,
             "error_px": params.error_px, "from": "each LOD's measured error (Hausdorff for meshes, held-out "
             "silhouette displacement and texel size for impostors) projected to error_px pixels; the ladder drops "
             "a mesh LOD that a later, cheaper representation already matches at that distance"}, sort_keys=True))
    stage.GetRootLayer().Save()
    return {"lod_switch_m": switches}
